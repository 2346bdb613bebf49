"""Each shortcut of the per-frame path (issue 10) gives what the plain computation gives.

The per-frame speed-ups replace whole-grid or general computations with ones restricted to
what can change; here each is checked against the plain formulation written out in the
test, on small generated masks and graphs, to the bit.
"""

import numpy as np
import scipy.sparse as sp

from FevarPlannerLib.graph import SkeletonGraph, smooth_positions
from FevarPlannerLib.skeleton import skeletonize_2d
from fixtures import y_mask_2d


def _laplacian_smoothing_by_sparse_product(graph: SkeletonGraph, iterations: int, weight: float) -> np.ndarray:
    """Laplacian smoothing as a sparse mean-of-neighbours operator applied to every node."""
    hops = graph.adjacency.copy()
    hops.data[:] = 1.0
    degrees = np.asarray(hops.sum(axis=1)).ravel()
    mean_of_neighbours = sp.diags(1.0 / np.maximum(degrees, 1.0)) @ hops
    positions = np.array(graph.positions, dtype=float)
    for _ in range(iterations):
        step = mean_of_neighbours @ positions - positions
        positions[degrees == 2] += weight * step[degrees == 2]
    return positions


def test_smooth_positions_equals_the_sparse_operator_to_the_bit():
    rng = np.random.default_rng(4)
    graph = SkeletonGraph.from_image(skeletonize_2d(y_mask_2d()))
    graph = graph.with_positions(graph.positions + rng.normal(0.0, 0.3, graph.positions.shape))
    assert np.count_nonzero(graph.degrees == 2) > 50 and np.any(graph.degrees == 3)
    for iterations, weight in ((10, 0.5), (3, 0.8)):
        smoothed = smooth_positions(graph, iterations, weight)
        np.testing.assert_array_equal(smoothed.positions,
                                      _laplacian_smoothing_by_sparse_product(graph, iterations, weight))
        np.testing.assert_array_equal(smoothed.edges(), graph.edges())

"""The literal skeletons of fixtures.py give exactly the graph written beside them (Definition 1)."""

import numpy as np
import pytest

from FevarPlannerLib.graph import SkeletonGraph
from fixtures import LITERAL_SKELETONS, TINY_STAIRCASE, TINY_STAIRCASE_UNPRUNED_EDGES


@pytest.mark.parametrize("name", sorted(LITERAL_SKELETONS))
def test_literal_skeleton_gives_its_exact_graph(name):
    image, expected = LITERAL_SKELETONS[name]
    graph = SkeletonGraph.from_image(image)
    np.testing.assert_array_equal(graph.positions, expected["positions"])
    np.testing.assert_array_equal(graph.edges(), expected["edges"])
    np.testing.assert_array_equal(graph.degrees, expected["degrees"])
    weights = [graph.adjacency[a, b] for a, b in expected["edges"]]
    np.testing.assert_allclose(weights, expected["weights"], rtol=1e-15)
    assert graph.adjacency.nnz == 2 * len(expected["edges"])          # symmetric, nothing else


def test_triangle_pruning_is_what_turns_the_staircase_into_a_path():
    literal = SkeletonGraph.from_image(TINY_STAIRCASE, prune_triangles=False)
    np.testing.assert_array_equal(literal.edges(), TINY_STAIRCASE_UNPRUNED_EDGES)

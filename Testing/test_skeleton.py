"""Tests of the skeleton stage: mask clean-up, 2D/3D thinning, the grid neighbourhood.

The synthetic AAA shapes (tubes with hemispherical caps, drawn from their exact distance to
each axis segment) live in fixtures.py, shared with test_graph.py and the benchmark.
"""

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from FevarPlannerLib.io import Volume
from skimage.morphology import skeletonize as skimage_skeletonize

from FevarPlannerLib.skeleton import (ACTIVE_SET_ABOVE_PIXELS, _thin_active_set, clean_mask, grid_edges,
                                      local_radius, skeletonize_2d, skeletonize_3d, thin_zhang_suen)
from fixtures import aaa_grid, aaa_mask_3d, draw_tubes, random_masks, y_mask_2d

def neighbour_count(skeleton):
    """Number of 8/26 neighbours of every skeleton element."""
    kernel = np.ones((3,) * skeleton.ndim, dtype=int)
    return ndi.convolve(skeleton.astype(int), kernel, mode="constant")[skeleton.astype(bool)] - 1


# ---------------------------------------------------------------------------------------
# clean_mask
# ---------------------------------------------------------------------------------------

def test_clean_mask_keeps_largest_component_and_fills_holes_2d():
    mask = np.zeros((60, 60), dtype=np.uint8)
    mask[10:40, 10:40] = 1
    mask[20:25, 20:25] = 0          # a hole
    mask[50:53, 50:53] = 1          # a speck
    cleaned = clean_mask(mask, min_size=10)
    assert cleaned.dtype == bool and cleaned.shape == mask.shape
    assert cleaned[10:40, 10:40].all()
    assert not cleaned[50:53, 50:53].any()
    assert cleaned.sum() == 900


def test_clean_mask_min_size_keeps_big_components_when_not_only_largest():
    mask = np.zeros((60, 60), dtype=bool)
    mask[5:20, 5:20] = True
    mask[30:40, 30:40] = True       # 100 px
    mask[50:52, 50:52] = True       # 4 px
    cleaned = clean_mask(mask, largest_component=False, min_size=50)
    assert cleaned.sum() == 225 + 100


def test_clean_mask_fills_cavities_but_not_tunnels_3d():
    mask = np.zeros((20, 20, 20), dtype=bool)
    mask[2:18, 2:18, 2:18] = True
    mask[8:11, 8:11, 8:11] = False  # enclosed cavity
    mask[4:6, 4:6, :] = False       # tunnel through the block
    cleaned = clean_mask(mask)
    assert cleaned[8:11, 8:11, 8:11].all()
    assert not cleaned[4:6, 4:6, :].any()


def test_clean_mask_rejects_empty_nan_and_tiny():
    with pytest.raises(ValueError, match="empty"):
        clean_mask(np.zeros((10, 10)))
    with pytest.raises(ValueError, match="NaN"):
        clean_mask(np.full((10, 10), np.nan))
    tiny = np.zeros((10, 10))
    tiny[2, 2] = 1
    with pytest.raises(ValueError, match="min_size"):
        clean_mask(tiny, min_size=5)
    with pytest.raises(ValueError, match="2D or 3D"):
        clean_mask(np.ones(10))


# ---------------------------------------------------------------------------------------
# grid_edges (Definition 1)
# ---------------------------------------------------------------------------------------

def test_grid_edges_8_neighbourhood_and_triangle_pruning():
    # an L-corner: (0,0)-(0,1)-(1,1); the diagonal (0,0)-(1,1) is bypassed by the corner pixel
    points = np.array([[0, 0], [0, 1], [1, 1], [2, 2]])
    full = {tuple(e) for e in np.sort(grid_edges(points, (3, 3), prune_triangles=False), axis=1)}
    assert full == {(0, 1), (1, 2), (0, 2), (2, 3)}
    pruned = {tuple(e) for e in np.sort(grid_edges(points, (3, 3)), axis=1)}
    assert pruned == {(0, 1), (1, 2), (2, 3)}


def test_grid_edges_3d_counts_26_neighbours_of_a_full_cube():
    points = np.argwhere(np.ones((3, 3, 3), dtype=bool))
    edges = grid_edges(points, (3, 3, 3), prune_triangles=False)
    degree = np.bincount(edges.ravel(), minlength=27)
    centre = 13
    assert degree[centre] == 26 and len(edges) == (27 * 26 - sum(26 - degree)) // 2
    # pruning keeps only the 6-neighbourhood inside a full cube
    assert len(grid_edges(points, (3, 3, 3))) == 54


# ---------------------------------------------------------------------------------------
# 2D thinning
# ---------------------------------------------------------------------------------------

def test_skeletonize_2d_of_a_y_is_thin_connected_with_three_ends():
    skeleton = skeletonize_2d(y_mask_2d(), smooth_sigma=1.0)
    assert skeleton.dtype == bool and skeleton.shape == (120, 120)
    assert ndi.label(skeleton, structure=np.ones((3, 3)))[1] == 1
    counts = neighbour_count(skeleton)
    assert np.sum(counts == 1) == 3
    # no 2x2 block of skeleton pixels
    assert not (skeleton[:-1, :-1] & skeleton[1:, :-1] & skeleton[:-1, 1:] & skeleton[1:, 1:]).any()
    # the stem lies on the mask's axis u = 60
    stem = np.argwhere(skeleton[75:105])
    assert np.all(np.abs(stem[:, 1] - 60) <= 1)


def test_skeletonize_2d_downsampled_keeps_topology_and_place():
    mask = np.kron(y_mask_2d((120, 120), width=4.0), np.ones((2, 2), dtype=bool))
    fine = skeletonize_2d(mask, downsample=1)
    coarse = skeletonize_2d(mask, downsample=2)
    assert ndi.label(coarse, structure=np.ones((3, 3)))[1] == 1
    assert np.sum(neighbour_count(coarse) == 1) == 3
    distance, _ = cKDTree(np.argwhere(fine)).query(np.argwhere(coarse))
    assert np.percentile(distance, 95) <= 2.0


def test_thin_zhang_suen_equals_scikit_image_pixel_for_pixel():
    masks = list(random_masks(seed=11, count=300))
    masks += [y_mask_2d(), np.ones((9, 9), dtype=bool), np.zeros((4, 6), dtype=bool),
              draw_tubes(np.stack(np.indices((90, 140)), axis=-1).astype(float),
                         [(np.array([10.0, 10.0]), np.array([80.0, 130.0]), 14.0),
                          (np.array([45.0, 70.0]), np.array([10.0, 130.0]), 4.0)])]
    for mask in masks:
        fast = _thin_active_set(mask)       # the path of large grids, on small ones
        assert fast.dtype == bool and fast.shape == mask.shape
        np.testing.assert_array_equal(fast, skimage_skeletonize(mask))
    # a 2x2 block thins to its upper pair (the first sub-iteration takes the lower one)
    block = np.array([[0, 0, 0, 0], [0, 1, 1, 0], [0, 1, 1, 0], [0, 0, 0, 0]], dtype=bool)
    np.testing.assert_array_equal(np.argwhere(_thin_active_set(block)), [[1, 1], [1, 2]])
    # a grid large enough for the public function to take that path
    large = np.kron(masks[-1], np.ones((3, 3), dtype=bool))
    assert large.size >= ACTIVE_SET_ABOVE_PIXELS
    np.testing.assert_array_equal(thin_zhang_suen(large), skimage_skeletonize(large))


def test_skeletonize_2d_rejects_vanishing_and_3d_masks():
    hairline = np.zeros((50, 50), dtype=bool)
    hairline[25, 5:45] = True
    hairline[5:45, 25] = True
    with pytest.raises(ValueError, match="vanished"):
        skeletonize_2d(hairline, smooth_sigma=2.0)
    with pytest.raises(ValueError, match="2D"):
        skeletonize_2d(np.ones((5, 5, 5)))


# ---------------------------------------------------------------------------------------
# 3D thinning
# ---------------------------------------------------------------------------------------

def test_skeletonize_3d_of_a_straight_tube_is_its_axis():
    grid = Volume(np.zeros((40, 24, 24), dtype=np.uint8), [1.5, 1.5, 2.0], [-10.0, 5.0, 20.0], np.eye(3))
    kji = np.indices(grid.shape).reshape(3, -1).T
    points = grid.index_to_lps(kji)
    start, end = grid.index_to_lps([5, 11.5, 11.5]), grid.index_to_lps([34, 11.5, 11.5])
    mask = draw_tubes(points, [(start, end, 7.0)]).reshape(grid.shape)
    skeleton = skeletonize_3d(grid.with_array(mask.astype(np.uint8)))
    assert skeleton.array.dtype == np.uint8 and skeleton.shape == grid.shape
    np.testing.assert_allclose(skeleton.origin, grid.origin)
    lps = skeleton.index_to_lps(np.argwhere(skeleton.array))
    # on the axis within a voxel, spanning the tube's axis within a voxel at each end
    assert np.all(np.abs(lps[:, 0] - start[0]) <= 1.5) and np.all(np.abs(lps[:, 1] - start[1]) <= 1.5)
    assert lps[:, 2].min() == pytest.approx(start[2], abs=2.0)
    assert lps[:, 2].max() == pytest.approx(end[2], abs=2.0)
    assert np.sum(neighbour_count(skeleton.array) == 1) == 2


def test_skeletonize_3d_smoothing_and_errors():
    grid = aaa_grid(3.0)
    mask = aaa_mask_3d(3.0)
    smooth = skeletonize_3d(mask, smooth_sigma=1.5)
    assert ndi.label(smooth.array, structure=np.ones((3, 3, 3)))[1] == 1
    assert 40 < smooth.array.sum() < 400
    with pytest.raises(ValueError, match="empty"):
        skeletonize_3d(grid)


def test_skeletonize_3d_survives_two_voxel_thick_parts():
    # scikit-image's Lee thinning alone empties a 4x4 column (issue #3757)
    column = np.zeros((30, 12, 12), dtype=np.uint8)
    column[3:27, 4:8, 4:8] = 1
    grid = Volume(column, [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], np.eye(3))
    skeleton = skeletonize_3d(grid).array
    assert skeleton.sum() >= 18
    assert ndi.label(skeleton, structure=np.ones((3, 3, 3)))[1] == 1
    assert np.sum(neighbour_count(skeleton) == 1) == 2


def test_nonzero_linear_matches_flatnonzero():
    from FevarPlannerLib.skeleton import nonzero_linear
    rng = np.random.default_rng(3)
    for shape, dtype in [((7, 5, 3), np.uint8), ((13, 11), bool), ((4, 6), np.float32)]:
        array = (rng.random(shape) > 0.9).astype(dtype)
        np.testing.assert_array_equal(nonzero_linear(array), np.flatnonzero(array))


# ---------------------------------------------------------------------------------------
# local_radius
# ---------------------------------------------------------------------------------------

def test_local_radius_is_the_distance_to_the_background():
    """Against the exact distance transform: a disc, a bar, and points outside."""
    mask = np.zeros((80, 120), dtype=bool)
    rr, cc = np.ogrid[:80, :120]
    mask |= (rr - 40) ** 2 + (cc - 30) ** 2 <= 15 ** 2
    mask[30:41, 50:115] = True                      # a bar 11 rows thick
    points = np.array([[40, 30], [35, 80], [30, 80], [5, 5], [40, 44]])
    radii = local_radius(mask, points)
    exact = ndi.distance_transform_edt(mask)[tuple(points.T)]
    np.testing.assert_allclose(radii[:3], exact[:3], atol=1.5)
    assert radii[0] == pytest.approx(15.0, abs=1.0) and radii[1] == pytest.approx(6.0, abs=0.5)
    assert radii[3] == 0.0
    assert abs(radii[4] - exact[4]) <= 0.75


def test_local_radius_in_3d_uses_the_spacing():
    mask = np.zeros((20, 30, 30), dtype=bool)
    kk, jj, ii = np.ogrid[:20, :30, :30]
    mask |= ((jj - 15) * 0.5) ** 2 + ((ii - 15) * 0.5) ** 2 <= 5.0 ** 2     # a rod along k, radius 5 mm
    radii = local_radius(mask, np.array([[10, 15, 15]]), spacing=(2.0, 0.5, 0.5))
    assert radii[0] == pytest.approx(5.25, abs=0.5)
    with pytest.raises(ValueError, match="outside the mask"):
        local_radius(mask, np.array([[20, 0, 0]]))

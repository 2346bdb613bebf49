"""Tests of the skeleton stage: mask clean-up, 2D/3D thinning, the grid neighbourhood.

The synthetic AAA shapes defined here (tubes with hemispherical caps, drawn from their exact
distance to each axis segment) are shared with test_graph.py and the benchmark.
"""

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from FevarPlannerLib.io import Volume
from FevarPlannerLib.projection import project
from FevarPlannerLib.skeleton import clean_mask, grid_edges, skeletonize_2d, skeletonize_3d

# ---------------------------------------------------------------------------------------
# Synthetic AAA: axis segments (start, end, radius) in LPS mm. +x = patient left,
# -y = anterior, +z = superior. Renals run exactly along x and iliacs at exactly 45 degrees
# in the x-z plane, so their digital skeletons have no staircase error.
# ---------------------------------------------------------------------------------------

TOP = np.array([0.0, 0.0, 100.0])
RENAL_LEFT_ORIGIN = np.array([0.0, 0.0, 60.0])
RENAL_RIGHT_ORIGIN = np.array([0.0, 0.0, 51.0])
BIFURCATION = np.array([0.0, 0.0, -30.0])
TIPS = {
    "aorta": TOP,
    "renal_left": np.array([40.0, 0.0, 60.0]),
    "renal_right": np.array([-40.0, 0.0, 51.0]),
    "iliac_left": np.array([45.0, 0.0, -75.0]),
    "iliac_right": np.array([-45.0, 0.0, -75.0]),
}
ORIGINS = {"aorta": RENAL_LEFT_ORIGIN, "renal_left": RENAL_LEFT_ORIGIN, "renal_right": RENAL_RIGHT_ORIGIN,
           "iliac_left": BIFURCATION, "iliac_right": BIFURCATION}
TRUE_LENGTHS = {name: float(np.linalg.norm(TIPS[name] - ORIGINS[name])) for name in TIPS}
SAC_CENTRE, SAC_RADIUS = np.array([0.0, 0.0, 12.0]), 22.0


def aaa_segments(extra_branches=False):
    """(start, end, radius) of the AAA tubes; extras: SMA and two internal iliacs."""
    segments = [
        (TOP, BIFURCATION, 10.0),
        (RENAL_LEFT_ORIGIN, TIPS["renal_left"], 3.5),
        (RENAL_RIGHT_ORIGIN, TIPS["renal_right"], 3.5),
        (BIFURCATION, TIPS["iliac_left"], 5.0),
        (BIFURCATION, TIPS["iliac_right"], 5.0),
    ]
    if extra_branches:
        segments += [
            (np.array([0.0, 0.0, 78.0]), np.array([0.0, -24.0, 78.0]), 3.0),        # SMA, anterior
            (np.array([27.0, 0.0, -57.0]), np.array([27.0, 18.0, -57.0]), 2.5),     # internal iliac L
            (np.array([-27.0, 0.0, -57.0]), np.array([-27.0, 18.0, -57.0]), 2.5),   # internal iliac R
        ]
    return segments


def draw_tubes(points, segments, sphere=None):
    """Boolean membership of ``points`` (..., d) in the union of capsules (and a ball)."""
    inside = np.zeros(points.shape[:-1], dtype=bool)
    for start, end, radius in segments:
        axis = end - start
        t = np.clip(((points - start) @ axis) / (axis @ axis), 0.0, 1.0)
        inside |= np.linalg.norm(points - start - t[..., None] * axis, axis=-1) <= radius
    if sphere is not None:
        centre, radius = sphere
        inside |= np.linalg.norm(points - centre, axis=-1) <= radius
    return inside


def aaa_grid(spacing=1.5):
    """An LPS-aligned grid around the synthetic AAA."""
    lo, hi = np.array([-60.0, -36.0, -90.0]), np.array([60.0, 36.0, 116.0])
    shape_ijk = np.floor((hi - lo) / spacing).astype(int) + 1
    return Volume(np.zeros(shape_ijk[::-1], dtype=np.uint8), [spacing] * 3, lo, np.eye(3))


def aaa_mask_3d(spacing=1.5, extra_branches=False, sac=True, cut=None):
    """The AAA lumen as a uint8 Volume; ``cut=(z_lo, z_hi, side)`` empties a slab of one iliac."""
    grid = aaa_grid(spacing)
    kji = np.indices(grid.shape).reshape(3, -1).T
    points = grid.index_to_lps(kji)
    mask = draw_tubes(points, aaa_segments(extra_branches), (SAC_CENTRE, SAC_RADIUS) if sac else None)
    if cut is not None:
        z_lo, z_hi, side = cut
        mask &= ~((points[:, 2] >= z_lo) & (points[:, 2] <= z_hi) & (np.sign(points[:, 0]) == side))
    return grid.with_array(mask.reshape(grid.shape).astype(np.uint8))


def aaa_mask_2d(P, shape, extra_branches=False, sac=True):
    """The AAA projected through ``P`` and drawn as a 2D mask (radii scaled by magnification)."""
    rows, cols = shape
    uv = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).astype(float)
    scale = np.linalg.norm(project(P, [1.0, 0, 0]) - project(P, [0.0, 0, 0]))
    segments = [(project(P, a), project(P, b), r * scale) for a, b, r in aaa_segments(extra_branches)]
    sphere = (project(P, SAC_CENTRE), SAC_RADIUS * scale) if sac else None
    return draw_tubes(uv, segments, sphere)


def y_mask_2d(shape=(120, 120), width=4.0):
    """A 2D Y: stem from (60, 110) up to (60, 60), arms to (20, 15) and (100, 15) as (u, v)."""
    rows, cols = shape
    uv = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).astype(float)
    fork = np.array([60.0, 60.0])
    segments = [(np.array([60.0, 110.0]), fork, width), (fork, np.array([20.0, 15.0]), width),
                (fork, np.array([100.0, 15.0]), width)]
    return draw_tubes(uv, segments)


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

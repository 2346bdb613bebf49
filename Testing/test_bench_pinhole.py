"""The bench-phantom kind (scenarios.bench, issue 10): a short pinhole that geometry.json
expresses exactly, the raw thinned voxel skeleton, the JPEG-damaged label and the reader
that no longer takes its halo for vessel, and the other kinds' seed streams kept."""

from __future__ import annotations

import numpy as np
import pytest

from FevarPlannerLib import io, plausibility, scenarios
from FevarPlannerLib.io.fluoro import read_mask_2d
from FevarPlannerLib.projection import project, read_geometry_json, source_position, write_geometry_json
from FevarPlannerLib.scenarios import bench
from FevarPlannerLib.scenarios.frames import paint_capsules


def test_new_kind_is_last_and_the_other_kinds_draw_as_before():
    assert scenarios.KINDS[-1] == "bench_pinhole"
    # seeds drawn before the kind was added (main at e0f5294): appending it changed no stream
    assert [s.seed for s in scenarios.plan_scenarios("out_of_plane", 2, 0)] == [1722792822, 1421746521]
    assert [s.seed for s in scenarios.plan_scenarios("patient_like", 2, 0)] == [1200917762, 565090682]
    assert scenarios.plan_scenarios("clipped", 1, 0)[0].sod_mm == pytest.approx(790.879, abs=1e-3)


def test_bench_plan_is_a_short_pinhole_with_strong_perspective():
    for scenario in scenarios.plan_scenarios("bench_pinhole", 4, 5):
        assert 180.0 <= scenario.sod_mm <= 280.0
        assert 1.08 <= scenario.sid_mm / scenario.sod_mm <= 1.2
        assert scenario.info["frame_px"] == 512 and 70 <= scenario.info["jpeg_quality"] <= 85
        assert "geometry" not in scenario.info       # moved onto the scenario's C-arm fields
        carm, P = bench.fixed_carm(scenario, scenario.views[0], np.zeros(3))
        assert (carm.rows, carm.cols) == (512, 512)
        assert np.linalg.norm(source_position(P)) == pytest.approx(scenario.sod_mm, rel=1e-9)
        # magnification changes 0.36-0.56 % per mm of depth (clinical SOD 760 mm: 0.13 %)
        assert 0.0035 < bench.depth_magnification_per_mm(P, np.zeros(3)) < 0.0056


def _authors_pinhole(n: int, depth: float) -> np.ndarray:
    """The authors' projection as a 3x4 on voxel indices (x, y, z) of an n-cube: normalised
    x / n - 0.5, rotated by R0, shifted by (0, 0, depth), u = X / Z, pixel = (u + 0.5) n."""
    R0 = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    K = np.array([[n, 0.0, n / 2.0], [0.0, n, n / 2.0], [0.0, 0.0, 1.0]])
    Rt = np.hstack([R0 / n, (np.array([0.0, 0.0, depth]) - R0 @ np.full(3, 0.5))[:, None]])
    return K @ Rt


def test_geometry_json_expresses_the_short_pinhole_exactly(tmp_path):
    n, spacing, depth = 64, 0.4526, 0.9
    volume = io.Volume(np.zeros((n, n, n), dtype=np.uint8), (spacing,) * 3, np.array([-10.0, 5.0, -200.0]), np.eye(3))
    P_index = _authors_pinhole(n, depth)
    index_to_lps = volume.index_to_lps_matrix                         # (i, j, k, 1) -> LPS
    P = P_index @ np.linalg.inv(index_to_lps)
    write_geometry_json(tmp_path / "geometry.json", P)
    P_read = read_geometry_json(tmp_path / "geometry.json")
    ijk = np.random.default_rng(0).uniform(0, n - 1, size=(200, 3))
    lps = volume.index_to_lps(ijk[:, ::-1])
    normalised = (np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) @ (ijk / n - 0.5).T).T + [0, 0, depth]
    expected = (normalised[:, :2] / normalised[:, 2:] + 0.5) * n
    assert np.abs(project(P_read, lps) - expected).max() < 1e-9
    # the source sits 0.9 n voxels from the volume's centre, as in the authors' set-up
    centre = volume.index_to_lps(np.full((1, 3), n / 2.0))[0]
    assert np.linalg.norm(source_position(P_read) - centre) == pytest.approx(depth * n * spacing, rel=1e-9)


def _tube_mask(shape=(48, 48)) -> np.ndarray:
    mask = np.zeros(shape, dtype=bool)
    paint_capsules(mask, np.array([[4.0, 10.0], [43.0, 30.0]]), np.array([5.0, 3.0]))
    return mask


def test_jpeg_label_keeps_a_halo_that_the_reader_thresholds_away(tmp_path):
    clean = _tube_mask((96, 96))
    grey = bench.jpeg_damaged(clean, 75)
    assert grey.dtype == np.uint8 and len(np.unique(grey)) > 8
    halo = np.count_nonzero((grey != 0) & ~clean)
    assert halo > 0.05 * clean.sum()                 # "non-zero = vessel" would widen every vessel
    assert np.array_equal(grey > 127, clean)         # ringing of a 0/255 label never crosses mid-grey
    io.write_png(tmp_path / "fluoro_mask.png", grey)
    assert np.array_equal(read_mask_2d(tmp_path / "fluoro_mask.png"), clean)


def test_a_label_mask_with_few_values_stays_non_zero_is_vessel(tmp_path):
    labels = np.zeros((32, 32), dtype=np.uint8)
    labels[4:10, 4:20], labels[20:24, 2:30] = 1, 2      # two label values: both are vessel
    io.write_png(tmp_path / "fluoro_mask.png", labels)
    assert np.array_equal(read_mask_2d(tmp_path / "fluoro_mask.png"), labels != 0)


def test_rough_lumen_thins_to_a_raw_one_voxel_skeleton(tmp_path):
    volume = io.Volume(np.zeros((60, 40, 40), dtype=np.uint8), (0.45,) * 3, np.zeros(3), np.eye(3))
    lumen = np.zeros(volume.shape, dtype=bool)
    paint_capsules(lumen, np.array([[5.0, 20.0, 20.0], [54.0, 20.0, 20.0]]), np.array([11.0, 11.0]))
    rough = bench.roughened(volume.with_array(lumen.astype(np.uint8)), np.random.default_rng(3))
    changed = np.count_nonzero(rough.array.astype(bool) != lumen) / lumen.sum()
    assert 0.02 < changed < 0.5                       # the wall moved, the tube stayed
    skeleton = bench.thinned_skeleton(rough)
    assert 30 <= int(skeleton.array.sum()) <= 200
    plausibility.check_skeleton_is_thin(skeleton, tmp_path / "skeleton3d.nrrd")      # no error: thin
    io.write_volume(tmp_path / "skeleton3d.nrrd", skeleton)
    assert np.array_equal(io.read_volume(tmp_path / "skeleton3d.nrrd").array.astype(bool), skeleton.array.astype(bool))


def test_axial_depth_floor_is_zero_for_a_move_parallel_to_a_short_pinholes_detector():
    from FevarPlannerLib import evaluation
    from FevarPlannerLib.centerline import Centerline
    from FevarPlannerLib.projection import CArmGeometry, projection_matrix_from_carm

    P = projection_matrix_from_carm(CArmGeometry(230.0, 208.5, (0.45, 0.45), 0.0, 0.0, 512, 512))
    z = np.linspace(-60.0, 60.0, 121)
    edges = np.column_stack([np.arange(120), np.arange(1, 121)])
    pre = Centerline(np.column_stack([np.full_like(z, 60.0), np.zeros_like(z), z]), edges, ["iliac_left"] * 121)
    moved = pre.with_points(pre.points + [10.0, 0.0, 0.0])   # AP view: x is parallel to the detector
    axial = evaluation.depth_floor(pre, moved, P, depth="axial")
    ranged = evaluation.depth_floor(pre, moved, P)
    assert axial["max"] < 1e-9
    # keeping the distance from the source instead puts the oracle off by about d x / D
    assert 2.0 < ranged["mean"] < 4.5
    with pytest.raises(ValueError, match="depth measure"):
        evaluation.depth_floor(pre, moved, P, depth="radial")


def test_a_face_connected_staircase_skeleton_is_thin_and_a_solid_is_not(tmp_path):
    grid = {"spacing": (0.45,) * 3, "origin": np.zeros(3), "direction": np.eye(3)}
    stairs = np.zeros((8, 40, 40), dtype=np.uint8)
    for step in range(38):          # x+1, then y+1: every inner voxel has 3-4 26-neighbours
        stairs[4, step // 2 + step % 2, step // 2] = 1
    kernel = np.ones((3, 3, 3))
    kernel[1, 1, 1] = 0
    from scipy import ndimage

    crowded = ndimage.convolve(stairs, kernel.astype(np.uint8), mode="constant")[stairs > 0] > 2
    assert crowded.mean() > 0.8                     # refused by a count of 26-neighbours
    plausibility.check_skeleton_is_thin(io.Volume(stairs, **grid), tmp_path / "skeleton3d.nrrd")
    solid = np.zeros((12, 12, 12), dtype=np.uint8)
    solid[3:9, 3:9, 3:9] = 1
    with pytest.raises(io.InputError, match=r"100% of its 216 voxels lie in solid 2x2x2 blocks"):
        plausibility.check_skeleton_is_thin(io.Volume(solid, **grid), tmp_path / "skeleton3d.nrrd")


def _tube(grid, start, stop, radius) -> np.ndarray:
    """Voxels (``grid``: x, y, z in mm, each shaped like the volume) within ``radius`` of a segment."""
    start, stop = np.asarray(start, dtype=float), np.asarray(stop, dtype=float)
    axis = (stop - start) / np.linalg.norm(stop - start)
    offset = np.stack(grid, axis=-1) - start
    along = np.clip(offset @ axis, 0.0, np.linalg.norm(stop - start))
    return np.linalg.norm(offset - along[..., None] * axis, axis=-1) <= radius


def _aortic_trunk_targets(P):
    """Aorta (radius 6 mm, 1 mm voxels) with a renal leaving backwards and down at z = 75 and
    iliacs leaving backwards at z = 30, thinned in 3D and, projected frontally, in 2D: the 3D
    trunk between the two junctions: its projection's rows through :data:`P_FRONTAL`
    and the rows of its eq. (5) targets on the 2D trunk (with ``P`` for the fit, or None)."""
    from skimage.morphology import skeletonize

    from FevarPlannerLib import graph
    from FevarPlannerLib.conventions import IOTA_MM, LPS_DIRECTIONS
    from FevarPlannerLib.matching import paper

    nz, ny, nx = 110, 40, 80
    z, y, x = np.mgrid[0:nz, 0:ny, 0:nx].astype(float)
    lumen = _tube((x, y, z), (40, 20, 30), (40, 20, 100), 6.0) | _tube((x, y, z), (40, 20, 75), (66, 35, 66), 2.5)
    for side in (-1.0, 1.0):
        lumen |= _tube((x, y, z), (40, 20, 30), (40 + side * 14.3, 28, 9.5), 4.0)
    g3 = graph.SkeletonGraph.from_volume(io.Volume(skeletonize(lumen).astype(np.uint8), np.ones(3), np.zeros(3), np.eye(3)))
    g3 = graph.smooth_positions(graph.classify(g3, iota=IOTA_MM, directions=LPS_DIRECTIONS, tau=4).graph, 10)
    g2 = graph.skeleton_graph_2d(lumen.any(axis=1)[::-1], radii=True)      # rows run down z
    c2 = graph.classify(g2, iota=IOTA_MM, directions={"left": np.array([1.0, 0.0]), "superior": np.array([0.0, -1.0])}, tau=4)
    g2 = graph.smooth_positions(c2.graph, 10)
    c3 = graph.classify(g3, iota=IOTA_MM, directions=LPS_DIRECTIONS, tau=4)
    nodes3 = paper._oriented_trunk(g3, c3.trunks[0], np.array([0.0, 0.0, 1.0]))
    nodes2 = paper._oriented_trunk(g2, c2.trunks[0], np.array([0.0, -1.0]))
    chain, path = paper._sliding_trunk_lengths(g3, g2, [(nodes3, nodes2)], P)
    inside, low, high, w_low, w_high = paper._assign_by_arc_length(path, nodes2, g2.positions[nodes2])
    rows = w_low * g2.positions[low, 1] + w_high * g2.positions[high, 1]
    return project(P_FRONTAL, g3.positions[chain])[inside, 1], rows[inside]


#: Frontal and orthographic, 1 px per mm: u = x, row = 109 - z (the mask's rows run down z).
P_FRONTAL = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 109.0], [0.0, 0.0, 0.0, 1.0]])


def test_trunk_targets_follow_the_projection_where_2d_and_3d_thinning_place_junctions_apart():
    """The anatomy does not move, so each 3D node's target is its own projection. The 2D
    thinning puts both junctions a pixel lower than the 3D one does: eq. (5), pinning the
    trunk's ends to the 2D junctions, misplaces the targets by a pixel. With the knots fitted
    to the projected trunk (matching.paper._sliding_trunk_lengths with P) the bottom end,
    whose 2D junction lies outwards (beyond where the 3D one belongs), slides in and its
    targets are right; the top end, whose 2D junction lies inwards, stays pinned (an end
    slides inwards only): 0.5 px."""
    projected, eq5 = _aortic_trunk_targets(None)
    assert np.abs(eq5 - projected).mean() == pytest.approx(1.0, abs=0.1)
    assert abs(eq5[-1] - projected[-1]) == pytest.approx(1.0, abs=0.1)
    projected, fitted = _aortic_trunk_targets(P_FRONTAL)
    assert np.abs(fitted - projected).mean() == pytest.approx(0.5, abs=0.1)
    assert abs(fitted[-1] - projected[-1]) < 0.05 and abs(fitted[0] - projected[0]) == pytest.approx(1.0, abs=0.1)

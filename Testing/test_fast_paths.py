"""Each shortcut of the per-frame path (issue 10) gives what the plain computation gives.

The per-frame speed-ups replace whole-grid or general computations with ones restricted to
what can change; here each is checked against the plain formulation written out in the
test, on small generated masks and graphs, to the bit.
"""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy import ndimage as ndi
from scipy.linalg import cholesky_banded
from scipy.sparse import csgraph

from FevarPlannerLib import pipeline
from FevarPlannerLib.deformation import ThinPlateSpline3D, fill_unassigned
from FevarPlannerLib.deformation import fill as fill_module
from FevarPlannerLib.deformation.energy import _build_model
from FevarPlannerLib.projection import homogeneous_columns, pull_back_columns
from FevarPlannerLib.deformation import deform_assigned
from FevarPlannerLib.deformation import solve as solve_module
from FevarPlannerLib.deformation.solve import _BandedPreconditioner
from FevarPlannerLib.deformation.tps import FixedControlsTPS
from FevarPlannerLib.graph import SkeletonGraph, skeleton_graph_2d, smooth_positions
from FevarPlannerLib.graph.skeleton_graph import _walk_back
from FevarPlannerLib.pipeline import fallback
from FevarPlannerLib.segmentation import fluoro
from FevarPlannerLib.skeleton import _euler_number_2d, clean_mask, skeleton_2d_box, skeletonize_2d
from fixtures import carm, drawn_mask, phantom_case, preop_model, random_masks, vessel_tree, y_mask_2d


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


def test_euler_number_counts_components_minus_holes():
    for mask in random_masks(seed=2, count=200):
        components = ndi.label(mask, structure=np.ones((3, 3)))[1]
        background, regions = ndi.label(~np.pad(mask, 1))
        holes = regions - 1 if mask.size else 0
        assert _euler_number_2d(mask) == components - holes


def test_clean_mask_equals_dropping_small_pieces_then_filling_holes():
    checked = 0
    for mask in random_masks(seed=3, count=200):
        labels, count = ndi.label(mask, structure=np.ones((3, 3)))
        sizes = np.bincount(labels.ravel(), minlength=count + 1)
        sizes[0] = 0
        expected = ndi.binary_fill_holes((sizes >= 8)[labels])
        if expected.sum() < 8:
            continue
        np.testing.assert_array_equal(clean_mask(mask, largest_component=False, min_size=8), expected)
        checked += 1
    assert checked > 100


def test_upsampling_a_sparse_soft_mask_thresholds_like_the_full_interpolation():
    rng = np.random.default_rng(8)
    for trial in range(60):
        coarse_shape = tuple(rng.integers(1, 40, size=2))
        factor = int(rng.integers(1, 5))
        shape = tuple(n * factor - int(rng.integers(0, factor)) for n in coarse_shape)
        blobs = ndi.gaussian_filter((rng.random(coarse_shape) < 0.05).astype(np.float32), 0.7) * 4.0
        soft = np.where(rng.random() < 0.1, np.zeros_like(blobs), blobs).astype(np.float32)
        level = float(rng.choice([0.0, 0.25, 0.5]))
        np.testing.assert_array_equal(fluoro._upsample_above(soft, factor, shape, level),
                                      fluoro._upsample(soft, factor, shape) > level)


def test_walk_back_follows_dijkstra_predecessors_to_the_source():
    graph = SkeletonGraph.from_image(skeletonize_2d(y_mask_2d()))
    _, predecessors = csgraph.dijkstra(graph.adjacency, indices=0, return_predecessors=True)
    for node in (0, 7, len(graph) - 1, int(np.argmax(predecessors))):
        path = [node]
        while predecessors[path[-1]] >= 0:
            path.append(int(predecessors[path[-1]]))
        walked = _walk_back(predecessors, node)
        assert walked.dtype == np.int64
        np.testing.assert_array_equal(walked, path)


def test_with_positions_equals_rebuilding_the_graph_from_its_edges():
    rng = np.random.default_rng(6)
    graph = SkeletonGraph.from_image(skeletonize_2d(y_mask_2d()))
    positions = graph.positions + rng.normal(0.0, 0.4, graph.positions.shape)
    positions[3] = positions[graph.adjacency.indices[graph.adjacency.indptr[3]]]      # a zero-length edge
    moved = graph.with_positions(positions)
    rebuilt = SkeletonGraph(positions, SkeletonGraph._weighted_adjacency(positions, graph.edges()),
                            graph.grid_indices, graph.unit_mm, graph.radii)
    for part in ("indptr", "indices", "data"):
        mine, plain = getattr(moved.adjacency, part), getattr(rebuilt.adjacency, part)
        assert mine.dtype == plain.dtype
        np.testing.assert_array_equal(mine, plain)
    np.testing.assert_array_equal(moved.degrees, rebuilt.degrees)
    np.testing.assert_array_equal(moved.positions, positions)
    assert moved.dim == 2 and moved.unit_mm == graph.unit_mm and moved.grid_indices is graph.grid_indices
    assert moved.adjacency.data is not graph.adjacency.data


def _never_worse_than_sv_vessel_by_vessel(result, alternatives, preop, views):
    """The plausibility check with every vessel's fit measured on its own (one query per vessel)."""
    sv = preop.centerline.points
    vessels = sorted((v for v in fallback._vessels(preop.centerline) if v.label != "other"),
                     key=lambda v: v.label != "aorta")
    result, warnings = result.copy(), []
    sv_fits = fallback._fits_px(sv, [vessel.nodes for vessel in vessels], views, preop.kept)
    for vessel, sv_fit in zip(vessels, sv_fits):
        reason, _ = fallback._judge(result, vessel, sv, sv_fit, views, preop.kept)
        if reason is None:
            continue
        best, best_fit, best_name = None, np.inf, None
        for points, name in list(alternatives()) + [(sv, fallback.SV_NAME)]:
            moved = fallback._replaced(result, points, vessel)
            why, fit = fallback._judge(moved, vessel, sv, sv_fit, views, preop.kept)
            if why is None and fit < best_fit:
                best, best_fit, best_name = moved, fit, name
        if best is None:
            best, best_name = fallback._replaced(result, sv, vessel), fallback.SV_NAME
        result = best
        warnings.append(f"{vessel.label}: {reason}; replaced by {best_name}")
    return result, warnings


def test_plausibility_fits_in_one_query_equal_the_vessel_by_vessel_check():
    case = phantom_case("fallback", seed=11)
    preop = preop_model(case)
    mask = drawn_mask(preop.centerline, case.P_true, (case.carm.rows, case.carm.cols))
    view = pipeline._prepare_view(preop, mask, case.P_true, "main", None, "proposed", False, {})
    result = pipeline.register_frame(preop, mask, case.P_true).deformed.points
    vessels = {v.label: v for v in fallback._vessels(preop.centerline)}
    rng = np.random.default_rng(2)
    variants = [result]
    for labels, scale, shift in ((("iliac_left",), 1.2, 0.0), (("aorta",), 1.0, 9.0),
                                 (("renal_right", "iliac_right"), 0.9, 4.0), (("aorta", "renal_left"), 1.1, 6.0)):
        changed = result.copy()
        for label in labels:
            nodes = vessels[label].nodes
            root = changed[nodes].mean(axis=0)
            changed[nodes] = root + scale * (changed[nodes] - root) + shift * rng.normal(size=3)
        variants.append(changed)
    replaced = 0
    for changed in variants:
        alternatives = lambda: [(result, "registration"), (variants[2], "shifted aorta")]     # noqa: E731
        fast, warnings = fallback._never_worse_than_sv(changed, alternatives, preop, [view])
        plain, plain_warnings = _never_worse_than_sv_vessel_by_vessel(changed, alternatives, preop, [view])
        np.testing.assert_array_equal(fast, plain)
        assert warnings == plain_warnings
        replaced += len(warnings)
    assert replaced >= 4


def test_banded_hessian_summed_by_bincount_equals_np_add_at():
    """The preconditioner's band storage: every Hessian entry added into its place in order."""
    tree = vessel_tree(160)
    rng = np.random.default_rng(9)
    extra = [(carm(50.0), rng.normal(256.0, 40.0, (len(tree.points), 2)), rng.random(len(tree.points)))]
    model = _build_model(tree.points, rng.normal(256.0, 40.0, (len(tree.points), 2)), tree.edges, carm(0.0),
                         500.0, 10.0, None, None, extra)
    preconditioner = _BandedPreconditioner(model, 0.1)
    assert preconditioner.usable
    rows, cols, values = preconditioner._hessian_blocks(model, model.points, 0.1)
    upper = rows <= cols
    assert len(np.unique(np.c_[rows[upper], cols[upper]], axis=0)) < np.count_nonzero(upper)     # places shared
    band = np.zeros((preconditioner.band + 1, 3 * len(tree.points)))
    np.add.at(band, (preconditioner.band + rows[upper] - cols[upper], cols[upper]), values[upper])
    np.testing.assert_array_equal(preconditioner.factor, cholesky_banded(band, lower=False, check_finite=False))


def test_skeleton_graph_from_the_skeleton_box_equals_the_full_grid_graph():
    for mask in [y_mask_2d(), np.pad(y_mask_2d(width=6.0), ((30, 5), (3, 40)))]:
        mask = mask.copy()
        mask[-12:-4, 2:9] = True                 # a second piece, away from the tree
        plain = SkeletonGraph.from_image(skeletonize_2d(mask), 0.4, mask=mask)
        box, thin = skeleton_2d_box(mask)
        assert thin.shape == tuple(b.stop - b.start for b in box) != mask.shape
        fast = skeleton_graph_2d(mask, pixel_size=0.4, radii=True)
        assert len(fast) == len(plain) > 50 and fast.unit_mm == plain.unit_mm
        for part in ("positions", "grid_indices", "radii", "degrees"):
            np.testing.assert_array_equal(getattr(fast, part), getattr(plain, part))
        for part in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(fast.adjacency, part), getattr(plain.adjacency, part))
        assert skeleton_graph_2d(mask).radii is None


def _two_raw_views():
    """A phantom's pre-operative model and its intra-operative anatomy rendered as raw frames
    seen AP and LAO 30 (:func:`phantom.render_fluoro`), with each view's projected prior."""
    from dataclasses import replace

    from FevarPlannerLib import phantom
    from FevarPlannerLib.pipeline import frame
    from FevarPlannerLib.projection import projection_matrix_from_carm
    from FevarPlannerLib.quality import FluoroPrior

    case = phantom_case("worker", seed=11)
    preop = preop_model(case)
    sources = []
    for name, angle in (("ap", 0.0), ("lao30", 30.0)):
        params = replace(case.params, primary_angle_deg=angle)
        isocentre = case.grid.center_lps()
        geometry = phantom.fit_detector(case.intraop, params, isocentre)
        P = projection_matrix_from_carm(geometry, isocentre)
        image, _ = phantom.render_fluoro(case.intraop, P, geometry, params, np.random.default_rng(5))
        sources.append(frame.ViewSource(name, P, image, prior=FluoroPrior.from_centerline(preop.centerline, P),
                                           check=True))
    return preop, sources


def _same_outcome(remote, local):
    np.testing.assert_array_equal(remote.mask, local.mask)
    assert (remote.mask_error, remote.check_error, remote.view_error) == (None, None, None)
    assert (local.mask_error, local.check_error, local.view_error) == (None, None, None)
    for part in ("P", "visible"):
        np.testing.assert_array_equal(getattr(remote.view, part), getattr(local.view, part))
    np.testing.assert_array_equal(remote.view.g2.positions, local.view.g2.positions)
    assert [b.label for b in remote.view.c2.branches] == [b.label for b in local.view.c2.branches]
    assert len(remote.view.candidates) == len(local.view.candidates) >= 1


@pytest.fixture
def view_worker():
    """The view worker module, switched on for the test and back to its default after it."""
    from FevarPlannerLib.pipeline import workers

    workers.set_enabled(True)
    yield workers
    workers.set_enabled(None)


def test_the_view_worker_prepares_and_registers_a_second_view_as_this_process_does(view_worker, monkeypatch):
    """Issue 10: the second view's 2D side in the worker process (mask from the raw frame, frame
    check, skeleton, Algorithm 1, pose check) and the registration after it, to the bit."""
    from FevarPlannerLib.pipeline import frame

    workers = view_worker
    preop, sources = _two_raw_views()
    assert workers.wait_until_ready(120.0)
    sent = []
    submit = workers.submit
    monkeypatch.setattr(workers, "submit", lambda *args: sent.append(submit(*args)) or sent[-1])
    outcomes = frame.prepare_views(preop, sources)
    assert [job.remote for job in sent] == [True, False]    # the second view; the first one's check (worker busy)
    workers.set_enabled(False)
    serial = frame.prepare_views(preop, sources)
    assert not any(job.remote for job in sent[2:]) and len(sent) == 5
    for remote, local in zip(outcomes, serial):
        _same_outcome(remote, local)
    parallel, alone = (frame.register_prepared(preop, found) for found in (outcomes, serial))
    np.testing.assert_array_equal(parallel.deformed.points, alone.deformed.points)
    assert (parallel.correspondence, parallel.warnings, parallel.energy) == (alone.correspondence, alone.warnings,
                                                                             alone.energy)


def test_the_view_worker_ends_with_shutdown_and_stays_off_when_switched_off(view_worker, monkeypatch):
    workers = view_worker
    assert workers.wait_until_ready(120.0)
    process = workers._state["worker"]._process
    assert process.poll() is None
    workers.shutdown()
    assert process.poll() is not None and workers._state["worker"] is None
    workers.set_enabled(None)
    monkeypatch.setenv(workers.ENV_SWITCH, "0")
    assert not workers.enabled()
    assert not workers.submit(len, [1, 2]).remote and workers._state["worker"] is None


def test_a_job_whose_worker_died_is_done_here(view_worker):
    """The worker killed in the middle of a job: the job runs in this process instead."""
    workers = view_worker
    assert workers.wait_until_ready(120.0)
    worker = workers._state["worker"]
    matrix = np.random.default_rng(3).normal(size=(500, 500))
    job = workers.submit(np.linalg.svd, matrix, False, False)     # singular values, killed while at it
    assert job.remote
    worker._process.kill()
    np.testing.assert_array_equal(job.result(), np.linalg.svd(matrix, False, False))
    assert workers._state["worker"] is not worker and not worker.alive()
    assert workers.submit(np.add, np.arange(3), 1).result().tolist() == [1, 2, 3]


def test_a_job_packed_with_its_arrays_in_the_shared_file_unpacks_to_the_same_job():
    import os

    from FevarPlannerLib.pipeline import workers

    rng = np.random.default_rng(4)
    frame = rng.integers(0, 4096, (300, 400), dtype=np.uint16)
    job = (7, {"frame": frame, "mask": frame > 2000, "small": np.arange(5.0), "fortran": np.asfortranarray(
        rng.normal(size=(200, 90)))}, "name")
    shared = workers._shared_file()
    try:
        for target in ([shared] if shared is not None else []) + [None]:
            data, places = workers._packed(job, target)
            assert (places is None) == (target is None)
            if target is not None:
                assert len(places) == 3 and len(data) < 10_000       # the three large arrays outside the pickle
            token, arrays, name = workers._unpacked((data, places), target)
            assert (token, name, sorted(arrays)) == (7, "name", sorted(job[1]))
            for key, value in job[1].items():
                np.testing.assert_array_equal(arrays[key], value)
                assert arrays[key].dtype == value.dtype and arrays[key].flags.writeable
    finally:
        if shared is not None:
            os.close(shared)


def test_a_frame_check_in_the_idle_worker_gives_this_process_verdict(view_worker):
    """One view: its frame check runs in the worker beside the 2D side; passed or failed, the
    same verdict as here."""
    from dataclasses import replace

    from FevarPlannerLib.pipeline import frame

    workers = view_worker
    preop, sources = _two_raw_views()
    scattered = np.random.default_rng(6).random(sources[0].image.shape) < 0.002
    checked = [replace(sources[0], check=True), replace(sources[0], mask=scattered, check=True)]
    assert workers.wait_until_ready(120.0)
    verdicts = {}
    for use_worker in (True, False):
        workers.set_enabled(use_worker)
        found = []
        for source in checked:
            outcome = frame._view_stage(preop, source, "proposed", "auto")
            assert (outcome.check_job is not None) == use_worker
            found.append(outcome.finish_check())
        verdicts[use_worker] = [None if error is None else (type(error), str(error)) for error in found]
    assert verdicts[True] == verdicts[False]
    assert verdicts[True][0] is None and "pieces" in verdicts[True][1][1]


def _best_shift_by_loop(distance, uv, tolerance_px, shift_px, step_px):
    """The frame check's shift search as a double loop over shifts, the first best kept."""
    offsets = np.arange(-shift_px, shift_px + step_px / 2, step_px)
    rows, cols = distance.shape
    best, best_shift = -1.0, np.zeros(2)
    for du in offsets:
        for dv in offsets:
            u = np.clip(np.round(uv[:, 0] + du).astype(int), 0, cols - 1)
            v = np.clip(np.round(uv[:, 1] + dv).astype(int), 0, rows - 1)
            score = float(np.mean(distance[v, u] <= tolerance_px))
            if score > best:
                best, best_shift = score, np.array([du, dv])
    return best_shift


def test_the_shift_search_finds_the_loops_first_best_shift_to_the_bit():
    from FevarPlannerLib import quality

    rng = np.random.default_rng(7)
    for trial in range(12):
        shape = tuple(rng.integers(20, 90, size=2))
        skeleton = rng.random(shape) < rng.uniform(0.002, 0.05)
        distance = ndi.distance_transform_edt(~skeleton) if trial % 4 else np.zeros(shape)   # all shifts tie
        uv = rng.uniform(-10, max(shape) + 10, size=(int(rng.integers(5, 120)), 2))
        labels = rng.integers(0, 3, size=len(uv))
        tolerance = np.array([1.5, 2.0, 3.7])[labels] if trial % 3 else 2.5
        groups = {f"g{k}": labels == k for k in range(3)}
        shift_px, step_px = rng.uniform(3, 15), (1.0, 1.7, 2.5)[trial % 3]
        coverage, shift = quality._best_shift_coverage(distance, uv, groups, tolerance, shift_px, step_px)
        expected = _best_shift_by_loop(distance, uv, tolerance, shift_px, step_px)
        np.testing.assert_array_equal(shift, expected)
        assert list(coverage) == list(groups)


def _contrast_to_noise_on_the_whole_frame(frame, mask, ring_px=6):
    """Contrast to noise with the ring dilated over the whole frame (the pixel noise: the
    check's own, tested against the whole frame's below)."""
    from FevarPlannerLib import quality

    grey = np.asarray(frame, dtype=np.float32)
    if grey.ndim == 3:
        grey = grey[..., :3].mean(axis=-1) if grey.shape[-1] in (3, 4) else grey[0]
    mask = np.asarray(mask) > 0
    ring = ndi.binary_dilation(mask, iterations=ring_px) & ~ndi.binary_dilation(mask, iterations=2)
    if not mask.any() or not ring.any():
        return 0.0
    return abs(float(np.median(grey[mask]) - np.median(grey[ring]))) / quality._pixel_noise(grey)


def test_contrast_to_noise_in_the_masks_box_equals_the_whole_frame_to_the_bit():
    from FevarPlannerLib import quality

    rng = np.random.default_rng(3)
    checked = 0
    for k, small in enumerate(random_masks(seed=5, count=60)):
        shape = (small.shape[0] + int(rng.integers(0, 40)), small.shape[1] + int(rng.integers(0, 40)))
        mask = np.zeros(shape, dtype=bool)
        r0, c0 = int(rng.integers(0, shape[0] - small.shape[0] + 1)), int(rng.integers(0, shape[1] - small.shape[1] + 1))
        mask[r0:r0 + small.shape[0], c0:c0 + small.shape[1]] = small
        frame = 1000.0 - 300.0 * mask + rng.normal(0.0, 40.0, shape)
        frame = frame.astype(np.uint16) if k % 2 else frame
        if k % 5 == 0:
            frame = np.repeat(frame[..., None], 3, axis=-1)
        for ring_px in (6, 3, 2, 1):
            assert quality.vessel_contrast_to_noise(frame, mask, ring_px) == \
                _contrast_to_noise_on_the_whole_frame(frame, mask, ring_px)
        checked += mask.any()
    assert checked > 40


def _radii_on_the_whole_volume(points, lumen):
    distance = ndi.distance_transform_edt(np.asarray(lumen.array) > 0, sampling=np.asarray(lumen.spacing)[::-1])
    index = np.clip(np.round(lumen.lps_to_index(points)).astype(int), 0, np.array(lumen.shape) - 1)
    return distance[tuple(index.T)]


def test_lumen_radii_in_the_lumens_box_equal_the_whole_volume_to_the_bit():
    from types import SimpleNamespace

    from FevarPlannerLib import quality
    from FevarPlannerLib.io import Volume

    rng = np.random.default_rng(9)
    for trial in range(8):
        shape = tuple(int(n) for n in rng.integers(8, 40, size=3))
        blobs = ndi.gaussian_filter(rng.random(shape), rng.uniform(0.8, 2.5)) > rng.uniform(0.5, 0.56)
        if trial == 0:
            blobs[:] = False
        if trial == 1:
            blobs[:, :, :3] = True          # the lumen touches the volume's border
        lumen = Volume(blobs.astype(np.uint8), rng.uniform(0.5, 2.0, 3), rng.normal(0, 20, 3), np.diag([1.0, -1.0, 1.0]))
        index = rng.uniform(-3, np.array(shape) + 3, size=(200, 3))       # (k, j, i), some outside
        inside = np.argwhere(blobs)
        if len(inside):
            index[:100] = inside[rng.integers(0, len(inside), 100)]
        points = SimpleNamespace(points=lumen.index_to_lps(index))
        np.testing.assert_array_equal(quality._radii(points, lumen), _radii_on_the_whole_volume(points.points, lumen))
        assert trial < 2 or quality._radii(points, lumen)[:100].max() > 0


def test_the_reordering_median_equals_np_median_to_the_bit():
    from FevarPlannerLib import quality

    rng = np.random.default_rng(12)
    for size in (1, 2, 3, 10, 11, 1000, 1001):
        for dtype in (np.float32, np.float64):
            values = rng.normal(0.0, 3.0, size).astype(dtype)
            values[: size // 3] = np.round(values[: size // 3])          # ties
            expected = np.median(values)
            got = quality._median_reordering(values.copy())
            assert got == expected and got.dtype == expected.dtype
    with_nan = rng.normal(size=9).astype(np.float32)
    with_nan[4] = np.nan
    assert np.isnan(quality._median_reordering(with_nan)) and np.isnan(np.median(with_nan))


def _detail_of_the_whole_frame(grey):
    return grey - ndi.gaussian_filter(grey, 1.0)


def test_the_noise_grid_detail_equals_the_whole_frame_blur_at_its_pixels():
    from FevarPlannerLib import quality

    rng = np.random.default_rng(21)
    r = quality.NOISE_BLUR_RADIUS
    for shape, stride in (((9, 9), 1), ((40, 33), 1), ((41, 57), 2), ((64, 90), 3), ((130, 129), 4)):
        grey = (500.0 + 80.0 * rng.normal(size=shape) + np.linspace(0, 300, shape[1])).astype(np.float32)
        grid = quality._detail_on_grid(grey, stride)
        expected = _detail_of_the_whole_frame(grey)[r:shape[0] - r:stride, r:shape[1] - r:stride]
        assert grid.shape == expected.shape
        np.testing.assert_allclose(grid, expected, atol=2e-3)


def test_the_noise_stride_keeps_enough_pixels_and_at_most_one_in_sixteen():
    from FevarPlannerLib import quality

    assert [quality._noise_stride((n, n)) for n in (64, 256, 511, 512, 767, 768, 1024, 4096)] == [1, 1, 1, 2, 2, 3, 4, 4]
    for n in (256, 512, 700, 1024, 2048):
        stride = quality._noise_stride((n, n))
        samples = ((n - 2 * quality.NOISE_BLUR_RADIUS - 1) // stride + 1) ** 2
        assert samples >= 0.9 * quality.NOISE_MIN_SAMPLES and stride <= quality.NOISE_MAX_STRIDE


def test_the_sampled_pixel_noise_is_the_whole_frames_within_two_percent():
    from FevarPlannerLib import quality

    rng = np.random.default_rng(4)
    rows, cols = np.mgrid[0:1024, 0:1024]
    vessels = 400.0 * (np.abs(np.sin(rows / 90.0) * 200 - cols + 512) < 12)       # edges the MAD must ignore
    for sigma in (5.0, 40.0):
        grey = (2000.0 - vessels + 300.0 * np.cos(cols / 300.0) + rng.normal(0.0, sigma, (1024, 1024))).astype(np.float32)
        detail = _detail_of_the_whole_frame(grey)
        whole = 1.4826 * float(np.median(np.abs(detail - np.median(detail)))) / 0.78 + 1e-6
        sampled = quality._pixel_noise(grey)
        assert abs(sampled - whole) < 0.02 * whole
        assert abs(sampled - sigma) < 0.2 * sigma
    blank = np.full((6, 300), 7.0, dtype=np.float32)        # too thin for the grid: every pixel
    assert quality._pixel_noise(blank) == 1e-6


def test_pieces_labelled_in_the_masks_box_are_the_whole_frames_to_the_number():
    from FevarPlannerLib import quality

    rng = np.random.default_rng(8)
    eight = np.ones((3, 3), dtype=bool)
    for small in random_masks(seed=11, count=30):
        if not small.any():
            continue
        mask = np.zeros((small.shape[0] + 30, small.shape[1] + 25), dtype=bool)
        r0, c0 = int(rng.integers(0, 31)), int(rng.integers(0, 26))
        mask[r0:r0 + small.shape[0], c0:c0 + small.shape[1]] = small
        box = quality._padded_box(mask, 0)
        labels, count = ndi.label(mask[box], structure=eight)
        expected, expected_count = ndi.label(mask, structure=eight)
        assert count == expected_count
        np.testing.assert_array_equal(quality._in_frame(labels, box, mask.shape), expected)


def test_a_tps_with_fixed_controls_equals_fitting_and_transforming_to_the_bit():
    """FixedControlsTPS precomputes the control side once; every refit is the plain TPS's."""
    rng = np.random.default_rng(21)
    general = rng.uniform(-40.0, 40.0, (30, 3))
    repeated = np.vstack([general[:12], general[3:7]])                     # merged, targets averaged
    coplanar = np.column_stack([rng.uniform(-30.0, 30.0, (15, 2)), np.zeros(15)])
    queries = rng.uniform(-60.0, 60.0, (25, 3))
    for source, regularization, ratio in ((general, 0.0, 1e-8), (repeated, 0.0, 0.05), (coplanar, 2.5, 0.05)):
        fixed = FixedControlsTPS(source, queries, regularization, min_extent_ratio=ratio)
        for _ in range(3):                                                 # several targets, one set-up
            target = source + rng.normal(0.0, 3.0, source.shape)
            plain = ThinPlateSpline3D().fit(source, target, regularization, min_extent_ratio=ratio)
            np.testing.assert_array_equal(fixed.apply(target), plain.transform(queries))
    with pytest.raises(ValueError, match="same"):
        FixedControlsTPS(general, queries).apply(general[:-1])


def _fill_skeleton():
    """vessel_tree(200) with its adjacency and an assigned mask with gaps, a cut branch end and a lone node."""
    tree = vessel_tree(200)
    n = len(tree.points)
    adjacency = sp.csr_matrix((np.ones(len(tree.edges)), (tree.edges[:, 0], tree.edges[:, 1])), shape=(n, n))
    assigned = np.ones(n, dtype=bool)
    assigned[[5, 6, 7, 40, 41, 90]] = False
    assigned[-12:] = False
    return tree.points, adjacency, assigned


def _fill_by_plain_splines(plan, points, moved, assigned, regularization=0.0, ratio=0.05):
    """The fill as it was before plans: one ThinPlateSpline3D fitted and evaluated per piece."""
    result = points.copy()
    result[assigned] = moved[assigned]
    for nodes, controls, _ in plan.splines:
        spline = ThinPlateSpline3D().fit(points[controls], moved[controls], regularization, min_extent_ratio=ratio)
        result[nodes] = spline.transform(points[nodes])
    return result


def test_a_cached_fill_plan_gives_the_uncached_fill_to_the_bit(monkeypatch):
    """Passes of a frame reuse the plan (controls, graph, TPS systems); the fill is unchanged to the bit."""
    monkeypatch.setattr(fill_module, "_plan_cache", type(fill_module._plan_cache)())
    points, adjacency, assigned = _fill_skeleton()
    rng = np.random.default_rng(22)
    passes = [points + rng.normal(0.0, 2.0, points.shape) for _ in range(3)]
    filled = [fill_unassigned(points.copy(), moved, assigned, adjacency) for moved in passes]
    assert len(fill_module._plan_cache) == 1                              # one plan for all passes
    plan = next(iter(fill_module._plan_cache.values()))
    assert sum(len(nodes) for nodes, _, _ in plan.splines) == np.count_nonzero(~assigned)
    for moved, result in zip(passes, filled):
        np.testing.assert_array_equal(result, _fill_by_plain_splines(plan, points, moved, assigned))

    other = assigned.copy()                                               # another mask: another plan
    other[100:104] = False
    result = fill_unassigned(points, passes[0], other, adjacency)
    assert len(fill_module._plan_cache) == 2
    fresh = fill_module._FillPlan(points, *fill_module._stored_edges(adjacency), other, [], 80, 40.0, 0.0, 0.05)
    np.testing.assert_array_equal(result, _fill_by_plain_splines(fresh, points, passes[0], other))
    cut = sp.lil_matrix(adjacency)                                        # another skeleton: another plan
    cut[100, 101] = 0.0
    cut = cut.tocsr()
    cut.eliminate_zeros()
    fill_unassigned(points, passes[0], other, cut)
    assert len(fill_module._plan_cache) == 3
    for size in range(fill_module._PLAN_CACHE_SIZE + 2):                  # the cache stays small
        fill_unassigned(points + size, passes[0], assigned, adjacency)
    assert len(fill_module._plan_cache) == fill_module._PLAN_CACHE_SIZE


def _two_view_model(tree, seed):
    rng = np.random.default_rng(seed)
    n = len(tree.points)
    extra = [(carm(40.0 + seed), rng.normal(256.0, 40.0, (n, 2)), rng.random(n))]
    return _build_model(tree.points, rng.normal(256.0, 40.0, (n, 2)), tree.edges, carm(float(seed)),
                        500.0, 10.0, None, None, extra)


def test_a_kept_band_layout_gives_the_preconditioner_of_a_fresh_one_to_the_bit(monkeypatch):
    """Solves with the same edges share the node order and band layout; factor and solution unchanged."""
    tree = vessel_tree(160)
    monkeypatch.setattr(solve_module, "_layout_cache", type(solve_module._layout_cache)())
    _BandedPreconditioner(_two_view_model(tree, 1), 0.1)                 # leaves its layout behind
    assert len(solve_module._layout_cache) == 1
    warm = _BandedPreconditioner(_two_view_model(tree, 2), 0.1)
    assert len(solve_module._layout_cache) == 1
    adjacency = sp.csr_matrix((np.ones(len(tree.edges)), tuple(tree.edges.T)), shape=(len(tree.points),) * 2)
    order = csgraph.reverse_cuthill_mckee((adjacency + adjacency.T).tocsr(), symmetric_mode=True)
    np.testing.assert_array_equal(warm.position[order], np.arange(len(tree.points)))
    solve_module._layout_cache.clear()
    cold = _BandedPreconditioner(_two_view_model(tree, 2), 0.1)
    for name in ("factor", "position", "to_permuted", "from_permuted"):
        np.testing.assert_array_equal(getattr(warm, name), getattr(cold, name))
    assert warm.band == cold.band

    rng = np.random.default_rng(3)
    n = len(tree.points)
    P_lao = carm(50.0)
    targets = rng.normal(256.0, 30.0, (n, 2))
    extra = [(P_lao, rng.normal(256.0, 30.0, (n, 2)), None)]
    solve_module._layout_cache.clear()
    cold, warm = (deform_assigned(tree.points, targets, tree.edges, carm(0.0), extra_views=extra, max_iter=30)
                  for _ in range(2))                                      # the second one with the kept layout
    np.testing.assert_array_equal(cold.points, warm.points)
    assert cold.n_evaluations == warm.n_evaluations


def _data_term_as_written(P, targets, weights, y):
    """eq. 1 and eqs. 7-9 for one view, each factor formed where the formula has it."""
    h = homogeneous_columns(P, y)
    sign = 1.0 if np.all(h[2] > 0) else -1.0
    if np.any(h[2] * sign <= 0):
        return None
    inverse_w = 1.0 / h[2]
    fu, fv = h[0] * inverse_w, h[1] * inverse_w
    ru, rv = targets[:, 0] - fu, targets[:, 1] - fv
    scale = -2.0 * weights * inverse_w
    return float(weights @ (ru * ru + rv * rv)), pull_back_columns(P, fu, fv, scale * ru, scale * rv)


@pytest.mark.parametrize("behind", [False, True])
def test_the_data_term_with_its_factors_kept_equals_the_formula_to_the_bit(behind):
    """The view keeps -2 w_j and its crossing test; values, gradients and reweighting unchanged."""
    tree = vessel_tree(120)
    rng = np.random.default_rng(31)
    P = carm(25.0)
    if behind:                                                            # a P with w < 0 in front
        P = -P
    n = len(tree.points)
    targets = rng.normal(256.0, 30.0, (n, 2))
    model = _build_model(tree.points, targets, tree.edges, P, 500.0, 10.0, rng.random(n), None)
    view = model.views[0]
    assert view.depth_sign == (-1.0 if behind else 1.0)
    for step in range(3):
        if step == 2:                                                     # as ICP-TPS re-weights its view
            view.data_weights = rng.random(n) / n
        y = model._points_cm + rng.normal(0.0, 2.0, (3, n))
        s_d, grad = view.data_term(y, True)
        plain_s_d, plain_grad = _data_term_as_written(P, targets, view.data_weights, y)
        assert s_d == plain_s_d
        np.testing.assert_array_equal(grad, plain_grad)
    far = model._points_cm.copy()
    far[:, 7] -= 5000.0 * np.sign(P[2, :3]) * (-1.0 if behind else 1.0)   # one node through the source plane
    assert _data_term_as_written(P, targets, view.data_weights, far) is None
    assert view.data_term(far, True) is None


def _frangi_written_out(image: np.ndarray, sigmas, polarities, beta: float = 0.5, c_fraction: float = 0.5) -> dict:
    """Multi-scale Frangi vesselness as first written: ordered eigenvalues over the whole image."""
    image = np.asarray(image, dtype=np.float32)
    best = {polarity: np.zeros_like(image) for polarity in polarities}
    for sigma in sigmas:
        smooth = ndi.gaussian_filter(image, float(sigma), mode="nearest")
        hrr, hcc = np.empty_like(smooth), np.empty_like(smooth)
        hrr[1:-1] = smooth[2:] - 2 * smooth[1:-1] + smooth[:-2]
        hrr[0], hrr[-1] = hrr[1], hrr[-2]
        hcc[:, 1:-1] = smooth[:, 2:] - 2 * smooth[:, 1:-1] + smooth[:, :-2]
        hcc[:, 0], hcc[:, -1] = hcc[:, 1], hcc[:, -2]
        hrc = np.gradient(np.gradient(smooth, axis=0), axis=1)
        scale = float(sigma) ** 2
        half_trace = 0.5 * (hrr + hcc) * scale
        root = np.sqrt((0.5 * (hrr - hcc)) ** 2 + hrc ** 2) * scale
        a, b = half_trace + root, half_trace - root
        swap = np.abs(a) > np.abs(b)
        l1, l2 = np.where(swap, b, a), np.where(swap, a, b)
        structure = l1 ** 2 + l2 ** 2
        c2 = (c_fraction ** 2) * float(structure.max()) + 1e-12
        rb2 = (l1 / np.where(l2 == 0, 1e-12, l2)) ** 2
        response = np.exp(-rb2 / (2 * beta ** 2)) * (1 - np.exp(-structure / (2 * c2)))
        for polarity, running in best.items():
            right_sign = (l2 < 0) if polarity == "bright" else (l2 > 0)
            np.maximum(running, np.where(right_sign, response, 0.0), out=running)
    return best


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8))


def test_vesselness_in_a_band_equals_the_whole_images_response_times_the_band_to_the_bit():
    rng = np.random.default_rng(12)
    for trial in range(12):
        shape = tuple(rng.integers(8, 90, size=2))
        image = ndi.gaussian_filter(rng.random(shape), 1.0).astype(np.float32)
        image[rng.integers(0, shape[0]), :] += 0.5                    # a bright line
        sigmas = np.geomspace(0.8, float(rng.uniform(1.0, 4.5)), 4)
        band = ndi.binary_dilation(rng.random(shape) < 0.05, iterations=int(rng.integers(1, 6)))
        polarities = ("bright",) if trial % 2 else ("bright", "dark")
        plain = _frangi_written_out(image, sigmas, polarities)
        whole = fluoro.vesselness(image, sigmas, polarities=polarities)
        banded = fluoro.vesselness(image, sigmas, polarities=polarities, inside=band)
        for polarity in polarities:
            assert _same_bits(whole[polarity], plain[polarity])
            assert _same_bits(banded[polarity], plain[polarity] * band)
        assert np.count_nonzero(banded["bright"]) > 0


def test_square_filters_by_doubling_spans_equal_scipys_grey_filters_to_the_bit():
    rng = np.random.default_rng(13)
    for trial in range(60):
        shape = tuple(rng.integers(1, 70, size=2))
        image = rng.random(shape).astype(np.float32 if trial % 2 else np.float64)
        radius = int(rng.integers(1, 16))
        size = (2 * radius + 1,) * 2
        top_hat = image - ndi.grey_dilation(ndi.grey_erosion(image, size=size), size=size)
        assert _same_bits(fluoro._local_contrast(image, radius), top_hat)
        assert _same_bits(fluoro._centred_square_extreme(image, radius, np.maximum, -np.inf),
                          ndi.grey_dilation(image, size=size))


def test_cross_dilation_erosion_and_diamond_opening_equal_scipys_binary_morphology():
    rng = np.random.default_rng(14)
    for mask in random_masks(seed=15, count=120):
        iterations = int(rng.integers(1, 6))
        assert np.array_equal(fluoro._cross_dilation(mask, iterations), ndi.binary_dilation(mask, iterations=iterations))
        assert np.array_equal(fluoro._cross_erosion(mask, iterations), ndi.binary_erosion(mask, iterations=iterations))
        for radius in (1, 2):
            disk = np.hypot(*np.mgrid[-radius:radius + 1, -radius:radius + 1]) <= radius
            assert np.array_equal(fluoro._diamond_opening(mask, radius), ndi.binary_opening(mask, structure=disk))


def test_the_kept_vessels_and_pieces_are_those_of_the_centerline_asked_about():
    case = phantom_case("fallback", seed=11)
    centerline = preop_model(case).centerline
    stretched = centerline.with_points(centerline.points * np.array([1.0, 1.0, 1.3]))
    for line in (centerline, stretched, centerline):
        vessels, pieces = fallback._judged_vessels(line)
        plain = sorted((v for v in fallback._vessels(line) if v.label != "other"), key=lambda v: v.label != "aorta")
        assert [v.label for v in vessels] == [v.label for v in plain] and vessels[0].label == "aorta"
        for vessel, cut, fresh in zip(vessels, pieces, plain):
            np.testing.assert_array_equal(vessel.nodes, fresh.nodes)
            again = fallback._pieces(fresh, line.points)
            assert [(p.start_mm, p.end_mm) for p in cut] == [(p.start_mm, p.end_mm) for p in again]
            for p, q in zip(cut, again):
                np.testing.assert_array_equal(p.nodes, q.nodes)
                np.testing.assert_array_equal(p.edges, q.edges)
    assert fallback._judged_vessels(centerline)[1][0][0].end_mm != fallback._judged_vessels(stretched)[1][0][0].end_mm


def test_hysteresis_by_label_indexing_equals_scikit_images():
    from skimage.filters import apply_hysteresis_threshold

    rng = np.random.default_rng(16)
    for trial in range(80):
        shape = tuple(rng.integers(1, 60, size=2))
        image = ndi.gaussian_filter(rng.random(shape), rng.uniform(0.5, 3.0)).astype(np.float32)
        image = (image - image.min()) / max(float(np.ptp(image)), 1e-6)
        low, high = sorted(rng.uniform(0.0, 1.0, size=2))
        if trial % 5 == 0:
            low, high = high, low           # low above high: clipped to it
        assert np.array_equal(fluoro._hysteresis(image, low, high), apply_hysteresis_threshold(image, low, high))


def _nearest_on_every_segment(points: np.ndarray, curve: np.ndarray):
    """Each point's nearest segment of ``curve`` measured against every segment (argmin: the first on a tie)."""
    start, step = curve[:-1], np.diff(curve, axis=0)
    squared = np.maximum(np.einsum("md,md->m", step, step), 1e-12)
    offset = points[:, None, :] - start[None]
    t = np.clip(np.einsum("nmd,md->nm", offset, step) / squared, 0.0, 1.0)
    gap = offset - t[..., None] * step[None]
    distance = np.einsum("nmd,nmd->nm", gap, gap)
    segment = np.argmin(distance, axis=1)
    rows = np.arange(len(points))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(step, axis=1))])
    return segment, arc[segment] + t[rows, segment] * np.sqrt(squared[segment]), np.sqrt(distance[rows, segment])


@pytest.mark.parametrize("seed", range(6))
def test_segments_searched_near_each_point_give_the_all_segment_answer_to_the_bit(seed):
    from FevarPlannerLib.matching import paper

    rng = np.random.default_rng(seed)
    for points_count, segments in ((24, 9), (24, 310), (120, 318), (300, 60)):
        curve = np.cumsum(rng.normal(0.0, 1.0, (segments + 1, 2)) + [0.3, 1.0], axis=0)
        curve[rng.integers(0, segments, 3)] *= 1.0 + rng.normal(0, 0.2)      # some long jumps
        points = curve[rng.integers(0, len(curve), points_count)] + rng.normal(0.0, 6.0, (points_count, 2))
        points[:4] = curve[[0, 1, 1, -1]]                                         # on vertices: ties
        segment, arc, distance = _nearest_on_every_segment(points, curve)
        point, found, _, squared = paper._nearest_segments(points, curve)
        assert np.array_equal(point, np.arange(points_count))
        assert np.array_equal(found, segment)
        assert _same_bits(np.sqrt(squared), distance)
        assert _same_bits(paper._arc_positions(curve, points), arc)
        assert _same_bits(paper._distance_to_polyline(points, curve), distance)


def test_nearest_matched_junctions_in_one_run_equal_one_dijkstra_per_junction():
    from FevarPlannerLib.matching import paper

    model = preop_model(phantom_case("fallback", seed=11))
    graph, classification = model.graph, model.classification
    junctions = [b.junction for b in classification.branches]
    matched = sorted({int(j) for j in junctions})[::2]
    one_by_one = [int(np.asarray(matched)[np.argmin(graph.geodesic_from(int(j))[matched])]) for j in junctions]
    assert paper._nearest_matched_junctions(graph, junctions, set(matched)) == one_by_one
    assert len(set(junctions)) >= 2 and len(junctions) > len(set(junctions))


@pytest.mark.parametrize("seed", range(4))
def test_segments_of_several_polylines_give_the_nearest_of_each_polylines_distance_to_the_bit(seed):
    from FevarPlannerLib.matching import paper

    rng = np.random.default_rng(seed)
    curves = [np.cumsum(rng.normal(0.0, 1.0, (size, 2)) + [0.2, 1.0], axis=0) + rng.normal(0, 20, 2)
              for size in (320, 12, 1, 90)]
    segments = paper._Segments(curves)
    for count in (5, 24, 200):           # small problems measure all pairs, large ones reuse one KD-tree
        points = curves[0][rng.integers(0, 320, count)] + rng.normal(0.0, 8.0, (count, 2))
        points[0] = curves[2][0]
        each = np.min([_nearest_on_every_segment(points, c)[2] if len(c) > 1 else np.linalg.norm(points - c[0], axis=1)
                       for c in curves], axis=0)
        assert _same_bits(segments.distances(points), each)
    assert segments._tree is not None


@pytest.mark.parametrize("shape, block", [((1024, 1024), 4), ((1001, 777), 3), ((64, 50), 1)])
def test_block_means_are_the_means_of_whole_blocks(shape, block):
    from FevarPlannerLib import quality

    image = np.random.default_rng(5).normal(1000.0, 30.0, shape).astype(np.float32)
    rows, cols = shape[0] // block * block, shape[1] // block * block
    expected = image[:rows, :cols].reshape(rows // block, block, cols // block, block).mean(axis=(1, 3))
    np.testing.assert_allclose(quality.block_means(image, block), expected, rtol=1e-6)


def _skeleton_graph_of_a_tree(seed: int) -> SkeletonGraph:
    """The 2D skeleton graph (with radii) of a drawn Y-shaped vessel mask, its positions jittered."""
    mask = y_mask_2d((160, 160), width=6.0)
    g2 = skeleton_graph_2d(mask, radii=True)
    return g2.with_positions(g2.positions + np.random.default_rng(seed).normal(0.0, 0.2, g2.positions.shape)), mask


@pytest.mark.parametrize("seed", range(3))
def test_an_induced_adjacency_equals_two_sparse_fancy_indexings(seed):
    rng = np.random.default_rng(seed)
    g2, _ = _skeleton_graph_of_a_tree(seed)
    for share in (0.02, 0.3, 0.9, 1.0):
        nodes = np.flatnonzero(rng.random(len(g2)) < share)
        plain = g2.adjacency[nodes][:, nodes]
        fast = g2.induced_adjacency(nodes)
        for part in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(fast, part), getattr(plain, part))
        assert fast.shape == plain.shape
        assert csgraph.connected_components(fast, directed=True)[0] == csgraph.connected_components(plain, directed=True)[0]


def test_row_norms_equal_numpys_vector_norms_to_the_bit():
    from FevarPlannerLib.graph import row_norms

    rng = np.random.default_rng(3)
    for shape in ((0, 2), (1, 2), (17, 2), (500, 3), (40, 7)):
        for scale in (1e-8, 1.0, 1e6):
            vectors = rng.normal(0.0, scale, shape)
            assert _same_bits(row_norms(vectors), np.linalg.norm(vectors, axis=1))
            assert _same_bits(row_norms(vectors.astype(np.float32)), np.linalg.norm(vectors.astype(np.float32), axis=1))


def test_smoothed_positions_are_those_of_the_smoothed_graph():
    from FevarPlannerLib.graph import smoothed_positions

    g2, _ = _skeleton_graph_of_a_tree(1)
    moved = g2.positions + 0.5
    np.testing.assert_array_equal(smoothed_positions(g2, 40), smooth_positions(g2, 40).positions)
    np.testing.assert_array_equal(smoothed_positions(g2, 10, positions=moved),
                                  smooth_positions(g2.with_positions(moved), 10).positions)


def _centred_the_plain_way(g2, mask):
    """centre_in_outline written out: tangents from the smoothed graph, each wall searched on its own, the
    moved positions smoothed as a graph."""
    from scipy.spatial import cKDTree

    from FevarPlannerLib.matching import centring

    radii = g2.radii.astype(float)
    movable = np.flatnonzero(g2.degrees == 2)
    junctions = np.flatnonzero(g2.degrees >= 3)
    near, _ = cKDTree(g2.positions[junctions]).query(g2.positions[movable])
    movable = movable[near > centring.JUNCTION_RADII * radii[movable]]
    tangent = centring._chain_tangents(g2, smooth_positions(g2, centring.TANGENT_SMOOTHING).positions, movable)
    length = np.linalg.norm(tangent, axis=1)
    movable, tangent = movable[length > 0], tangent[length > 0] / length[length > 0, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    reach = centring.WALL_SEARCH_RADII * radii[movable] + 2.0
    binary = np.ascontiguousarray(np.asarray(mask) > 0)
    shift = 0.5 * (centring._wall_offsets(binary, g2.positions[movable], normal, reach)
                   - centring._wall_offsets(binary, g2.positions[movable], -normal, reach))
    moved = np.isfinite(shift)
    positions = np.array(g2.positions, dtype=float)
    positions[movable[moved]] += shift[moved, None] * normal[moved]
    return smooth_positions(g2.with_positions(positions), centring.SHIFT_SMOOTHING), np.count_nonzero(moved)


@pytest.mark.parametrize("mask_type", [bool, np.uint8])
def test_centring_both_walls_in_one_search_gives_the_plain_centring_to_the_bit(mask_type):
    from FevarPlannerLib.matching import centre_in_outline

    g2, mask = _skeleton_graph_of_a_tree(2)
    plain, moved = _centred_the_plain_way(g2, mask)
    fast = centre_in_outline(g2, mask.astype(mask_type))
    assert moved > 50
    np.testing.assert_array_equal(fast.positions, plain.positions)
    for part in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(fast.adjacency, part), getattr(plain.adjacency, part))


def _same_assignment(a, b):
    for part in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(a.M, part), getattr(b.M, part))
    np.testing.assert_array_equal(a.targets, b.targets)
    np.testing.assert_array_equal(a.assigned, b.assigned)
    assert a.counted_from_exits == b.counted_from_exits and a.correspondence is b.correspondence


def test_the_soft_assignment_pair_equals_soft_assignment_with_and_without_exits():
    """The pose check's two soft assignments from one pass: a renal counted from the aorta's outline
    (test_renal_exit's oblique renal), and a phantom frame where no branch is (the same object twice)."""
    import test_renal_exit as renal

    from FevarPlannerLib import graph, matching
    from FevarPlannerLib.graph import Branch, Classification
    from FevarPlannerLib.matching import Correspondence
    from FevarPlannerLib.preop import SMOOTHING_ITERATIONS

    g3, upper3, lower3, renal3 = renal.tree_3d()
    P = renal.projection()
    mask = renal.lumen_mask(P, [(g3.positions[np.concatenate([upper3, lower3[1:]])], renal.AORTA_RADIUS_MM),
                                (g3.positions[renal3], renal.RENAL_RADIUS_MM)])
    g2 = graph.smooth_positions(graph.skeleton_graph_2d(mask, radii=True), SMOOTHING_ITERATIONS)
    upper2, lower2, renal2 = renal.frame_chains(g2, P, g3.positions[renal3[0]])
    c3 = Classification([Branch(renal3, int(renal3[0]), int(renal3[-1]), 0.0, "renal_left")], [], [],
                        np.empty(0), np.empty(0), np.empty(0), [])
    correspondence = Correspondence([(0, None)], [(upper3, upper2), (lower3, lower2)],
                                    {int(renal3[0]): int(renal2[0])}, "test", {0: renal2})
    with_exits, without = matching.soft_assign_with_and_without_exits(g3, c3, g2, None, P, correspondence)
    assert with_exits.counted_from_exits == (0,)
    _same_assignment(with_exits, matching.soft_assign(g3, c3, g2, None, P, correspondence))
    _same_assignment(without, matching.soft_assign(g3, c3, g2, None, P, correspondence, side_branch_exits=False))

    case = phantom_case("fallback", seed=11)
    preop = preop_model(case)
    view = pipeline._prepare_view(preop, drawn_mask(preop.centerline, case.P_true, (case.carm.rows, case.carm.cols)),
                                  case.P_true, "main", None, "proposed", False, {})
    g3, c3 = preop.graph, preop.classification
    shows = view.visibility.shows
    for candidate in view.candidates:
        first, second = matching.soft_assign_with_and_without_exits(g3, c3, view.g2, view.c2, view.P, candidate, shows)
        _same_assignment(first, matching.soft_assign(g3, c3, view.g2, view.c2, view.P, candidate, shows=shows))
        plain = matching.soft_assign(g3, c3, view.g2, view.c2, view.P, candidate, shows=shows, side_branch_exits=False)
        _same_assignment(second, plain)
        assert (second is first) == (not first.counted_from_exits)


def test_track_checks_the_runs_side_on_the_first_frames_own_mask(tmp_path, monkeypatch):
    """The mirror test of a run gets the vessel mask its first frame was registered with, not a second
    segmentation of that frame: one segmentation per frame, the same mask to the bit."""
    from FevarPlannerLib import quality, segmentation, tracking
    from FevarPlannerLib.pipeline import workers
    from fixtures import phantom_run_folder

    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(tmp_path / "cache"))
    workers.set_enabled(False)
    folder, _ = phantom_run_folder(tmp_path, 2)
    segmented, checked = [], []
    real_segment, real_check = segmentation.segment_fluoro, tracking._check_run_side
    monkeypatch.setattr(segmentation, "segment_fluoro", lambda *a, **k: segmented.append(1) or real_segment(*a, **k))
    monkeypatch.setattr(tracking, "_check_run_side", lambda *a: checked.append(a) or real_check(*a))
    try:
        result = tracking.track_case(folder)
    finally:
        workers.set_enabled(None)
    assert len(result.records) == 2 and all(r.fit_2d_px is not None for r in result.records)
    assert len(segmented) == 2 and len(checked) == 1
    preop, case, index, fluoro, mask, _ = checked[0]
    prior = quality.FluoroPrior.from_centerline(preop.centerline, case.P)
    np.testing.assert_array_equal(mask, real_segment(fluoro.image, prior))
    assert index == 0


def test_a_candidates_floor_takes_its_nodes_without_moving_its_targets(monkeypatch):
    """score_floor needs only which 3D nodes a candidate assigns: the soft assignment, not its targets'
    corrections (centring, the held upper aorta, the route offsets), which keep the nodes; a later
    full assignment of that candidate reuses the soft assignment and equals one computed afresh."""
    import copy

    from test_candidate_floor import _lao_view

    from FevarPlannerLib.pipeline import frame, multiview

    preop, (outcome,) = _lao_view(3)
    view = outcome.view
    fresh = copy.deepcopy(view)
    second = view.candidates[1]
    corrected = []
    real = frame._centred_targets
    monkeypatch.setattr(frame, "_centred_targets", lambda *a: corrected.append(1) or real(*a))
    floor_nodes = multiview._nodes_with_targets(preop, [view], (second,))
    assert corrected == [] and id(second) not in view.assignments
    _, nodes = multiview._target_nodes(preop, [fresh], (fresh.candidates[1],))
    np.testing.assert_array_equal(floor_nodes, nodes)
    assert corrected == [1]
    later, afresh = view.assignment(preop, second), fresh.assignment(preop, fresh.candidates[1])
    for part in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(later.M, part), getattr(afresh.M, part))
    np.testing.assert_array_equal(later.targets, afresh.targets)
    np.testing.assert_array_equal(later.assigned, afresh.assigned)


def _random_symmetric(rng, n: int, shuffled: bool) -> sp.csr_matrix:
    """A random symmetric adjacency; ``shuffled``: its entries stored out of column order in each row."""
    upper = sp.triu(sp.random(n, n, density=0.15, random_state=int(rng.integers(1 << 30)), format="csr"), k=1)
    adjacency = (upper + upper.T).tocsr()
    if shuffled:
        for row in range(n):
            span = slice(adjacency.indptr[row], adjacency.indptr[row + 1])
            order = rng.permutation(span.stop - span.start)
            adjacency.indices[span], adjacency.data[span] = adjacency.indices[span][order], adjacency.data[span][order]
        adjacency.has_sorted_indices = False
    return adjacency


def test_upper_entries_are_the_triangle_scipy_gives_in_its_order():
    from FevarPlannerLib.graph.skeleton_graph import upper_entries

    rng = np.random.default_rng(6)
    for k in range(60):
        adjacency = _random_symmetric(rng, int(rng.integers(2, 80)), shuffled=bool(k % 2))
        plain = sp.triu(adjacency, k=1).tocoo()
        rows, cols, values = upper_entries(adjacency)
        for fast, slow in ((rows, plain.row), (cols, plain.col), (values, plain.data)):
            np.testing.assert_array_equal(fast, slow)
            assert fast.dtype == slow.dtype


def _chords_by_set_membership(adjacency):
    """The forest's chords as written first: every upper edge whose key is not among the forest's edge keys."""
    n = adjacency.shape[0]
    _, labels = csgraph.connected_components(adjacency, directed=True)
    roots = np.unique(labels, return_index=True)[1]
    pred = csgraph.dijkstra(adjacency, directed=True, indices=roots, min_only=True, return_predecessors=True)[1]
    child = np.flatnonzero(pred >= 0)
    tree_keys = np.minimum(child, pred[child]) * n + np.maximum(child, pred[child])
    upper = sp.triu(adjacency, k=1).tocoo()
    chord = ~np.isin(upper.row.astype(np.int64) * n + upper.col, tree_keys)
    return np.stack([upper.row[chord], upper.col[chord]], axis=1).astype(np.int64)


def test_chords_found_from_the_predecessors_equal_the_edge_key_lookup():
    from FevarPlannerLib.graph.repair import _chords

    rng = np.random.default_rng(7)
    graph, _ = _skeleton_graph_of_a_tree(3)
    cases = [graph.adjacency] + [_random_symmetric(rng, int(rng.integers(3, 90)), bool(k % 2)) for k in range(40)]
    found = 0
    for adjacency in cases:
        chords = _chords(adjacency)
        np.testing.assert_array_equal(chords, _chords_by_set_membership(adjacency))
        found += len(chords)
    assert found > 100


def test_the_classified_graph_between_living_nodes_equals_the_diagonal_product():
    from FevarPlannerLib.graph.algorithm1 import _between

    rng = np.random.default_rng(8)
    graph, _ = _skeleton_graph_of_a_tree(4)
    for share in (0.0, 0.5, 0.95, 1.0):
        alive = rng.random(len(graph)) < share
        keep = sp.diags(alive.astype(float))
        plain = SkeletonGraph(graph.positions, (keep @ graph.adjacency @ keep).tocsr()).adjacency
        fast = SkeletonGraph(graph.positions, _between(graph.adjacency, alive)).adjacency
        for part in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(fast, part), getattr(plain, part))


def test_the_silhouette_distance_looks_further_only_outside_the_nearest_disk():
    """``_outside_silhouette_px`` against the plain formula: the least distance beyond the disks of the
    SILHOUETTE_DISKS nearest nodes, clipped at 0, for points inside, on the rim of and outside the vessels."""
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from FevarPlannerLib.pipeline import multiview

    graph, _ = _skeleton_graph_of_a_tree(5)
    view = SimpleNamespace(g2=graph)
    rng = np.random.default_rng(9)
    nodes = rng.integers(0, len(graph), 400)
    angle = rng.uniform(0.0, 2.0 * np.pi, 400)
    reach = graph.radii[nodes] * rng.choice([0.0, 0.5, 0.99, 1.0, 1.3, 3.0, 8.0], 400)
    uv = graph.positions[nodes] + reach[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    uv[:3] = graph.positions[:3]
    distance, index = cKDTree(graph.positions).query(uv, k=multiview.SILHOUETTE_DISKS)
    plain = np.maximum((distance - graph.radii[index]).min(axis=1), 0.0)
    fast = multiview._outside_silhouette_px(view, uv)
    assert _same_bits(fast, plain)
    assert 50 < np.count_nonzero(plain > 0) < 350


def test_nearest_nodes_on_the_legs_reuse_the_legs_cost_queries_to_the_bit():
    """_matches_on_legs takes a branch's nearest leg nodes from the queries that priced the legs
    (_legs_of_vessels), not from a second query of the same tree: the same distances and nodes."""
    from dataclasses import replace

    from FevarPlannerLib.pipeline import frame, multiview, workers
    from FevarPlannerLib.projection import project

    preop, sources = _two_raw_views()
    workers.set_enabled(False)
    try:
        outcomes = frame.prepare_views(preop, [replace(source, check=False) for source in sources])
    finally:
        workers.set_enabled(None)
    view = outcomes[1].view
    nodes = preop.kept
    uv = project(view.P, preop.graph.positions[nodes] + np.random.default_rng(3).normal(0.0, 2.0, (len(nodes), 3)))
    usable = view.visible[nodes]
    distance, index, legs, past = multiview._matches_on_legs(view, nodes, preop, uv, usable)
    facts = multiview._facts(view.g2)
    plain_distance, plain_index = facts.tree.query(uv)
    for rows, own in multiview._legs_of_vessels(view, nodes, preop, uv, usable, facts.legs).values():
        on_leg, tree = facts.leg_trees[own]
        plain_distance[rows], found = tree.query(uv[rows])
        plain_index[rows] = on_leg[found]
    assert len(legs) >= 2
    assert _same_bits(distance, plain_distance)
    np.testing.assert_array_equal(index, plain_index)


def _metal_tails_written_out(grey, mask):
    """The polarity reading's (dark, bright, floor) as first written: SciPy's grey closing and
    opening of 2 f - 1 px and the binary dilation of the mask (:func:`quality._metal_tails`)."""
    from FevarPlannerLib import quality

    factor = quality._working_scale(mask.shape)
    box = quality._padded_box(mask, quality.METAL_REACH * factor + 2 * factor)
    values = ndi.gaussian_filter(np.asarray(grey[box], dtype=np.float32), quality.METAL_SMOOTH * factor)
    near = ndi.binary_dilation(mask[box], iterations=quality.METAL_REACH * factor)
    size = max(3, 2 * factor - 1)
    dark = float(np.percentile((ndi.grey_closing(values, size=size) - values)[near], quality.METAL_TAIL))
    bright = float(np.percentile((values - ndi.grey_opening(values, size=size))[near], quality.METAL_TAIL))
    return dark, bright, quality.METAL_MIN_NOISE * quality._pixel_noise(values)


@pytest.mark.parametrize("scale", [1, 2, 3, 4])
def test_the_metal_tails_by_doubling_spans_equal_scipys_closing_and_opening_to_the_bit(scale):
    """Frames of 256 scale px (working scales 1 to 4) with a dark wire and a bright marker near a
    vessel mask, which reaches the frame's edge on some: the polarity reading's top-hats and
    dilation by shifted slices equal SciPy's grey and binary morphology."""
    from FevarPlannerLib import quality

    rng = np.random.default_rng(20 + scale)
    for k, small in enumerate(random_masks(seed=21 + scale, count=8)):
        shape = (256 * scale - 7 * k, 256 * scale)
        mask = np.zeros(shape, dtype=bool)
        mask[:small.shape[0] * scale, 5 * k:5 * k + small.shape[1] * scale] = np.kron(small, np.ones((scale, scale)))
        if not mask.any():
            continue
        grey = 900.0 - 200.0 * mask + rng.normal(0.0, 15.0, shape)
        grey[rng.integers(0, shape[0]), :] -= 400.0                                 # a dark wire across
        grey[shape[0] // 3:shape[0] // 3 + scale, 20 * k:20 * k + 2 * scale] += 600.0     # a bright marker
        grey = grey.astype(np.uint16) if k % 2 else grey.astype(np.float32)
        assert quality._metal_tails(grey, mask) == _metal_tails_written_out(grey, mask)


def test_square_dilation_by_doubling_spans_equals_scipys_iterated_3x3_dilation():
    from FevarPlannerLib.pipeline import visibility

    rng = np.random.default_rng(30)
    for mask in random_masks(seed=31, count=80):
        radius = int(rng.integers(1, 10))
        expected = ndi.binary_dilation(mask, structure=np.ones((3, 3), dtype=bool), iterations=radius)
        assert np.array_equal(visibility._square_dilation(mask, radius), expected)


def _round_field_with_leaves(seed: int, size: int = 320):
    """A noisy frame inside a round field (a flat dark surround) whose top and left carry
    collimator leaves held near the field's darkest level, their edges turned by a few degrees."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    image = 900.0 + 150.0 * np.sin(cols / 37.0 + seed) + rng.normal(0.0, 20.0, (size, size))
    turn = np.deg2rad(rng.uniform(-5.0, 5.0))
    top = rows * np.cos(turn) - cols * np.sin(turn) < rng.uniform(0.12, 0.22) * size
    left = cols * np.cos(turn) + rows * np.sin(turn) < rng.uniform(0.12, 0.22) * size if seed % 2 else False
    image[top | left] = 60.0 + rng.normal(0.0, 3.0, np.count_nonzero(top | left))
    image[(rows - size / 2) ** 2 + (cols - size / 2) ** 2 > (0.47 * size) ** 2] = 0.0
    return image.astype(np.float32)


def _leaves_turn_by_turn(image, unexposed):
    """visibility._collimator_leaves as first written: a profile per turn, side and level at a time."""
    from FevarPlannerLib.pipeline import visibility as v
    from FevarPlannerLib.quality import block_means

    blocks = block_means(image, v.LEAF_BLOCK).astype(float)
    field = ~unexposed[:blocks.shape[0] * v.LEAF_BLOCK:v.LEAF_BLOCK, :blocks.shape[1] * v.LEAF_BLOCK:v.LEAF_BLOCK]
    field &= ~ndi.binary_dilation(~field, iterations=2)
    values = blocks[field]
    p1, p99 = np.percentile(values, [1, 99])
    span = float(p99 - p1)
    at_extreme = [flags for flags in (np.abs(values - level) <= v.LEAF_FLATNESS * span for level in (p1, p99))
                  if v.LEAF_MIN_SHARE <= flags.mean() <= 0.5]
    rr, cc = np.nonzero(field)
    leaves = np.zeros(blocks.shape, dtype=bool)
    for turn in np.arange(-v.LEAF_MAX_TURN_DEG, v.LEAF_MAX_TURN_DEG + 1e-9, v.LEAF_TURN_STEP_DEG):
        c, s_ = np.cos(np.deg2rad(turn)), np.sin(np.deg2rad(turn))
        across_rows, across_cols = rr * c - cc * s_, cc * c + rr * s_
        for distance in (across_rows - across_rows.min(), across_rows.max() - across_rows,
                         across_cols - across_cols.min(), across_cols.max() - across_cols):
            for flags in at_extreme:
                bins = np.floor(distance).astype(int)
                counts = np.bincount(bins)
                share = np.bincount(bins, weights=flags.astype(float)) / np.maximum(counts, 1)
                depth = v._leaf_depth(share, counts >= v.LEAF_MIN_BIN)
                if depth:
                    leaves[rr[distance < depth], cc[distance < depth]] = True
    return leaves


def test_the_leaf_search_over_every_turn_at_once_and_the_flooded_shutter_equal_the_plain_ones():
    """Collimator leaves inside a round field: the blade search with every turn and side in one
    bincount finds the blocks the turn-by-turn search finds, and the shutter flooded from a corner
    is the corner's 4-connected flat piece as ndimage.label numbers it."""
    from FevarPlannerLib.pipeline import visibility

    found = 0
    for seed in range(6):
        image = _round_field_with_leaves(seed)
        unexposed = visibility._shutter(image)
        surround = np.abs(image) <= visibility.FLAT_BAND_FRACTION * (np.percentile(image[::4, ::4], 99) -
                                                                     np.percentile(image[::4, ::4], 1))
        pieces, _ = ndi.label(surround)
        assert np.array_equal(unexposed, pieces == pieces[0, 0])
        leaves = visibility._collimator_leaves(image, unexposed)
        plain = _leaves_turn_by_turn(image, unexposed)
        grown = np.kron(plain, np.ones((visibility.LEAF_BLOCK, visibility.LEAF_BLOCK), dtype=bool))
        if leaves is None:
            assert not plain.any()
            continue
        assert np.array_equal(leaves[:grown.shape[0], :grown.shape[1]], grown) and not leaves[grown.shape[0]:].any()
        found += 1
    assert found >= 4


def test_piece_sizes_and_centres_over_the_touching_pixels_equal_ndimage_measurements():
    from FevarPlannerLib.pipeline import visibility

    for mask in random_masks(seed=32, count=60):
        pieces, count = ndi.label(ndi.binary_dilation(mask, iterations=2))
        if not count:
            continue
        sizes, centres = visibility._piece_sizes_and_centres(mask, pieces, count)
        np.testing.assert_array_equal(sizes, ndi.sum(mask, pieces, range(1, count + 1)))
        np.testing.assert_array_equal(centres, np.array(ndi.center_of_mass(mask, pieces, range(1, count + 1))))

"""Registration end to end (issue 4): matching, soft assignment, deformation, TPS, outputs."""

import json
import subprocess
import sys

import numpy as np
import pytest

from FevarPlannerLib import benchmark, evaluation, export, matching, phantom, pipeline, skeleton
from fixtures import drawn_mask, phantom_case, phantom_case_fixtures, preop_model


case, preop = phantom_case_fixtures("t")


@pytest.fixture(scope="module")
def intra(case):
    return pipeline.preop_from_lumen(phantom.rasterize_lumen(case.intraop, case.grid))


def simulated_mask(case, centerline, P=None):
    """The simulation protocol's 2D side: a 3D skeleton projected and drawn."""
    return drawn_mask(centerline, case.P_true if P is None else P, (case.carm.rows, case.carm.cols))


def test_preop_graph_is_labelled_anatomy(preop):
    labels = {b.label for b in preop.classification.branches}
    assert labels == {"aorta", "renal_left", "renal_right", "iliac_left", "iliac_right"}
    assert set(preop.centerline.labels) <= {"aorta", "renal_left", "renal_right", "iliac_left", "iliac_right", "other"}
    assert len(preop.centerline) > 200


def test_intraop_equal_to_preop_is_recovered_exactly(case, preop):
    """Up to the thinning of the drawn 2D skeleton, which moves a junction by a pixel or two:
    nodes may slide along their vessel (eq. 4 assigns by arc length from the junction) but
    stay on the pre-operative curve."""
    mask = simulated_mask(case, preop.centerline)
    frame = pipeline.register_frame(preop, mask, case.P_true, refine_pose=False)
    off_curve = evaluation.point_to_graph(frame.deformed.points, preop.centerline.points, preop.centerline.edges)
    assert off_curve.mean() < 0.25 and np.percentile(off_curve, 95) < 0.5 and off_curve.max() < 1.5
    moved = np.linalg.norm(frame.deformed.points - preop.centerline.points, axis=1)
    assert moved.mean() < 1.0 and np.percentile(moved, 95) < 1.5  # voxels of 1.25 mm
    assert frame.deformed.labels == preop.centerline.labels


def test_preop_centreline_is_centred_in_the_lumen(case, preop):
    """Sub-voxel centring brings the thinned skeleton closer to the true centreline."""
    lumen = phantom.rasterize_lumen(case.preop, case.grid)
    thinned_only = pipeline.preop_from_skeleton(skeleton.skeletonize_3d(lumen))
    truth = case.preop.to_centerline()
    before = evaluation.point_to_graph(thinned_only.centerline.points, truth.points, truth.edges).mean()
    after = evaluation.point_to_graph(preop.centerline.points, truth.points, truth.edges).mean()
    assert after < 0.7 * before and after < 0.3
    assert "preop_centring" in preop.timings and "preop_centring" not in thinned_only.timings
    assert preop.centerline.labels == thinned_only.centerline.labels


def test_noise_free_phantom_registers_in_2d_and_beats_rigid_in_3d(case, preop, intra):
    mask = simulated_mask(case, intra.centerline)
    gt = case.intraop.to_centerline()
    errors = {}
    for method in ("rigid", "proposed"):
        frame = pipeline.register_frame(preop, mask, case.P_true, method=method, refine_pose=False)
        errors[method] = evaluation.evaluate(frame.deformed, gt, frame.P, frame.skeleton2d.positions,
                                             frame.skeleton2d.edges())
    assert errors["proposed"]["2d_px"]["mean"] < 0.5
    assert errors["rigid"]["2d_px"]["mean"] > 3.0
    assert errors["proposed"]["3d_mm"]["mean"] < 0.6 * errors["rigid"]["3d_mm"]["mean"]
    assert errors["proposed"]["3d_mm"]["mean"] < 2.0
    assert errors["proposed"]["3d_reverse_mm"]["mean"] < 2.5


def test_soft_assignment_rows_sum_to_one_and_targets_lie_on_the_2d_skeleton(case, preop):
    mask = simulated_mask(case, preop.centerline)
    frame = pipeline.register_frame(preop, mask, case.P_true, refine_pose=False)
    g2, c2 = frame.skeleton2d, frame.classification2d
    candidate = matching.candidate_correspondences(preop.graph, preop.classification, g2, c2, case.P_true)[0]
    assignment = matching.soft_assign(preop.graph, preop.classification, g2, c2, case.P_true, candidate)
    column_sums = np.asarray(assignment.M.sum(axis=0)).ravel()
    np.testing.assert_allclose(column_sums[assignment.assigned], 1.0, atol=1e-9)
    assert np.all(column_sums[~assignment.assigned] == 0)
    assert assignment.assigned[preop.kept].mean() > 0.95
    on_skeleton = evaluation.point_to_graph(assignment.targets[assignment.assigned], g2.positions, g2.edges())
    assert on_skeleton.max() < 1e-6
    pairs = {(preop.classification.branches[i].label, c2.branches[j].label) for i, j in candidate.branch_pairs}
    assert all(a == b for a, b in pairs) and len(pairs) == 5


def test_branch_assignment_follows_projected_arc_length():
    """Eq. (4): a 3D node at projected arc length s gets the 2D point at arc length s."""
    s3 = np.array([0.0, 0.5, 1.0, 2.5, 3.0, 3.5])
    x2 = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    inside, lo, hi, w_lo, w_hi = matching._assign_by_arc_length(s3, np.arange(4), x2)
    targets = w_lo[:, None] * x2[lo] + w_hi[:, None] * x2[hi]
    np.testing.assert_allclose(targets[inside, 0], s3[inside])
    assert inside.tolist() == [True, True, True, True, True, False]
    np.testing.assert_allclose(w_lo + w_hi, 1.0)


def test_energy_decreases(case, preop, intra):
    mask = simulated_mask(case, intra.centerline)
    frame = pipeline.register_frame(preop, mask, case.P_true, refine_pose=False)
    g2, c2 = frame.skeleton2d, frame.classification2d
    candidate = matching.candidate_correspondences(preop.graph, preop.classification, g2, c2, case.P_true)[0]
    assignment = matching.soft_assign(preop.graph, preop.classification, g2, c2, case.P_true, candidate,
                                      shows=frame.views[0].visibility.shows)
    # the pipeline takes a single view's targets at the 2D nodes centred between the walls
    assignment = matching.targets_at(assignment, matching.centre_in_outline(g2, mask).positions)
    # the pipeline holds the upper aorta on the frame's aorta (no slide along itself)
    assignment = pipeline.frame._held_upper_aorta(preop, g2, c2, case.P_true, frame.views[0].visibility,
                                                   assignment)
    assigned = np.flatnonzero(assignment.assigned)
    from FevarPlannerLib import deformation
    result = deformation.deform_assigned(preop.graph.positions[assigned], assignment.targets[assigned],
                                         pipeline._induced_edges(preop.graph, assigned), case.P_true)
    assert result.energy_final < 0.05 * result.energy_initial
    assert frame.energy == pytest.approx(result.energy_final, rel=1e-6)


def test_unknown_method_is_refused(preop, case):
    with pytest.raises(ValueError, match="unknown method"):
        pipeline.register_frame(preop, np.zeros((10, 10), bool), case.P_true, method="magic")


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory, case):
    return phantom.write_case(case, tmp_path_factory.mktemp("cases") / "case", mask_only=True)


def test_plan_case_writes_valid_outputs(case_dir, tmp_path):
    result = pipeline.plan_case(case_dir, tmp_path / "out", method="proposed")
    data = export.read_result_json(tmp_path / "out" / "result.json")
    assert data["method"] == "proposed" and data["version"] == 1
    assert len(data["deformed_centerline"]["points"]) == len(data["preop_centerline"]["points"])
    assert data["deformed_centerline"]["labels"] == data["preop_centerline"]["labels"]
    assert data["path"]["from"] == "iliac_right" and data["path"]["to"] == "renal_left"
    assert data["timings_s"]["registration"] < data["timings_s"]["total"]
    for name in ("deformed_centerline.vtp", "path.mrk.json", "overlay.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    assert result.errors["2d_px"]["mean"] < 1.0
    gt = json.loads((case_dir / "gt.json").read_text())
    gt_renal = np.array([p for p, l in zip(gt["intraop_centerline"]["points"], gt["intraop_centerline"]["labels"])
                         if l == "renal_left"])
    assert np.linalg.norm(gt_renal - result.path.points[-1], axis=1).min() < 6.0


def test_cli_plan_and_a_clear_error_for_bad_input(case_dir, tmp_path):
    cli = [sys.executable, "-m", "FevarPlannerLib.cli", "-q"]
    ok = subprocess.run(cli + ["plan", str(case_dir), "--out", str(tmp_path / "o"), "--method", "rigid"],
                        capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert "method rigid" in ok.stdout and (tmp_path / "o" / "result.json").exists()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "aorta_mask.nrrd").write_bytes(b"")
    (bad / "fluoro_mask.png").write_bytes(b"")
    failed = subprocess.run(cli + ["plan", str(bad), "--out", str(tmp_path / "o2")], capture_output=True,
                            text=True, timeout=300)
    assert failed.returncode == 2
    lines = failed.stderr.strip().splitlines()
    assert len(lines) == 1 and "aorta_mask.nrrd" in lines[0] and "empty" in lines[0]
    assert not (tmp_path / "o2" / "result.json").exists()


@pytest.mark.parametrize("segmenter", ["threshold", "unet"])
def test_raw_images_only_run_end_to_end(case, tmp_path, segmenter):
    """ct/ + fluoro.dcm + geometry.json: both segmentations, then the registration (issue 6)."""
    full = phantom.write_case(case, tmp_path / "full")
    raw = tmp_path / "raw"
    raw.mkdir()
    for name in ("ct", "fluoro.dcm", "geometry.json", "gt.json"):
        (full / name).rename(raw / name)
    result = pipeline.plan_case(raw, tmp_path / "out", segmenter=segmenter)
    assert set(result.inputs) >= {"ct", "fluoro", "geometry"} and "aorta_mask" not in result.inputs
    assert result.errors["2d_px"]["mean"] < 1.0
    assert result.errors["3d_mm"]["mean"] < 2.5
    assert (tmp_path / "out" / "result.json").exists()


def test_robustness_reads_an_offset_frame_as_patient_motion_or_as_a_wrong_P(case, preop, intra):
    """Paper Fig. 5: the anatomy moved 30 px / 10 degrees in the image, P kept. Following the
    frame is right if the patient moved and wrong by about the offset if P is off instead."""
    gt = case.intraop.to_centerline()
    shape = (case.carm.rows, case.carm.cols)
    curves = benchmark._robustness("t", preop, intra.centerline, case.P_true, gt, shape, (30,), (10,), lambda m: None)
    for kind in ("translation_px", "rotation_deg"):
        (point,) = curves[kind]
        proposed, rigid = point["results"]["Proposed"], point["results"]["SV"]
        assert proposed["3d_mm"]["mean"] < 1.5 and proposed["3d_mm"]["mean"] < 0.25 * rigid["3d_mm"]["mean"]
        assert proposed["3d_mm_if_P_off"]["mean"] > 4.0 > rigid["3d_mm_if_P_off"]["mean"]


def test_a_stretched_vessel_falls_back_to_sv_moved_with_its_junction(case, preop):
    """Never worse than SV: a vessel whose length changed by 20 % is replaced, with a warning."""
    mask = simulated_mask(case, preop.centerline)
    view = pipeline._prepare_view(preop, mask, case.P_true, "main", None, "proposed", False, {})
    result = pipeline.register_frame(preop, mask, case.P_true).deformed.points
    kept, warnings = pipeline._never_worse_than_sv(result, lambda: [(result, "itself")], preop, [view])
    assert warnings == [] and np.array_equal(kept, result)
    iliac = next(v for v in pipeline._vessels(preop.centerline) if v.label == "iliac_left")
    stretched = result.copy()
    root = result[iliac.attachments[0, 1]]
    stretched[iliac.nodes] = root + 1.2 * (result[iliac.nodes] - root)
    fixed, warnings = pipeline._never_worse_than_sv(stretched, lambda: [(stretched, "itself")], preop, [view])
    assert len(warnings) == 1 and warnings[0].startswith("iliac_left: length changed by +")
    assert float(warnings[0].split("+")[1].split("%")[0]) == pytest.approx(20.0, abs=0.5)   # of the registered length
    assert "(SV)" in warnings[0]
    sv = preop.centerline.points
    shift = fixed[iliac.nodes] - sv[iliac.nodes]
    np.testing.assert_allclose(shift, shift[:1].repeat(len(shift), axis=0), atol=1e-9)   # SV, moved rigidly
    others = np.setdiff1d(np.arange(len(result)), iliac.nodes)
    np.testing.assert_array_equal(fixed[others], stretched[others])


def test_a_2d_fork_the_3d_tree_lacks_gives_no_confident_wrong_answer():
    """Internal iliacs in the frame only (a distal fork): the matching puts the aorta on the
    wrong chain (measured without the checks: 10.2 mm, 2D 17.4 px, against 1.1 mm for SV);
    the checks see the aorta stretched by a third and fall back to SV."""
    plain = phantom_case(seed=5)
    forked = phantom_case(seed=5, internal_iliacs=True)
    preop = preop_model(plain)
    mask = simulated_mask(plain, forked.intraop.to_centerline())
    gt = plain.intraop.to_centerline()
    errors = {}
    for method in ("rigid", "proposed"):
        frame = pipeline.register_frame(preop, mask, plain.P_true, method=method)
        errors[method] = evaluation.evaluate(frame.deformed, gt, frame.P, frame.skeleton2d.positions,
                                             frame.skeleton2d.edges())["3d_mm"]["mean"]
    assert errors["proposed"] <= errors["rigid"] + 0.05
    assert frame.warnings or errors["proposed"] < 1.0

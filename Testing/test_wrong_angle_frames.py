"""Issue 11: a frame whose geometry belongs to another view (a wrong C-arm angle) is refused.

The length term keeps each vessel's length, so the registration cannot lengthen a renal that
the given ``P`` foreshortens more than the frame does: the frame's renal goes on beyond the
registered one's end. One renal 12 mm or more beyond, as one vessel, refuses on its own (one
going on into the kidney's branches does not), each from 9 mm is a
doubt (:func:`plausibility._doubts`); a frame that fits mirrored at under 0.35 of its direct
fit is refused on its own too. Tested on the hand-made tree of ``test_wrong_frames`` (an affine
P of 1 px per mm) and end to end on a scenario case whose geometry is turned 40 degrees about
the patient's long axis.
"""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from FevarPlannerLib import plausibility, quality
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.projection import project
from test_wrong_frames import P, SHAPE, hand_tree, moved


def lengthened(tree: Centerline, label: str, mm: float) -> Centerline:
    """``tree`` with ``label`` (a straight branch) carried on ``mm`` beyond its end, in its direction."""
    points, edges, labels = tree.points.copy(), np.asarray(tree.edges), list(tree.labels)
    nodes = np.flatnonzero(np.asarray(labels) == label)
    end, before = points[nodes[-1]], points[nodes[-2]]
    step = (end - before) / np.linalg.norm(end - before)
    count = int(np.ceil(mm / 5.0))
    extra = end + step * np.linspace(mm / count, mm, count)[:, None]
    first = len(points)
    new_edges = [(nodes[-1], first)] + [(first + k, first + k + 1) for k in range(count - 1)]
    return Centerline(np.vstack([points, extra]), np.vstack([edges, new_edges]), labels + [label] * count)


def skeleton_of(tree: Centerline, step_px: float = 2.0):
    """The frame's 2D skeleton graph, connected as a thinned mask's is: the tree's projected nodes,
    and nodes every ``step_px`` or less inside each edge."""
    uv = project(P, tree.points)
    points, edges = list(uv), []
    for a, b in np.asarray(tree.edges):
        count = max(1, int(np.ceil(np.linalg.norm(uv[b] - uv[a]) / step_px)))
        chain = [a] + list(range(len(points), len(points) + count - 1)) + [b]
        points += [uv[a] + (uv[b] - uv[a]) * k / count for k in range(1, count)]
        edges += list(zip(chain[:-1], chain[1:]))
    return np.array(points), np.array(edges)


def check(preop: Centerline, deformed: Centerline, frame_tree: Centerline):
    return plausibility.check_registration(preop, deformed, P, *skeleton_of(frame_tree), SHAPE, "frame.png")


def frame_check(tree: Centerline, frame_tree: Centerline):
    """The check of ``tree`` registered as it is, against the frame drawn from ``frame_tree``."""
    return check(tree, tree, frame_tree)


def test_a_renal_the_frame_shows_20_mm_longer_is_refused_by_name_and_place():
    tree = hand_tree()
    with pytest.raises(quality.QualityError) as caught:
        frame_check(tree, lengthened(tree, "renal_left", 20.0))
    message = str(caught.value)
    assert "\n" not in message and "renal_left is longer in the frame than the CT's projects" in message
    assert "goes on 20 mm beyond its end, to near pixel (u=330, v=164)" in message     # (79.7, 0, 96.4) mm, projected


def test_a_renal_10_mm_longer_is_a_warning_and_4_mm_is_nothing():
    tree = hand_tree()
    signals = frame_check(tree, lengthened(tree, "renal_right", 10.0))
    assert 9.0 <= signals["renal_continuation_mm"]["renal_right"] <= 11.0
    notes = plausibility.registration_warnings(signals)
    assert len(notes) == 1 and "renal_right is longer in the frame" in notes[0] and "check the overlay" in notes[0]
    quiet = frame_check(tree, lengthened(tree, "renal_right", 4.0))
    assert quiet["renal_continuation_mm"]["renal_right"] < 9.0 and plausibility.registration_warnings(quiet) == []
    assert frame_check(tree, tree)["renal_continuation_mm"] == {"renal_left": 0.0, "renal_right": 0.0}


def with_kidney_branches(tree: Centerline, label: str, mm: float = 12.0) -> Centerline:
    """``tree`` with three branches of ``mm`` fanning out in the image plane (-35, 0, +35 degrees)
    from the end of ``label``: the kidney's own arterial tree, as a DSA frame shows it."""
    points, edges, labels = tree.points.copy(), [tuple(e) for e in np.asarray(tree.edges)], list(tree.labels)
    nodes = np.flatnonzero(np.asarray(labels) == label)
    end = points[nodes[-1]]
    ahead = (end - points[nodes[-2]]) / np.linalg.norm(end - points[nodes[-2]])
    extra = []
    for degrees in (-35.0, 0.0, 35.0):
        step = Rotation.from_euler("y", degrees, degrees=True).apply(ahead)
        chain = [nodes[-1]] + list(range(len(points) + len(extra), len(points) + len(extra) + 3))
        extra += [end + step * mm * k / 3 for k in (1, 2, 3)]
        edges += list(zip(chain[:-1], chain[1:]))
    return Centerline(np.vstack([points, extra]), np.array(edges), labels + [label] * len(extra))


def test_a_renal_going_on_into_the_kidneys_branches_is_a_doubt_not_a_refusal():
    """A real CT's renal, segmented to near the hilum, ends before the frame's: a DSA frame shows
    the renal on and the kidney's arterial tree beyond. As long as a wrong geometry's, but branched."""
    tree = hand_tree()
    kidney = with_kidney_branches(lengthened(tree, "renal_left", 8.0), "renal_left")
    signals = frame_check(tree, kidney)
    assert signals["renal_continuation_mm"]["renal_left"] >= plausibility.RENAL_CONTINUATION_REFUSE_MM
    assert signals["renal_continuation_branches_mm"]["renal_left"] > plausibility.RENAL_CONTINUATION_BRANCHES_MM
    notes = plausibility.registration_warnings(signals)
    assert len(notes) == 1 and "renal_left is longer in the frame" in notes[0]
    single = plausibility.registration_signals(tree, tree, P, *skeleton_of(lengthened(tree, "renal_left", 20.0)), SHAPE)
    assert single["renal_continuation_branches_mm"]["renal_left"] < 2.0


def test_both_renals_10_mm_longer_are_two_doubts_and_refused():
    tree = hand_tree()
    both = lengthened(lengthened(tree, "renal_left", 10.0), "renal_right", 10.0)
    with pytest.raises(quality.QualityError, match=r"renal_left is longer .*; and renal_right is longer"):
        frame_check(tree, both)


def test_a_renal_turned_out_of_the_image_plane_in_the_ct_but_in_it_in_the_frame_is_refused():
    """What a geometry 40-50 degrees off does to a renal: the CT's renal_left runs 50 degrees out
    of the image plane under P (its projection 0.64 of its length), the frame shows it in the plane."""
    tree = hand_tree()
    labels = np.asarray(tree.labels)
    renal = np.flatnonzero(labels == "renal_left")
    ostium = tree.points[renal[0]]
    turn = Rotation.from_euler("z", 50.0, degrees=True)           # about the long axis through the ostium
    points = tree.points.copy()
    points[renal] = ostium + turn.apply(points[renal] - ostium)
    ct = tree.with_points(points)
    with pytest.raises(quality.QualityError, match="renal_left is longer in the frame"):
        check(ct, ct, tree)
    assert plausibility.registration_warnings(check(ct, ct, ct)) == []


def test_a_frame_fitting_far_better_mirrored_is_refused_on_that_alone():
    """Renal ostia 25 mm apart in height, the registered tree lying on the mirrored frame: only the
    side check speaks (ratio about 0), and it refuses alone."""
    tree = moved(moved(hand_tree(), "renal_left", (0.0, 0.0, 12.0)), "renal_right", (0.0, 0.0, -13.0))
    mirrored = tree.with_points(tree.points @ np.diag([-1.0, 1.0, 1.0]))
    frame = Centerline(mirrored.points, mirrored.edges, list(tree.labels))
    signals = plausibility.registration_signals(tree, frame, P, *skeleton_of(frame), SHAPE)
    direct, flipped = signals["side_fit_mm"]
    assert flipped < plausibility.MIRROR_CERTAIN_RATIO * direct
    verdict = plausibility.registration_verdict(signals)
    assert verdict is not None and verdict.startswith("the frame looks mirrored left-right")


# --- end to end: a scenario case whose geometry.json is that of a view 40 degrees away


def turned_about_long_axis(P_given: np.ndarray, centre: np.ndarray, degrees: float) -> np.ndarray:
    """``P_given`` of a C-arm turned ``degrees`` about the LPS z axis through ``centre``."""
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    motion[:3, 3] = centre - motion[:3, :3] @ centre
    return np.asarray(P_given, dtype=float) @ motion


def test_a_geometry_40_degrees_off_is_refused_with_exit_2_one_line_and_the_qc_picture(tmp_path):
    from FevarPlannerLib.pipeline import plan_case
    from FevarPlannerLib.scenarios import plan_scenarios, write_scenario

    case = write_scenario(plan_scenarios("straightening", 4, 0)[-1], tmp_path / "case")
    wrong = tmp_path / "wrong"
    shutil.copytree(case, wrong)
    geometry = json.loads((wrong / "geometry.json").read_text())
    centre = np.asarray(json.loads((case / "gt.json").read_text())["preop_centerline"]["points"]).mean(axis=0)
    geometry["projection_matrix"] = turned_about_long_axis(geometry["projection_matrix"], centre, 40.0).tolist()
    (wrong / "geometry.json").write_text(json.dumps(geometry))
    run = subprocess.run([sys.executable, "-m", "FevarPlannerLib.cli", "-q", "plan", str(wrong), "--out",
                          str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stdout + run.stderr
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "registration check: renal_left is longer in the frame" in lines[0], run.stderr
    assert (tmp_path / "out" / "segmentation_qc.png").stat().st_size > 1000
    assert not (tmp_path / "out" / "result.json").exists()
    right = plan_case(case, tmp_path / "right")
    assert not any("longer in the frame" in note for note in right.warnings)
    assert right.errors["3d_mm"]["mean"] < 6.0

"""Issue 11 on image-only cases: what a wrong frame needed just beyond every right frame warns.

Four wrong image-only frames of the development set (``bench_wrong_frames.py --scenario-kinds
image_only --bench-frames 241 ... 249``) were answered without any warning: a swap between
scenario cases, a bench frame swapped with its geometry and a mirrored one moved a renal ostium
4.4-4.9 mm beyond a rigid motion (right frames: at most 3.95), and a bench frame with the
geometry of a view 40 degrees away left the registered renal's end 6.9 mm beyond the frame's
renal (right frames without a warning: at most 2.8). Each now warns
(:data:`plausibility.OSTIUM_MOVE_WARN_MM`, :data:`plausibility.RENAL_OVERHANG_WARN_MM`) without
counting as a doubt (two doubts refuse). Pinned on the hand-made tree of ``test_wrong_frames.py``
(1 px per mm).
"""

import numpy as np
import pytest

from FevarPlannerLib import plausibility

from test_wrong_frames import P, SHAPE, check, hand_tree, moved, skeleton_of


def ostium_moved(tree, mm: float):
    """``tree`` with renal_right moved ``mm`` up (z), its ostium with it: the registered tree of a
    frame whose renal leaves the aorta higher."""
    return moved(tree, "renal_right", (0.0, 0.0, mm))


@pytest.mark.parametrize("mm, notes", [(3.5, 0), (5.0, 1)])
def test_an_ostium_moved_over_4_3_mm_warns_and_under_it_does_not(mm, notes):
    """Moved 3.5 / 5 mm with the renal, the rigid motion of the whole tree takes 0.3 / 0.5 mm of it."""
    tree = hand_tree()
    registered = ostium_moved(tree, mm)
    signals = check(tree, registered, registered)
    moved_by = signals["ostium_move_mm"]["renal_right"]
    assert 0.85 * mm < moved_by < mm and (moved_by > plausibility.OSTIUM_MOVE_WARN_MM) == bool(notes)
    assert moved_by <= plausibility.MAX_OSTIUM_MOVE_MM
    assert plausibility.registration_verdict(signals) is None
    found = plausibility.registration_warnings(signals)
    assert len(found) == notes
    if notes:
        assert "renal_right: the fit moved its ostium" in found[0] and "over 4.3 mm" in found[0]
        assert "check the overlay" in found[0]


def test_an_ostium_warning_is_no_doubt():
    """With a doubt besides (the registered renal_left 1.7 mm off the frame's), it still only
    warns: two notes, no refusal."""
    tree = hand_tree()
    registered = ostium_moved(tree, 5.0)
    frame = moved(registered, "renal_left", (0.0, 0.0, 1.7))
    signals = check(tree, registered, frame)
    assert signals["vessel_fit_mm"]["renal_left"] > plausibility.RENAL_FIT_DOUBT_MM
    assert plausibility.registration_verdict(signals) is None
    found = plausibility.registration_warnings(signals)
    assert len(found) == 2 and "renal_left does not fit" in found[0] and "moved its ostium" in found[1]


def renal_cut(tree, label: str, mm: float):
    """The frame's 2D skeleton of ``tree`` with the last ``mm`` of ``label`` missing (the frame's
    renal shorter than the CT's projects)."""
    points, edges = skeleton_of(tree)
    nodes = np.flatnonzero(np.asarray(tree.labels) == label)
    start, end = P[:2, :3] @ tree.points[nodes[0]] + P[:2, 3], P[:2, :3] @ tree.points[nodes[-1]] + P[:2, 3]
    unit = (end - start) / np.linalg.norm(end - start)
    along = (points - start) @ unit
    near = np.abs((points - start) @ np.array([-unit[1], unit[0]])) < 1.0      # within 1 px of the renal's line
    gone = near & (along > np.linalg.norm(end - start) - mm)
    keep = ~gone[edges].any(axis=1)
    index = np.cumsum(~gone) - 1
    return points[~gone], index[edges[keep]]


@pytest.mark.parametrize("mm, warned", [(3.0, False), (6.5, True)])
def test_a_registered_renal_ending_beyond_the_frames_renal_warns(mm, warned):
    """The overhang counts the registered renal's nodes (every 4.7 mm here) off the frame's vessel."""
    tree = hand_tree()
    points, edges = renal_cut(tree, "renal_right", mm)
    signals = plausibility.check_registration(tree, tree, P, points, edges, SHAPE, "frame.png")
    assert mm <= signals["renal_overhang_mm"]["renal_right"] < mm + 4.7
    assert signals["renal_overhang_mm"]["renal_left"] == 0.0
    assert signals["vessel_fit_mm"]["renal_right"] < plausibility.RENAL_FIT_DOUBT_MM
    found = plausibility.registration_warnings(signals)
    assert len(found) == int(warned)
    if warned:
        assert "renal_right ends beyond the frame's vessel" in found[0]
        assert "near pixel (u=190, v=160)" in found[0]       # its end, (-60, 0, 100) mm, projected


def test_an_overhang_is_not_judged_on_a_view_of_several():
    tree = hand_tree()
    points, edges = renal_cut(tree, "renal_right", 6.5)
    signals = plausibility.registration_signals(tree, tree, P, points, edges, SHAPE, views=2)
    assert signals["renal_overhang_mm"]["renal_right"] > plausibility.RENAL_OVERHANG_WARN_MM
    assert plausibility.registration_warnings(signals) == []

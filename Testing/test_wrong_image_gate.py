"""Issue 11 on image-only cases: a renal the registration could not lay onto the frame's vessels.

The CT's renal keeps its length (eq. 6, S_L), so when the frame is another patient's (or of
another view) a registered renal may stay millimetres off the frame's vessels while the aorta
lies on them; a right frame's renal comes to lie on its vessel to the skeleton's pixel steps.
Over :data:`plausibility.RENAL_FIT_DOUBT_MM` that is a doubt, from
:data:`plausibility.RENAL_FIT_REFUSE_MM` (the aorta :data:`plausibility.RENAL_FIT_OVER_AORTA`
times closer) a refusal on its own. Pinned on the hand-made tree of ``test_wrong_frames.py`` and
end to end on an image-only scenario case (CT + 16-bit frame, no masks) whose frame is another
case's (Testing/benchmarks/bench_wrong_frames.py measures it on many).
"""

import shutil

import numpy as np
import pytest

from FevarPlannerLib import plausibility, quality
from FevarPlannerLib.files import InputError

from test_wrong_frames import P, SHAPE, check, hand_tree, moved, skeleton_of


def renal_shifted(tree, label: str, mm: float):
    """``tree`` with the renal ``label`` but its ostium node moved ``mm`` along z (in the image
    plane: the frame's renal of another course; the ostium stays on the aorta)."""
    nodes = np.flatnonzero(np.asarray(tree.labels) == label)
    points = tree.points.copy()
    points[nodes[1:], 2] += mm
    return tree.with_points(points)


def test_a_renal_5_mm_off_the_frames_renal_is_refused_by_name_and_place():
    tree = hand_tree()
    frame = renal_shifted(tree, "renal_right", 4.0)        # the registered tree is the CT's: renal_right 4 mm below
    signals = plausibility.registration_signals(tree, tree, P, *skeleton_of(frame), SHAPE)
    assert 3.0 <= signals["vessel_fit_mm"]["renal_right"] < plausibility.RENAL_FIT_REFUSE_MM
    assert signals["vessel_fit_mm"]["aorta"] < 0.1
    assert max(signals["renal_misfit_mm"].values()) < plausibility.MAX_RENAL_RIGID_MISFIT_MM   # no other doubt
    assert plausibility.registration_verdict(signals) is None and len(plausibility.registration_warnings(signals)) == 1
    with pytest.raises(quality.QualityError) as caught:
        check(tree, tree, renal_shifted(tree, "renal_right", 5.5))
    message = str(caught.value)
    assert "\n" not in message and message.startswith("frame.png: registration check: renal_right does not fit")
    assert "on average 4.9 mm off them (over 4 mm, the aorta 0.0 mm)" in message
    assert "worst near pixel (u=190, v=160)" in message     # its end, (-60, 0, 100) mm, projected


def test_a_renal_1_5_mm_off_is_a_warning_and_half_a_millimetre_is_nothing():
    tree = hand_tree()
    notes = plausibility.registration_warnings(check(tree, tree, renal_shifted(tree, "renal_left", 1.7)))
    assert len(notes) == 1 and "renal_left does not fit the frame's vessels" in notes[0]
    assert "check the overlay" in notes[0]
    assert plausibility.registration_warnings(check(tree, tree, renal_shifted(tree, "renal_left", 0.5))) == []


def test_a_renal_off_where_the_aorta_is_off_too_is_only_a_doubt():
    """A registration the fallback kept rigid lies off the whole frame (bench 246, a right frame:
    aorta 1.8 mm, renal 2.8 mm): the renal is no worse than the rest, one doubt, a warning."""
    tree = hand_tree()
    frame = renal_shifted(moved(tree, "aorta", (2.0, 0.0, 0.0)), "renal_left", 6.0)
    signals = check(tree, tree, frame)
    assert signals["vessel_fit_mm"]["renal_left"] >= plausibility.RENAL_FIT_REFUSE_MM
    assert signals["vessel_fit_mm"]["renal_left"] < plausibility.RENAL_FIT_OVER_AORTA * signals["vessel_fit_mm"]["aorta"]
    assert plausibility.registration_verdict(signals) is None
    assert len(plausibility.registration_warnings(signals)) == 1


def test_a_renal_off_and_the_renals_off_before_deformation_are_two_doubts_and_refused():
    tree = hand_tree()
    frame = moved(renal_shifted(tree, "renal_left", 1.7), "renal_left", (0.0, 0.0, -7.0))
    frame = moved(frame, "renal_right", (0.0, 0.0, -7.0))
    registered = moved(moved(tree, "renal_left", (0.0, 0.0, -7.0)), "renal_right", (0.0, 0.0, -7.0))
    with pytest.raises(quality.QualityError, match=r"renal_\w+ not found where the CT puts it.*; and renal_left does "
                                                   r"not fit the frame's vessels after registration: on average 1\.\d"):
        check(tree, registered, frame)


@pytest.fixture(scope="module")
def image_only_pair(tmp_path_factory):
    """Scenario image_only seed 300, cases 01 (right) and 01 with case 02's frame (16-bit PNG)."""
    from FevarPlannerLib.scenarios import plan_scenarios, write_scenario

    root = tmp_path_factory.mktemp("image_only")
    plans = plan_scenarios("image_only", 4, 300)
    right = write_scenario(plans[1], root / "right")
    wrong = root / "wrong"
    shutil.copytree(right, wrong)
    other = plans[2]
    shutil.copy2(write_scenario(other, root / "other") / "fluoro.png", wrong / "fluoro.png")
    return right, wrong, root


def test_another_cases_image_is_refused_and_this_cases_answered(image_only_pair):
    """Main answered the swapped frame 3.9 mm off the truth with no warning: its registered
    renal_left lay 6.7 mm off the frame's vessels, the aorta 0.4 mm. The right frame: 1.5 mm."""
    from FevarPlannerLib.pipeline import plan_case

    right, wrong, root = image_only_pair
    assert not (wrong / "fluoro_mask.png").exists() and (wrong / "ct.nrrd").exists()
    cache = root / "cache"                    # the CT, segmented once for both
    with pytest.raises(InputError) as caught:
        plan_case(wrong, root / "out", cache=cache)
    message = str(caught.value)
    assert isinstance(caught.value, quality.QualityError) and "\n" not in message
    assert "wrong/fluoro.png: registration check: renal_left does not fit the frame's vessels" in message
    assert (root / "out" / "segmentation_qc.png").stat().st_size > 1000
    answered = plan_case(right, None, cache=cache)
    assert answered.errors["3d_mm"]["mean"] < 2.5
    assert not [note for note in answered.warnings if note.startswith("registration check")]


def test_a_renal_off_one_view_of_several_is_no_evidence():
    """Two views fitted at once: a steep second view (LAO 70, RAO 90) shows a renal along the ray,
    its shadow on the aorta's, and right frames leave it 5-8 mm off that view's skeleton."""
    tree = hand_tree()
    frame = renal_shifted(tree, "renal_right", 5.5)
    alone = plausibility.registration_signals(tree, tree, P, *skeleton_of(frame), SHAPE)
    several = plausibility.registration_signals(tree, tree, P, *skeleton_of(frame), SHAPE, views=2)
    assert several["vessel_fit_mm"]["renal_right"] == alone["vessel_fit_mm"]["renal_right"] > 4.0
    assert "renal_right does not fit" in plausibility.registration_verdict(alone)
    assert plausibility.registration_verdict(several) is None and plausibility.registration_warnings(several) == []

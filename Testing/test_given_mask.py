"""Conditioning of a given binary 2D mask (given_mask, issue 10): a JPEG'd label binarised
strictly (pinholes, ragged edge) or loosely (halo fringe, specks) thins to about the clean
label's skeleton once conditioned, and a clean mask is left as it is."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from FevarPlannerLib import skeleton
from FevarPlannerLib.given_mask import (DITHERED_ABOVE, condition_given_mask, dithered_fraction, repaired_mask,
    vessel_half_width_px)
from FevarPlannerLib.pipeline import case as case_module
from FevarPlannerLib.scenarios import bench
from FevarPlannerLib.scenarios.frames import paint_capsules


def _tree_label(shape=(320, 320)) -> np.ndarray:
    """A phantom-like label (rows, cols): aorta with a sac, two renals, two iliacs; 5 ends."""
    mask = np.zeros(shape, dtype=bool)
    aorta = np.array([[20.0, 160.0], [90.0, 160.0], [150.0, 158.0], [200.0, 160.0]])
    paint_capsules(mask, aorta, np.array([14.0, 14.0, 30.0, 14.0]))
    paint_capsules(mask, np.array([[80.0, 160.0], [70.0, 60.0]]), np.array([6.0, 5.0]))
    paint_capsules(mask, np.array([[82.0, 160.0], [76.0, 262.0]]), np.array([6.0, 5.0]))
    paint_capsules(mask, np.array([[200.0, 160.0], [290.0, 110.0]]), np.array([10.0, 8.0]))
    paint_capsules(mask, np.array([[200.0, 160.0], [292.0, 214.0]]), np.array([10.0, 8.0]))
    return mask


def _skeleton_ends(mask: np.ndarray) -> int:
    thin = skeleton.skeletonize_2d(mask)
    neighbours = ndimage.convolve(thin.astype(int), np.ones((3, 3), int), mode="constant") - 1
    return int(np.count_nonzero(thin & (neighbours == 1)))


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


@pytest.fixture(scope="module")
def binarised():
    """The label JPEG'd as the authors store it (quality 75), binarised three ways."""
    clean = _tree_label()
    grey = bench.jpeg_damaged(clean, 75)            # vessels bright, halo and specks kept
    return {"clean": clean, "strict": grey == 255, "loose": grey > 0, "mid": grey > 128}


def test_the_binarisations_are_damaged_as_a_user_would_get_them(binarised):
    clean = binarised["clean"]
    assert _dice(binarised["mid"], clean) > 0.999          # ringing of a 0/255 label never crosses 128
    assert _skeleton_ends(clean) == 5
    # unconditioned, both damaged ones thin to many spurs
    assert _skeleton_ends(binarised["strict"]) >= 10
    assert _skeleton_ends(binarised["loose"]) >= 10


@pytest.mark.parametrize("way", ["strict", "loose", "mid"])
def test_a_damaged_mask_conditioned_thins_to_the_clean_skeleton(binarised, way):
    conditioned = condition_given_mask(binarised[way])
    assert abs(_skeleton_ends(conditioned) - _skeleton_ends(binarised["clean"])) <= 1
    labels, count = ndimage.label(conditioned, np.ones((3, 3)))
    assert count == 1                                       # specks gone
    assert not (ndimage.binary_fill_holes(conditioned) & ~conditioned).any()   # pinholes filled
    # the loose one keeps the halo's solid inner part: about 1.5 px too wide a side
    assert _dice(conditioned, binarised["clean"]) > (0.86 if way == "loose" else 0.95)


def test_only_a_dithered_mask_is_conditioned(binarised):
    assert dithered_fraction(binarised["clean"]) < 0.05
    assert dithered_fraction(binarised["mid"]) < 0.05
    assert dithered_fraction(binarised["strict"]) > 1.5 * DITHERED_ABOVE
    assert dithered_fraction(binarised["loose"]) > 1.5 * DITHERED_ABOVE
    assert np.array_equal(condition_given_mask(binarised["clean"]), binarised["clean"])


def _ring() -> np.ndarray:
    yy, xx = np.mgrid[:200, :200]
    radius = np.hypot(yy - 100, xx - 100)
    return (radius > 60) & (radius < 72)


def test_the_repair_barely_changes_a_clean_mask(binarised):
    clean = binarised["clean"]
    assert _dice(repaired_mask(clean, vessel_half_width_px(clean)), clean) >= 0.99
    # a real loop (a background region far larger than a vessel cross-section) stays open
    ring = _ring()
    repaired = repaired_mask(ring, vessel_half_width_px(ring))
    assert _dice(repaired, ring) >= 0.98
    assert not repaired[100, 100]


def test_half_width_is_read_from_the_mask_not_its_damage(binarised):
    bar = np.zeros((120, 200), dtype=bool)
    bar[50:70, 20:180] = True                               # half-width 10 px
    assert vessel_half_width_px(bar) == pytest.approx(10.0, rel=0.15)
    holed = bar.copy()
    holed[55:65:3, 30:170:4] = False                        # pinholes
    assert vessel_half_width_px(holed) == pytest.approx(10.0, rel=0.15)
    assert vessel_half_width_px(binarised["loose"]) == pytest.approx(
        vessel_half_width_px(binarised["clean"]), rel=0.2)
    assert vessel_half_width_px(binarised["strict"]) == pytest.approx(
        vessel_half_width_px(binarised["clean"]), rel=0.3)     # 20 % of the vessel lost at quality 75


def test_the_case_route_conditions_a_given_mask(binarised):
    class _Frame:
        fluoro_mask = binarised["loose"]

    used = case_module._vessel_mask(_Frame())
    assert np.array_equal(used, condition_given_mask(binarised["loose"]))
    assert ndimage.label(binarised["loose"], np.ones((3, 3)))[1] > 10
    assert ndimage.label(used, np.ones((3, 3)))[1] == 1     # the specks are gone


def test_empty_and_wrong_shapes():
    assert not condition_given_mask(np.zeros((8, 8), dtype=np.uint8)).any()
    with pytest.raises(ValueError, match="2D"):
        condition_given_mask(np.zeros((4, 4, 4), dtype=bool))

"""The frame check on raw bench-phantom frames of the independent realbench family.

An empty silicone phantom in air (no contrast) shows its tubes as tram tracks: walls denser
than the middle. The mask that follows such a tube passes every other frame rule (a band
denser than both sides, along the projected tree, above the noise); the frame check must
refuse it as not contrast-filled, while the same phantom filled with iodine passes.

An air-filled phantom in a water bath is a negative angiogram: its lumen attenuates less than
the water around it, and since either display polarity is accepted its mask looks like a
vessel's. The metal in and along it (guidewire, catheter marker) says which grey side is dense;
the frame check must refuse the lumen on the other side, in either display polarity, while the
iodine-filled phantom passes in both.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent / "benchmarks"))

import realbench_frames as rb  # noqa: E402
from FevarPlannerLib import quality  # noqa: E402

SEED = 483


def rendered_fills(water: bool, fills: dict, inverted=None):
    """Seed 483's phantom on a bench with or without a water bath, rendered once per named
    ``fill`` (the same noise each time), with its projected tree; ``inverted`` forces the
    display's polarity (None: the seed's own)."""
    case = rb.make_case(SEED)
    rng = np.random.default_rng([SEED, 11])
    bench = replace(rb.draw_bench(rng, case.intraop), water=water)
    chain = rb.draw_chain(rng, (case.carm.rows, case.carm.cols))
    chain = chain if inverted is None else replace(chain, inverted=inverted)
    shown = {}
    for name, fill in fills.items():
        grey, mask, _ = rb.render_frame(case, bench, chain, np.random.default_rng([SEED, 13]), contrast=True, fill=fill)
        shown[name] = (grey, mask)
    return shown, quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_true)


AIR = rb.Fill(0.0, 0.0, 0.0, {"renal": 1.0, "iliac": 1.0, "other": 1.0}, 0, "air")


@pytest.fixture(scope="module")
def frames():
    filled = rb.Fill(60.0, 0.2, 0.3, {"renal": 0.9, "iliac": 0.9, "other": 0.8}, 3, "water")
    return rendered_fills(False, {"empty": AIR, "filled": filled})


def test_contrast_filled_phantom_passes_the_frame_check(frames):
    shown, prior = frames
    grey, mask = shown["filled"]
    report = quality.check_frame_mask(mask, prior, frame=grey)
    assert report["filled_share"]["aorta"] >= 0.9


def test_empty_phantom_is_refused_as_not_contrast_filled(frames):
    shown, prior = frames
    grey, mask = shown["empty"]
    with pytest.raises(quality.QualityError, match="not filled with contrast"):
        quality.check_frame_mask(mask, prior, frame=grey)


@pytest.fixture(scope="module")
def bath_frames():
    iodine = rb.Fill(40.0, 0.3, 0.3, {"renal": 0.9, "iliac": 0.9, "other": 0.8}, 3, "water")
    rendered, prior = rendered_fills(True, {"air": AIR, "iodine": iodine}, inverted=False)
    shown = {}
    for name, (grey, mask) in rendered.items():
        shown[name, False] = (grey, mask)
        shown[name, True] = (255 - grey, mask)        # the display's grey scale inverted
    return shown, prior


@pytest.mark.parametrize("inverted", [False, True])
def test_iodine_phantom_in_a_water_bath_passes_in_either_polarity(bath_frames, inverted):
    shown, prior = bath_frames
    grey, mask = shown["iodine", inverted]
    report = quality.check_frame_mask(mask, prior, frame=grey)
    assert report["dense_side"] == (1 if inverted else -1)


@pytest.mark.parametrize("inverted", [False, True])
def test_air_filled_phantom_in_a_water_bath_is_refused_as_a_negative_angiogram(bath_frames, inverted):
    shown, prior = bath_frames
    grey, mask = shown["air", inverted]
    with pytest.raises(quality.QualityError, match="less dense than their surroundings: air or CO2, not iodine"):
        quality.check_frame_mask(mask, prior, frame=grey)
    assert quality.dense_side(grey, mask) == (1 if inverted else -1)


def test_collimator_leaves_inside_a_round_field_are_unexposed():
    """Leaves that let a few per cent through are held at the display's extreme level but are
    not flat enough for the corner flood: they must be unexposed too, and the field kept."""
    from FevarPlannerLib.pipeline.visibility import shutter_filled

    seed = 480
    case = rb.make_case(seed)
    rng = np.random.default_rng([seed, 11])
    bench = rb.draw_bench(rng, case.intraop)
    chain = rb.draw_chain(rng, (case.carm.rows, case.carm.cols))
    chain = replace(chain, collimator=(0.0, 0.0, 0.13 * case.carm.cols, 0.1 * case.carm.cols, 2.0), inverted=False)
    grey, _, _ = rb.render_frame(case, bench, chain, np.random.default_rng([seed, 13]), contrast=True)
    exposed = rb.exposed_field(grey.shape, chain)
    in_circle = rb._round_field(grey.shape, chain) >= 1.0
    _, unexposed = shutter_filled(grey)
    assert unexposed is not None
    leaves = in_circle & ~exposed
    assert np.mean(unexposed[leaves]) >= 0.6
    assert np.mean(unexposed[exposed]) <= 0.01

"""An aorta over a vertebral body's edge on an unsubtracted frame (issue 11): a band, not a step.

Where a vertebral body lies under part of the aorta, the line opening that flattens an
unsubtracted frame's background fits in the aorta and the body together: the aorta's part off
the body was flattened away and the mask kept only its part over the body (bench seed 249,
every distractor: Dice 0.82, half of the aorta off the bodies missed; now 0.90). The aorta's own
two edges are still there, of equal size, whatever step lies between them: the flattening now
keeps, within the projected aorta's lumen on frames with bone under the vessels, the contrast of
a band between a rise and a matching fall as far apart as the vessel is wide
(``fluoro._bands_between_edges``).
"""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from FevarPlannerLib import quality
from FevarPlannerLib import segmentation as seg
from FevarPlannerLib.phantom import distractors
from FevarPlannerLib.phantom.fluoro import _project_tubes
from FevarPlannerLib.segmentation import fluoro

RADIUS = 8.0          # px: a wide vessel on the reduced grid
WIDTH = 96


def profile_rows(levels_by_column, rows: int = 8) -> np.ndarray:
    """An image whose rows all carry the same profile (vessels bright)."""
    return np.repeat(np.asarray(levels_by_column, dtype=np.float32)[None, :], rows, axis=0)


def aorta_with_step(step_at: int, step_to: int, bone: float, iodine: float = 0.3) -> np.ndarray:
    """A vessel's chord profile (centre column 40, RADIUS) over a bone plateau from ``step_at`` to
    ``step_to`` (columns), on a zero background, blurred by 1 px (the detector, the block mean)."""
    u = np.arange(WIDTH, dtype=np.float32)
    chord = iodine * np.sqrt(np.clip(1.0 - ((u - 40.0) / RADIUS) ** 2, 0.0, None))
    return profile_rows(ndimage.gaussian_filter1d(chord + bone * ((u >= step_at) & (u < step_to)), 1.0))


@pytest.mark.parametrize("step_at, step_to", [(42, 90), (0, 37)])
def test_a_band_spans_the_whole_vessel_across_a_bone_step_inside_it(step_at, step_to):
    image = aorta_with_step(step_at, step_to, bone=0.6)         # the bone twice as dense as the iodine
    band = fluoro._bands_between_edges(image, (0, 1), RADIUS)[4]
    inside = np.abs(np.arange(WIDTH) - 40.0) <= RADIUS - 3.0      # the edges are read R / 3 px inside
    outside = np.abs(np.arange(WIDTH) - 40.0) >= RADIUS + 2.0
    assert band[inside].min() >= 0.5 * 0.3                 # the whole lumen, at the iodine's contrast
    assert band[outside].max() == 0.0                      # not the bone beyond the vessel


def test_a_bone_just_beyond_the_vessel_does_not_widen_it():
    # the body's far edge 3 px beyond the vessel's: a band as wide as the vessel ends at its own edge
    image = aorta_with_step(36, 40 + int(RADIUS) + 3, bone=0.3)
    band = fluoro._bands_between_edges(image, (0, 1), RADIUS)[4]
    assert band[np.arange(WIDTH) >= 40 + RADIUS + 1.5].max() == 0.0


def test_a_step_alone_is_no_band():
    u = np.arange(WIDTH)
    image = profile_rows(ndimage.gaussian_filter1d(0.5 * (u >= 40.0), 1.0))
    assert fluoro._bands_between_edges(image, (0, 1), RADIUS).max() == 0.0


@pytest.fixture(scope="module")
def vertebrae_under_the_aorta():
    """Bench seed 249's unsubtracted frame with every distractor: its vertebral bodies lie under the
    aorta's right half, their far edge beyond the aorta's."""
    case = distractors.bench_case(249)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    frame = distractors.render_bench_frame(case, np.random.default_rng(249))
    aorta_only = dataclasses.replace(case.intraop, vessels={"aorta": case.intraop.vessels["aorta"]})
    aorta, _ = _project_tubes(aorta_only, case.P_true, frame.mask.shape)
    return prior, frame, aorta


def test_the_aorta_off_the_vertebral_bodies_is_kept(vertebrae_under_the_aorta):
    prior, frame, aorta = vertebrae_under_the_aorta
    off_bone = aorta & ~frame.parts["spine"]
    mask = seg.segment_fluoro(frame.frame, prior)
    assert (mask & off_bone).sum() / off_bone.sum() >= 0.7      # 0.49 before (0.77 now)
    assert seg.dice(mask, frame.mask) >= 0.88                   # 0.82 before (0.90 now)


def bands_one_pixel_at_a_time(part: np.ndarray, step: tuple, radius: float) -> np.ndarray:
    """The bands between edges read pixel by pixel along the lines (the definition of
    ``fluoro._bands_between_edges``, slowly): every pixel tried as a band's rise at every width,
    narrowest first, each rise and each fall taken once."""
    reach, shortest, longest = fluoro._band_extents(step, radius)
    rows, cols = part.shape

    def on_grid(p):
        return 0 <= p[0] < rows and 0 <= p[1] < cols

    def at(p, n):
        return (p[0] + n * step[0], p[1] + n * step[1])

    def value(p):
        return part[p] if on_grid(p) else np.inf

    def jump(p):
        change = value(at(p, reach)) - value(at(p, -reach)) if on_grid(p) else 0.0
        return change if np.isfinite(change) else 0.0

    def steepest(p, sign):
        here = sign * jump(p)
        return here if here > 0 and here >= sign * jump(at(p, 1)) and here >= sign * jump(at(p, -1)) else 0.0

    pixels = [(r, c) for r in range(rows) for c in range(cols)]
    rise = {p: steepest(p, 1.0) for p in pixels}
    fall = {p: steepest(p, -1.0) for p in pixels}
    rise_taken, fall_taken, bands = set(), set(), []
    for width in range(shortest, longest + 1):
        taken = []
        for s in pixels:
            end = at(s, width)
            if s in rise_taken or not on_grid(end) or end in fall_taken:
                continue
            contrast = min(rise[s], fall[end])
            if not (contrast > 0 and contrast >= fluoro.BAND_EDGE_BALANCE * max(rise[s], fall[end])):
                continue
            least = min(value(at(s, reach + j)) for j in range(max(width - 2 * reach, 1)))
            flank = min(value(at(s, -reach)), value(at(end, reach)))
            if least - flank >= fluoro.BAND_INSIDE * contrast:
                taken.append((s, end, width, contrast, flank))
        for s, end, width_, contrast, flank in taken:
            rise_taken.add(s)
            fall_taken.add(end)
            bands.append((s, width_, contrast, flank))
    best, lowest = np.zeros_like(part), np.full_like(part, np.inf)
    for s, width, contrast, flank in bands:
        for k in range(1, width):
            best[at(s, k)] = max(best[at(s, k)], contrast)
            lowest[at(s, k)] = min(lowest[at(s, k)], flank)
    return np.where(best > 0, np.clip(part - np.where(best > 0, lowest, 0.0), 0.0, best), 0.0)


def vessels_over_steps(seed: int, size: int = 40) -> np.ndarray:
    """A noisy frame (vessels bright) of bright bars 4-14 px wide, across and along, some
    crossing a bone's step, and a ramp: many rises and falls, matching and not."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:size, 0:size].astype(np.float64)
    image = 0.004 * c + 0.3 * (r + rng.uniform(-8, 8) * np.sign(c - 20) > rng.uniform(10, 30))
    for _ in range(4):
        angle, offset, width = rng.uniform(0, np.pi), rng.uniform(-15, 15), rng.uniform(4, 14)
        across = (c - 20) * np.cos(angle) + (r - 20) * np.sin(angle) - offset
        image += rng.uniform(0.2, 0.5) * (np.abs(across) < width / 2)
    return ndimage.gaussian_filter(image, 0.8) + rng.normal(0.0, 0.02, image.shape)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("step", [(0, 1), (1, 1), (1, 0), (1, -1)])
def test_the_bands_paired_from_the_rises_are_those_of_every_pixel_and_width(seed, step):
    image = vessels_over_steps(seed)
    for radius in (2.2, 4.0):
        expected = bands_one_pixel_at_a_time(image, step, radius)
        assert (expected > 0).sum() >= 40                       # the frame has bands to find
        np.testing.assert_array_equal(fluoro._bands_between_edges(image, step, radius), expected)
        needed = np.zeros(image.shape, dtype=bool)
        needed[12:28, 15:30] = True                             # only these: only the rises near them paired
        np.testing.assert_array_equal(fluoro._bands_between_edges(image, step, radius, needed),
                                      np.where(needed, expected, 0.0))

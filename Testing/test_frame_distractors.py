"""Frame segmentation with the projected pre-operative tree as prior: thin renal arteries keep
their width and their tips (issue 11; the image-only cases of issue 10)."""

import numpy as np
import pytest

from FevarPlannerLib import phantom as ph
from FevarPlannerLib import quality
from FevarPlannerLib import segmentation as seg
from fixtures import coarse_phantom_folders


@pytest.fixture(scope="module")
def rendered():
    rng = np.random.default_rng(7)
    case = ph.generate_case(ph.random_params(rng))
    frame, truth = ph.render_fluoro(case.intraop, case.P_true, case.carm, case.params, rng)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    return frame, truth, prior


def _renal_zone(prior, shape):
    distance, nearest = prior.rasterise(shape, 1)
    labels = np.asarray(prior.labels)[np.maximum(nearest, 0)]
    return np.isin(labels, ["renal_left", "renal_right"]) & (distance < 40)


def test_thin_renals_keep_their_width(rendered):
    frame, truth, prior = rendered
    mask = seg.segment_fluoro(frame, prior)
    zone = _renal_zone(prior, truth.shape)
    ratio = (mask & zone).sum() / (truth & zone).sum()
    assert 0.9 <= ratio <= 1.1, ratio           # was 0.6: renals came out about half as wide
    assert seg.dice(mask, truth) >= 0.93


def test_noise_frame_is_refused_in_one_line(rendered):
    frame, _, prior = rendered
    noise = np.random.default_rng(3).normal(2000, 300, frame.shape)
    with pytest.raises(quality.QualityError, match="frame check") as failure:
        quality.check_frame_mask(seg.segment_fluoro(noise, prior), prior, frame=noise)
    assert "\n" not in str(failure.value)


# ----------------------------------------------------------------------------------------
# Unusable frames through the command line: exit code 2, one line, a QC picture
# ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_case(tmp_path_factory):
    """A small phantom case (lumen mask, raw frame as PNG, geometry) and its frame."""
    from PIL import Image

    full, case = coarse_phantom_folders(tmp_path_factory.mktemp("frames"), "case", ("aorta_mask.nrrd", "geometry.json"))
    from FevarPlannerLib import io

    frame = io.load_case(full).fluoro.image.astype(float)
    frame = (255 * (frame - frame.min()) / (frame.max() - frame.min())).astype(np.uint8)
    Image.fromarray(frame).save(case / "fluoro.png")
    return case, frame


def _plan_with_frame(case, frame, out, capsys):
    from PIL import Image

    from FevarPlannerLib import cli

    Image.fromarray(frame).save(case / "fluoro.png")
    code = cli.main(["-q", "plan", str(case), "--out", str(out)])
    return code, capsys.readouterr().err.strip()


def test_an_angiogram_plans_and_unusable_frames_are_refused_with_a_qc_picture(small_case, tmp_path, capsys):
    case, frame = small_case
    code, _ = _plan_with_frame(case, frame, tmp_path / "good", capsys)
    assert code == 0 and (tmp_path / "good" / "segmentation_qc.png").exists()
    rng = np.random.default_rng(11)
    background = np.full(frame.shape, np.median(frame))
    unusable = {"noise": rng.integers(0, 255, frame.shape).astype(np.uint8),
                "no_contrast": np.clip(background + rng.normal(0, 4, frame.shape), 0, 255).astype(np.uint8),
                "wrong_anatomy": np.ascontiguousarray(frame.T)}    # the tree lies across, not down
    for name, bad in unusable.items():
        out = tmp_path / name
        code, err = _plan_with_frame(case, bad, out, capsys)
        assert code == 2, (name, err)
        assert len(err.splitlines()) == 1 and "fluoro.png" in err, (name, err)
        assert (out / "segmentation_qc.png").stat().st_size > 1000, name


def test_a_run_with_the_bolus_arriving_is_segmented_on_its_fullest_frame():
    import dataclasses

    rng = np.random.default_rng(12)
    case = ph.generate_case(ph.random_params(rng))
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    run, truth = [], None
    for fill in (0.0, 0.3, 1.0, 0.6):          # contrast arriving, full, washing out
        attenuation = fill * case.params.fluoro_attenuation_per_mm
        params = dataclasses.replace(case.params, fluoro_attenuation_per_mm=attenuation)
        frame, mask = ph.render_fluoro(case.intraop, case.P_true, case.carm, params, np.random.default_rng(5))
        run.append(frame)
        truth = mask if fill == 1.0 else truth
    run = np.stack(run)
    assert seg.select_frame(run, prior) == 2
    assert seg.dice(seg.segment_fluoro(run, prior), truth) >= 0.95


# ----------------------------------------------------------------------------------------
# Bench frames (phantom.distractors): bones, the phantom's box and rail, table, collimator,
# devices, ruler, text and exposure; unsubtracted and DSA, either polarity
# ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bench():
    from FevarPlannerLib.phantom import distractors

    case = distractors.bench_case(102)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    return case, prior


def _render(case, seed, **kwargs):
    from FevarPlannerLib.phantom import distractors

    return distractors.render_bench_frame(case, np.random.default_rng(seed), **kwargs)


def _taken(mask, truth, part) -> float:
    """The fraction of a distractor's pixels (away from the vessels) that the mask takes."""
    from scipy import ndimage as ndi

    away = part & ~ndi.binary_dilation(truth, iterations=3)
    return float((mask & away).sum() / max(away.sum(), 1))


def test_bench_frames_draw_each_distractor_and_subtraction_removes_the_bones(bench):
    case, _ = bench
    raw = _render(case, 1, distractors=("spine", "wire", "text"))
    dsa = _render(case, 1, distractors=("spine", "wire", "text"), subtracted=True)
    bright = _render(case, 1, distractors=("spine", "wire", "text"), polarity="bright")
    assert set(raw.parts) == {"spine", "wire", "text"} and set(dsa.parts) == {"wire", "text"}
    spine = raw.parts["spine"] & ~raw.mask
    assert np.median(raw.frame[spine]) < 0.8 * np.median(dsa.frame[spine])     # the vertebrae absorb
    assert np.median(bright.frame[raw.mask]) > np.median(bright.frame[~raw.mask])  # vessels bright
    with pytest.raises(ValueError, match="unknown"):
        _render(case, 1, distractors=("bone",))


def test_unsubtracted_frame_keeps_the_vessels_and_drops_the_spine(bench):
    case, prior = bench
    frame = _render(case, 2, distractors=("spine",))
    mask = seg.segment_fluoro(frame.frame, prior)
    assert seg.dice(mask, frame.mask) >= 0.85          # 0.62-0.67 before the background flattening
    assert _taken(mask, frame.mask, frame.parts["spine"]) <= 0.1


@pytest.mark.parametrize("drawn", [("spine",), ("exposure",)])
def test_an_aorta_cut_at_its_renal_ostia_is_not_taken_for_vertebral_bodies(drawn):
    """Bench case 238: the aorta's pixels at the renal ostia lie nearest the renals' first nodes;
    judged by the renals' radius they were not wide, the aorta's core broke in pieces and the
    whole angiogram was taken for vertebrae without contrast (an empty mask, Dice 0). The
    widest projected radius nearby keeps it: 0.90 (spine) and 0.98 (exposure)."""
    from FevarPlannerLib.phantom import distractors

    case = distractors.bench_case(238)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    frame = _render(case, 238, distractors=drawn)
    assert seg.dice(seg.segment_fluoro(frame.frame, prior), frame.mask) >= 0.85


@pytest.mark.parametrize("subtracted, polarity, least", [(False, "dark", 0.8), (True, "bright", 0.93)])
def test_bench_frame_with_every_distractor(bench, subtracted, polarity, least):
    case, prior = bench
    frame = _render(case, 3, subtracted=subtracted, polarity=polarity)
    mask = seg.segment_fluoro(frame.frame, prior)
    assert seg.dice(mask, frame.mask) >= least
    taken = {name: _taken(mask, frame.mask, part) for name, part in frame.parts.items()}
    assert max(taken.values()) <= 0.1, taken
    quality.check_frame_mask(mask, prior, frame=frame.frame)      # an angiogram passes the gate


@pytest.mark.parametrize("subtracted, drawn", [(False, None), (True, None), (False, ("spine",))])
def test_bench_frame_without_contrast_is_refused_in_one_line(bench, subtracted, drawn):
    from FevarPlannerLib.phantom import distractors

    case, prior = bench
    frame = _render(case, 4, subtracted=subtracted, contrast=False, distractors=drawn or distractors.DISTRACTORS)
    with pytest.raises(quality.QualityError, match="frame check") as failure:
        quality.check_frame_mask(seg.segment_fluoro(frame.frame, prior), prior, frame=frame.frame)
    assert "\n" not in str(failure.value)


def test_line_opening_flattens_plateaus_and_steps_but_keeps_a_tube():
    from scipy import ndimage as ndi

    from FevarPlannerLib.segmentation import fluoro

    image = np.random.default_rng(0).random((40, 50)).astype(np.float32)
    footprint = np.zeros((13, 13), dtype=bool)
    footprint[6 + np.arange(6), 6 + np.arange(6)] = True            # 6 pixels along the diagonal
    reference = ndi.grey_opening(image, footprint=footprint)
    mine = fluoro._line_opening(image, (1, 1), 5 * np.sqrt(2))
    assert np.allclose(mine[8:-8, 8:-8], reference[8:-8, 8:-8])
    columns = np.arange(80)
    plateau = 0.3 * ((columns >= 10) & (columns < 60))               # a vertebra: 50 px wide
    tube = 0.2 * np.sqrt(np.clip(1 - ((columns - 30) / 6.0) ** 2, 0, None))   # a vessel: 12 px wide
    image = np.tile(plateau + tube + 0.001 * columns, (30, 1)).astype(np.float32)  # and an exposure slope
    across = fluoro.LinesAcross({(0, 20.0): np.ones(image.shape, dtype=bool)})
    flat = fluoro._flatten_across(image, across)[15]
    assert flat[30] > 0.2 and np.abs(np.delete(flat, np.arange(23, 38))).max() < 0.05


def test_unsubtracted_bench_frames_through_plan_run_or_exit_2(small_case, tmp_path, capsys):
    """The command line on the small case with its frame rendered as an unsubtracted bench frame
    (spine, pelvis, box, devices, ...): with contrast it plans; without, exit code 2, one line."""
    from FevarPlannerLib.phantom import distractors

    case_dir, _ = small_case
    case = ph.generate_case(ph.PhantomParams(ct_spacing_mm=2.0, detector_pixel_mm=1.2, seed=3), name="case")
    for contrast, expected in ((True, 0), (False, 2)):
        frame = distractors.render_bench_frame(case, np.random.default_rng(8), contrast=contrast).frame
        code, err = _plan_with_frame(case_dir, frame, tmp_path / str(contrast), capsys)
        assert code == expected, (contrast, err)
        if expected == 2:
            assert len(err.splitlines()) == 1 and "fluoro.png" in err and "frame check" in err, err


def test_flattening_is_skipped_only_where_the_background_is_already_flat(bench):
    """A DSA frame without a collimator shutter in view (even exposure, or the heel effect and
    vignetting) skips the line openings (~4 ms at 1024^2) and keeps its Dice; an unsubtracted
    spine frame and a DSA frame with a shutter across the vessels are flattened."""
    from unittest import mock

    from FevarPlannerLib.segmentation import fluoro

    case, prior = bench
    devices = ("wire", "catheter", "text")
    frames = ((_render(case, 2, subtracted=True, distractors=devices), False, 0.95),
              (_render(case, 5, subtracted=True, distractors=devices + ("exposure",)), False, 0.95),
              (_render(case, 2, distractors=("spine",)), True, 0.85),
              (_render(case, 5, subtracted=True, distractors=devices + ("collimator",)), True, 0.95))
    for frame, flattened, least in frames:
        with mock.patch.object(fluoro, "_flatten_across", wraps=fluoro._flatten_across) as flatten:
            mask = seg.segment_fluoro(frame.frame, prior)
        assert flatten.called == flattened
        assert seg.dice(mask, frame.mask) >= least


def test_square_opening_clears_the_corners_of_a_block_beside_a_diagonal_vessel():
    """A line across a diagonal vessel does not fit in the corners of an upright block (a
    vertebral body by a renal or an iliac): without the square opening they stay as bright
    triangles; with it they go, and the vessel stays."""
    from unittest import mock

    from FevarPlannerLib.segmentation import fluoro

    rows, cols = np.mgrid[0:80, 0:80]
    block = 0.3 * ((rows >= 20) & (rows < 50) & (cols >= 10) & (cols < 50))
    tube = 0.2 * np.sqrt(np.clip(1 - ((rows + cols - 120) / (4.0 * np.sqrt(2))) ** 2, 0, None))   # runs along (1, -1)
    image = (block + tube).astype(np.float32)
    across = fluoro.LinesAcross({(1, 12.0): np.ones(image.shape, dtype=bool)})            # lines along (1, 1)
    corners = np.zeros(image.shape, dtype=bool)
    corners[20:24, 46:50] = corners[46:50, 10:14] = True
    with mock.patch.object(fluoro, "SQUARE_ON_DIAGONALS", False):
        without = fluoro._flatten_across(image, across)
    with_square = fluoro._flatten_across(image, across)
    assert without[corners].max() > 0.25                     # the triangles the lines leave
    assert with_square[corners].max() < 0.01
    assert with_square[60, 60] > 0.19 and without[60, 60] > 0.19       # the vessel's centre
    assert np.abs(with_square[block > 0]).max() < 0.01       # the block is all background


def test_integer_frames_give_the_same_mask_as_their_float_copy(bench):
    from FevarPlannerLib.files import InputError

    case, prior = bench
    frame = _render(case, 2, distractors=("spine",)).frame
    assert frame.dtype == np.uint16
    assert np.array_equal(seg.segment_fluoro(frame, prior), seg.segment_fluoro(frame.astype(np.float64), prior))
    spoiled = frame.astype(np.float64)
    spoiled[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        seg.segment_fluoro(spoiled, prior)


def test_renals_and_iliacs_beside_vertebral_bodies_keep_the_dice():
    """Bench case 212, spine alone: 0.90 before the square opening beside diagonal lines (the
    vertebral corners by the renals and iliacs were kept), 0.93 with it."""
    from FevarPlannerLib.phantom import distractors

    case = distractors.bench_case(212)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    frame = distractors.render_bench_frame(case, np.random.default_rng(212), distractors=("spine",))
    mask = seg.segment_fluoro(frame.frame, prior)
    assert seg.dice(mask, frame.mask) >= 0.92
    assert _taken(mask, frame.mask, frame.parts["spine"]) <= 0.03

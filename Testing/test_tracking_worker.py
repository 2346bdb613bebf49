"""``track``: each frame's check in the view worker while this process registers (issue 10).

The frame check (:func:`quality.check_frame_mask`) runs in the worker process on runs of
``tracking.WORKER_MIN_FRAMES`` frames or more; the frame's answer, warnings and refusal are
the ones of the check done here, and a short run starts no worker.
"""

import warnings

import numpy as np
import pytest
from PIL import Image

from FevarPlannerLib import io, quality, tracking
from FevarPlannerLib.cache import preop_model
from FevarPlannerLib.pipeline import workers
from fixtures import phantom_run_folder


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(case, pre-operative model, prior) of a phantom run: two noisy angiograms and a frame of noise."""
    folder, _ = phantom_run_folder(tmp_path_factory.mktemp("run"), 2, noise_at=1)
    case = io.load_case(folder, frame=0)
    preop = preop_model(case, use_cache=False).preop
    return case, preop, quality.FluoroPrior.from_centerline(preop.centerline, case.P)


@pytest.fixture
def sent(monkeypatch):
    """The jobs given to workers.submit, as (function name, remote)."""
    found = []
    submit = workers.submit

    def recorded(function, *args):
        job = submit(function, *args)
        found.append((function.__name__, job.remote))
        return job

    monkeypatch.setattr(workers, "submit", recorded)
    yield found
    workers.set_enabled(None)


def _frame(run, index):
    """register_run_frame of frame ``index``: (result or the InputError's text, warnings, times)."""
    case, preop, prior = run
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result, times = tracking.register_run_frame(preop, case, index, prior=prior)
        except io.InputError as exc:
            return str(exc), [], {}
    return result, sorted(str(w.message) for w in caught), times


def test_a_frame_checked_in_the_worker_registers_and_is_refused_as_checked_here(run, sent):
    workers.set_enabled(True)
    assert workers.wait_until_ready(120.0)
    remote = [_frame(run, index) for index in range(3)]
    workers.set_enabled(False)
    local = [_frame(run, index) for index in range(3)]
    assert sent == [("_frame_check_and_warnings", True)] * 3 + [("_frame_check_and_warnings", False)] * 3
    for (far, far_warnings, far_times), (near, near_warnings, near_times) in zip(remote, local):
        assert far_warnings == near_warnings
        if isinstance(near, str):
            assert far == near and "not a usable angiogram" in near
            continue
        np.testing.assert_array_equal(far.deformed.points, near.deformed.points)
        assert far.warnings == near.warnings and far.energy == near.energy
        assert set(far_times) == set(near_times) == set(tracking.TIMED_STEPS) | {"total"}
        assert far_times["total"] == pytest.approx(sum(far_times[step] for step in tracking.TIMED_STEPS))
    assert isinstance(local[1][0], str) and not isinstance(local[0][0], str) and not isinstance(local[2][0], str)


def test_the_checks_warnings_reach_the_frame_as_if_it_ran_here(run, monkeypatch):
    case, preop, prior = run
    check = quality.check_frame_mask

    def warning_check(*args, **kwargs):
        warnings.warn("contrast is low here", RuntimeWarning)
        return check(*args, **kwargs)

    monkeypatch.setattr(quality, "check_frame_mask", warning_check)
    mask = np.zeros(case.fluoro.image.shape, dtype=bool)
    error, caught, side = tracking._frame_check_and_warnings(preop, mask, prior, case.fluoro.image)
    assert isinstance(error, quality.QualityError) and caught == [(RuntimeWarning, "contrast is low here")]
    assert side is None
    workers.set_enabled(False)
    try:
        _, messages, _ = _frame(run, 0)
    finally:
        workers.set_enabled(None)
    assert "contrast is low here" in messages


def test_a_short_run_starts_no_worker_and_a_long_one_uses_it(run, sent, monkeypatch):
    case, _, _ = run
    workers.set_enabled(None)
    tracking.track_case(case.case_dir, count=2)
    assert sent and not any(remote for _, remote in sent)
    assert workers.set_enabled(None) is None            # the caller's setting is back
    sent.clear()
    monkeypatch.setattr(tracking, "WORKER_MIN_FRAMES", 2)
    workers.set_enabled(True)
    assert workers.wait_until_ready(120.0)
    result = tracking.track_case(case.case_dir)
    assert [remote for _, remote in sent] == [True] * 3
    assert [r.fit_2d_px is None for r in result.records] == [False, True, False]


def test_a_run_parsed_once_gives_read_fluoros_frames_and_errors(run, tmp_path):
    case, _, _ = run
    frames = io.FluoroRun(case.fluoro.path)
    for index in (2, 0, 1):
        once, each = frames.frame(index), io.read_fluoro(case.fluoro.path, frame=index)
        np.testing.assert_array_equal(once.image, each.image)
        assert once.image.dtype == each.image.dtype
        assert (once.carm, once.pixel_spacing, once.frame, once.n_frames, once.missing_tags) == \
            (each.carm, each.pixel_spacing, each.frame, each.n_frames, each.missing_tags)
    for bad in (3, -1):
        with pytest.raises(io.InputError) as once:
            frames.frame(bad)
        with pytest.raises(io.InputError) as each:
            io.read_fluoro(case.fluoro.path, frame=bad)
        assert str(once.value) == str(each.value)
    picture = tmp_path / "frame.png"
    Image.fromarray(np.arange(64, dtype=np.uint8).reshape(8, 8)).save(picture)
    np.testing.assert_array_equal(io.FluoroRun(picture).frame(0).image, io.read_fluoro(picture).image)
    with pytest.raises(io.InputError, match="missing.dcm: no such file"):
        io.FluoroRun(tmp_path / "missing.dcm").frame(0)


def test_a_tracked_frame_of_a_round_field_is_segmented_and_registered_as_plan_does(tmp_path):
    """``track`` takes a frame's mask from the same route as ``plan`` (``pipeline.segment_frame``:
    the round field's surround filled, no vessel kept there) and registers it with the frame,
    so that nodes beyond the field get no data term (it segmented the raw frame and registered
    the mask without the frame before)."""
    import pydicom

    from FevarPlannerLib.pipeline import register_frame, segment_frame

    folder, _ = phantom_run_folder(tmp_path, 1)
    dataset = pydicom.dcmread(folder / "fluoro.dcm")
    pixels = dataset.pixel_array.copy()
    rows, cols = np.indices(pixels.shape[-2:])
    half = pixels.shape[-1] / 2.0
    outside = (rows - half) ** 2 + (cols - half) ** 2 > (0.42 * pixels.shape[-1]) ** 2
    pixels[..., outside] = 0
    dataset.PixelData = pixels.tobytes()
    dataset.save_as(folder / "fluoro.dcm")
    case = io.load_case(folder, frame=0)
    preop = preop_model(case, use_cache=False).preop
    prior = quality.FluoroPrior.from_centerline(preop.centerline, case.P)
    workers.set_enabled(False)
    try:
        result, times, frame, mask = tracking._registered_run_frame(preop, case, 0, method="proposed",
                                                                   start="iliac_right", target="renal_left",
                                                                   prior=prior, run=None)
    finally:
        workers.set_enabled(None)
    np.testing.assert_array_equal(mask, segment_frame(frame.image, prior))
    assert not (mask & outside).any()
    planned = register_frame(preop, mask, case.P, image=frame.image)
    assert planned.views[0].visibility.field is not None
    np.testing.assert_array_equal(result.deformed.points, planned.deformed.points)

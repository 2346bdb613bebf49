"""The display's polarity is the run's: ``track`` reads it off a frame's metal until one shows it,
then the frame check of the frames after it uses that side instead of reading again (issue 10:
the reading, two grey top-hats near the mask, was a fixed cost of every frame)."""

import numpy as np
import pytest

from FevarPlannerLib import phantom, quality, tracking
from FevarPlannerLib.pipeline import workers
from fixtures import phantom_run_folder
from test_realbench import bath_frames  # noqa: F401  (the fixture: seed 483 in a water bath)


@pytest.fixture
def no_reading(monkeypatch):
    """quality.dense_side made to fail: a check given the run's side must not read the frame."""
    def unread(grey, mask):
        raise AssertionError("the metal was read again")

    monkeypatch.setattr(quality, "dense_side", unread)


@pytest.mark.parametrize("inverted", [False, True])
def test_a_known_side_refuses_the_air_filled_frame_and_passes_the_iodine_one_without_reading(bath_frames,  # noqa: F811
                                                                                            no_reading, inverted):
    shown, prior = bath_frames
    side = 1 if inverted else -1
    grey, mask = shown["iodine", inverted]
    assert quality.check_frame_mask(mask, prior, frame=grey, run_dense_side=side)["dense_side"] == side
    with pytest.raises(quality.QualityError, match="less dense than their surroundings"):
        quality.check_frame_mask(mask, prior, frame=grey, run_dense_side=-side)
    grey, mask = shown["air", inverted]
    with pytest.raises(quality.QualityError, match="less dense than their surroundings: air or CO2, not iodine"):
        quality.check_frame_mask(mask, prior, frame=grey, run_dense_side=side)


def test_the_run_side_is_kept_from_the_first_verdict_and_learnt_from_passed_checks_only():
    polarity = tracking._RunPolarity()
    for side in (None, 0):
        polarity.learn(side)
        assert polarity.dense_side is None
    polarity.learn(-1)
    polarity.learn(1)
    assert polarity.dense_side == -1


def _with_a_guidewire(folder, generated) -> None:
    """The run's frames with a guidewire in the vessels: a 2-pixel line down the middle of each
    row's vessel pixels, much darker than the contrast (the metal shows the dense side: dark)."""
    import pydicom

    _, truth = phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                     np.random.default_rng(0))
    dataset = pydicom.dcmread(folder / "fluoro.dcm")
    pixels = dataset.pixel_array.copy()
    for row in np.flatnonzero(truth.any(axis=1)):
        middle = int(np.flatnonzero(truth[row]).mean())
        pixels[..., row, middle:middle + 2] //= 4
    dataset.PixelData = pixels.tobytes()
    dataset.save_as(folder / "fluoro.dcm")


def _tracked(folder, monkeypatch, learn: bool):
    """track_case of the run (no worker): (its records, the frame checks' run_dense_side per call, readings)."""
    given, readings = [], []
    check, read = quality.check_frame_mask, quality.dense_side

    def spied_check(*args, **kwargs):
        given.append(kwargs.get("run_dense_side"))
        return check(*args, **kwargs)

    def spied_read(grey, mask):
        readings.append(read(grey, mask))
        return readings[-1]

    monkeypatch.setattr(quality, "check_frame_mask", spied_check)
    monkeypatch.setattr(quality, "dense_side", spied_read)
    if not learn:
        monkeypatch.setattr(tracking._RunPolarity, "learn", lambda self, side: None)
    workers.set_enabled(False)
    try:
        records = tracking.track_case(folder).records
    finally:
        workers.set_enabled(None)
        monkeypatch.undo()
    return records, given, readings


def test_track_reads_the_runs_polarity_once_and_answers_every_frame_as_reading_each(tmp_path, monkeypatch):
    """A run of three angiograms with a guidewire and a frame of noise second: the first frame's
    check reads the metal, the noise frame is refused before the polarity rule (nothing learnt
    from it), the last frames are checked with the first one's side, unread; every frame's answer
    is the one of the check reading every frame."""
    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(tmp_path / "cache"))
    folder, generated = phantom_run_folder(tmp_path, 3, noise_at=1)
    _with_a_guidewire(folder, generated)
    once, given, readings = _tracked(folder, monkeypatch, learn=True)
    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(tmp_path / "cache"))
    each, given_each, readings_each = _tracked(folder, monkeypatch, learn=False)
    assert len(readings) == 1 and readings[0] != 0
    assert given == [None, readings[0], readings[0], readings[0]] and given_each == [None] * 4
    assert len(readings_each) == 3 and set(readings_each) == {readings[0]}
    assert [r.fit_2d_px is None for r in once] == [False, True, False, False]
    for a, b in zip(once, each):
        assert (a.frame, a.fit_2d_px, a.path_length_mm, a.warnings) == (b.frame, b.fit_2d_px, b.path_length_mm,
                                                                         b.warnings)

"""The surround search of a raw frame runs once per frame (issue 10, per-frame time).

A frame with a round (image-intensifier) field is searched for its flooded flat surround,
the collimator leaves inside it and its collimated bands (``pipeline.visibility.find_field``)
by the segmentation (the surround filled) and by the visibility (nodes beyond the field get
no data term). The per-frame path hands the segmentation's search to the visibility; the
results are those of the two searches it replaced, to the bit.
"""

from dataclasses import replace

import numpy as np
import pytest

from FevarPlannerLib import phantom, quality, segmentation
from FevarPlannerLib.pipeline import frame, visibility, workers
from fixtures import preop_model

FIELD_RADIUS = 0.42       # of the frame's side: the corners and 41 rows / columns along each side lie outside


def _round_field(image: np.ndarray) -> np.ndarray:
    """``image`` seen through a round field (a black surround, flat bands along the sides)."""
    rows, cols = np.indices(image.shape)
    half = image.shape[0] / 2.0
    seen = image.copy()
    seen[(rows - half) ** 2 + (cols - half) ** 2 > (FIELD_RADIUS * image.shape[0]) ** 2] = 0
    return seen


@pytest.fixture(scope="module")
def round_frame():
    """(pre-operative model, P, raw 512 x 512 frame through a round field, prior) of a phantom."""
    params = replace(phantom.random_params(np.random.default_rng(410), ct_spacing_mm=2.0), detector_rows=512,
                     detector_cols=512)
    case = phantom.generate_case(params, name="round")
    preop = preop_model(case)
    image, _ = phantom.render_fluoro(case.intraop, case.P_given, case.carm, case.params,
                                     np.random.default_rng([params.seed, 2]))
    prior = quality.FluoroPrior.from_centerline(preop.centerline, case.P_given)
    return preop, case.P_given, _round_field(image), prior


def _counting(monkeypatch, name: str) -> list:
    """Count the calls of ``visibility.<name>`` (the call still runs)."""
    calls = []
    original = getattr(visibility, name)

    def counted(*args, **kwargs):
        calls.append(name)
        return original(*args, **kwargs)

    monkeypatch.setattr(visibility, name, counted)
    return calls


def _assert_same_visibility(found: visibility.Visibility, expected: visibility.Visibility) -> None:
    assert found.shape == expected.shape and found.exposed == expected.exposed
    assert found.clipped_border == expected.clipped_border and found.margin_px == expected.margin_px
    assert (found.field is None) == (expected.field is None)
    if expected.field is not None:
        np.testing.assert_array_equal(found.field.unexposed, expected.field.unexposed)
        np.testing.assert_array_equal(found.field.distance_px, expected.field.distance_px)
        assert found.field.margin_px == expected.field.margin_px


def test_the_per_frame_path_searches_a_round_fields_surround_once(round_frame, monkeypatch):
    preop, P, image, prior = round_frame
    # the route as it was: the segmentation and the visibility each search the frame
    filled, unexposed = visibility.shutter_filled(image)
    old_mask = segmentation.segment_fluoro(filled, prior) & ~unexposed
    old_visibility = visibility.frame_visibility(old_mask, image)
    assert old_visibility.field is not None and old_visibility.exposed == (41, 471, 41, 471)

    searches, bands = _counting(monkeypatch, "_shutter_and_leaves"), _counting(monkeypatch, "_collimated_bands")
    workers.set_enabled(False)
    try:
        outcome = frame.prepare_views(preop, [frame.ViewSource("main", P, image, prior=prior)])[0]
    finally:
        workers.set_enabled(None)
    assert len(searches) == 1 and len(bands) == 1
    np.testing.assert_array_equal(outcome.mask, old_mask)
    _assert_same_visibility(outcome.view.visibility, old_visibility)


def test_a_given_search_gives_the_visibility_and_fill_of_a_new_one(round_frame):
    _, _, image, _ = round_frame
    mask = np.zeros(image.shape, dtype=bool)
    mask[:, 250:262] = True                     # a vessel running into the shutter at both ends
    search = visibility.find_field(image)
    assert search.shutter is not None and not search.shutter.flags.writeable
    _assert_same_visibility(visibility.frame_visibility(mask, image, search), visibility.frame_visibility(mask, image))
    for shared, fresh in zip(visibility.shutter_filled(image, search), visibility.shutter_filled(image)):
        np.testing.assert_array_equal(shared, fresh)
    assert visibility.find_field(np.zeros((3, 8, 8))) is None     # a run of frames: nothing to search


def test_a_tracked_frame_hands_its_search_to_the_registration(round_frame, monkeypatch):
    """``track``'s route (``segment_frame_and_field``, then ``register_frame(..., search=)``) searches
    the frame once and registers it as the route that searches it twice."""
    from FevarPlannerLib.pipeline import register_frame, segment_frame_and_field

    preop, P, image, prior = round_frame
    workers.set_enabled(False)
    try:
        mask, _ = segment_frame_and_field(image, prior)
        twice = register_frame(preop, mask, P, image=image)
        searches = _counting(monkeypatch, "_shutter_and_leaves")
        mask_once, search = segment_frame_and_field(image, prior)
        once = register_frame(preop, mask_once, P, image=image, search=search)
    finally:
        workers.set_enabled(None)
    assert len(searches) == 1
    np.testing.assert_array_equal(mask_once, mask)
    _assert_same_visibility(once.views[0].visibility, twice.views[0].visibility)
    np.testing.assert_array_equal(once.deformed.points, twice.deformed.points)

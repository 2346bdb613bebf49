"""A candidate correspondence that cannot win is not deformed (issue 10, per-frame time).

``pipeline.frame._candidate_trials`` skips the deformation of a candidate whose score floor
(:func:`pipeline.multiview.score_floor`: its share of unassigned 3D nodes, the part of
:func:`matching.candidate_score` known before deforming) is not below the best score so far.
Here: the floor never exceeds the score, the registration is the one that deforms every
candidate, to the bit, and a fallback that asks for the skipped candidates gets them.
"""

from dataclasses import replace

import numpy as np
import pytest

from FevarPlannerLib import phantom, pipeline
from FevarPlannerLib.pipeline import frame, multiview, workers
from FevarPlannerLib.quality import FluoroPrior

ALPHA, BETA = 500.0, 10.0


def _lao_view(seed: int):
    """(pre-operative model, prepared outcomes) of a 512 x 512 LAO 30 raw frame of phantom ``seed``
    (seeds 3 and 10: two candidate correspondences, the second's floor above the first's score;
    seed 4's was, until the frame masks of 2026-11-30 kept a renal's ostium and faint renals)."""
    params = replace(phantom.random_params(np.random.default_rng(seed)), detector_rows=512, detector_cols=512,
                     primary_angle_deg=30.0, secondary_angle_deg=0.0)
    case = phantom.generate_case(params, name=f"floor_{seed}")
    preop = pipeline.preop_from_lumen(phantom.rasterize_lumen(case.preop, case.grid))
    image, _ = phantom.render_fluoro(case.intraop, case.P_true, case.carm, case.params,
                                     np.random.default_rng(params.seed))
    source = frame.ViewSource("lao30", case.P_true, image, prior=FluoroPrior.from_centerline(preop.centerline,
                                                                                             case.P_true))
    workers.set_enabled(False)
    try:
        return preop, frame.prepare_views(preop, [source])
    finally:
        workers.set_enabled(None)


@pytest.fixture(scope="module", params=[3, 10])
def lao_view(request):
    return _lao_view(request.param)


def _counted_deformations(monkeypatch):
    calls = []
    deform = frame._deform_with

    def counted(*args, **kwargs):
        calls.append(args[2])
        return deform(*args, **kwargs)

    monkeypatch.setattr(frame, "_deform_with", counted)
    return calls


def test_the_floor_never_exceeds_the_score_and_equals_it_without_energy_and_stretch(lao_view):
    preop, (outcome,) = lao_view
    view = outcome.view
    assert len(view.candidates) == 2
    for correspondence in view.candidates:
        floor = multiview.score_floor(preop, [view], (correspondence,), ALPHA)
        _, energy, score = multiview._deform_with(preop, [view], (correspondence,), ALPHA, BETA)
        assert 0.0 < floor <= score and energy > 0.0
        unassigned = floor / multiview.matching.UNASSIGNED_PX2      # the share of 3D nodes left without target
        assert 0.0 < unassigned < 1.0


def test_skipping_a_candidate_that_cannot_win_registers_as_deforming_every_one(lao_view, monkeypatch):
    preop, outcomes = lao_view
    calls = _counted_deformations(monkeypatch)
    skipped = frame.register_prepared(preop, outcomes)
    assert len(calls) == 1 and calls[0] == (outcomes[0].view.candidates[0],)     # the second is never deformed
    monkeypatch.setattr(frame, "score_floor", lambda *args: -np.inf)               # every candidate deformed
    every = frame.register_prepared(preop, outcomes)
    assert len(calls) == 3
    np.testing.assert_array_equal(skipped.deformed.points, every.deformed.points)
    assert (skipped.correspondence, skipped.energy, skipped.warnings) == (every.correspondence, every.energy,
                                                                          every.warnings)


def test_a_fallback_that_asks_for_the_skipped_candidate_gets_its_deformation(lao_view, monkeypatch):
    preop, (outcome,) = lao_view
    view = outcome.view
    calls = _counted_deformations(monkeypatch)
    trials, best = frame._candidate_trials(preop, view, ALPHA, BETA)
    assert best == 0 and len(trials) == 2 and len(calls) == 1
    alternatives = frame._alternatives(preop, [view], trials, trials[best][1], ALPHA, BETA)
    assert len(calls) == 2 and [name for _, name in alternatives] == ["candidate 2"]
    deformed = multiview._deform_with(preop, [view], (view.candidates[1],), ALPHA, BETA)[0]
    np.testing.assert_array_equal(alternatives[0][0], deformed)
    frame._alternatives(preop, [view], trials, trials[best][1], ALPHA, BETA)
    assert len(calls) == 2          # deformed once

"""Vessels merged in a view (issue 10): tortuous iliacs crossing in a 70 degree view, where the
frame's skeleton cannot be classified and each node takes its nearest 2D skeleton point.

Two vessels that the estimate puts apart in the view but whose nearest 2D points are one are
both pulled onto one 2D vessel; neither may take its target there
(``multiview._claimed_by_two_vessels``). Iliacs that overlap in the view (side by side in a
lateral view) keep their shared centre line.
"""

import numpy as np
import pytest

from FevarPlannerLib import evaluation, scenarios
from FevarPlannerLib.pipeline import multiview
from FevarPlannerLib.pipeline.frame import register_views
from FevarPlannerLib.preop import preop_from_lumen


def _registered(kind: str, seed: int, index: int):
    """(3D error per main vessel (mm), mean 3D error (mm), warnings) of a generated two-view case."""
    case = scenarios.generate(scenarios.plan_scenarios(kind, 4, seed=seed)[index])
    preop = preop_from_lumen(case.lumen)
    result = register_views(preop, [(v.mask, v.P_given) for v in case.views], names=[v.name for v in case.views])
    depth = evaluation.depth_analysis(result.deformed, preop.centerline, case.preop.centerline(),
                                      case.intraop.centerline(), case.views[0].P_true)
    per_vessel = {label: row["3d_mm"] for label, row in depth["per_vessel"].items()}
    return per_vessel, depth["3d_mm"]["mean"], result.warnings


@pytest.fixture(scope="module")
def crossing_iliacs():
    """Seed 36, case 3: main view and a 70 degree view in which the iliacs cross; the second
    view's skeleton has 4 ends (a renal hidden), so it gives nearest-point targets."""
    return _registered("two_views", 36, 2)


def test_crossing_iliacs_in_a_nearest_point_view_do_not_pull_one_iliac_onto_the_other(crossing_iliacs):
    """Before: both iliacs took the nearest points of one 2D leg in the 70 degree view, and the
    right iliac was 13.8 mm off in 3D (the case 2.57 mm). Now the shared points give no target:
    the right iliac within 2 mm (measured 1.3), the case under 1 mm (measured 0.73)."""
    per_vessel, mean, warnings = crossing_iliacs
    assert any("nearest 2D skeleton points" in w for w in warnings)      # the view is unclassified
    assert per_vessel["iliac_right"] < 2.0
    assert per_vessel["iliac_left"] < 2.0
    assert mean < 1.0


def test_vessels_apart_in_the_view_claiming_one_2d_point_get_no_target(crossing_iliacs, monkeypatch):
    """The rule off (every nearest point is a target) brings the 13.8 mm back: the test can fail."""
    monkeypatch.setattr(multiview, "_claimed_by_two_vessels", lambda view, nodes, *args: np.zeros(len(nodes), bool))
    per_vessel, _, _ = _registered("two_views", 36, 2)
    assert per_vessel["iliac_right"] > 8.0

"""Two views (issue 10): the second view follows the first one's estimate.

The first view Algorithm 1 classifies (the anchor) gives the first deformation alone; every
other view then adds nearest-point targets on its own 2D skeleton, each 3D branch on the 2D
leg assigned to it one-to-one. Two failures pinned here on generated two-view cases:

* a classified 70 degree view whose iliacs overlap below the bifurcation: its 2D junction is
  where the legs part in the image, 20-30 mm below the anatomical one, and its own match
  stretched the aorta to it (seed 42, case 3: iliacs 7.3 mm off after the fallback to the
  first view alone);
* an iliac whose first estimate lies at the wrong depth, so far from its 2D leg in the
  second view that the view-wide outlier limit took all its targets, and whose upper nodes,
  past the leg's junction end inside the merged silhouette, were pulled down along the
  vessel (seed 39, case 3: 5.7 mm on that iliac).

A result that still leaves a view's silhouette is flagged (``outside_silhouette_warnings``).
"""

from types import SimpleNamespace

import numpy as np
import pytest

from FevarPlannerLib import evaluation, scenarios
from FevarPlannerLib.pipeline import multiview
from FevarPlannerLib.pipeline.frame import _prepare_view, register_views
from FevarPlannerLib.preop import preop_from_lumen


def _case(seed: int, index: int):
    case = scenarios.generate(scenarios.plan_scenarios("two_views", 4, seed=seed)[index])
    return case, preop_from_lumen(case.lumen)


def _errors(case, preop, deformed):
    """(3D error per main vessel (mm), mean 3D error (mm)) of a deformed centre line."""
    depth = evaluation.depth_analysis(deformed, preop.centerline, case.preop.centerline(),
                                      case.intraop.centerline(), case.views[0].P_true)
    return {label: row["3d_mm"] for label, row in depth["per_vessel"].items()}, depth["3d_mm"]["mean"]


def _registered(case, preop, views=None):
    views = case.views if views is None else views
    return register_views(preop, [(v.mask, v.P_given) for v in views], names=[v.name for v in views])


@pytest.fixture(scope="module")
def crossed_legs():
    """Seed 42, case 3: AP and a 70 degree view whose skeleton Algorithm 1 classifies."""
    return _case(42, 2)


@pytest.fixture(scope="module")
def beyond_the_cap():
    """Seed 39, case 3: AP and a 70 degree view with 4 skeleton ends (unclassified)."""
    return _case(39, 2)


def test_a_classified_second_view_with_overlapping_legs_follows_the_first(crossed_legs):
    """Measured: iliacs 0.52 / 0.40 mm, case 0.50 mm (before: 7.3 / 7.3 and 2.94 mm; the
    view's own match stretched the aorta by 5.2 % and the guard fell back to AP alone)."""
    case, preop = crossed_legs
    result = _registered(case, preop)
    per_vessel, mean = _errors(case, preop, result.deformed)
    assert result.views[1].classification2d is not None          # Algorithm 1 did label the view
    assert result.views[1].correspondence == "nearest points"    # ... and its labels are not used
    assert per_vessel["iliac_left"] < 1.5 and per_vessel["iliac_right"] < 1.5
    assert mean < 1.0
    assert not any("outside the vessels" in w or "replaced by" in w for w in result.warnings)


def test_an_iliac_far_off_its_leg_still_reaches_it(beyond_the_cap, monkeypatch):
    """Measured: left iliac 0.65 mm, case 0.58 mm (before: 5.8 and 1.21 mm). Either rule off
    leaves the left iliac over 3 mm off: targets past a leg's end kept (9.7 mm), or the
    view-wide outlier limit for a branch with a leg (4.9 mm, flagged 1.1 mm outside the
    70 degree view's silhouette). The test can fail. The counterfactuals run with the solver's
    own stall window on the refinement (multiview.WARM_START_WINDOW None): with the shorter one
    the passes reach the leg even without the past-the-end rule (0.54 mm)."""
    case, preop = beyond_the_cap
    result = _registered(case, preop)
    per_vessel, mean = _errors(case, preop, result.deformed)
    assert per_vessel["iliac_left"] < 1.5 and mean < 1.0
    assert not any("outside the vessels" in w for w in result.warnings)
    monkeypatch.setattr(multiview, "WARM_START_WINDOW", None)
    monkeypatch.setattr(multiview, "_past_leg_ends", lambda g2, leg, index, uv: np.zeros(len(index), dtype=bool))
    assert _errors(case, preop, _registered(case, preop).deformed)[0]["iliac_left"] > 3.0
    monkeypatch.undo()
    monkeypatch.setattr(multiview, "WARM_START_WINDOW", None)
    monkeypatch.setattr(multiview, "_outlier_limits", lambda distance, usable, legs: np.full(
        len(distance), multiview.CLOSEST_POINT_OUTLIER * max(float(np.median(distance[usable])), 1.0)))
    assert _errors(case, preop, _registered(case, preop).deformed)[0]["iliac_left"] > 3.0


def test_a_result_the_second_view_contradicts_is_flagged(crossed_legs):
    """The first view alone leaves the iliacs at the CT's depth, 7 mm off: checked against
    both views it lies outside the 70 degree view's silhouette (about 2-3 mm), and each iliac
    is named; the two-view result is not flagged."""
    case, preop = crossed_legs
    alone = _registered(case, preop, case.views[:1])
    views = [_prepare_view(preop, v.mask, v.P_given, v.name, None, "proposed", "auto", {}) for v in case.views]
    flagged = multiview.outside_silhouette_warnings(preop, views, alone.deformed.points)
    assert any("iliac_left" in w for w in flagged) and any("iliac_right" in w for w in flagged)
    assert all(w.startswith(f"view {case.views[1].name}:") for w in flagged)
    assert multiview.outside_silhouette_warnings(preop, views, _registered(case, preop).deformed.points) == []


# ---------------------------------------------------------------------------------------
# The rules on hand-made data: a 1 px = 1 mm orthographic view, u = x, v = -z
# ---------------------------------------------------------------------------------------

P_FRONT = np.array([[1.0, 0.0, 0.0, 200.0], [0.0, 0.0, -1.0, 200.0], [0.0, 0.0, 0.0, 1.0]])


def _skeleton2d(chains, radius=3.0):
    """A 2D SkeletonGraph from polylines given as lists of points (1 px steps, shared ends merged)."""
    from FevarPlannerLib.graph import SkeletonGraph

    points, edges, index = [], [], {}

    def node(p):
        key = (round(p[0], 6), round(p[1], 6))
        if key not in index:
            index[key] = len(points)
            points.append(key)
        return index[key]

    for a, b in chains:
        a, b = np.asarray(a, float), np.asarray(b, float)
        steps = np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(b - a))) + 1)
        ids = [node(a + t * (b - a)) for t in steps]
        edges += list(zip(ids[:-1], ids[1:]))
    g2 = SkeletonGraph.from_points(np.array(points, float), np.array(edges))
    g2.radii = np.full(len(points), radius)
    return g2


def test_a_branch_off_its_own_leg_keeps_a_limit_of_its_own():
    """The view's median distance is 0.5 px (limit 5 px); a branch that lies 8 px off its own
    leg throughout keeps its targets (limit 40 px), the nodes without a leg keep 5 px."""
    distance = np.r_[np.full(30, 0.5), np.full(10, 8.0)]
    usable = np.ones(40, dtype=bool)
    limit = multiview._outlier_limits(distance, usable, {3: (np.arange(30, 40), 1)})
    np.testing.assert_allclose(limit, np.r_[np.full(30, 5.0), np.full(10, 40.0)])
    assert (distance <= limit).all()
    assert not (distance <= multiview._outlier_limits(distance, usable, {}))[30:].any()


def test_points_past_either_end_of_a_leg_are_found():
    """A leg from a junction at (200, 100) down to (200, 140), beside a trunk: a point level
    with the leg is not past it; points below the free end and above the junction end are."""
    g2 = _skeleton2d([((200, 60), (200, 100)), ((200, 100), (200, 140)), ((200, 100), (230, 130))])
    leg = multiview._skeleton_legs(g2)
    down = leg[np.argmin(np.linalg.norm(g2.positions - (200, 140), axis=1))]
    on_leg = np.flatnonzero(leg == down)
    uv = np.array([[203.0, 120.0], [201.0, 150.0], [199.0, 95.0]])
    from scipy.spatial import cKDTree
    index = on_leg[cKDTree(g2.positions[on_leg]).query(uv)[1]]
    assert multiview._past_leg_ends(g2, leg, index, uv).tolist() == [False, True, True]


def test_outside_the_silhouette_is_measured_over_the_union_of_disks():
    """A vertical 2D vessel of radius 3 px: points 2 px off its centre line are inside (0 mm),
    points 7 px off are 4 mm outside (within 0.02: disks 1 px apart); a result 7 px off is flagged, one 2 px off is not."""
    g2 = _skeleton2d([((200, 50), (200, 150))])
    view = SimpleNamespace(name="side", P=P_FRONT, g2=g2, visible=np.ones(40, dtype=bool))
    z = -np.linspace(60.0, 140.0, 40) + 200.0                  # v = -z + 200 -> rows 60..140
    near = np.c_[np.full(40, 2.0), np.zeros(40), z]
    far = np.c_[np.full(40, 7.0), np.zeros(40), z]
    np.testing.assert_allclose(multiview.outside_silhouette_mm(view, near, np.zeros(3)), 0.0, atol=1e-9)
    np.testing.assert_allclose(multiview.outside_silhouette_mm(view, far, np.zeros(3)), 4.0, atol=0.02)   # disks 1 px apart
    preop = SimpleNamespace(centerline=SimpleNamespace(labels=["iliac_left"] * 40), kept=np.arange(40),
                            centre=np.zeros(3))
    assert multiview.outside_silhouette_warnings(preop, [view], near) == []
    flagged = multiview.outside_silhouette_warnings(preop, [view], far)
    assert flagged == ["view side: the iliac_left lies 4.0 mm outside the vessels of this view on average: "
                       "the views disagree on it; check it before use"]

"""Vessels merged in a view (issue 10): tortuous iliacs crossing in a 70 degree view, where the
frame's skeleton cannot be classified and each node takes its nearest 2D skeleton point.

Two vessels that part at an acute angle and that the estimate puts apart in the view, but
whose nearest 2D points are one, are both pulled onto one 2D vessel; neither may take its
target there (``multiview._claimed_by_two_vessels``). Iliacs that overlap in the view (side
by side in a lateral view) keep their shared centre line.
"""

import numpy as np
import pytest

from FevarPlannerLib import evaluation, scenarios
from FevarPlannerLib.matching import paper
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
    right iliac was 13.8 mm off in 3D (the case 2.57 mm). Now the shared points give no target
    and each iliac takes its own 2D leg: the right iliac within 2 mm (measured 0.59; 1.3 with
    the shared-point rule alone), the case under 1 mm (measured 0.50; 0.73 before the legs)."""
    per_vessel, mean, warnings = crossing_iliacs
    assert any("nearest 2D skeleton points" in w for w in warnings)      # the view is unclassified
    assert per_vessel["iliac_right"] < 2.0
    assert per_vessel["iliac_left"] < 2.0
    assert mean < 1.0


def test_vessels_apart_in_the_view_claiming_one_2d_point_get_no_target(monkeypatch):
    """Each of the two rules alone keeps the right iliac within 2 mm: the shared points giving
    no target (one-to-one legs off: measured 1.3 mm) and the one-to-one legs (shared-point rule
    off: measured 0.53 mm). Both off (every nearest point is a target) brings the 13.8 mm back
    when the main view's iliacs are counted from the 2D junction in the crotch, as eq. (4) has
    it (``paper.CROTCH_RADII`` out of reach): the test can fail. (Counted from where the legs
    part, the main view's iliac targets lie 1-3 px from the truth instead of 9-10 px, and
    this case no longer needs either rule: 1.24 mm with both off.)"""
    monkeypatch.setattr(multiview, "_legs_of_vessels", lambda *args: {})
    assert _registered("two_views", 36, 2)[0]["iliac_right"] < 2.0
    monkeypatch.setattr(multiview, "_claimed_by_two_vessels", lambda view, nodes, *args: np.zeros(len(nodes), bool))
    monkeypatch.setattr(paper, "CROTCH_RADII", 1e9)
    assert _registered("two_views", 36, 2)[0]["iliac_right"] > 8.0
    monkeypatch.undo()
    monkeypatch.setattr(multiview, "_claimed_by_two_vessels", lambda view, nodes, *args: np.zeros(len(nodes), bool))
    assert _registered("two_views", 36, 2)[0]["iliac_right"] < 2.0


# ---------------------------------------------------------------------------------------
# The rule on a hand-made tree: a 1 px = 1 mm orthographic view, u = x, v = -z
# ---------------------------------------------------------------------------------------

P_FRONT = np.array([[1.0, 0.0, 0.0, 200.0], [0.0, 0.0, -1.0, 200.0], [0.0, 0.0, 0.0, 1.0]])


def _polyline(a, b, step=1.0):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a + np.linspace(0.0, 1.0, int(np.linalg.norm(b - a) / step) + 1)[:, None] * (b - a)


def _tree(vessels):
    """A 3D SkeletonGraph and its stand-in pre-op from {label: (start, end, radius)} (each
    vessel a chain of 1 mm steps; a vessel starting where another one's chain passes joins it)."""
    from types import SimpleNamespace

    from FevarPlannerLib.graph import SkeletonGraph

    positions, edges, labels, radii, branches = [], [], [], [], []
    for label, (start, end, radius) in vessels.items():
        chain = _polyline(start, end)
        first = len(positions)
        if positions:
            joint = int(np.argmin(np.linalg.norm(np.asarray(positions) - chain[0], axis=1)))
            edges.append((joint, first))
        positions += list(chain)
        edges += [(first + k, first + k + 1) for k in range(len(chain) - 1)]
        labels += [label] * len(chain)
        radii += [radius] * len(chain)
        branches.append(SimpleNamespace(nodes=np.arange(first, first + len(chain))))
    positions = np.asarray(positions)
    adjacency = SkeletonGraph._weighted_adjacency(positions, np.asarray(edges))
    g3 = SkeletonGraph(positions, adjacency, radii=np.asarray(radii))
    classification = SimpleNamespace(node_labels=labels, branches=branches[1:])
    return SimpleNamespace(graph=g3, classification=classification)


def _claimed_in_front_view(preop, legs, radius2=6.0):
    """Labels flagged by the rule when the frame's 2D skeleton is the polylines ``legs`` (u, v)."""
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from FevarPlannerLib.projection import project

    points2 = np.concatenate([_polyline(a, b) for a, b in legs])
    view = SimpleNamespace(P=P_FRONT, g2=SimpleNamespace(positions=points2, radii=np.full(len(points2), radius2)))
    nodes = np.arange(len(preop.graph.positions))
    uv = project(P_FRONT, preop.graph.positions)
    index = cKDTree(points2).query(uv)[1]
    claimed = multiview._claimed_by_two_vessels(view, nodes, preop, preop.graph.positions, uv, index)
    labels = np.asarray(preop.classification.node_labels, dtype=object)
    return {label: int(np.count_nonzero(claimed & (labels == label))) for label in dict.fromkeys(labels)}


def test_two_iliacs_apart_in_the_view_on_one_2d_leg_lose_their_targets_side_by_side_keep_them():
    """Iliacs parting at 28 degrees, 14 mm apart at their ends (radius 4: apart in the view):
    the frame shows one leg between them (the other off at u = +60), so both iliacs' nearest
    points lie on it: more than half of each is claimed by two, so each loses all its targets.
    The same iliacs nearly on top of each other (3 mm apart at the ends: they overlap in the
    view) keep them."""
    parted = _tree({"aorta": ((0, 0, 100), (0, 0, 0), 9.0), "iliac_left": ((0, 0, 0), (-7, 0, -28), 4.0),
                    "iliac_right": ((0, 0, 0), (7, 0, -28), 4.0)})
    legs = [((200, 100), (200, 200)), ((200, 200), (200, 228)), ((200, 200), (260, 228))]
    flagged = _claimed_in_front_view(parted, legs)
    assert flagged["aorta"] == 0
    assert flagged["iliac_left"] == flagged["iliac_right"] == 29         # every node: the whole branch
    together = _tree({"aorta": ((0, 0, 100), (0, 0, 0), 9.0), "iliac_left": ((0, 0, 0), (-1.5, -20, -28), 4.0),
                      "iliac_right": ((0, 0, 0), (1.5, 20, -28), 4.0)})
    assert _claimed_in_front_view(together, legs) == {"aorta": 0, "iliac_left": 0, "iliac_right": 0}


def test_renals_running_on_from_one_another_along_the_rays_keep_their_shared_points(monkeypatch):
    """Renals leaving the aorta towards and away from the viewer, 12 px apart at their tips
    (apart in the view) and both nearest to the aorta's 2D centre line: the path between them
    along the tree is as long as their distance (they do not part at an acute angle), so they
    keep their targets; counting every pair (PARTED_DETOUR 0) would flag them."""
    renals = _tree({"aorta": ((0, 0, 100), (0, 0, 0), 9.0), "renal_left": ((0, 0, 60), (6, 30, 60), 3.0),
                    "renal_right": ((0, 0, 60), (-6, -30, 60), 3.0)})
    legs = [((200, 100), (200, 200))]
    assert _claimed_in_front_view(renals, legs) == {"aorta": 0, "renal_left": 0, "renal_right": 0}
    monkeypatch.setattr(multiview, "PARTED_DETOUR", 0.0)
    flagged = _claimed_in_front_view(renals, legs)
    assert flagged["renal_left"] > 10 and flagged["renal_right"] > 10


# ---------------------------------------------------------------------------------------
# One-to-one legs: each 3D branch of a nearest-point view keeps to its own 2D leg
# ---------------------------------------------------------------------------------------

def _skeleton2d(legs):
    """A 2D SkeletonGraph of polylines (u, v) in 1 px steps; a polyline starting on an earlier
    one's node joins it there (a junction)."""
    from FevarPlannerLib.graph import SkeletonGraph

    points, edges = [], []
    for a, b in legs:
        chain = list(_polyline(a, b))
        if points:
            joint = int(np.argmin(np.linalg.norm(np.asarray(points) - chain[0], axis=1)))
            chain = chain[1:]
            edges.append((joint, len(points)))
        first = len(points)
        points += chain
        edges += [(first + k, first + k + 1) for k in range(len(chain) - 1)]
    return SkeletonGraph.from_points(np.asarray(points), np.asarray(edges))


@pytest.fixture()
def iliac_between_legs():
    """The aorta and a left iliac on their 2D legs; the right iliac's estimate (to (4, 0, -28))
    lies between the left leg (to u = 193) and its own (to u = 220), nearer the left one."""
    from types import SimpleNamespace

    preop = _tree({"aorta": ((0, 0, 100), (0, 0, 0), 9.0), "iliac_left": ((0, 0, 0), (-7, 0, -28), 4.0),
                   "iliac_right": ((0, 0, 0), (4, 0, -28), 4.0)})
    preop.centre = np.zeros(3)
    g2 = _skeleton2d([((200, 100), (200, 200)), ((200, 200), (193, 228)), ((200, 200), (220, 228))])
    view = SimpleNamespace(P=P_FRONT, g2=g2)
    return preop, view


def _targets_by_leg(preop, view, rule):
    """Per iliac, the number of its nodes whose target lies on the left and on the right 2D leg."""
    from FevarPlannerLib.projection import project

    nodes = np.arange(len(preop.graph.positions))
    uv = project(P_FRONT, preop.graph.positions)
    _, index = rule(view, nodes, preop, uv, np.ones(len(nodes), dtype=bool))
    pieces = multiview._skeleton_legs(view.g2)
    piece = pieces[index]
    left, right = (pieces[np.argmin(np.linalg.norm(view.g2.positions - end, axis=1))] for end in ((193, 228), (220, 228)))
    labels = np.asarray(preop.classification.node_labels, dtype=object)
    return {label: (int(np.count_nonzero((labels == label) & (piece == left))),
                    int(np.count_nonzero((labels == label) & (piece == right))))
            for label in ("iliac_left", "iliac_right")}


def test_the_iliac_between_two_legs_takes_its_own_leg_one_to_one(iliac_between_legs):
    """Nearest points: both iliacs take the left leg with 28 of their 29 nodes (the first sits on
    the junction, in no leg). One-to-one (Hungarian on the mean distance: left iliac 0.04 px on
    the left leg plus right iliac 6.6 px on the right one, against 11.0 + 5.4 px the other way
    round): each iliac takes all its 29 targets on its own leg (the first node too, now off the
    junction)."""
    preop, view = iliac_between_legs

    from scipy.spatial import cKDTree

    def nearest(view, nodes, preop, uv, usable):
        return cKDTree(view.g2.positions).query(uv)

    plain = _targets_by_leg(preop, view, nearest)
    assert plain == {"iliac_left": (28, 0), "iliac_right": (28, 0)}
    assert _targets_by_leg(preop, view, multiview._nearest_on_legs) == {"iliac_left": (29, 0), "iliac_right": (0, 29)}


def test_a_branch_further_than_the_cost_cap_from_every_leg_keeps_its_nearest_points(iliac_between_legs,
                                                                                   monkeypatch):
    """With the cap below the right iliac's 6.6 px on its own leg it takes no leg (the "no leg"
    column is cheaper) and falls back to the nearest points, on the left leg."""
    preop, view = iliac_between_legs
    monkeypatch.setattr(multiview, "LEG_COST_CAP_MM", 3.0)
    legs = _targets_by_leg(preop, view, multiview._nearest_on_legs)
    assert legs == {"iliac_left": (29, 0), "iliac_right": (28, 0)}

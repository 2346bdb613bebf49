"""Robust matching (issue 10): 2D branches the 3D tree lacks, spurs off a wide sac, accessory
renals, eroded tips. One phantom (its pre-operative tree has no internal iliacs, no SMA, no
accessory renal); each test draws a frame of its intra-operative anatomy with something
added or taken away, as a real DSA frame shows it, and registers the pre-operative tree.

Measured before this matching (the tangent / label match on Algorithm 1's five longest 2D
branches): the distal-fork frame 12.2 mm mean 3D error (iliacs 41 and 25 mm, both sent down
the wrong vessel), the accessory-renal frame 1.44 mm (left renal 7.2 mm on the accessory),
the frame without the right renal 4.9 mm (right renal 31.8 mm, laid on a side branch).
"""

from dataclasses import replace

import numpy as np
import pytest

from FevarPlannerLib import evaluation, graph, matching, phantom, pipeline
from FevarPlannerLib.phantom import Anatomy, Vessel
from FevarPlannerLib.projection import pixels_per_mm, project
from fixtures import phantom_case_fixtures

SEED = 5


case, preop = phantom_case_fixtures("m", seed=SEED, misalign_rotation3d_deg=(0.0, 0.0, 0.0))


def frame_mask(case, anatomy):
    """The projected lumen of ``anatomy`` (what a segmented DSA frame gives)."""
    return phantom.render_fluoro(anatomy, case.P_true, case.carm, case.params, np.random.default_rng(0))[1]


def with_vessels(anatomy, **extra):
    return Anatomy({**anatomy.vessels, **extra})


def side_branch(anatomy, parent, index, direction, length, radius):
    """A straight branch (label other) leaving ``parent`` at its point ``index``."""
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    points = anatomy.vessels[parent].points[index] + np.linspace(0.0, length, int(length) + 1)[:, None] * direction
    return Vessel("other", points, radius, radius + 0.5, np.zeros(3), parent=parent, parent_index=index)


def graph_2d(case, preop, mask):
    """The 2D side of pipeline._register_frame: skeleton graph with radii, Algorithm 1, smoothing."""
    P = case.P_true
    g2 = pipeline._skeleton2d_graph(mask, 1.0 / pixels_per_mm(P, preop.centre))
    c2 = pipeline._classify_2d(g2, P, preop.centre)
    return graph.smooth_positions(c2.graph, pipeline.SMOOTHING_ITERATIONS), c2


def matched_ends(case, preop, g2, c2):
    """3D branch label -> 2D position of the end its chain reaches, for the best projection match."""
    best = matching.match_by_projection(preop.graph, preop.classification, g2, c2, case.P_true)[0]
    return {preop.classification.branches[i3].label: g2.positions[chain[-1]] for i3, chain in best.branch_chains.items()}


def true_end(case, anatomy, name):
    return project(case.P_true, anatomy.vessels[name].points[[-1]])[0]


def registered(case, preop, mask):
    frame = pipeline.register_frame(preop, mask, case.P_true)
    truth = case.intraop.to_centerline()
    distance = evaluation.point_to_graph(frame.deformed.points, truth.points, truth.edges)
    labels = np.array(frame.deformed.labels)
    return frame, distance.mean(), {label: distance[labels == label].mean() for label in set(labels)}


def vessel_length(centerline, label):
    inside = np.array(centerline.labels) == label
    edges = centerline.edges[inside[centerline.edges[:, 0]] & inside[centerline.edges[:, 1]]]
    return np.linalg.norm(centerline.points[edges[:, 0]] - centerline.points[edges[:, 1]], axis=1).sum()


# ---------------------------------------------------------------------------------------
# Failure modes of issue 10
# ---------------------------------------------------------------------------------------

def test_distal_iliac_fork_the_3d_iliac_follows_the_continuing_branch(case, preop):
    """Internal iliacs in the frame, one common iliac in 3D: each 3D iliac must run on along
    its external (continuing) arm, never down the internal iliac."""
    forked = replace(case.params, internal_iliacs=True)
    anatomy = phantom.deform_anatomy(phantom.build_preop_anatomy(forked), forked)
    g2, c2 = graph_2d(case, preop, frame_mask(case, anatomy))
    ends = matched_ends(case, preop, g2, c2)
    # left: both arms are in the 2D graph; right: the external arm beyond the fork (16 mm,
    # 10 mm after thinning) is shorter than iota and deleted as a spur, so the internal
    # iliac is all the frame offers, and the 3D iliac follows it only as far as it goes
    reached = ends["iliac_left"]
    assert np.linalg.norm(reached - true_end(case, anatomy, "iliac_left")) < 8.0
    assert np.linalg.norm(reached - true_end(case, anatomy, "internal_iliac_left")) > 25.0
    _, mean, per_vessel = registered(case, preop, frame_mask(case, anatomy))
    assert mean < 1.5  # 12.2 mm before
    assert max(per_vessel["iliac_left"], per_vessel["iliac_right"]) < 3.0


def test_wide_sac_spurs_are_pruned_by_the_local_radius(case, preop):
    """Bumps of a quarter radius on the sac wall thin to spurs longer than iota (10 mm) but
    shorter than two sac radii: with the radius rule they are deleted, with iota alone they
    stay in the graph."""
    aorta = case.intraop.vessels["aorta"]
    middle = int(np.argmax(aorta.radius))
    bumps = {f"bump{k}": side_branch(case.intraop, "aorta", i, d, aorta.radius[i] + 3.0, 6.0)
             for k, (i, d) in enumerate([(middle, [1, 0, 0]), (middle - 15, [-1, 0, 0.2]), (middle + 15, [1, 0, -0.3])])}
    anatomy = with_vessels(case.intraop, **bumps)
    mask = frame_mask(case, anatomy)
    tips = np.array([true_end(case, anatomy, name) for name in bumps])

    def ends_near_bumps(c):
        kept = c.graph.degrees == 1
        positions = c.graph.positions[kept]
        return int(np.sum(np.min(np.linalg.norm(positions[:, None] - tips[None], axis=2), axis=1) < 15.0))

    g2 = pipeline._skeleton2d_graph(mask, 1.0 / pixels_per_mm(case.P_true, preop.centre))
    iota_only = graph.classify(g2, spur_radius_factor=0.0)
    by_radius = graph.classify(g2)
    assert ends_near_bumps(iota_only) >= 2
    assert ends_near_bumps(by_radius) == 0
    g2s, c2 = graph_2d(case, preop, mask)
    ends = matched_ends(case, preop, g2s, c2)
    assert sorted(ends) == sorted(graph.BRANCH_LABELS)
    for label in ("renal_left", "renal_right", "iliac_left", "iliac_right"):
        assert np.linalg.norm(ends[label] - true_end(case, anatomy, label)) < 8.0, label
    _, mean, _ = registered(case, preop, mask)
    assert mean < 1.0


def test_accessory_renal_beside_the_main_one_is_left_unmatched(case, preop):
    """An accessory left renal 10 mm above the main one, as long: the 3D renal (which has no
    accessory) goes to the main renal, the one closest to its projection."""
    renal = case.intraop.vessels["renal_left"]
    aorta = case.intraop.vessels["aorta"]
    above = renal.parent_index - 10
    shifted = renal.points + (aorta.points[above] - aorta.points[renal.parent_index])
    accessory = Vessel("other", shifted, 2.5, 3.0, np.zeros(3), parent="aorta", parent_index=above)
    anatomy = with_vessels(case.intraop, accessory=accessory)
    g2, c2 = graph_2d(case, preop, frame_mask(case, anatomy))
    reached = matched_ends(case, preop, g2, c2)["renal_left"]
    assert np.linalg.norm(reached - true_end(case, anatomy, "renal_left")) < 6.0
    assert np.linalg.norm(reached - true_end(case, anatomy, "accessory")) > 10.0
    _, mean, per_vessel = registered(case, preop, frame_mask(case, anatomy))
    assert per_vessel["renal_left"] < 1.5  # 7.2 mm before
    assert mean < 1.0


def test_a_tip_shorter_by_one_radius_is_not_compressed(case, preop):
    """The left renal ends one radius short in the frame (thinning's erosion): its 3D branch
    keeps its length; the tip nodes beyond the 2D end are left to the TPS."""
    renal = case.intraop.vessels["renal_left"]
    keep = renal.arc_length() <= renal.length - renal.radius[-1]
    short = replace(renal, points=renal.points[keep], radius=renal.radius[keep],
                    outer_radius=renal.outer_radius[keep], outer_offset=renal.outer_offset[keep])
    mask = frame_mask(case, with_vessels(case.intraop, renal_left=short))
    frame, mean, _ = registered(case, preop, mask)
    before, after = vessel_length(preop.centerline, "renal_left"), vessel_length(frame.deformed, "renal_left")
    assert abs(after / before - 1.0) < 0.02
    assert mean < 1.0
    g2, c2 = graph_2d(case, preop, mask)
    best = matching.candidate_correspondences(preop.graph, preop.classification, g2, c2, case.P_true)[0]
    assignment = matching.soft_assign(preop.graph, preop.classification, g2, c2, case.P_true, best)
    branch = preop.classification.branch("renal_left")
    assert not assignment.assigned[branch.end]
    assert assignment.assigned[branch.nodes[: len(branch.nodes) // 2]].all()


def test_a_3d_branch_missing_from_the_frame_gets_no_partner(case, preop):
    """The right renal is not in the frame (not opacified) but a side branch leaves the sac
    towards the right: the 3D right renal stays unmatched instead of landing on it."""
    aorta = case.intraop.vessels["aorta"]
    middle = int(np.argmax(aorta.radius))
    anatomy = Anatomy({name: v for name, v in case.intraop.vessels.items() if name != "renal_right"})
    anatomy = with_vessels(anatomy, lumbar=side_branch(anatomy, "aorta", middle + 10, [-1.0, 0.0, -0.6], 50.0, 2.5))
    g2, c2 = graph_2d(case, preop, frame_mask(case, anatomy))
    best = matching.match_by_projection(preop.graph, preop.classification, g2, c2, case.P_true)[0]
    labels = {preop.classification.branches[i3].label for i3 in best.branch_chains}
    assert labels == set(graph.BRANCH_LABELS) - {"renal_right"}
    _, mean, per_vessel = registered(case, preop, frame_mask(case, anatomy))
    assert per_vessel["iliac_right"] < 2.0 and per_vessel["renal_left"] < 2.0
    assert per_vessel["renal_right"] < 5.0 and mean < 1.5  # 31.8 and 4.9 mm on the side branch before


# ---------------------------------------------------------------------------------------
# Pieces
# ---------------------------------------------------------------------------------------

def test_turned_residual_undoes_a_swing_about_the_junction():
    arc = np.linspace(0.0, 40.0, matching._SAMPLES)
    first = np.stack([arc, 0.1 * arc**1.5], axis=1)[None]
    angle = np.deg2rad(12.0)
    turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    second = first @ turn.T + np.array([5.0, -3.0])
    residual, found = matching._turned_residual(first, second)
    assert residual[0] < 1e-9 and found[0] == pytest.approx(angle)
    assert matching._curve_distances(first, second)[0] > 1.0


def test_candidate_score_counts_stretch_and_unassigned_nodes():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    edges = np.array([[0, 1], [1, 2]])
    assert matching.candidate_score(0.5, 1.0, points, points, edges, 500.0) == pytest.approx(0.5)
    stretched = points * np.array([1.1, 1, 1])
    assert matching.candidate_score(0.5, 1.0, points, stretched, edges, 500.0) == pytest.approx(0.5 + 500 * 0.01)
    assert matching.candidate_score(0.5, 0.8, points, points, edges, 500.0) == pytest.approx(
        0.5 + 0.2 * matching.UNASSIGNED_PX2)

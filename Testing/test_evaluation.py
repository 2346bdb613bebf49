"""Tests of the evaluation metrics: point-to-curve distances (MATLAB distance2curve) and the
2D / 3D errors of the paper."""

import numpy as np
import pytest

from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.evaluation import (common_labels, distance_statistics, error_2d, error_3d, evaluate,
                                        graph_index, point_to_graph, point_to_segments,
                                        restrict_to_labels)
from FevarPlannerLib.projection import CArmGeometry, project, projection_matrix_from_carm

AP = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(0.4, 0.4), primary_angle=0.0,
                  secondary_angle=0.0, rows=512, cols=512)


def brute_force(points, seg_a, seg_b):
    """Reference: loop over every point and segment, clamped projection."""
    out = np.empty(len(points))
    for i, p in enumerate(points):
        best = np.inf
        for a, b in zip(seg_a, seg_b):
            ab = b - a
            t = 0.0 if ab @ ab == 0 else min(1.0, max(0.0, (p - a) @ ab / (ab @ ab)))
            best = min(best, np.linalg.norm(p - (a + t * ab)))
        out[i] = best
    return out


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("n_segments", [5, 300])
def test_point_to_segments_matches_brute_force(dim, n_segments):
    rng = np.random.default_rng(dim * 100 + n_segments)
    seg_a = rng.uniform(-50, 50, size=(n_segments, dim))
    seg_b = seg_a + rng.normal(scale=4.0, size=(n_segments, dim))
    seg_b[::17] = seg_a[::17]                       # some single-point segments
    seg_b[3] = seg_a[3] + 60.0                      # one long segment widens the search bound
    points = rng.uniform(-60, 60, size=(120, dim))
    expected = brute_force(points, seg_a, seg_b)
    np.testing.assert_allclose(point_to_segments(points, seg_a, seg_b), expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(point_to_segments(points, seg_a, seg_b, chunk_elements=7), expected,
                               rtol=1e-12, atol=1e-12)


def test_a_graph_index_answers_far_points_exactly_and_again():
    """Points far from a dense curve need more than the first candidates; the index escalates
    and gives the all-pairs answer, the same on every query."""
    rng = np.random.default_rng(7)
    curve = np.cumsum(rng.normal(size=(400, 2)), axis=0)
    edges = np.stack([np.arange(399), np.arange(1, 400)], axis=1)
    points = curve[rng.integers(0, 400, 60)] + rng.normal(scale=40.0, size=(60, 2))
    index = graph_index(curve, edges)
    expected = brute_force(points, curve[edges[:, 0]], curve[edges[:, 1]])
    np.testing.assert_allclose(index.distances(points), expected, rtol=1e-12, atol=1e-12)
    assert np.array_equal(index.distances(points), point_to_graph(points, curve, edges))
    assert np.array_equal(index.distances(points[::-1])[::-1], index.distances(points))


def test_point_to_segments_hand_cases():
    a, b = np.array([[0.0, 0.0]]), np.array([[10.0, 0.0]])
    points = np.array([[5.0, 3.0],      # above the middle: the perpendicular height
                       [13.0, 4.0],     # beyond the end: distance to the end point (3-4-5)
                       [-6.0, -8.0],    # before the start
                       [2.5, 0.0]])     # on the segment
    np.testing.assert_allclose(point_to_segments(points, a, b), [3.0, 5.0, 10.0, 0.0])
    a3, b3 = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 8.0]])
    np.testing.assert_allclose(point_to_segments([[3.0, 4.0, 2.0], [0.0, 0.0, 11.0]], a3, b3), [5.0, 3.0])


def test_point_to_graph_uses_edges_and_isolated_nodes_not_just_vertices():
    graph = np.array([[0.0, 0.0], [10.0, 0.0], [50.0, 50.0]])   # node 2 has no edge
    d = point_to_graph([[5.0, 2.0], [50.0, 47.0]], graph, [[0, 1]])
    np.testing.assert_allclose(d, [2.0, 3.0])          # the nearest vertex of point 0 is 5.4 away


def test_point_to_segments_rejects_bad_input():
    with pytest.raises(ValueError, match="no segments"):
        point_to_segments([[0.0, 0.0]], np.empty((0, 2)), np.empty((0, 2)))
    with pytest.raises(ValueError, match="NaN"):
        point_to_segments([[np.nan, 0.0]], [[0.0, 0.0]], [[1.0, 0.0]])
    with pytest.raises(ValueError, match="shape"):
        point_to_segments([[0.0, 0.0]], [[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="out of range"):
        point_to_graph([[0.0, 0.0]], [[0.0, 0.0], [1.0, 1.0]], [[0, 2]])


def test_distance_statistics_uses_sample_std():
    stats = distance_statistics([1.0, 2.0, 3.0, 10.0])
    assert stats == pytest.approx({"mean": 4.0, "std": np.std([1, 2, 3, 10], ddof=1), "median": 2.5, "max": 10.0})
    assert distance_statistics([2.0])["std"] == 0.0


def planar_tree() -> Centerline:
    """A Y in the plane z = 0 (the trunk along y, the limbs spreading in x), LPS mm."""
    trunk = np.column_stack([np.zeros(11), np.linspace(-50, 0, 11), np.zeros(11)])
    left = np.column_stack([np.linspace(3, 30, 10), np.linspace(3, 30, 10), np.zeros(10)])
    right = np.column_stack([np.linspace(-3, -30, 10), np.linspace(3, 30, 10), np.zeros(10)])
    points = np.vstack([trunk, left, right])
    edges = [[i, i + 1] for i in range(10)] + [[10, 11]] + [[i, i + 1] for i in range(11, 20)]
    edges += [[10, 21]] + [[i, i + 1] for i in range(21, 30)]
    labels = ["aorta"] * 11 + ["iliac_left"] * 10 + ["iliac_right"] * 10
    return Centerline(points, edges, labels)


def test_evaluate_identical_curves_gives_zero():
    tree = planar_tree()
    P = projection_matrix_from_carm(AP)
    skeleton = project(P, tree.points)
    metrics = evaluate(tree, tree, P, skeleton, tree.edges)
    for key in ("2d_px", "2d_reverse_px", "3d_mm", "3d_reverse_mm", "3d_symmetric_mm"):
        assert metrics[key]["max"] == pytest.approx(0.0, abs=1e-9)
    assert metrics["labels"] == ["aorta", "iliac_left", "iliac_right"]


def test_evaluate_translated_copy_gives_the_offset():
    tree = planar_tree()
    moved = tree.with_points(tree.points + [0.0, 0.0, 2.5])     # off the tree's plane: every distance is 2.5
    P = projection_matrix_from_carm(AP)
    metrics = evaluate(moved, tree, P, project(P, moved.points), moved.edges)
    for key in ("3d_mm", "3d_reverse_mm", "3d_symmetric_mm"):
        assert metrics[key]["mean"] == pytest.approx(2.5)
        assert metrics[key]["max"] == pytest.approx(2.5)
        assert metrics[key]["std"] == pytest.approx(0.0, abs=1e-9)
    assert metrics["2d_px"]["max"] == pytest.approx(0.0, abs=1e-9)


def test_error_2d_known_offset_of_a_straight_vessel():
    P = projection_matrix_from_carm(AP)
    vessel = np.column_stack([np.zeros(20), np.zeros(20), np.linspace(-40, 40, 20)])   # projects to a column
    skeleton = project(P, vessel) + [3.0, 0.0]
    edges = [[i, i + 1] for i in range(19)]
    stats = error_2d(vessel, P, skeleton, edges)
    assert stats["mean"] == pytest.approx(3.0) and stats["max"] == pytest.approx(3.0)


def test_error_3d_reverse_exposes_a_collapsed_result():
    tree = planar_tree()
    collapsed = (np.repeat(tree.points[:1], len(tree), axis=0), tree.edges)   # every node on one gt node
    errors = error_3d(collapsed, tree)
    assert errors["forward"]["max"] == pytest.approx(0.0)
    assert errors["reverse"]["max"] > 40.0
    assert errors["symmetric"]["max"] == errors["reverse"]["max"]


def test_restrict_to_labels_keeps_the_subgraph():
    tree = planar_tree()
    left = restrict_to_labels(tree, ["aorta", "iliac_left"])
    assert len(left) == 21
    assert left.labels.count("iliac_right") == 0
    assert len(left.edges) == 20 and left.edges.max() == 20
    np.testing.assert_array_equal(left.points, tree.points[:21])
    with pytest.raises(ValueError, match="unknown"):
        restrict_to_labels(tree, ["liver"])
    with pytest.raises(ValueError, match="no centreline node"):
        restrict_to_labels(tree, ["renal_left"])


def test_evaluate_compares_only_vessels_present_in_both():
    tree = planar_tree()
    result = restrict_to_labels(tree, ["aorta", "iliac_left"])
    lifted = np.where(np.array(tree.labels)[:, None] == "iliac_right", [0.0, 0.0, 20.0], 0.0)
    gt = tree.with_points(tree.points + lifted)                   # the right limb leaves the plane by 20 mm
    P = projection_matrix_from_carm(AP)
    metrics = evaluate(result, gt, P, project(P, tree.points), tree.edges)
    assert common_labels(result, gt) == ["aorta", "iliac_left"]
    assert metrics["labels"] == ["aorta", "iliac_left"]
    assert metrics["3d_reverse_mm"]["max"] == pytest.approx(0.0, abs=1e-9)   # the moved gt limb is left out
    explicit = evaluate(tree, gt, P, project(P, tree.points), tree.edges, labels=["iliac_right"])
    assert explicit["3d_mm"]["mean"] == pytest.approx(20.0)


def test_evaluate_without_ground_truth_and_bad_labels():
    tree = planar_tree()
    P = projection_matrix_from_carm(AP)
    metrics = evaluate(tree, None, P, project(P, tree.points) + [0.0, 1.0], tree.edges)
    assert metrics["3d_mm"] is None and metrics["3d_reverse_mm"] is None
    assert metrics["2d_px"]["mean"] == pytest.approx(1.0, abs=0.05)
    with pytest.raises(ValueError, match="unknown"):
        evaluate(tree, None, P, project(P, tree.points), tree.edges, labels=["heart"])
    other = Centerline(tree.points, tree.edges, ["renal_left"] * len(tree))
    with pytest.raises(ValueError, match="share no anatomy label"):
        evaluate(tree, other, P, project(P, tree.points), tree.edges)


# --------------------------------------------------------------------------- depth (issue 10)

from FevarPlannerLib.evaluation import (closest_points_on_graph, depth_analysis, depth_floor,  # noqa: E402
                                        depth_floor_points, ray_components)
from FevarPlannerLib.projection import source_position  # noqa: E402

FIVE = ("aorta", "renal_left", "renal_right", "iliac_left", "iliac_right")


def arc_tree(P, radius_from_source, n_per_vessel=40):
    """Five short chains on a sphere about the X-ray source (every node at the same distance)."""
    source = source_position(P)
    points, edges, labels = [], [], []
    for k, label in enumerate(FIVE):
        angles = np.linspace(-0.05, 0.05, n_per_vessel)
        tilt = 0.02 * (k - 2)
        dirs = np.column_stack([np.sin(angles), -np.cos(angles) * np.cos(tilt), np.cos(angles) * np.sin(tilt)])
        assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
        start = len(points)
        points.extend(source + radius_from_source * dirs)
        edges.extend([start + i, start + i + 1] for i in range(n_per_vessel - 1))
        labels.extend([label] * n_per_vessel)
    return Centerline(np.array(points), np.array(edges), labels)


def test_depth_floor_of_an_undeformed_case_is_zero():
    P = projection_matrix_from_carm(AP)
    tree = arc_tree(P, 700.0)
    floor = depth_floor(tree, tree, P)
    assert floor["mean"] == pytest.approx(0.0, abs=1e-9) and floor["max"] == pytest.approx(0.0, abs=1e-9)
    assert set(floor["per_vessel"]) == set(FIVE)


def test_depth_floor_of_a_pure_along_ray_move_equals_the_move():
    P = projection_matrix_from_carm(AP)
    pre, intra = arc_tree(P, 700.0), arc_tree(P, 707.5)      # every node 7.5 mm farther along its ray
    # the oracle puts each true point back at its pre-operative distance: on the pre-op arc
    np.testing.assert_allclose(depth_floor_points(intra.points, pre.points, P), pre.points, atol=1e-9)
    floor = depth_floor(pre, intra, P)
    assert floor["mean"] == pytest.approx(7.5, abs=1e-3)
    assert floor["per_vessel"]["iliac_left"]["max"] == pytest.approx(7.5, abs=1e-3)
    # the rigid result (the pre-op tree) sits on the floor, all of its error along the ray
    rigid = depth_analysis(pre, pre, pre, intra, P)
    assert rigid["3d_mm"]["mean"] == pytest.approx(7.5, abs=1e-3)
    assert rigid["along_ray_mm"]["mean"] == pytest.approx(7.5, abs=1e-3)
    assert rigid["in_plane_mm"]["max"] < 0.01
    assert rigid["out_of_plane_recovered"] == pytest.approx(0.0, abs=1e-3)
    assert rigid["per_vessel"]["renal_left"]["true_along_ray_mm"] == pytest.approx(7.5, abs=1e-6)
    # a result at the true depth recovers all of it; one halfway, half
    perfect = depth_analysis(intra, pre, pre, intra, P)
    assert perfect["3d_mm"]["max"] < 1e-9 and perfect["out_of_plane_recovered"] == pytest.approx(1.0)
    halfway = depth_analysis(arc_tree(P, 703.75), pre, pre, intra, P)
    assert halfway["out_of_plane_recovered"] == pytest.approx(0.5, abs=1e-3)


def test_in_plane_and_along_ray_parts_sum_in_quadrature_to_the_total():
    P = projection_matrix_from_carm(AP)
    truth = arc_tree(P, 720.0)
    rng = np.random.default_rng(5)
    points = truth.points[::3] + rng.normal(scale=3.0, size=(len(truth.points[::3]), 3))
    parts = ray_components(points, truth.points, truth.edges, P)
    np.testing.assert_allclose(parts["distance"] ** 2, parts["along"] ** 2 + parts["in_plane"] ** 2, rtol=1e-9)
    np.testing.assert_allclose(parts["distance"], point_to_graph(points, truth.points, truth.edges), rtol=1e-12)
    assert np.abs(parts["along"]).mean() > 0.5 and parts["in_plane"].mean() > 0.5
    result = Centerline(points, np.empty((0, 2)), truth.labels[::3])
    rms = depth_analysis(result, result, truth, truth, P)["rms_mm"]
    assert rms["3d"] ** 2 == pytest.approx(rms["in_plane"] ** 2 + rms["along_ray"] ** 2)


def test_a_move_along_the_ray_is_all_along_ray_and_a_sideways_move_all_in_plane():
    P = projection_matrix_from_carm(AP)
    source = source_position(P)
    # a segment across the central ray (through the isocentre, at the origin)
    truth = Centerline(np.array([[-10.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), [[0, 1]], ["aorta", "aorta"])
    ray = -source / np.linalg.norm(source)
    parts = ray_components([4.0 * ray, [0.0, 0.0, 3.0]], truth.points, truth.edges, P)
    np.testing.assert_allclose(parts["along"], [4.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(parts["in_plane"], [0.0, 3.0], atol=1e-9)


def test_closest_points_on_graph_hand_case():
    distance, nearest = closest_points_on_graph([[5.0, 3.0], [13.0, 4.0], [50.0, 47.0]],
                                                [[0.0, 0.0], [10.0, 0.0], [50.0, 50.0]], [[0, 1]])
    np.testing.assert_allclose(distance, [3.0, 5.0, 3.0])
    np.testing.assert_allclose(nearest, [[5.0, 0.0], [10.0, 0.0], [50.0, 50.0]])


def test_depth_floor_refuses_truths_that_do_not_correspond():
    P = projection_matrix_from_carm(AP)
    tree = arc_tree(P, 700.0)
    with pytest.raises(ValueError, match="correspond"):
        depth_floor(tree, arc_tree(P, 700.0, n_per_vessel=30), P)

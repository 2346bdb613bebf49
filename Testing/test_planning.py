import numpy as np
import pytest

from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.planning import CatheterPath, path_length, plan_path, resample_path, smooth_path


class TreeBuilder:
    """Builds a labelled centreline from polylines attached to existing nodes."""

    def __init__(self):
        self.points, self.edges, self.labels = [], [], []

    def add(self, polyline, label, attach_to=None) -> list[int]:
        first = len(self.points)
        indices = list(range(first, first + len(polyline)))
        self.points.extend(np.asarray(polyline, dtype=float))
        self.labels.extend([label] * len(polyline))
        self.edges.extend(zip(indices[:-1], indices[1:]))
        if attach_to is not None:
            self.edges.append((attach_to, indices[0]))
        return indices

    def build(self) -> Centerline:
        return Centerline(np.array(self.points), np.array(self.edges), self.labels)


def line(a, b, n):
    return np.linspace(a, b, n)


@pytest.fixture()
def aaa():
    """Aorta along z (bifurcation at z=0), renals at z=150, iliacs down and out (LPS mm)."""
    tree = TreeBuilder()
    # aorta from the bifurcation (node 0) upwards, slightly bulging (the aneurysm)
    z = np.linspace(0.0, 200.0, 41)
    aorta = tree.add(np.column_stack([8 * np.sin(np.pi * z / 200), np.zeros_like(z), z]), "aorta")
    junction = aorta[30]  # z = 150
    p = tree.points[junction]
    tree.add(line(p + [3, 0, 0], p + [45, 5, -6], 12), "renal_left", attach_to=junction)
    tree.add(line(p + [-3, 0, 0], p + [-45, 5, -6], 12), "renal_right", attach_to=junction)
    tree.add(line([4, 0, -4], [60, 10, -120], 25), "iliac_left", attach_to=aorta[0])
    right = tree.add(line([-4, 0, -4], [-60, 10, -120], 25), "iliac_right", attach_to=aorta[0])
    return tree.build(), aorta, junction, right


def test_path_runs_from_right_iliac_end_to_left_renal_ostium(aaa):
    centerline, aorta, junction, right = aaa
    path = plan_path(centerline)
    assert isinstance(path, CatheterPath)
    assert path.nodes[0] == right[-1]
    renal_left = [i for i, label in enumerate(centerline.labels) if label == "renal_left"]
    assert path.nodes[-1] == renal_left[0]
    assert path.nodes[-2] == junction
    expected_nodes = right[::-1] + aorta[:31] + [renal_left[0]]
    np.testing.assert_array_equal(path.nodes, expected_nodes)
    expected = path_length(centerline.points[expected_nodes])
    assert path.length_mm == pytest.approx(expected, abs=1e-6)
    # by hand: iliac segment, link to the bifurcation, aorta arc and the ostium step
    pts = centerline.points
    by_hand = (np.linalg.norm(pts[right[-1]] - pts[right[0]]) + np.linalg.norm(pts[right[0]] - pts[aorta[0]])
               + path_length(pts[aorta[:31]]) + np.linalg.norm(pts[renal_left[0]] - pts[junction]))
    assert path.length_mm == pytest.approx(by_hand, abs=1e-6)
    np.testing.assert_allclose(path.points, pts[path.nodes])
    data = path.to_dict()
    assert data["from"] == "iliac_right" and data["to"] == "renal_left"
    assert data["length_mm"] == pytest.approx(path.length_mm)
    assert np.array(data["points"]).shape == (len(path.nodes), 3)


def test_path_to_the_end_of_the_target_and_other_vessels(aaa):
    centerline, aorta, junction, right = aaa
    labels = np.array(centerline.labels)
    path = plan_path(centerline, start="iliac_left", target="renal_right", to="end")
    assert labels[path.nodes[0]] == "iliac_left" and labels[path.nodes[-1]] == "renal_right"
    assert path.nodes[-1] == np.flatnonzero(labels == "renal_right")[-1]
    assert path.nodes[0] == np.flatnonzero(labels == "iliac_left")[-1]
    # the path only visits the two vessels and the aorta
    assert set(labels[path.nodes]) == {"iliac_left", "aorta", "renal_right"}


def test_node_order_and_edge_direction_do_not_matter(aaa):
    centerline, *_ = aaa
    rng = np.random.default_rng(3)
    order = rng.permutation(len(centerline))
    inverse = np.argsort(order)
    shuffled = Centerline(centerline.points[order], inverse[centerline.edges[:, ::-1]],
                          [centerline.labels[i] for i in order])
    a, b = plan_path(centerline), plan_path(shuffled)
    np.testing.assert_allclose(a.points, b.points)
    assert a.length_mm == pytest.approx(b.length_mm, abs=1e-9)


def test_path_follows_the_deformed_positions(aaa):
    centerline, *_ = aaa
    moved = centerline.with_points(centerline.points * [1.0, 1.0, 1.1] + [5.0, -3.0, 2.0])
    path = plan_path(moved)
    np.testing.assert_array_equal(path.nodes, plan_path(centerline).nodes)
    np.testing.assert_allclose(path.points, moved.points[path.nodes])


def test_shortcut_through_a_loop_is_taken(aaa):
    centerline, aorta, junction, right = aaa
    # a skeleton artefact: a direct chord between aorta nodes 5 and 25 (shorter than the arc)
    chord = Centerline(centerline.points, np.vstack([centerline.edges, [[aorta[5], aorta[25]]]]),
                       centerline.labels)
    path = plan_path(chord)
    assert path.length_mm < plan_path(centerline).length_mm
    assert aorta[10] not in path.nodes


def test_missing_label_is_named(aaa):
    centerline, *_ = aaa
    labels = ["other" if label == "renal_left" else label for label in centerline.labels]
    with pytest.raises(ValueError, match=r"no 'renal_left' nodes.*labels present: \['aorta', 'iliac_left'"):
        plan_path(Centerline(centerline.points, centerline.edges, labels))
    with pytest.raises(ValueError, match="target vessel must be one of"):
        plan_path(centerline, target="aorta")
    with pytest.raises(ValueError, match="'to' must be one of"):
        plan_path(centerline, to="middle")


def test_disconnected_target_is_reported(aaa):
    centerline, aorta, junction, right = aaa
    keep = ~((centerline.edges == junction).any(axis=1)
             & (np.array(centerline.labels)[centerline.edges] == "renal_left").any(axis=1))
    cut = Centerline(centerline.points, centerline.edges[keep], centerline.labels)
    with pytest.raises(ValueError, match="'renal_left' nodes are not connected to the aorta"):
        plan_path(cut)


def test_resample_keeps_ends_and_length_with_even_steps():
    rng = np.random.default_rng(0)
    points = np.cumsum(rng.normal(size=(15, 3)) * 4.0, axis=0)
    out = resample_path(points, step_mm=0.7)
    np.testing.assert_array_equal(out[0], points[0])
    np.testing.assert_array_equal(out[-1], points[-1])
    steps = np.linalg.norm(np.diff(out, axis=0), axis=1)
    assert steps.max() <= 0.7 + 1e-9
    # straight-line samples along a polyline: length can only shrink, by little at this step
    assert path_length(out) <= path_length(points) + 1e-9
    assert path_length(out) > 0.97 * path_length(points)
    straight = resample_path([[0, 0, 0], [0, 0, 0], [10, 0, 0]], step_mm=3.0)
    np.testing.assert_allclose(straight[:, 0], [0, 2.5, 5, 7.5, 10])
    with pytest.raises(ValueError, match="NaN"):
        resample_path([[0, 0, 0], [np.nan, 0, 0]])


def test_smooth_keeps_end_points_and_straight_lines_and_reduces_kinks():
    straight = np.array([[0.0, 0, 0], [30.0, 10, -5]])
    smoothed = smooth_path(straight, sigma_mm=3.0, step_mm=0.5)
    direction = (straight[1] - straight[0]) / np.linalg.norm(straight[1] - straight[0])
    offsets = (smoothed - straight[0]) - np.outer((smoothed - straight[0]) @ direction, direction)
    assert np.abs(offsets).max() < 1e-9
    corner = np.array([[0.0, 0, 0], [20.0, 0, 0], [20.0, 20, 0]])
    smooth = smooth_path(corner, sigma_mm=2.0, step_mm=0.5)
    np.testing.assert_array_equal(smooth[0], corner[0])
    np.testing.assert_array_equal(smooth[-1], corner[-1])
    # the 90 degree corner is rounded: the curve misses the corner point by > 1 mm
    assert np.linalg.norm(smooth - corner[1], axis=1).min() > 1.0
    steps = np.diff(smooth, axis=0)
    steps /= np.linalg.norm(steps, axis=1, keepdims=True)
    turn_deg = np.degrees(np.arccos(np.clip(np.sum(steps[1:] * steps[:-1], axis=1), -1, 1)))
    assert turn_deg.max() < 15.0  # the unsmoothed corner turns 90 degrees in one step

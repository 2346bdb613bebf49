"""The aortic bifurcation of a 3D tree whose left common iliac forks into an internal and an
external iliac, the internal one's tip touching the external one (as their lumens touch in a
CT mask): the bifurcation is where the routes from the upper aorta to the two iliac ends part,
not the lowest junction on the way, and the leg that continues is the wide external iliac.

The tree (LPS mm, 1 mm steps): aorta from z = 0 down to the bifurcation at (0, 0, -200),
renals at z = -80, a straight right iliac, a left common iliac to its fork at (20, 0, -240),
an external iliac (radius 5) swinging out to x = 34 and down to (30, 20, -262) and on to its
end at (40, 20, -320), and an internal iliac (radius 3, posterior) from the fork straight to
(30, 20, -262), where it touches the external iliac.
"""

from __future__ import annotations

import numpy as np
import pytest

from FevarPlannerLib.conventions import LPS_DIRECTIONS
from FevarPlannerLib.graph import SkeletonGraph, classify, label_anatomy
from FevarPlannerLib.graph.anatomy import aortic_bifurcation
from FevarPlannerLib.matching.paper import _backbone

BIFURCATION = np.array([0.0, 0.0, -200.0])
ILIAC_FORK = np.array([20.0, 0.0, -240.0])
TOUCH = np.array([30.0, 20.0, -262.0])
RADII = {"aorta": 10.0, "renal": 3.0, "iliac": 5.0, "internal": 3.0}


def _polyline(*corners) -> np.ndarray:
    """Points 1 mm apart along straight segments through ``corners`` (first and last included)."""
    pieces = []
    for a, b in zip(corners[:-1], corners[1:]):
        a, b = np.asarray(a, float), np.asarray(b, float)
        steps = max(1, int(np.ceil(np.linalg.norm(b - a))))
        pieces.append(a + np.outer(np.arange(steps) / steps, b - a))
    return np.vstack(pieces + [np.asarray(corners[-1], float)[None]])


class _TreeBuilder:
    """Polylines joined at shared points into one graph with a radius per node."""

    def __init__(self):
        self.points, self.radii, self.edges, self.index = [], [], [], {}

    def node(self, xyz) -> int:
        key = tuple(np.round(np.asarray(xyz, float), 6))
        if key not in self.index:
            self.index[key] = len(self.points)
            self.points.append(np.array(key))
            self.radii.append(np.nan)
        return self.index[key]

    def add(self, line: np.ndarray, radius: float) -> list:
        nodes = [self.node(p) for p in line]
        for i in nodes:
            self.radii[i] = radius if np.isnan(self.radii[i]) else max(self.radii[i], radius)
        self.edges += list(zip(nodes[:-1], nodes[1:]))
        return nodes

    def graph(self, with_radii: bool = True) -> SkeletonGraph:
        positions = np.array(self.points)
        points_only = SkeletonGraph.from_points(positions, np.array(self.edges))
        return SkeletonGraph(positions, points_only.adjacency, unit_mm=1.0,
                             radii=np.array(self.radii) if with_radii else None)


def _tree(touching: bool = True):
    """The tree of the module docstring; returns (builder, node lists by vessel)."""
    t = _TreeBuilder()
    vessels = {
        "aorta": t.add(_polyline((0, 0, 0), (0, 0, -80), BIFURCATION), RADII["aorta"]),
        "renal_left": t.add(_polyline((0, 0, -80), (50, 5, -95)), RADII["renal"]),
        "renal_right": t.add(_polyline((0, 0, -80), (-50, 5, -95)), RADII["renal"]),
        "iliac_right": t.add(_polyline(BIFURCATION, (-40, 5, -300)), RADII["iliac"]),
        "common_iliac_left": t.add(_polyline(BIFURCATION, ILIAC_FORK), RADII["iliac"]),
        "external_iliac_left": t.add(_polyline(ILIAC_FORK, (34, 0, -245), TOUCH, (40, 20, -320)), RADII["iliac"]),
    }
    internal_end = TOUCH if touching else TOUCH + np.array([-6.0, 4.0, 0.0])
    vessels["internal_iliac_left"] = t.add(_polyline(ILIAC_FORK, internal_end), RADII["internal"])
    return t, vessels


def _labelled(graph: SkeletonGraph, max_loop: float = 30.0):
    """Algorithm 1 and the labels; ``max_loop`` below the cycle's length keeps the cycle."""
    c = classify(graph, iota=10.0, max_loop=max_loop, directions=LPS_DIRECTIONS)
    return label_anatomy(graph, c, **LPS_DIRECTIONS)


def _labels_of(c, nodes) -> set:
    return {c.node_labels[i] for i in nodes}


def _interior(nodes, trim: int = 2) -> list:
    """A vessel's nodes without the few next to its ends (the junction nodes are the parent's)."""
    return nodes[trim:-trim]


@pytest.fixture(scope="module")
def touching():
    t, vessels = _tree()
    g = t.graph()
    return g, _labelled(g), vessels


def test_the_cycle_is_kept_so_algorithm_1_leaves_junctions_on_the_left_common_iliac():
    t, _ = _tree()
    g = t.graph()
    c = classify(g, iota=10.0, max_loop=30.0, directions=LPS_DIRECTIONS)
    lowest = min(c.junction_nodes.tolist(), key=lambda j: g.positions[j, 2])
    # unlabelled, the lowest junction is where the internal iliac's tip touches, 62 mm below
    assert np.linalg.norm(g.positions[lowest] - TOUCH) <= 2.0


def test_the_bifurcation_is_where_the_routes_to_the_iliac_ends_part(touching):
    g, c, _ = touching
    bifurcation = aortic_bifurcation(c)
    assert bifurcation is not None
    assert np.linalg.norm(g.positions[bifurcation] - BIFURCATION) <= 1.0
    assert c.branch("iliac_left").junction == c.branch("iliac_right").junction == bifurcation
    assert c.node_labels[bifurcation] == "aorta"


def test_the_common_iliac_is_iliac_not_aorta_and_the_aorta_ends_at_the_bifurcation(touching):
    g, c, vessels = touching
    assert _labels_of(c, _interior(vessels["common_iliac_left"])) == {"iliac_left"}
    assert _labels_of(c, _interior(vessels["iliac_right"])) == {"iliac_right"}
    aorta_z = g.positions[[i for i in c.kept_nodes() if c.node_labels[i] == "aorta"], 2]
    assert aorta_z.min() == pytest.approx(BIFURCATION[2], abs=1.0)
    assert all(t.label == "aorta" and g.positions[t.nodes, 2].min() >= BIFURCATION[2] - 1.0 for t in c.trunks)
    assert not set(c.junction_nodes.tolist()) & set(_interior(vessels["common_iliac_left"]))


def test_the_wide_external_iliac_continues_the_leg_and_the_narrow_internal_one_is_other(touching):
    g, c, vessels = touching
    assert _labels_of(c, _interior(vessels["external_iliac_left"])) == {"iliac_left"}
    assert _labels_of(c, _interior(vessels["internal_iliac_left"])) == {"other"}
    left = c.branch("iliac_left")
    assert np.linalg.norm(g.positions[left.end] - np.array([40.0, 20.0, -320.0])) <= 1.0
    # the branch's path is the anatomical leg: common (44.7 mm) + external (14.9 + 26.6 + 58.9 mm)
    assert left.length == pytest.approx(44.7 + 14.9 + 26.6 + 58.9, abs=1.0)


def test_the_backbone_runs_from_the_top_junction_to_the_bifurcation(touching):
    g, c, _ = touching
    chain = _backbone(g, c, np.array([0.0, 0.0, 1.0]))
    assert np.linalg.norm(g.positions[chain[0]] - np.array([0.0, 0.0, -80.0])) <= 1.0
    assert np.linalg.norm(g.positions[chain[-1]] - BIFURCATION) <= 1.0
    assert len(chain) == pytest.approx(121, abs=2)


def test_labelling_twice_gives_the_same_labels(touching):
    g, c, _ = touching
    before = list(c.node_labels)
    assert label_anatomy(g, c, **LPS_DIRECTIONS).node_labels == before


def test_without_the_touch_the_internal_iliac_is_an_omitted_branch_and_nothing_moves():
    t, vessels = _tree(touching=False)
    g = t.graph()
    c = classify(g, iota=10.0, directions=LPS_DIRECTIONS)
    junctions_before = c.junction_nodes.copy()
    iliacs_before = {id(b): b.nodes.copy() for b in c.branches}
    label_anatomy(g, c, **LPS_DIRECTIONS)
    assert np.array_equal(c.junction_nodes, junctions_before)
    assert all(np.array_equal(b.nodes, iliacs_before[id(b)]) for b in c.branches)
    assert np.linalg.norm(g.positions[aortic_bifurcation(c)] - BIFURCATION) <= 1.0
    assert _labels_of(c, _interior(vessels["common_iliac_left"])) == {"iliac_left"}
    assert _labels_of(c, _interior(vessels["internal_iliac_left"])) == {"other"}


def test_a_short_cycle_is_broken_on_the_narrow_internal_iliac_not_on_the_longer_external_one():
    t, vessels = _tree()
    g = t.graph()
    c = _labelled(g, max_loop=100.0)         # the 73 mm cycle is broken before Algorithm 1
    assert len(c.loop_nodes) > 0
    assert set(c.loop_nodes.tolist()) <= set(vessels["internal_iliac_left"])
    assert _labels_of(c, _interior(vessels["external_iliac_left"])) == {"iliac_left"}
    assert c.branch("iliac_left").length == pytest.approx(44.7 + 14.9 + 26.6 + 58.9, abs=1.0)


def test_without_radii_the_short_cycle_loses_its_longest_arc_as_before():
    t, vessels = _tree()
    g = t.graph(with_radii=False)
    c = _labelled(g, max_loop=100.0)
    # the external arc (41 mm) is longer than the internal one (31 mm)
    assert set(c.loop_nodes.tolist()) <= set(vessels["external_iliac_left"])

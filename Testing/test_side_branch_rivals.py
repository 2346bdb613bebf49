"""The 3D tree's own side branches compete for 2D ends in the projection match
(matching.projected): a main vessel does not take the 2D end of a side branch the CT shows.

The 3D tree (LPS mm, frontal view along y): the left common iliac forks at (20, 0, -240)
into an external iliac ending at (40, 0, -320) and an internal iliac (posterior) ending at
(36, 25, -306), 14 mm above the external one's end in projection. In the frame the wire has
swung the external iliac out to end at (75, -318) in x/z, while the internal iliac stays:
the projected pre-operative external iliac then ends right beside the frame's internal
iliac, and only the internal iliac of the 3D tree, claiming that end, sends the external
iliac to its own.
"""

from __future__ import annotations

import numpy as np
import pytest

from FevarPlannerLib.conventions import LPS_DIRECTIONS
from FevarPlannerLib.graph import SkeletonGraph, classify, label_anatomy
from FevarPlannerLib.matching import match_by_projection
from FevarPlannerLib.projection import image_directions, project

#: A frontal C-arm view (source anterior, 786 mm from the origin; ~2.4 px per mm).
P = np.array([[1888.6, -175.5, 0.0, 132929.6],
              [0.0, -415.5, -1888.6, 66168.1],
              [0.0, -1.0, 0.0, 785.9]])
FORK = (20.0, 0.0, -240.0)
EXTERNAL_END_3D = (40.0, 0.0, -320.0)
INTERNAL_END_3D = (36.0, 25.0, -306.0)
EXTERNAL_END_FRAME = (75.0, 0.0, -318.0)


def _polyline(*corners, step: float = 1.0) -> np.ndarray:
    pieces = []
    for a, b in zip(corners[:-1], corners[1:]):
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        pieces.append(a + np.outer(np.arange(n) / n, b - a))
    return np.vstack(pieces + [np.asarray(corners[-1], float)[None]])


def _tree_lines(external_end) -> list:
    return [_polyline((0, 0, 0), (0, 0, -80), (0, 0, -200)),
            _polyline((0, 0, -80), (50, 5, -95)),
            _polyline((0, 0, -80), (-50, 5, -95)),
            _polyline((0, 0, -200), (-40, 5, -300)),
            _polyline((0, 0, -200), FORK),
            _polyline(FORK, external_end),
            _polyline(FORK, INTERNAL_END_3D)]


def _graph(lines, transform=lambda p: p, unit_mm: float = 1.0) -> SkeletonGraph:
    """One graph of polylines that share their end points."""
    index, points, edges = {}, [], []
    for line in lines:
        nodes = []
        for p in line:
            key = tuple(np.round(p, 6))
            if key not in index:
                index[key] = len(points)
                points.append(p)
            nodes.append(index[key])
        edges += list(zip(nodes[:-1], nodes[1:]))
    positions = transform(np.array(points))
    return SkeletonGraph.from_points(positions, np.array(edges), unit_mm=unit_mm)


@pytest.fixture(scope="module")
def matched_case():
    g3 = _graph(_tree_lines(EXTERNAL_END_3D))
    c3 = label_anatomy(g3, classify(g3, iota=10.0, directions=LPS_DIRECTIONS), **LPS_DIRECTIONS)
    g2 = _graph(_tree_lines(EXTERNAL_END_FRAME), transform=lambda p: project(P, p), unit_mm=1 / 2.4)
    left, superior = image_directions(P, np.array([0.0, 0.0, -150.0]))
    c2 = classify(g2, iota=24.0, directions={"left": left, "superior": superior})
    c2 = label_anatomy(g2, c2, left=left, superior=superior)
    return g3, c3, g2, c2


def _matched_end(g2, correspondence, c3, label) -> np.ndarray:
    i3 = next(i for i, b in enumerate(c3.branches) if b.label == label)
    return g2.positions[correspondence.branch_chains[i3][-1]]


def test_the_3d_tree_holds_the_internal_iliac_as_an_omitted_branch(matched_case):
    g3, c3, _, _ = matched_case
    assert len(c3.omitted) == 1
    assert np.linalg.norm(g3.positions[c3.omitted[0].end] - INTERNAL_END_3D) <= 1.0
    # the premise: projected, the pre-operative external end lies nearer the internal
    # iliac's end (15 mm) than the frame's external end (35 mm)
    external, internal, frame = project(P, np.array([EXTERNAL_END_3D, INTERNAL_END_3D, EXTERNAL_END_FRAME]))
    assert np.linalg.norm(external - internal) < 0.5 * np.linalg.norm(external - frame)


def test_the_external_iliac_takes_its_own_end_not_the_internal_iliacs(matched_case):
    g3, c3, g2, c2 = matched_case
    best = match_by_projection(g3, c3, g2, c2, P)[0]
    end = _matched_end(g2, best, c3, "iliac_left")
    assert np.linalg.norm(end - project(P, np.array([EXTERNAL_END_FRAME]))[0]) <= 3.0


def test_without_the_side_branch_as_rival_the_external_iliac_lands_on_the_internal_one(matched_case):
    g3, c3, g2, c2 = matched_case
    omitted, c3.omitted = c3.omitted, []
    try:
        best = match_by_projection(g3, c3, g2, c2, P)[0]
    finally:
        c3.omitted = omitted
    end = _matched_end(g2, best, c3, "iliac_left")
    assert np.linalg.norm(end - project(P, np.array([INTERNAL_END_3D]))[0]) <= 3.0

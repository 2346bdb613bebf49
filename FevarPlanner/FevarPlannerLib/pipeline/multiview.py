"""Deformation over several views: each view's targets (the anchor's soft assignment, nearest
points for the views that follow it), pieces a view does not show carried rigidly.
"""

from __future__ import annotations

import functools
import itertools
from collections import OrderedDict

import numpy as np
import scipy.sparse
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from .. import deformation, matching
from ..graph import row_norms
from ..preop import Preoperative
from ..projection import pixels_per_mm, project


#: Graphs whose facts (:class:`_GraphFacts`) are kept: the few of the frames in hand.
GRAPH_FACTS_KEPT = 8
_graph_facts: OrderedDict = OrderedDict()


class _GraphFacts:
    """What the nearest-point passes ask of one graph again and again, found once: its edges,
    the KD-tree of its nodes, and (a 2D skeleton's) legs, their KD-trees and end neighbours,
    node directions and the KD-trees of matched chains. The graph does not change meanwhile."""

    def __init__(self, g):
        self.graph, self.positions, self.adjacency = g, g.positions, getattr(g, "adjacency", None)
        self._chain_trees, self._branch_rows = {}, {}

    def holds(self, g) -> bool:
        """Whether these are still the facts of ``g`` (the same graph, arrays not replaced)."""
        return self.graph is g and self.positions is g.positions and self.adjacency is getattr(g, "adjacency", None)

    @functools.cached_property
    def edges(self) -> np.ndarray:
        return self.graph.edges()

    @functools.cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.positions)

    @functools.cached_property
    def legs(self) -> np.ndarray:
        """Per node its leg (:func:`_skeleton_legs`)."""
        return _skeleton_legs(self.graph, self.edges)

    @functools.cached_property
    def leg_trees(self) -> list:
        """Per leg (its nodes, the KD-tree of their positions)."""
        found = []
        for j in range(int(self.legs.max()) + 1 if len(self.legs) else 0):
            on_leg = np.flatnonzero(self.legs == j)
            found.append((on_leg, cKDTree(self.positions[on_leg])))
        return found

    @functools.cached_property
    def leg_end_neighbour(self) -> np.ndarray:
        """Per node the one neighbour on its leg where it is the leg's end, -1 elsewhere (:func:`_past_leg_ends`)."""
        return _leg_end_neighbours(self.edges, self.legs)

    @functools.cached_property
    def directions(self) -> tuple:
        """(direction, degree) per node (:func:`_node_directions`)."""
        return _node_directions(self.positions, self.edges, len(self.positions))

    def chain_tree(self, chain: np.ndarray) -> cKDTree:
        """The KD-tree of the positions of the node chain ``chain``."""
        key = (chain.dtype.str, chain.tobytes())
        if key not in self._chain_trees:
            self._chain_trees[key] = cKDTree(self.positions[chain])
        return self._chain_trees[key]

    def labels(self, classification) -> np.ndarray:
        """The node labels of ``classification`` (of this graph) as an array."""
        found = self.__dict__.get("_labels")
        if found is None or found[0] is not classification:
            found = self._labels = (classification, np.asarray(classification.node_labels, dtype=object))
        return found[1]

    def branch_rows(self, classification, nodes: np.ndarray) -> list:
        """Per branch of ``classification`` (of this graph) the rows of ``nodes`` that are its nodes."""
        key = (id(classification), nodes.dtype.str, nodes.tobytes())
        found = self._branch_rows.get(key)
        if found is None or found[0] is not classification:
            if len(self._branch_rows) >= GRAPH_FACTS_KEPT * MAX_CANDIDATE_COMBINATIONS:
                self._branch_rows.clear()
            local = np.full(len(self.positions), -1, dtype=np.int64)
            local[nodes] = np.arange(len(nodes))
            rows = [local[branch.nodes] for branch in classification.branches]
            found = self._branch_rows[key] = (classification, [r[r >= 0] for r in rows])
        return found[1]


def _facts(g) -> _GraphFacts:
    """The :class:`_GraphFacts` of graph ``g`` (found again while ``g`` is among the last few)."""
    found = _graph_facts.get(id(g))
    if found is None or not found.holds(g):
        found = _graph_facts[id(g)] = _GraphFacts(g)
        while len(_graph_facts) > GRAPH_FACTS_KEPT:
            _graph_facts.popitem(last=False)
    _graph_facts.move_to_end(id(g))
    return found


def _branch_rows(preop: Preoperative, nodes: np.ndarray) -> list:
    """Per pre-operative branch the rows of ``nodes`` (graph node indices) that are its nodes."""
    return _facts(preop.graph).branch_rows(preop.classification, np.asarray(nodes))


def _induced(g, nodes: np.ndarray) -> np.ndarray:
    """Edges of ``g`` between ``nodes``, renumbered to positions in ``nodes`` (as ``preop._induced_edges``)."""
    index = np.full(len(g.positions), -1)
    index[nodes] = np.arange(len(nodes))
    edges = index[_facts(g).edges]
    return edges[np.all(edges >= 0, axis=1)]


#: Most candidate correspondences of the anchor view deformed (the first in order).
MAX_CANDIDATE_COMBINATIONS = 16
#: Length (mm) of the seen vessel next to an unseen piece whose direction that piece keeps.
TANGENT_MM = 15.0


def _carry_unseen(preop: Preoperative, moved: np.ndarray, assigned: np.ndarray, visible: list) -> np.ndarray:
    """Move each unassigned piece that a frame border cuts rigidly with the vessel it hangs from.

    A piece of kept nodes without a 2D target in any view that holds a node no view shows
    (outside every frame, in a collimated band, or within the vessel's half-width of a
    border it runs out of, where thinning is unreliable) and hangs from one place of the
    assigned tree has no data term: the length and smoothness terms of eq. 6 are smallest
    when it keeps its shape (a rigid motion), and it turns with
    the direction of the last :data:`TANGENT_MM` of the vessel it hangs from, so that a
    vessel leaving the frame goes on the way it left instead of the TPS extrapolating it.
    Changes ``moved`` in place and returns the carried graph nodes.
    """
    g3 = preop.graph
    n = len(g3.positions)
    free = np.zeros(n, dtype=bool)
    free[preop.kept] = ~assigned[preop.kept]
    unseen = free & ~np.logical_or.reduce(visible)
    if not unseen.any():
        return np.empty(0, dtype=np.int64)
    edges = _facts(g3).edges
    inner = edges[free[edges[:, 0]] & free[edges[:, 1]]]
    adjacency = scipy.sparse.coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])), shape=(n, n))
    _, component = csgraph.connected_components(adjacency, directed=False)
    links = edges[free[edges[:, 0]] != free[edges[:, 1]]]
    links = np.where(free[links[:, :1]], links, links[:, ::-1])          # (free node, assigned node)
    links = links[assigned[links[:, 1]]]
    pair = edges[assigned[edges[:, 0]] & assigned[edges[:, 1]]]
    length = row_norms(g3.positions[pair[:, 0]] - g3.positions[pair[:, 1]])
    assigned_graph = scipy.sparse.coo_matrix((length, (pair[:, 0], pair[:, 1])), shape=(n, n)).tocsr()
    carried = []
    for label in np.unique(component[unseen]):
        piece = np.flatnonzero(free & (component == label))
        anchors = np.unique(links[np.isin(links[:, 0], piece), 1])
        if len(anchors) == 0:
            continue
        if len(anchors) > 1:
            apart = csgraph.dijkstra(assigned_graph, directed=False, indices=anchors[0], limit=TANGENT_MM)
            if not np.isfinite(apart[anchors]).all():
                continue                                    # hangs between two seen parts: the TPS
        distance = csgraph.dijkstra(assigned_graph, directed=False, indices=anchors, min_only=True, limit=TANGENT_MM)
        near = np.flatnonzero(np.isfinite(distance) & (distance > 0))
        anchor_before, anchor_after = g3.positions[anchors].mean(axis=0), moved[anchors].mean(axis=0)
        rotation = np.eye(3)
        if len(near):
            rotation = _rotation_between(anchor_before - g3.positions[near].mean(axis=0),
                                         anchor_after - moved[near].mean(axis=0))
        moved[piece] = anchor_after + (g3.positions[piece] - anchor_before) @ rotation.T
        carried.append(piece)
    return np.concatenate(carried) if carried else np.empty(0, dtype=np.int64)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation turning direction ``a`` into direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, cos = np.cross(a, b), float(a @ b)
    sin = np.linalg.norm(axis)
    if sin < 1e-12:
        return np.eye(3)
    k = axis / sin
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sin * K + (1 - cos) * K @ K


def _data_weights(has_target: np.ndarray) -> np.ndarray:
    """Eq. 6 weights of one view: 0 where a node has no target, otherwise scaled so that S_D
    stays the mean squared distance over the view's nodes with a target."""
    count = np.count_nonzero(has_target)
    return has_target * (len(has_target) / count) if count else np.zeros(len(has_target))


def _view_data(nodes: np.ndarray, assignment, visible: np.ndarray, P: np.ndarray, positions: np.ndarray):
    """(targets, weights) of one view for the deformation ``nodes``.

    Weights are 0 where the view has no target (unassigned, or not shown by the frame) and
    otherwise scaled so that S_D stays the mean squared distance over the view's assigned
    nodes (eq. 6).
    """
    has_target = assignment.assigned[nodes] & visible[nodes]
    targets = np.where(has_target[:, None], assignment.targets[nodes], project(P, positions[nodes]))
    return targets, _data_weights(has_target)


#: Most passes of nearest-point targets for a view without its own classification (ICP-like);
#: the passes stop earlier once the nodes move less than CLOSEST_POINT_SETTLED_MM on average.
CLOSEST_POINT_PASSES = 10
CLOSEST_POINT_SETTLED_MM = 0.05
#: A nearest 2D skeleton point further than this many times the median nearest distance of
#: the view is an outlier (another vessel, a part the 2D skeleton lacks) and gives no target.
CLOSEST_POINT_OUTLIER = 5.0


#: A node and its nearest 2D skeleton point must run within this angle (degrees) of each other
#: in the image, and the node's vessel must keep at least this fraction of its length in
#: projection (relative to the view's median): else the match crosses vessels.
CLOSEST_POINT_MAX_ANGLE_DEG = 45.0
CLOSEST_POINT_MIN_FORESHORTENING = 0.35
#: A branch with more than this fraction of such nodes (or of nodes claimed by two vessels:
#: :func:`_claimed_by_two_vessels`) gives no nearest-point target at all.
CLOSEST_POINT_HIDDEN_BRANCH = 0.5
#: A nearest 2D skeleton point whose vessel is this many times wider (relative to the node's own
#: radius, over the view's median of that ratio) is the centre line of a wider vessel.
CLOSEST_POINT_WIDER_VESSEL = 1.8


def _node_directions(positions: np.ndarray, edges: np.ndarray, n: int):
    """Per node the main direction of its edges in 2D (unit, sign-free) and its edge count.

    The principal eigenvector of the sum of the outer products of the node's unit edge
    vectors (closed form in 2D); zero where a node has no edge.
    """
    if not len(edges):
        return np.zeros((n, 2)), np.zeros(n, dtype=np.int64)
    vec = positions[edges[:, 1]] - positions[edges[:, 0]]
    vec = vec / np.maximum(row_norms(vec), 1e-12)[:, None]
    both = np.r_[edges[:, 0], edges[:, 1]]
    tensor = [np.bincount(both, np.r_[a, a], n) for a in (vec[:, 0] ** 2, vec[:, 0] * vec[:, 1], vec[:, 1] ** 2)]
    angle = 0.5 * np.arctan2(2.0 * tensor[1], tensor[0] - tensor[2])
    return np.c_[np.cos(angle), np.sin(angle)], np.bincount(both, minlength=n)


def _crosses_vessels(view, nodes: np.ndarray, preop: Preoperative, positions: np.ndarray, uv: np.ndarray,
                     index: np.ndarray) -> np.ndarray:
    """Nodes whose nearest 2D skeleton point is on another vessel: the node's vessel runs across
    it in the image, or nearly along the view's rays (foreshortened, hidden in a wider
    vessel's silhouette, so that the nearest skeleton point is that vessel's centre line),
    or (where both graphs know their radii) that point's vessel is much wider than the node's."""
    g3 = preop.graph
    n3 = len(g3.positions)
    local = np.full(n3, -1, dtype=np.int64)
    local[nodes] = np.arange(len(nodes))
    edges3 = _facts(g3).edges
    edges3 = local[edges3[(local[edges3[:, 0]] >= 0) & (local[edges3[:, 1]] >= 0)]]
    direction3, degree3 = _node_directions(uv, edges3, len(nodes))
    projected = row_norms(uv[edges3[:, 0]] - uv[edges3[:, 1]])
    spatial = row_norms(positions[nodes][edges3[:, 0]] - positions[nodes][edges3[:, 1]])
    ratio = projected / np.maximum(spatial, 1e-12)
    ratio = ratio / max(float(np.median(ratio)), 1e-12) if len(ratio) else ratio
    both = np.r_[edges3[:, 0], edges3[:, 1]]
    node_ratio = np.bincount(both, np.r_[ratio, ratio], len(nodes)) / np.maximum(degree3, 1)
    direction2, degree2 = _facts(view.g2).directions
    cosine = np.abs((direction3 * direction2[index]).sum(axis=1))
    crossing = (degree3 == 2) & (degree2[index] == 2) & (cosine < np.cos(np.radians(CLOSEST_POINT_MAX_ANGLE_DEG)))
    crossing |= (degree3 > 0) & (node_ratio < CLOSEST_POINT_MIN_FORESHORTENING)
    if g3.radii is not None and getattr(view.g2, "radii", None) is not None:     # radius of the 2D vessel
        wider = view.g2.radii[index] / np.maximum(g3.radii[nodes] * pixels_per_mm(view.P, positions[nodes]), 1e-6)
        crossing |= wider > CLOSEST_POINT_WIDER_VESSEL * np.median(wider)
    return _whole_branches(preop, nodes, crossing)


def _whole_branches(preop: Preoperative, nodes: np.ndarray, flagged: np.ndarray) -> np.ndarray:
    """A copy of ``flagged`` (one flag per deformation node of ``nodes``) in which a branch with
    more than :data:`CLOSEST_POINT_HIDDEN_BRANCH` of its nodes flagged is flagged whole: a
    branch mostly hidden in the view, all of it."""
    flagged = flagged.copy()
    for rows in _branch_rows(preop, nodes):
        if len(rows) and flagged[rows].mean() > CLOSEST_POINT_HIDDEN_BRANCH:
            flagged[rows] = True
    return flagged


#: Two nearest 2D skeleton points closer than this share of the 2D vessel's radius are one
#: point of the 2D skeleton (:func:`_claimed_by_two_vessels`).
SAME_POINT_RADII = 0.5
#: Two nodes whose projections lie further apart than this share of their summed projected
#: radii do not overlap in the view (their silhouettes are apart).
APART_SHARE = 1.0
#: Two vessels part at an acute angle (the iliacs at the bifurcation) when the path along the
#: tree between two of their nodes is more than this many times their 3D distance; vessels
#: that run on from one another (the left and right renals through the aorta, along the rays
#: in a lateral view) have a path about as long as the distance.
PARTED_DETOUR = 1.5


def _claimed_by_two_vessels(view, nodes: np.ndarray, preop: Preoperative, positions: np.ndarray, uv: np.ndarray,
                            index: np.ndarray) -> np.ndarray:
    """Nodes whose nearest 2D skeleton point is also that of a node of another vessel that the
    estimate puts apart from it in the view.

    Two vessels whose projections lie more than :data:`APART_SHARE` of their summed radii
    apart, yet whose nearest 2D skeleton points are one (within :data:`SAME_POINT_RADII` of
    its 2D radius), are both pulled onto one 2D vessel: where the view merged two vessels
    (tortuous iliacs crossing at 50-70 degrees) the frame's vessel near both is one of them,
    and the other's own 2D vessel lies further off, unclaimed. Which one belongs there is
    unknown, so neither takes a nearest-point target from this view (the other views and
    S_L, S_S move them); a branch mostly claimed so gives none at all. Two vessels that
    overlap in the estimate's projection (within the share: the iliacs side by side in a
    lateral view) share their 2D centre line rightly and keep it, and so do vessels that
    run on from one another rather than part at an acute angle (:data:`PARTED_DETOUR`).
    """
    radii2 = getattr(view.g2, "radii", None)
    radii3 = preop.graph.radii
    claimed = np.zeros(len(nodes), dtype=bool)
    if radii2 is None or radii3 is None or len(nodes) < 2:
        return claimed
    vessel = _facts(preop.graph).labels(preop.classification)[nodes]
    radius_px = radii3[nodes] * pixels_per_mm(view.P, positions[nodes])
    points2 = view.g2.positions[index]
    neighbours = cKDTree(points2).query_ball_point(points2, SAME_POINT_RADII * radii2[index])
    a = np.repeat(np.arange(len(nodes)), [len(n) for n in neighbours])
    b = np.fromiter(itertools.chain.from_iterable(neighbours), dtype=np.int64, count=len(a))
    apart = row_norms(uv[a] - uv[b]) > APART_SHARE * (radius_px[a] + radius_px[b])
    pairs = (vessel[a] != vessel[b]) & apart
    a, b = a[pairs], b[pairs]
    if len(a):
        bound = PARTED_DETOUR * row_norms(positions[nodes[a]] - positions[nodes[b]])
        sources, row = np.unique(nodes[a], return_inverse=True)
        along = csgraph.dijkstra(preop.graph.adjacency, directed=False, indices=sources, limit=float(bound.max()))
        parted = ~(along[row, nodes[b]] <= bound)
        claimed[a[parted]] = claimed[b[parted]] = True
    return _whole_branches(preop, nodes, claimed)


#: Mean distance (mm at the anatomy's depth) of a branch's projection to a 2D leg above which
#: :func:`_legs_of_vessels` rather leaves the branch without a leg (its "no leg" cost).
LEG_COST_CAP_MM = 25.0


def _skeleton_legs(g2, edges: np.ndarray | None = None) -> np.ndarray:
    """Per 2D skeleton node the leg it lies on, -1 for none: a leg is a chain between a junction
    (a node of degree three or more, on no leg) and a free end; legs are numbered 0, 1, ...
    Chains between two junctions (the aorta between the renals and the bifurcation, a piece
    between two crossings) are no leg. ``edges``: those of ``g2`` if already at hand."""
    inner = g2.degrees <= 2
    edges = g2.edges() if edges is None else edges
    edges = edges[inner[edges[:, 0]] & inner[edges[:, 1]]]
    n = len(g2.positions)
    adjacency = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, component = csgraph.connected_components(adjacency, directed=False)
    legs = np.unique(component[g2.degrees == 1])
    return np.where(inner & np.isin(component, legs), np.searchsorted(legs, component), -1)


def _legs_of_vessels(view, nodes: np.ndarray, preop: Preoperative, uv: np.ndarray, usable: np.ndarray,
                     leg: np.ndarray, queried: dict | None = None) -> dict:
    """One-to-one assignment of the 3D branches (upper aorta, renals, iliacs) to the 2D legs
    ``leg`` (:func:`_skeleton_legs`) of a view without a classification.

    The cost of a branch on a leg is the mean distance (mm at the anatomy's depth) of its
    projected usable nodes ``uv`` to the leg's nearest node; each branch may also take no leg
    at :data:`LEG_COST_CAP_MM`. The Hungarian method (scipy ``linear_sum_assignment``) picks
    the assignment of least total cost, so that of two iliacs whose nearest points all lie on
    one 2D leg the one further from it takes the other leg. Returns {branch index: (rows, leg)}
    with ``rows`` the branch's usable rows in ``nodes``; ``queried`` (a dict) receives each leg's
    nearest-node query of the rows of ``uv`` it measured, {leg: (distance, nearest node of the
    leg)}, arrays over all rows (a row not measured holds 0).
    """
    count = int(leg.max()) + 1 if len(leg) else 0
    vessels = []
    for k, rows in enumerate(_branch_rows(preop, nodes)):
        rows = rows[usable[rows]]
        if len(rows) >= 2:
            vessels.append((k, rows))
    if not vessels or count == 0:
        return {}
    scale = pixels_per_mm(view.P, preop.centre)
    facts = _facts(view.g2)
    trees = facts.leg_trees if leg is facts.legs else [(None, cKDTree(view.g2.positions[leg == j])) for j in range(count)]
    wanted = np.unique(np.concatenate([rows for _, rows in vessels]))
    cost = np.empty((len(vessels), count))
    for j, (_, tree) in enumerate(trees):
        distance, nearest = np.zeros(len(uv)), np.zeros(len(uv), dtype=np.int64)
        distance[wanted], nearest[wanted] = tree.query(uv[wanted])
        cost[:, j] = [distance[rows].mean() / scale for _, rows in vessels]
        if queried is not None:
            queried[j] = (distance, nearest)
    cost = np.c_[cost, np.full((len(vessels), len(vessels)), LEG_COST_CAP_MM)]       # the "no leg" columns
    chosen, legs = linear_sum_assignment(cost)
    return {vessels[i][0]: (vessels[i][1], int(j)) for i, j in zip(chosen, legs) if j < count}


def _nearest_on_legs(view, nodes: np.ndarray, preop: Preoperative, uv: np.ndarray, usable: np.ndarray):
    """(distance, index) of each node's nearest 2D skeleton node, where a branch that has a leg
    (:func:`_legs_of_vessels`) takes it on that leg only (:func:`_matches_on_legs`)."""
    distance, index, _, _ = _matches_on_legs(view, nodes, preop, uv, usable)
    return distance, index


def _matches_on_legs(view, nodes: np.ndarray, preop: Preoperative, uv: np.ndarray, usable: np.ndarray):
    """(distance, index, legs, past): each node's nearest 2D skeleton node, the one-to-one legs
    {branch index: (rows, leg)} of :func:`_legs_of_vessels`, and the nodes of a branch with a
    leg that lie past an end of it (:func:`_past_leg_ends`).

    Nearest points alone leave a branch between two 2D legs when the other branch's leg is
    nearer: it loses those targets (:func:`_claimed_by_two_vessels`) but nothing pulls it onto
    the unclaimed leg. A branch with a leg takes its nearest node on that leg only; the aorta's
    nodes and branches without a leg keep the nearest node of the whole skeleton.
    """
    facts = _facts(view.g2)
    distance, index = facts.tree.query(uv)
    leg = facts.legs
    queried = {}        # each leg's query of the branches' rows, made for their costs
    legs = _legs_of_vessels(view, nodes, preop, uv, usable, leg, queried)
    past = np.zeros(len(nodes), dtype=bool)
    for rows, own in legs.values():
        on_leg, tree = facts.leg_trees[own]
        leg_distance, leg_nearest = queried[own] if own in queried else tree.query(uv)
        distance[rows], found = leg_distance[rows], leg_nearest[rows]
        index[rows] = on_leg[found]
        past[rows] = _past_leg_ends(view.g2, leg, index[rows], uv[rows])
    return distance, index, legs, past


def _past_leg_ends(g2, leg: np.ndarray, index: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Points ``uv`` whose nearest leg node ``index`` is an end of its leg and that lie beyond it.

    Beyond the free end the 2D vessel stops before the 3D one (a tip the frame does not show);
    beyond the junction end the vessel runs on inside a wider silhouette where the view merged
    it with others (iliacs overlapping below the bifurcation at 50-70 degrees: the 2D junction
    is where they part in the image, not the anatomical one). There the leg's end node is no
    target: it would pull the node along its own vessel, against the other views.
    """
    facts = _facts(g2)
    neighbour = facts.leg_end_neighbour if leg is facts.legs else _leg_end_neighbours(facts.edges, leg)
    inward = neighbour[index]
    at_end = inward >= 0
    outward = g2.positions[index[at_end]] - g2.positions[inward[at_end]]
    past = np.zeros(len(index), dtype=bool)
    past[at_end] = ((uv[at_end] - g2.positions[index[at_end]]) * outward).sum(axis=1) > 0
    return past


def _leg_end_neighbours(edges: np.ndarray, leg: np.ndarray) -> np.ndarray:
    """Per 2D skeleton node its one neighbour on its leg where it ends the leg, -1 elsewhere."""
    edges = edges[(leg[edges[:, 0]] >= 0) & (leg[edges[:, 0]] == leg[edges[:, 1]])]
    both = np.r_[edges, edges[:, ::-1]]                       # (node, its neighbour on the leg)
    count = np.bincount(both[:, 0], minlength=len(leg))
    neighbour = np.full(len(leg), -1, dtype=np.int64)
    ends = both[count[both[:, 0]] == 1]
    neighbour[ends[:, 0]] = ends[:, 1]
    return neighbour


def _outlier_limits(distance: np.ndarray, usable: np.ndarray, legs: dict) -> np.ndarray:
    """Per node the nearest-point distance (px) beyond which it gives no target.

    :data:`CLOSEST_POINT_OUTLIER` times the view's median distance (at least 1 px): another
    vessel, a part the 2D skeleton lacks. A branch assigned its own leg one-to-one
    (:func:`_legs_of_vessels`) is measured against its own median instead where that is
    larger: the whole branch lies off its leg (the first estimate put it at the wrong depth,
    which a view at another angle shows as an offset), and the view-wide limit would take
    every target that could move it there, leaving it where it is.
    """
    view_median = float(np.median(distance[usable])) if usable.any() else 0.0
    limit = np.full(len(distance), CLOSEST_POINT_OUTLIER * max(view_median, 1.0))
    for rows, _ in legs.values():
        limit[rows] = np.maximum(limit[rows], CLOSEST_POINT_OUTLIER * float(np.median(distance[rows])))
    return limit


def _closest_point_data(view, nodes: np.ndarray, preop: Preoperative, estimate: np.ndarray):
    """(targets, weights) of a view without a classification: the nearest 2D skeleton points.

    ``estimate`` are the current kept positions; their projections through the view's P
    find the nearest node of its (smoothed) 2D skeleton, a branch's on the 2D leg assigned to
    it one-to-one (:func:`_matches_on_legs`); weights as in :func:`_view_data`.
    A node further from its point than its limit (:func:`_outlier_limits`), whose match
    crosses vessels (:func:`_crosses_vessels`) or whose nearest point another vessel, apart
    from it in the view, claims too (:func:`_claimed_by_two_vessels`) gets no target.
    """
    positions = np.array(preop.graph.positions, dtype=float)
    positions[preop.kept] = estimate
    uv = project(view.P, positions[nodes])
    usable = view.visible[nodes]
    distance, index, legs, past = _matches_on_legs(view, nodes, preop, uv, usable)
    has_target = usable & ~past & (distance <= _outlier_limits(distance, usable, legs))
    has_target &= ~_crosses_vessels(view, nodes, preop, positions, uv, index)
    has_target &= ~_claimed_by_two_vessels(view, nodes, preop, positions, uv, index)
    return np.where(has_target[:, None], view.g2.positions[index], uv), _data_weights(has_target)


#: Passes of chain-closest-point targets after the first deformation with several views (ICP-like).
CHAIN_REFINEMENT_PASSES = 1
#: The L-BFGS stall window (iterations, ``deform_assigned``'s ``window``; None: the solver's
#: default, 10) of a warm-started solve, the refinement of each pass (its targets moved a
#: little from the solution it starts at): stopping sooner there keeps the depth from creeping
#: along the valley :func:`deformation.deform_assigned` describes. Bent phantom, AP + LAO
#: 30 / 45 / 60: 0.409 / 0.349 / 0.297 mm against 0.444 / 0.359 / 0.298 mm with 10.
WARM_START_WINDOW = 5


def _closest_on_polyline(points: np.ndarray, polyline: np.ndarray):
    """Nearest point of a 2D polyline to each point: (nearest (k, 2), past an end (k,) bool).

    "Past an end" marks a point whose nearest polyline point is an end node and which lies
    beyond it along the end segment: the 2D vessel stops before this node does.
    """
    return _closest_on_polylines([points], [polyline], [cKDTree(polyline)])


def _closest_on_polylines(points: list, polylines: list, trees: list):
    """:func:`_closest_on_polyline` of several point sets at once, each on its own polyline
    (``trees``: their KD-trees): (nearest (k, 2), past an end (k,) bool), all sets in order.

    Each point's nearest vertex of its polyline picks the two segments at it; the nearest
    foot on those is its nearest point.
    """
    counts = [len(p) for p in points]
    segments = [len(polyline) - 1 for polyline in polylines]
    vertex = np.concatenate([tree.query(p)[1] for tree, p in zip(trees, points)])
    last = np.repeat(segments, counts) - 1
    first = np.repeat(np.cumsum([0] + segments[:-1]), counts)
    points = np.concatenate(points)
    start = np.concatenate([polyline[:-1] for polyline in polylines])
    step = np.concatenate([np.diff(polyline, axis=0) for polyline in polylines])
    length2 = np.maximum((step * step).sum(axis=1), 1e-12)
    local = np.clip(np.c_[vertex - 1, vertex], 0, last[:, None])                  # the segments at it
    candidates = local + first[:, None]
    t = ((points[:, None, :] - start[candidates]) * step[candidates]).sum(axis=2) / length2[candidates]
    clipped = np.clip(t, 0.0, 1.0)
    foot = start[candidates] + clipped[..., None] * step[candidates]
    row = np.arange(len(points))
    pick = np.argmin(((points[:, None, :] - foot) ** 2).sum(axis=2), axis=1)
    segment, along = local[row, pick], t[row, pick]
    past = ((segment == 0) & (along < 0)) | ((segment == last) & (along > 1))
    return foot[row, pick], past


#: Share of the parent vessel's 2D radius (at the chain's junction) within which a branch
#: chain's start is the thinning's bridge from the parent's centre line, not the branch.
PARENT_BRIDGE = 1.0


def _inside_parents(g2, chains: list, counts: list, foot: np.ndarray) -> np.ndarray:
    """Feet on a branch chain within the parent vessel's 2D radius of its junction (the first node).

    Thinning joins a branch to the parent's centre line across the parent's lumen. Where the
    branch leaves the parent obliquely in a view (a renal turning towards the rays in a 50-70
    degree view), that bridge runs inside the parent's silhouette, 5-11 mm off the branch,
    and the nearest-chain-point targets of the branch's first nodes lie on it, pulling the
    branch's origin along the parent. Those nodes get no target from this chain and follow
    their neighbours (S_L, S_S). False everywhere when the 2D graph has no radii. ``foot``
    holds ``counts`` feet on each of ``chains`` in turn.
    """
    radii = getattr(g2, "radii", None)
    if radii is None:
        return np.zeros(len(foot), dtype=bool)
    junction = np.repeat([int(chain[0]) for chain in chains], counts)
    return row_norms(foot - g2.positions[junction]) < PARENT_BRIDGE * radii[junction].astype(float)


def _matched_chains(view, correspondence, nodes: np.ndarray, preop: Preoperative, has_target: np.ndarray) -> list:
    """(rows, 2D chain, is a branch) per matched chain of ``correspondence`` that holds rows of
    ``nodes`` with a target: trunk pairs first, then branches; a row belongs to the first chain
    that holds it."""
    index = np.full(len(preop.graph.positions), -1, dtype=np.int64)
    index[nodes] = np.arange(len(nodes))
    chains = [(nodes3, nodes2, False) for nodes3, nodes2 in correspondence.trunk_pairs]
    chains += [(preop.classification.branches[i3].nodes, nodes2, True) for i3, nodes2 in
               (correspondence.branch_chains or {i3: view.c2.branches[i2].nodes
                                                 for i3, i2 in correspondence.branch_pairs}).items()]
    done = np.zeros(len(nodes), dtype=bool)
    found = []
    for nodes3, nodes2, is_branch in chains:
        rows = index[np.asarray(nodes3)]
        rows = rows[(rows >= 0)]
        rows = rows[~done[rows] & has_target[rows]]
        if len(rows) == 0 or len(nodes2) < 2:
            continue
        found.append((rows, np.asarray(nodes2), is_branch))
        done[rows] = True
    return found


def _chain_closest_data(view, correspondence, nodes: np.ndarray, preop: Preoperative, estimate: np.ndarray,
                        fallback):
    """(targets, weights) of a classified view from the current estimate: each 3D node's nearest
    point on the 2D chain its branch or trunk is matched to (a second soft assignment, ICP-like).

    The first assignment (eqs. 4-5) spreads the nodes along the 2D chain by the
    *pre-operative* projected path length; where the anatomy turned out of that view's plane
    the projected length changed and the targets slide along the vessel. Taking the nearest
    chain point of the deformed estimate's projection removes that slide. A node whose
    projection lies past the 2D chain's free end (the 2D vessel is shorter than the 3D one:
    a tip the frame does not show) gets no target and follows its neighbours (S_L, S_S);
    so does a node whose nearest point lies on the bridge thinning draws across the parent
    vessel's lumen at the chain's junction (:func:`_inside_parents`). ``fallback`` (targets,
    weights) of the first assignment is kept for the nodes that no chain holds.
    """
    positions = np.array(preop.graph.positions, dtype=float)
    positions[preop.kept] = estimate
    targets, has_target = np.array(fallback[0], dtype=float), fallback[1] > 0
    matched = _matched_chains(view, correspondence, nodes, preop, has_target)
    if not matched:
        return targets, _data_weights(has_target)
    rows = np.concatenate([r for r, _, _ in matched])
    counts = [len(r) for r, _, _ in matched]
    facts = _facts(view.g2)
    polylines = [view.g2.positions[chain] for _, chain, _ in matched]
    foot, past = _closest_on_polylines([project(view.P, positions[nodes[r]]) for r, _, _ in matched], polylines,
                                       [facts.chain_tree(chain) for _, chain, _ in matched])
    branch = np.repeat([is_branch for _, _, is_branch in matched], counts)
    free_end = np.concatenate([np.repeat(p[-1:], k, axis=0) for p, k in zip(polylines, counts)])
    junction = np.concatenate([np.repeat(p[:1], k, axis=0) for p, k in zip(polylines, counts)])
    past &= branch & (row_norms(foot - free_end) < row_norms(foot - junction))
    has_target[rows[past]] = False
    has_target[rows[branch & _inside_parents(view.g2, [chain for _, chain, _ in matched], counts, foot)]] = False
    targets[rows[~past]] = foot[~past]
    return targets, _data_weights(has_target)


#: A branch whose mean 2D residual (mm at the anatomy's depth) after the first deformation is
#: above this in one view, and at least VIEW_DISAGREEMENT_RATIO times that of the branch's
#: best-fitting view, is dropped from that view for the refinement: the views disagree on it
#: (one of them matched it to another 2D vessel) and the one that fits it worse gives way.
VIEW_DISAGREEMENT_MM = 1.0
VIEW_DISAGREEMENT_RATIO = 2.0


def _disagreeing_views(views, data, nodes: np.ndarray, points: np.ndarray, preop: Preoperative) -> list:
    """Per view a bool (n_a,) mask: the nodes of branches on which this view disagrees with the others."""
    drop = [np.zeros(len(nodes), dtype=bool) for _ in views]
    residual = [row_norms(project(v.P, points) - t) / pixels_per_mm(v.P, preop.centre)
                for v, (t, _) in zip(views, data)]
    for rows in _branch_rows(preop, nodes):
        mean = np.array([r[rows][w[rows] > 0].mean() if np.any(w[rows] > 0) else np.nan
                         for r, (_, w) in zip(residual, data)])
        if np.count_nonzero(np.isfinite(mean)) < 2:
            continue
        worst, best = int(np.nanargmax(mean)), float(np.nanmin(mean))
        if mean[worst] > VIEW_DISAGREEMENT_MM and mean[worst] >= VIEW_DISAGREEMENT_RATIO * best:
            drop[worst][rows] = True
    return drop


def _without(data, drop: np.ndarray):
    """(targets, weights) with the nodes ``drop`` taken out of the view (weights rescaled)."""
    targets, weights = data
    has_target = (weights > 0) & ~drop
    return targets, _data_weights(has_target)


#: A main vessel of the multi-view result whose projection lies on average further than this
#: (mm at the anatomy's depth) outside a view's vessel silhouette is flagged: the views disagree
#: on it (:func:`outside_silhouette_warnings`). Measured on the two-view sets: at most 0.7 mm on
#: results within 1.6 mm of the truth; 1.6-3.3 mm on the iliacs that were 5.8-7.3 mm off.
OUTSIDE_SILHOUETTE_MM = 1.0
#: 2D skeleton nodes whose disks (their 2D radius) make up a view's silhouette near a point.
SILHOUETTE_DISKS = 32
#: The vessels the warning speaks for (the "other" branches have no 2D partner to agree on).
CHECKED_VESSELS = ("aorta", "renal_left", "renal_right", "iliac_left", "iliac_right")


def outside_silhouette_mm(view, points: np.ndarray, at: np.ndarray) -> np.ndarray:
    """How far (mm at ``at``) each point's projection lies outside the view's vessel silhouette,
    the union of the disks of its 2D skeleton nodes (their radii); 0 inside, NaN without radii."""
    if getattr(view.g2, "radii", None) is None or len(points) == 0:
        return np.full(len(points), np.nan)
    return _outside_silhouette_px(view, project(view.P, points)) / pixels_per_mm(view.P, at)


def _outside_silhouette_px(view, uv: np.ndarray) -> np.ndarray:
    """How far (px) each image point ``uv`` lies outside the view's vessel silhouette (2D radii known):
    the least distance beyond the disks of its :data:`SILHOUETTE_DISKS` nearest nodes, 0 inside one.

    A point inside its nearest node's disk is inside (0) whatever the other disks say; only the
    others (a result's points mostly lie in the vessels) look for the other disks."""
    tree, radii = _facts(view.g2).tree, view.g2.radii
    nearest_distance, nearest = tree.query(uv)
    outside = np.zeros(len(uv))
    beyond = np.flatnonzero(nearest_distance > radii[nearest])
    if len(beyond):
        k = min(SILHOUETTE_DISKS, len(view.g2.positions))
        distance, index = tree.query(uv[beyond], k=k)
        distance, index = distance.reshape(len(beyond), k), index.reshape(len(beyond), k)
        outside[beyond] = np.maximum((distance - radii[index]).min(axis=1), 0.0)
    return outside


def outside_silhouette_warnings(preop: Preoperative, views, deformed: np.ndarray) -> list:
    """Warnings for main vessels of the result (kept positions ``deformed``) lying on average more
    than :data:`OUTSIDE_SILHOUETTE_MM` outside a view's silhouette, over the nodes it shows.

    Every view's silhouette holds the true vessels' projections; a result that leaves one is
    wrong there, whichever view the registration followed (the second view's iliacs crossed and
    matched the wrong way round, or one iliac left at the first view's depth). Not an answer to
    trust without a look.
    """
    labels = np.asarray(preop.centerline.labels, dtype=object)
    found = []
    for view in views:
        if getattr(view.g2, "radii", None) is None:
            continue                                # a view without radii says nothing
        shown = view.visible[preop.kept]
        checked = [(label, np.flatnonzero((labels == label) & shown)) for label in CHECKED_VESSELS]
        checked = [(label, rows) for label, rows in checked if len(rows) >= 2]
        if not checked:
            continue
        outside = _outside_silhouette_px(view, np.concatenate([project(view.P, deformed[rows]) for _, rows in checked]))
        split = np.split(outside / pixels_per_mm(view.P, preop.centre), np.cumsum([len(r) for _, r in checked])[:-1])
        for (label, _), off in zip(checked, (part.mean() for part in split)):
            if off > OUTSIDE_SILHOUETTE_MM:
                found.append(f"view {view.name}: the {label} lies {off:.1f} mm outside the vessels of this view on "
                             f"average: the views disagree on it; check it before use")
    return found


def _deform_on(points, edges, views, data, alpha, beta, initial=None):
    """eq. 6 over the assigned ``points`` with one (targets, weights) per view in ``data``."""
    extra = {"extra_views": [(v.P, t, w) for v, (t, w) in zip(views[1:], data[1:])]} if len(views) > 1 else {}
    targets, weights = data[0]
    if not np.any(weights) and not extra:
        raise ValueError(f"view {views[0].name}: no 3D node has a 2D target in the frame")
    weights_arg = None if np.all(weights == 1.0) else weights
    if initial is not None and WARM_START_WINDOW is not None:
        extra["window"] = WARM_START_WINDOW
    return deformation.deform_assigned(points, targets, edges, views[0].P, alpha=alpha, beta=beta,
                                       weights=weights_arg, initial=initial, **extra)


def follow_anchor(preop: Preoperative, views: list, correspondences, deformed: np.ndarray, alpha, beta):
    """Passes of nearest-point targets from the last result (the anchor's first deformation
    ``deformed``, kept positions) until the nodes move less than :data:`CLOSEST_POINT_SETTLED_MM`
    on average, at most :data:`CLOSEST_POINT_PASSES`; returns (kept positions, energy).

    Each pass solves from ``phi = 0``. Starting each pass from the last one's displacements
    saved 3-5 ms a frame but let the passes settle where they stood (development two-view
    seeds 0 / 36 / 39 / 42: 0.637 / 0.535 / 0.613 / 0.538 -> 0.643 / 0.537 / 0.624 / 0.558
    mm; the bent phantom AP + LAO 60: 0.30 -> 4.98 mm, its left iliac never reaching its
    second-view targets); stopping when the targets moved under 0.15 px on average cost 0.01-0.03
    mm there (nearest skeleton nodes move in whole steps). Neither is used.
    """
    energy = None
    for _ in range(CLOSEST_POINT_PASSES):
        previous = deformed
        deformed, energy, _ = _deform_with(preop, views, correspondences, alpha, beta, estimate=deformed)
        if row_norms(deformed - previous).mean() < CLOSEST_POINT_SETTLED_MM:
            break
    return deformed, energy


def _target_nodes(preop: Preoperative, views: list, correspondences) -> tuple[dict, np.ndarray]:
    """({view name: soft assignment}, the 3D nodes some classified view gives a target in its frame)."""
    classified = [(v, c) for v, c in zip(views, correspondences) if c is not None]
    assignments = {v.name: v.assignment(preop, c) for v, c in classified}
    has_target = [assignments[v.name].assigned & v.visible for v, _ in classified]
    return assignments, np.flatnonzero(np.logical_or.reduce(has_target))


def _nodes_with_targets(preop: Preoperative, views: list, correspondences) -> np.ndarray:
    """The nodes of :func:`_target_nodes`, without the assignments' targets (``view.assigned``)."""
    has_target = [v.assigned(preop, c) & v.visible for v, c in zip(views, correspondences) if c is not None]
    return np.flatnonzero(np.logical_or.reduce(has_target))


def _assigned_fraction(preop: Preoperative, nodes: np.ndarray) -> float:
    """The share of the kept 3D nodes among ``nodes`` (those the deformation moves by data)."""
    in_deformation = np.zeros(len(preop.graph.positions), dtype=bool)
    in_deformation[nodes] = True
    return in_deformation[preop.kept].mean()


def score_floor(preop: Preoperative, views: list, correspondences, alpha) -> float:
    """The least score :func:`_deform_with` can give ``correspondences`` (no estimate), found
    without deforming: :func:`matching.candidate_score` of the undeformed nodes with zero
    energy, which is its share for the 3D nodes left unassigned. The parts left out, the
    energy of eq. 6 and alpha times the mean squared stretch, are sums of squares (never
    negative), and adding a number that is not negative never rounds below the other: a
    candidate whose floor is not below the best score so far cannot win (issue 10: the
    LAO 30 view's second candidate, which leaves a renal without partner)."""
    nodes = _nodes_with_targets(preop, views, correspondences)
    points = preop.centerline.points
    return matching.candidate_score(0.0, _assigned_fraction(preop, nodes), points, points, preop.centerline.edges,
                                    alpha)


def _pass_targets(preop: Preoperative, views: list, correspondences, estimate):
    """(deformation nodes, (targets, weights) per view) of :func:`_deform_with` (its rows 6-12)."""
    g3 = preop.graph
    assignments, nodes = _target_nodes(preop, views, correspondences)
    data = [_view_data(nodes, assignments[v.name], v.visible, v.P, g3.positions) if v.name in assignments
            else _closest_point_data(v, nodes, preop, estimate) for v in views]
    if estimate is not None:        # later passes: the classified views' targets slide with the estimate too
        data = [_chain_closest_data(v, c, nodes, preop, estimate, d) if c is not None else d
                for v, c, d in zip(views, correspondences, data)]
    return nodes, data


def _vessel_labels(preop: Preoperative) -> np.ndarray:
    """The anatomical label of each kept node (the TPS fill's "connected branches or trunks")."""
    return _facts(preop.graph).labels(preop.classification)[preop.kept]


def _deform_with(preop: Preoperative, views: list, correspondences, alpha, beta, estimate=None):
    """Algorithm 2 rows 6-16 for one correspondence per view; returns (kept positions, energy, score).

    Every view soft-assigns the same 3D nodes (eqs. 3-5); one energy (eq. 6) with the data
    term averaged over the views moves them; the TPS fills the rest (row 16). A view whose
    correspondence is None (one that follows the anchor) takes the nearest 2D skeleton
    points of the kept positions ``estimate`` as targets instead (:func:`_closest_point_data`),
    and with an ``estimate`` the other views' first targets are already the nearest points of
    their matched chains to it (:func:`_chain_closest_data`): they slide along the vessel with
    the passes instead of pulling back to the first assignment's spacing. With several views,
    CHAIN_REFINEMENT_PASSES passes then re-assign each classified view's nodes to the nearest
    point of their matched 2D chain (:func:`_chain_closest_data`) and continue the
    minimisation from the last displacements. The score (matching.candidate_score) picks
    between candidates: the energy plus the 3D implausibility of the result.
    """
    g3 = preop.graph
    nodes, data = _pass_targets(preop, views, correspondences, estimate)
    edges = _induced(g3, nodes)
    result = _deform_on(g3.positions[nodes], edges, views, data, alpha, beta)
    for _ in range(CHAIN_REFINEMENT_PASSES if len(views) > 1 else 0):
        current = np.array(g3.positions, dtype=float)
        current[nodes] = result.points
        drop = _disagreeing_views(views, data, nodes, result.points, preop)
        data = [_chain_closest_data(v, c, nodes, preop, current[preop.kept], d) if c is not None else d
                for v, c, d in zip(views, correspondences, data)]
        data = [_without(d, x) for d, x in zip(data, drop)]
        result = _deform_on(g3.positions[nodes], edges, views, data, alpha, beta, initial=result.displacements)
    moved = np.array(g3.positions, dtype=float)
    moved[nodes] = result.points
    in_deformation = np.zeros(len(g3.positions), dtype=bool)
    in_deformation[nodes] = True
    assigned_fraction = _assigned_fraction(preop, nodes)
    in_deformation[_carry_unseen(preop, moved, in_deformation, [v.visible for v in views])] = True
    filled = deformation.fill_unassigned(g3.positions[preop.kept], moved[preop.kept], in_deformation[preop.kept],
                                         preop.kept_adjacency, vessels=_vessel_labels(preop))
    score = matching.candidate_score(result.energy_final, assigned_fraction, preop.centerline.points, filled,
                                     preop.centerline.edges, alpha)
    return filled, float(result.energy_final), score


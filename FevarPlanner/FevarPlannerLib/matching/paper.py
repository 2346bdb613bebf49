"""The paper's graph matching and soft assignment (Sec. II-B, eqs. 3-5) between the 3D and the 2D
skeleton graphs.

Equation numbers are those of the paper's source, where Definition 1's adjacency is eq.
(2): eq. (3) initialises ``M``, eq. (4) assigns branches, eq. (5) trunks.

Paper section II-B: trunks and junctions are matched first by ranked geodesic length,
then branches by the similarity of their tangents (eta_s = 1, eta_t = 10 along the
branch; 3D tangents projected through P) under the junction correspondence. Each matched
pair is then soft-assigned: branches by equal projected path length (eq. 4), trunks by
equal proportion of path length (eq. 5). The result gives every assigned 3D node its 2D
target ``t_j = X M[:, j]``.

Beyond the paper: both graphs also carry anatomical labels (graph.label_anatomy), and
where the tangent matching and the labels disagree, or the trunk ranks are ambiguous,
every consistent candidate is kept; the caller deforms with each and keeps the one with
the lowest final energy and 3D implausibility (Algorithm 2 run once per candidate).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csgraph

from ..graph import Classification, SkeletonGraph, row_norms
from ..graph.anatomy import aortic_bifurcation
from ..projection import image_directions, pixels_per_mm, project

__all__ = [
    "Correspondence",
    "SoftAssignment",
    "branch_tangents",
    "match_trunks",
    "match_branches",
    "soft_assign",
    "soft_assign_with_and_without_exits",
    "ETA_S",
    "ETA_T",
]

#: Tangent of a branch: from its node ``ETA_S`` to its node ``ETA_T`` (paper Sec. III, 1-based
#: in the paper, so nodes 1 and 10 there are indices 0 and 9 here).
ETA_S = 1
ETA_T = 10
_FORBIDDEN = 1e6
#: How far (mm of 3D path) a junction inside a trunk chain may slide along its 2D partner
#: towards the chain's proportional position (:func:`_sliding_trunk_lengths`): the ostia
#: of the renal arteries move 3-4 mm along the aorta between CT and frame.
JUNCTION_SLIDE_MM = 5.0
#: The fit of a trunk chain's projection along its 2D partner (:func:`_projected_length_fit`):
#: at least this many nodes, residuals beyond this many px (or 3 median residuals) left
#: out, and a slope (2D path per projected 3D path) within this range.
MIN_FIT_NODES = 10
FIT_OUTLIER_PX = 2.0
FIT_SLOPE_RANGE = (0.8, 1.25)
#: A branch that continues its trunk through a fork (:func:`_branch_start`): its 2D chain is
#: counted from this many 2D radii (at the junction) past the junction, and it continues the
#: trunk when its chain there leaves within this many degrees of the trunk's direction.
CROTCH_RADII = 1.5
CONTINUES_DEG = 60.0
#: A trunk chain's end at a fork (:func:`_is_fork`: two pieces of skeleton ahead within
#: ``FORK_DEG`` of the chain) may slide inwards by up to ``FORK_SLIDE_RADII`` 2D radii
#: (:func:`_end_slide_px`).
FORK_DEG = 60.0
FORK_SLIDE_RADII = 2.0
#: A leg at a fork whose 2D chain ends inside the frame is mapped end to end
#: (:func:`_leg_scale`) when the ratio of its 2D path length to its projected 3D path
#: length lies in this range; a 2D end within ``FRAME_MARGIN_RADII`` 2D radii of what the
#: frame shows is a cut, not the vessel's end.
LEG_SCALE_RANGE = (0.8, 1.2)
#: Slack (px) of the segment bound of :class:`_Segments`, far above its rounding.
_REACH_MARGIN = 1e-6
#: Up to this many (point, segment) pairs :class:`_Segments` measures them all (a
#: KD-tree's set-up costs more).
_DENSE_PAIRS = 6000
FRAME_MARGIN_RADII = 1.0
#: How much longer than parallel to the detector a leg may come out in the frame
#: (:func:`_largest_leg_scale`): a move of about 6 mm towards the source under the bench's
#: short pinhole (0.4-0.6 % of magnification per mm).
LEG_DEPTH_ALLOWANCE = 0.03
#: A branch that does not fork (a renal) is counted from where it leaves its trunk's outline
#: (:func:`_outline_exit`): where its centre line lies the trunk's 2D radius plus this many of
#: its own 2D radii from the trunk's centre line, in the frame and in the projection alike.
EXIT_BRANCH_RADII = 1.0
#: The labels of the trunk's own course (the iliacs are its legs at the fork); every other
#: branch leaves the trunk's side.
_MAIN_COURSE = ("aorta", "iliac_left", "iliac_right")


@dataclass
class Correspondence:
    """Which 3D branch/trunk goes with which 2D one.

    Attributes
    ----------
    branch_pairs : list of (int, int)
        ``(index into c3.branches, index into c2.branches)``; for a projection match the
        index of the preserved 2D branch that ends where the chain ends, or None when the
        chain ends on a 2D branch that Algorithm 1 omitted.
    trunk_pairs : list of (numpy.ndarray, numpy.ndarray)
        Matched node chains ``(3D nodes, 2D nodes)``, ordered from matched junction to
        matched junction.
    junction_pairs : dict
        3D junction node -> 2D junction node.
    source : str
        How it was found ("projection", "tangent", "labels"), for the report.
    branch_chains : dict
        3D branch index -> 2D node chain from its junction to its end (eq. 4's 2D side);
        by default the preserved 2D branch of ``branch_pairs``.
    """

    branch_pairs: list
    trunk_pairs: list
    junction_pairs: dict
    source: str = ""
    branch_chains: dict = field(default_factory=dict)

    def key(self) -> tuple:
        """Which 3D branch goes to which 2D end node: candidates that agree on it are duplicates
        (their junctions differ by a node or two at most)."""
        return tuple(sorted((int(i3), int(chain[-1])) for i3, chain in self.branch_chains.items()))


def _with_chains(correspondence: Correspondence, c2: Classification) -> Correspondence:
    correspondence.branch_chains = {i3: np.asarray(c2.branches[i2].nodes) for i3, i2 in correspondence.branch_pairs}
    return correspondence


@dataclass
class SoftAssignment:
    """The soft assignment matrix ``M`` (n2 x n3, eqs. 3-5) and the 2D target of each 3D node.

    Attributes
    ----------
    M : scipy.sparse.csr_matrix, shape (n2, n3)
    targets : numpy.ndarray, shape (n3, 2)
        ``X M`` column-wise; NaN for unassigned nodes.
    assigned : numpy.ndarray of bool, shape (n3,)
    correspondence : Correspondence
    counted_from_exits : tuple of int
        The 3D branches counted from where they leave the trunk's outline
        (:func:`_outline_exit`); empty when the paper's rule held for every branch.
    """

    M: sp.csr_matrix
    targets: np.ndarray
    assigned: np.ndarray
    correspondence: Correspondence = field(repr=False)
    counted_from_exits: tuple = ()


def branch_tangents(graph: SkeletonGraph, branches, P: np.ndarray | None = None,
                    eta_s: int = ETA_S, eta_t: int = ETA_T) -> np.ndarray:
    """Unit tangents of branches in the image plane (paper: T, similarity S = T^T T).

    The tangent runs from node ``eta_s`` to node ``eta_t`` of the branch (counted from its
    junction, 1-based as in the paper, clipped to the branch). 3D branches are projected
    through ``P`` first so that 2D and 3D tangents are comparable.
    """
    tangents = np.zeros((len(branches), 2))
    for row, branch in enumerate(branches):
        nodes = branch.nodes
        start = nodes[min(eta_s - 1, len(nodes) - 1)]
        stop = nodes[min(eta_t - 1, len(nodes) - 1)]
        ends = graph.positions[[start, stop]]
        if graph.dim == 3:
            ends = project(P, ends)
        vector = ends[1] - ends[0]
        norm = np.linalg.norm(vector)
        tangents[row] = vector / norm if norm > 0 else vector
    return tangents


def _oriented_trunk(graph: SkeletonGraph, trunk, superior: np.ndarray) -> np.ndarray:
    """Trunk nodes ordered from its more superior junction to the other one."""
    nodes = trunk.nodes
    heights = graph.positions[[nodes[0], nodes[-1]]] @ superior
    return nodes if heights[0] >= heights[1] else nodes[::-1]


def _backbone(graph: SkeletonGraph, classification: Classification, superior: np.ndarray) -> np.ndarray:
    """The aortic chain from the most superior junction to the aortic bifurcation.

    The bifurcation is the junction both labelled iliac branches leave
    (:func:`graph.anatomy.aortic_bifurcation`: where the routes to the iliac ends part),
    not the lowest junction, which may be a common iliac's own fork; the lowest junction
    only for an unlabelled classification.
    """
    junctions = np.asarray(classification.junction_nodes)
    heights = graph.positions[junctions] @ superior
    top = junctions[np.argmax(heights)]
    bottom = aortic_bifurcation(classification)
    bottom = junctions[np.argmin(heights)] if bottom is None else bottom
    return np.asarray(graph.shortest_path(top, bottom))


def match_trunks(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph, c2: Classification,
                 P: np.ndarray) -> list[tuple[list, dict]]:
    """Trunk and junction correspondences by ranked geodesic length (paper Sec. II-B-3).

    Returns candidate ``(trunk_pairs, junction_pairs)``: the rank match when both graphs
    have the same number of trunks and it maps junctions consistently; otherwise the
    backbone match (the aortic chain from the top junction to the bifurcation, as one
    trunk), which survives a renal junction that splits in one view and not the other.
    """
    at = g3.positions[c3.kept_nodes()].mean(axis=0)
    sup3, sup2 = np.array([0.0, 0.0, 1.0]), image_directions(P, at)[1]
    candidates = []
    if len(c3.trunks) == len(c2.trunks) and c3.trunks:
        order3 = np.argsort([-t.length for t in c3.trunks], kind="stable")
        order2 = np.argsort([-t.length for t in c2.trunks], kind="stable")
        pairs, junctions, consistent = [], {}, True
        for i3, i2 in zip(order3, order2):
            n3 = _oriented_trunk(g3, c3.trunks[i3], sup3)
            n2 = _oriented_trunk(g2, c2.trunks[i2], sup2)
            for a, b in ((n3[0], n2[0]), (n3[-1], n2[-1])):
                consistent &= junctions.setdefault(int(a), int(b)) == int(b)
            pairs.append((n3, n2))
        if consistent and len(set(junctions.values())) == len(junctions):
            candidates.append((pairs, junctions))
    if c3.trunks and c2.trunks and not candidates:
        b3, b2 = _backbone(g3, c3, sup3), _backbone(g2, c2, sup2)
        if len(b3) > 1 and len(b2) > 1:
            junctions = {int(b3[0]): int(b2[0]), int(b3[-1]): int(b2[-1])}
            candidates.append(([(b3, b2)], junctions))
    if not candidates:
        raise ValueError(f"no trunk to match: {len(c3.trunks)} trunk(s) in 3D, {len(c2.trunks)} in 2D")
    return candidates


def _nearest_matched_junctions(graph: SkeletonGraph, junctions, matched) -> list[int]:
    """The matched junction closest (geodesically) to each of ``junctions``.

    One Dijkstra run per distinct junction (a junction with several branches is asked once).
    """
    matched = np.asarray(sorted(matched))
    distinct = sorted({int(j) for j in junctions})
    if not distinct:
        return []
    distances = np.atleast_2d(graph.geodesic_from(distinct))[:, matched]
    nearest = {j: int(matched[np.argmin(row)]) for j, row in zip(distinct, distances)}
    return [nearest[int(j)] for j in junctions]


def match_branches(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph, c2: Classification,
                   P: np.ndarray, junction_pairs: dict) -> list[tuple[int, int]]:
    """Branch pairs maximising tangent similarity ``S = T2^T T3`` under the junctions.

    A 3D branch may pair with a 2D branch leaving the 2D junction that corresponds to its
    own junction; a branch on a junction left unmatched (a split renal junction) counts as
    leaving the nearest matched junction.
    """
    t3 = branch_tangents(g3, c3.branches, P)
    t2 = branch_tangents(g2, c2.branches)
    similarity = t3 @ t2.T
    anchor3 = _nearest_matched_junctions(g3, [b.junction for b in c3.branches], junction_pairs)
    inverse = {v: k for k, v in junction_pairs.items()}
    anchor2 = [inverse[j] for j in _nearest_matched_junctions(g2, [b.junction for b in c2.branches], inverse)]
    allowed = np.equal.outer(anchor3, anchor2)
    cost = np.where(allowed, -similarity, _FORBIDDEN)
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if allowed[r, c]]


def _cumulative_length(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(row_norms(np.diff(points, axis=0)))])


def _assign_by_arc_length(s3: np.ndarray, nodes2: np.ndarray, x2: np.ndarray):
    """Soft weights placing each 3D arc position ``s3`` between two consecutive 2D nodes.

    Implements the common core of eqs. (4) and (5): for the 2D node ``i`` with
    ``c_i <= s < c_{i+1}``, ``m(i+1, j) = (s - c_i) / |x_{i+1} - x_i|`` and
    ``m(i, j) = 1 - m(i+1, j)``; a 3D node beyond either end of the 2D chain gets no weight.
    """
    c2 = _cumulative_length(x2)
    inside = (s3 >= -1e-9) & (s3 <= c2[-1] + 1e-9)
    i = np.clip(np.searchsorted(c2, s3, side="right") - 1, 0, len(c2) - 2)
    step = c2[i + 1] - c2[i]
    m_next = np.where(step > 0, (s3 - c2[i]) / np.where(step > 0, step, 1.0), 0.0)
    m_next = np.clip(m_next, 0.0, 1.0)
    return inside, nodes2[i], nodes2[i + 1], 1.0 - m_next, m_next


def _joined(chains: list) -> np.ndarray:
    """Node chains that share their end nodes, as one chain."""
    return np.concatenate([np.asarray(chains[0])] + [np.asarray(c)[1:] for c in chains[1:]])


def _trunk_chains(trunk_pairs: list) -> list[list]:
    """Trunk pairs joined end to end into chains along the aorta.

    Two pairs join when the 3D and the 2D chain of one end where those of the other
    begin (either pair may be reversed for it). Returns lists of oriented ``(nodes3,
    nodes2)`` pairs.
    """
    chains = [[(np.asarray(n3), np.asarray(n2))] for n3, n2 in trunk_pairs]
    joined = True
    while joined:
        joined = False
        for a in range(len(chains)):
            for b in range(len(chains)):
                if a == b:
                    continue
                merged = _join_two(chains[a], chains[b])
                if merged is not None:
                    chains[a] = merged
                    del chains[b]
                    joined = True
                    break
            if joined:
                break
    return chains


def _join_two(first: list, second: list) -> list | None:
    """``first`` continued by ``second`` (or by ``second`` reversed, or the other way round),
    None when they share no end in both graphs."""
    def reverse(chain):
        return [(n3[::-1], n2[::-1]) for n3, n2 in chain[::-1]]

    def ends(chain):
        return (int(chain[0][0][0]), int(chain[0][1][0])), (int(chain[-1][0][-1]), int(chain[-1][1][-1]))

    for head in (first, reverse(first)):
        for tail in (second, reverse(second)):
            if ends(head)[1] == ends(tail)[0]:
                return head + tail
    return None


def _arc_positions(curve: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Path length along the polyline ``curve`` of its point nearest to each of ``points``."""
    point, segment, t, _ = _nearest_segments(points, curve)
    step = np.diff(curve, axis=0)
    squared = np.maximum(np.einsum("md,md->m", step, step), 1e-12)
    return _cumulative_length(curve)[segment] + t * np.sqrt(squared[segment])


def _nearest_segments(points: np.ndarray, curve: np.ndarray):
    """For each of ``points`` its nearest segment of the polyline ``curve`` (the first on a tie):
    ``(point, segment, t, squared distance)`` (:meth:`_Segments.nearest`)."""
    return _Segments([curve]).nearest(points)


class _Segments:
    """The segments of one or more polylines, for each point's nearest one.

    Only the segments that can hold a point's nearest are measured: those starting within
    the nearest segment start's distance plus the longest segment (and
    :data:`_REACH_MARGIN`, far above rounding), since a segment start bounds the nearest
    segment's distance from above and a segment lies no nearer than its start less its
    length. Each (point, segment) pair is measured as over all segments at once, which is
    what a small problem (up to :data:`_DENSE_PAIRS` pairs) does. The KD-tree of the
    segment starts is built once, at the first large problem.
    """

    def __init__(self, curves: list):
        lines = [np.asarray(c, float) for c in curves if len(c) >= 2]
        self.vertices = [np.asarray(c, float)[0] for c in curves if len(c) == 1]
        self.start = np.concatenate([c[:-1] for c in lines]) if lines else np.empty((0, 2))
        self.step = np.concatenate([np.diff(c, axis=0) for c in lines]) if lines else np.empty((0, 2))
        self.squared = np.maximum(np.einsum("md,md->m", self.step, self.step), 1e-12)
        self._tree = None

    def nearest(self, points: np.ndarray):
        """``(point, segment, t, squared distance)``: each point's nearest segment (the first on a
        tie), one entry per point in order, ``t`` the clipped position along the segment."""
        if len(points) * len(self.start) <= _DENSE_PAIRS:
            return _nearest_segments_dense(points, self.start, self.step, self.squared)
        if self._tree is None:
            from scipy.spatial import cKDTree
            self._tree = cKDTree(self.start)
        reach = self._tree.query(points)[0] + np.sqrt(self.squared.max()) + _REACH_MARGIN
        near = self._tree.query_ball_point(points, reach, return_sorted=True)
        point = np.repeat(np.arange(len(points)), [len(n) for n in near])
        segment = np.concatenate(near).astype(np.int64)
        offset = points[point] - self.start[segment]
        t = np.clip(np.einsum("kd,kd->k", offset, self.step[segment]) / self.squared[segment], 0.0, 1.0)
        gap = offset - t[:, None] * self.step[segment]
        distance = np.einsum("kd,kd->k", gap, gap)
        first = np.concatenate([[0], np.cumsum([len(n) for n in near])[:-1]])
        least = np.minimum.reduceat(distance, first)
        best = np.flatnonzero(distance == least[point])
        best = best[np.unique(point[best], return_index=True)[1]]
        return point[best], segment[best], t[best], distance[best]

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Distance of each point to the nearest of the polylines (a one-point polyline: its point)."""
        single = [row_norms(points - vertex) for vertex in self.vertices]
        lines = [np.sqrt(self.nearest(points)[3])] if len(self.start) else []
        return np.min(lines + single, axis=0)


def _nearest_segments_dense(points: np.ndarray, start: np.ndarray, step: np.ndarray, squared: np.ndarray):
    """:meth:`_Segments.nearest` measuring every (point, segment) pair."""
    offset = points[:, None, :] - start[None]
    t = np.clip(np.einsum("nmd,md->nm", offset, step) / squared, 0.0, 1.0)
    gap = offset - t[..., None] * step[None]
    distance = np.einsum("nmd,nmd->nm", gap, gap)
    point = np.arange(len(points))
    segment = np.argmin(distance, axis=1)
    return point, segment, t[point, segment], distance[point, segment]


def _projected_length_fit(curve2: np.ndarray, projected: np.ndarray) -> np.ndarray | None:
    """``(a, b)`` of the path position ``a + b s`` on the 2D chain ``curve2`` of the projected 3D
    chain's node at projected path length ``s``, or None when the fit is not to be trusted.

    Each projected node is placed at the path position of its nearest point of the 2D chain;
    nodes whose nearest point is an end of the chain (beyond it) are left out, and so, after
    a first least-squares fit, are those more than :data:`FIT_OUTLIER_PX` (or three times the
    median residual) off it. Fewer than :data:`MIN_FIT_NODES` nodes, or a slope outside
    :data:`FIT_SLOPE_RANGE`, give None.
    """
    s = _cumulative_length(projected)
    at = _arc_positions(curve2, projected)
    length = _cumulative_length(curve2)[-1]
    used = (at > 0.5) & (at < length - 0.5)
    design = np.stack([np.ones_like(s), s], axis=1)
    coefficients = None
    for _ in range(2):
        if used.sum() < MIN_FIT_NODES:
            return None
        coefficients = np.linalg.lstsq(design[used], at[used], rcond=None)[0]
        residual = np.abs(design @ coefficients - at)
        used &= residual <= max(FIT_OUTLIER_PX, 3.0 * float(np.median(residual[used])))
    low, high = FIT_SLOPE_RANGE
    return coefficients if low <= coefficients[1] <= high else None


def _end_slide_px(g2: SkeletonGraph, chain: np.ndarray, limit_px: float) -> float:
    """How far a chain's end ``chain[-1]`` may slide along its 2D partner.

    ``limit_px``, and no more than the 2D vessel radius at its junction where the graph knows
    it (a thinned junction lies within about a radius of the branch point), except at a fork
    (:func:`_is_fork`): there thinning puts the junction into the crotch, about
    ``r (1 - sin t) / (sin t (1 + sin t))`` below the branch point for legs of 2D radius
    ``r`` leaving ``t`` off the midline (1 radius at 25 degrees, 2.3 at 15; on the bench
    phantom the iliac fork lay 9-22 px, 1.25 radii at the junction, below the projected
    bifurcation), and the end may slide by up to :data:`FORK_SLIDE_RADII` radii.
    """
    if g2.radii is None:
        return limit_px
    radius = float(g2.radii[chain[-1]])
    if _is_fork(g2, chain, radius):
        return FORK_SLIDE_RADII * radius
    return min(limit_px, radius)


def _is_fork(g2: SkeletonGraph, chain: np.ndarray, radius: float) -> bool:
    """Whether the 2D chain ``chain`` runs into a fork at its end: at least two separate pieces of
    the skeleton 1.5-2.5 ``radius`` from its end node lie ahead, within :data:`FORK_DEG` of the
    chain's direction there (a side branch off a vessel that goes on leaves at a wider angle)."""
    x = g2.positions[chain]
    back = _cumulative_length(x[::-1])
    if radius <= 0 or back[-1] <= 0:
        return False
    behind = x[::-1][min(int(np.searchsorted(back, radius)), len(x) - 1)]
    direction = x[-1] - behind
    offset = g2.positions - x[-1]
    distance = row_norms(offset)
    ahead = (distance >= 1.5 * radius) & (distance <= 2.5 * radius) & \
        (offset @ direction >= np.cos(np.radians(FORK_DEG)) * distance * np.linalg.norm(direction))
    ring = np.flatnonzero(ahead)
    if len(ring) < 2:
        return False
    pieces, _ = csgraph.connected_components(g2.induced_adjacency(ring), directed=False)
    return pieces >= 2


def _sliding_trunk_lengths(g3: SkeletonGraph, g2: SkeletonGraph, segments: list,
                           P: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3D nodes of a trunk chain and the 2D path length each is assigned to (eq. 5, with sliding junctions).

    Eq. (5) maps a trunk's 3D path length onto its 2D partner in equal proportion. Applied
    to each trunk between two junctions it pins every junction to its 2D partner, and the
    ostia of the renal arteries move a few millimetres along the aorta between CT and
    frame: the few millimetres of aorta between two close renal junctions are then mapped
    onto a 2D stretch of another length, which stretches the aorta there by 20 % and more.
    Here the whole chain is mapped piecewise linearly between knots at its junctions.

    The 3D and the 2D skeleton junctions are not the same point of the anatomy either:
    thinning puts a junction up to about a vessel radius from the branch point, a 3D
    thinning and a 2D one differently (on the bench phantom the chain's top junction in 2D
    lay 8-22 px above where the 3D one belongs, its bottom one up to 16 px below: eq. (5)
    then stretched the aorta's targets by up to 10 %, which the length term turned into
    depth bulges of +-5 mm). With ``P``, the projected 3D chain tells where its junctions
    belong: each of its nodes is placed at the path position of its nearest 2D point, and
    a line fitted to those positions against the projected path length
    (:func:`_projected_length_fit`) gives every knot's expected 2D position. An inner
    junction's knot moves from its 2D partner towards it by up to :data:`JUNCTION_SLIDE_MM`
    (scaled by lambda2 / lambda3), an end's as far but no more than the 2D vessel radius at
    that junction (:func:`_end_slide_px`) and only inwards, shortening the 2D chain (a 2D
    junction thinned into the crotch lies outwards; a projection running beyond the 2D
    chain is a trunk bent out of the view's plane, whose foreshortening eq. 5 keeps: with
    outward slides an aorta bent 12 degrees towards an AP view came out 4.95 mm off with a
    LAO 60 second view, 0.30 mm without); between knots the mapping is eq. (5)'s (equal
    proportion of 3D path length). Without ``P`` or a trustworthy fit, the ends stay pinned as in eq. (5) and an inner
    knot moves towards the proportional position of the whole chain (a single trunk is
    then eq. 5).
    """
    nodes3 = _joined([n3 for n3, _ in segments])
    s3 = _cumulative_length(g3.positions[nodes3])
    if s3[-1] <= 0:
        return nodes3, s3
    knots3 = np.concatenate([[0.0], np.cumsum([_cumulative_length(g3.positions[n3])[-1] for n3, _ in segments])])
    knots2 = np.concatenate([[0.0], np.cumsum([_cumulative_length(g2.positions[n2])[-1] for _, n2 in segments])])
    scale = knots2[-1] / knots3[-1]                     # lambda2 / lambda3 of the whole chain
    slide = np.full(len(knots2), JUNCTION_SLIDE_MM * scale)
    fitted = _fitted_knots(g3, g2, segments, nodes3, P, slide)
    if fitted is not None:
        return nodes3, fitted
    knots = knots2 + np.clip(knots3 * scale - knots2, -slide, slide)
    knots[[0, -1]] = knots2[[0, -1]]
    if np.any(np.diff(knots) <= 0) or np.any(np.diff(knots3) <= 0):
        knots = knots2
    return nodes3, np.interp(s3, knots3, knots)


def _fitted_knots(g3: SkeletonGraph, g2: SkeletonGraph, segments: list, nodes3: np.ndarray, P, slide: np.ndarray):
    """The 2D path positions of a chain's nodes from knots moved towards the projected chain's
    fit (:func:`_sliding_trunk_lengths`), or None without ``P`` or a trustworthy fit."""
    if P is None:
        return None
    nodes2 = _joined([n2 for _, n2 in segments])
    projected = project(P, g3.positions[nodes3])
    fit = _projected_length_fit(g2.positions[nodes2], projected)
    if fit is None:
        return None
    bounds = np.concatenate([[0], np.cumsum([len(n3) - 1 for n3, _ in segments])])
    expected = fit[0] + fit[1] * _cumulative_length(projected)[bounds]
    knots2 = np.concatenate([[0.0], np.cumsum([_cumulative_length(g2.positions[n2])[-1] for _, n2 in segments])])
    slide = slide.copy()
    slide[0] = _end_slide_px(g2, nodes2[::-1], slide[0])
    slide[-1] = _end_slide_px(g2, nodes2, slide[-1])
    low, high = -slide, slide.copy()
    low[0], high[-1] = 0.0, 0.0          # the ends only inwards: thinning puts a junction outwards
    knots = knots2 + np.clip(expected - knots2, low, high)
    s3 = _cumulative_length(g3.positions[nodes3])
    if np.any(np.diff(knots) <= 0) or np.any(np.diff(s3[bounds]) <= 0):
        return None
    return np.interp(s3, s3[bounds], knots)


def _targets_so_far(rows: list, vals: list, cols: list, g2: SkeletonGraph, n3: int) -> dict:
    """3D node -> its 2D target from the weights added so far (the trunks' eq. 5)."""
    if not vals:
        return {}
    M = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(len(g2.positions), n3))
    assigned = np.flatnonzero(np.asarray(M.sum(axis=0)).ravel() > 0)
    targets = (M.T @ g2.positions)[assigned]
    return {int(j): t for j, t in zip(assigned, targets)}


def _branch_start(g2: SkeletonGraph, nodes2: np.ndarray, junction_target) -> tuple[int, float]:
    """Where a branch's eq. (4) starts on its 2D chain: ``(first chain node used, its 2D path
    distance from the 3D junction's target)``.

    Eq. (4) counts a branch's path length from its 2D junction. Thinning puts a fork's 2D
    junction into the crotch, below where the legs part: on the bench phantom the iliac
    bifurcation's 2D junction lay 9-22 px down the legs from the projected anatomical
    bifurcation, where eq. (5) puts the trunk's end (its knot slides back up by up to
    :data:`FORK_SLIDE_RADII` radii, :func:`_end_slide_px`). Counted from the 2D junction,
    every target of a leg then lies that far down the leg from its node: the leg is pulled
    along itself and its depth goes wrong (9-11 mm off on two of four bench cases). A branch
    that continues the trunk through its junction (its chain leaves the junction away from
    the junction's target) is therefore counted from the junction's target: from its chain
    node :data:`CROTCH_RADII` 2D radii down the chain (past the crotch, where the leg's
    skeleton has joined its centreline), which lies the straight distance from the target;
    its 3D nodes nearer the junction than that are spread in proportion over the chain's
    crotch part (:func:`_through_crotch`). Otherwise eq. (4) as in the paper: ``(0, 0.0)``.
    """
    if junction_target is None or g2.radii is None or len(nodes2) < 3:
        return 0, 0.0
    x2 = g2.positions[nodes2]
    back = x2[0] - np.asarray(junction_target)
    if np.linalg.norm(back) < 1.0:
        return 0, 0.0
    s2 = _cumulative_length(x2)
    start = int(np.searchsorted(s2, CROTCH_RADII * float(g2.radii[nodes2[0]])))
    if start >= len(nodes2) - 1:
        return 0, 0.0
    ahead = x2[start] - x2[0]
    cosine = float(ahead @ back) / max(float(np.linalg.norm(ahead) * np.linalg.norm(back)), 1e-9)
    if cosine < np.cos(np.radians(CONTINUES_DEG)):
        return 0, 0.0
    return start, float(np.linalg.norm(x2[start] - junction_target))


def _largest_leg_scale(positions3: np.ndarray, P: np.ndarray, length3: float) -> float:
    """The largest :func:`_leg_scale` a leg can follow without stretching: its projected path
    length if it lay parallel to the detector at its depth, plus :data:`LEG_DEPTH_ALLOWANCE`
    (a move towards the source magnifies it), over its projected path ``length3``."""
    if length3 <= 0:
        return 1.0
    middles = 0.5 * (positions3[1:] + positions3[:-1])
    parallel = float(np.sum(row_norms(np.diff(positions3, axis=0)) * pixels_per_mm(P, middles)))
    return (1.0 + LEG_DEPTH_ALLOWANCE) * parallel / length3


def _leg_scale(g2: SkeletonGraph, chain2: np.ndarray, lead: float, length3: float, shows,
               largest: float = np.inf) -> float:
    """How much longer than its projected 3D path a leg at a fork lies along its 2D chain: the
    2D path from its junction's target (``lead`` to ``chain2[0]``, then along ``chain2``) over
    the projected 3D path ``length3``; 1 where that is not to be trusted.

    Eq. (4) assumes a branch keeps its projected length. A leg that turns towards or away
    from the view's plane, or moves in depth under a short pinhole (0.4-0.6 % of
    magnification per mm), does not: on the bench phantom the iliacs' true projections were
    4-15 % shorter or longer than the pre-operative ones, and the targets drifted along the
    leg by that share of it. A leg at a fork has its start placed (:func:`_branch_start`),
    so where its 2D chain ends at the vessel's end both its ends are known and the leg is
    mapped end to end (eq. 5's equal proportion; the two thinnings retract a tip by about a
    radius each). A 2D end that lies within :data:`FRAME_MARGIN_RADII` radii of the edge of
    what the frame ``shows`` (a callable of (n, 2) points) is the frame's cut, not the
    vessel's end; without ``shows`` the ends are not trusted. A ratio outside
    :data:`LEG_SCALE_RANGE` is not trusted either, and one above ``largest``
    (:func:`_largest_leg_scale`, at least 1) is cut to it: a leg lying about parallel to
    the detector cannot follow longer targets but by stretching (on the bench phantom the
    2D ends then asked for 6-13 % more than that, and the leg, stretched by 7 %, failed the
    length check and fell back to its pre-operative shape).
    """
    if shows is None or length3 <= 0 or g2.radii is None:
        return 1.0
    end = g2.positions[chain2[-1]]
    margin = FRAME_MARGIN_RADII * float(g2.radii[chain2[-1]]) + 2.0
    around = end + margin * np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    if not np.all(shows(around)):
        return 1.0
    ratio = (lead + _cumulative_length(g2.positions[chain2])[-1]) / length3
    low, high = LEG_SCALE_RANGE
    return min(ratio, max(largest, 1.0)) if low <= ratio <= high else 1.0


#: A fork leg's 2D chain narrower than this share of its median 2D radius (past the crotch) is
#: no vessel: where an iliac's lumen touches its internal iliac in the frame, thinning joins
#: the two with a bridge a pixel or two wide, and the chain from the junction to the leg's end
#: (the shortest path) can take it across, off the leg's own centre line.
BRIDGE_RADII = 0.4


def _off_the_bridges(g2: SkeletonGraph, leg2: np.ndarray, s2: np.ndarray, crotch: float) -> np.ndarray:
    """``s2`` (2D path positions along a fork leg's whole chain, the leg proper from ``crotch``
    on, ``leg2`` its chain from there) with -1 (no target) for the positions on a bridge.

    Eq. (4) puts every node of the leg on its 2D chain. Where the chain runs along a bridge
    (narrower than :data:`BRIDGE_RADII` of the leg's median 2D radius, the thinning's join of
    two lumens that touch), the targets lie off the leg, 2-5 mm in the patient-like cases
    whose external iliacs run beside their internal iliacs; those nodes get no data term and
    follow their neighbours (S_L, S_S). Unchanged without 2D radii.
    """
    if g2.radii is None or len(leg2) < 2:
        return s2
    radii = g2.radii[leg2].astype(float)
    along = crotch + _cumulative_length(g2.positions[leg2])
    radius = np.interp(s2, along, radii)
    return np.where((s2 > crotch) & (radius < BRIDGE_RADII * float(np.median(radii))), -1.0, s2)


def _through_crotch(s3: np.ndarray, lead: float, crotch: float) -> np.ndarray:
    """2D path positions along a fork leg's whole chain of its 3D nodes at (scaled) projected path
    ``s3`` from the junction: past ``lead`` (:func:`_branch_start`) as far beyond the chain
    node that lies ``crotch`` along it, before it in proportion along the crotch's part of
    the chain. Those targets lie up to a few px off the legs, but without them the 3D nodes
    there had no data term in the main view, and a second view's nearest-point passes pulled
    them onto the other leg where the legs cross (test_overlap's crossing iliacs)."""
    return np.where(s3 >= lead, crotch + s3 - lead, s3 * crotch / max(lead, 1e-9))


def _distances_until(points: np.ndarray, curves: "_Segments", limit: float, chunk: int = 24) -> np.ndarray:
    """:meth:`_Segments.distances` of a path's points in order, a chunk at a time, up to the
    chunk where one first reaches ``limit``; the points after it get infinity. What
    :func:`_crossing` reads (up to the first point at ``limit``) is the same, at a fraction of
    the cost: a branch leaves its trunk's outline within its first few points."""
    distance = np.full(len(points), np.inf)
    for begin in range(0, len(points), chunk):
        distance[begin:begin + chunk] = curves.distances(points[begin:begin + chunk])
        if np.any(distance[begin:begin + chunk] >= limit):
            break
    return distance


def _distance_to_polyline(points: np.ndarray, curve: np.ndarray) -> np.ndarray:
    """Distance of each point to the polyline ``curve``."""
    return _Segments([curve]).distances(points)


def _crossing(s: np.ndarray, distance: np.ndarray, limit: float) -> float | None:
    """Path length ``s`` at which ``distance`` first reaches ``limit`` (linear between nodes), None
    if it never does or only at the last node."""
    beyond = np.flatnonzero(distance >= limit)
    if len(beyond) == 0 or beyond[0] >= len(s) - 1:
        return None
    k = int(beyond[0])
    if k == 0:
        return 0.0
    fraction = (limit - distance[k - 1]) / max(distance[k] - distance[k - 1], 1e-9)
    return float(s[k - 1] + np.clip(fraction, 0.0, 1.0) * (s[k] - s[k - 1]))


def _outline_exit(g2: SkeletonGraph, nodes2: np.ndarray, projected3: np.ndarray, trunk2: list, trunk3: list, *,
                  segments: tuple | None = None):
    """Where a branch that does not fork leaves its trunk's outline: ``(2D path, projected 3D path)``
    from the junction, or None where it cannot be told.

    Eq. (4) counts a branch from its 2D junction. Inside the trunk's outline the frame does
    not show the branch: thinning draws its own bridge from the trunk's centre line to where
    the branch comes out, and its junction lies where that bridge meets the trunk, not where
    the branch leaves it. Where the branch runs obliquely to the trunk in the image (a renal
    in an angulated view, foreshortened) the bridge is longer or shorter than the hidden part
    of the projected branch and runs elsewhere, so eq. (4)'s targets slide along the branch
    (up to 15 px on LAO/RAO 30 with CRA/CAU 15). Both sides are therefore counted from the
    same place of the anatomy: where the centre line lies the trunk's 2D radius at the
    junction plus :data:`EXIT_BRANCH_RADII` of the branch's own 2D radius (the median over
    its outer half) from the trunk's centre line, in the frame (the 2D chain to the 2D
    trunk) and in the projection (the projected 3D branch to the projected 3D trunk). Where
    the two hidden lengths agree within the branch's radius (a renal leaving the aorta about
    across the view, as in frontal views) the bridge runs along the hidden part and eq. (4)
    from the junction stands (None): its targets differ by less than that, and the nodes in
    the outline keep theirs (without them the renals of the clipped frames came out 0.1-0.3
    mm worse). ``segments``: :func:`_trunk_segments` of ``trunk2`` and ``trunk3`` when already built.
    """
    if g2.radii is None or len(nodes2) < 4 or not trunk2 or not trunk3:
        return None
    radii, x2 = g2.radii[nodes2], g2.positions[nodes2]
    own = float(np.median(radii[len(radii) // 2:]))
    limit = _trunk_radius(g2, trunk2, x2[0], float(radii[0])) + EXIT_BRANCH_RADII * own
    trunk2_curves, trunk3_curves = segments or _trunk_segments(g2, trunk2, trunk3)
    exit2 = _crossing(_cumulative_length(x2), _distances_until(x2, trunk2_curves, limit), limit)
    exit3 = _crossing(_cumulative_length(projected3), _distances_until(projected3, trunk3_curves, limit), limit)
    if exit2 is None or exit3 is None or abs(exit2 - exit3) <= own:
        return None
    return exit2, exit3


def _trunk_segments(g2: SkeletonGraph, trunk2: list, trunk3: list) -> tuple[_Segments, _Segments]:
    """The segments of the trunks' 2D chains (node lists ``trunk2``) and of their projections ``trunk3``."""
    return _Segments([g2.positions[n] for n in trunk2]), _Segments(trunk3)


def _trunk_radius(g2: SkeletonGraph, trunk2: list, junction: np.ndarray, junction_radius: float) -> float:
    """The trunk's 2D radius about a junction: the median over its 2D nodes within two junction
    radii (the junction's own disk takes in the branch's mouth and is wider)."""
    nodes = np.concatenate(trunk2)
    near = row_norms(g2.positions[nodes] - junction) <= 2.0 * junction_radius
    return float(np.median(g2.radii[nodes[near]])) if np.any(near) else junction_radius


def _counted_from_exit(s3: np.ndarray, exits) -> np.ndarray:
    """eq. (4) from the outline's exit (:func:`_outline_exit`): the 2D path position of each 3D node
    at projected path ``s3``; -1 (no target) for the nodes hidden in the trunk's outline."""
    if exits is None:
        return s3
    exit2, exit3 = exits
    return np.where(s3 >= exit3, exit2 + s3 - exit3, -1.0)


def soft_assign(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph, c2: Classification,
                P: np.ndarray, correspondence: Correspondence, shows=None, *,
                side_branch_exits: bool = True) -> SoftAssignment:
    """Soft-assign 3D nodes to 2D nodes along matched branches (eq. 4) and trunks (eq. 5).

    A node assigned by several chains (a junction) keeps its first assignment: trunks
    first, so junctions follow the aortic chain. The legs of a fork (the iliacs) start where
    eq. (5) put their junction, past the crotch (:func:`_branch_start`), and, where
    ``shows`` (a callable telling which (n, 2) image points the frame shows) says their 2D
    chains end inside the frame, run end to end (:func:`_leg_scale`); their nodes that fall on a
    thinning's bridge between two touching lumens get no target (:func:`_off_the_bridges`). With
    ``side_branch_exits`` a side branch of the trunk (a renal) is counted from where it
    leaves the trunk's outline (:func:`_outline_exit`), and its nodes hidden in the outline
    get no target (they follow their neighbours); without it, from its 2D junction as in
    the paper (the pose check fits every node of the renal ostia).
    """
    return _AssignmentChains(g3, c3, g2, c2, P, correspondence, shows, side_branch_exits).assembled(side_branch_exits)


def soft_assign_with_and_without_exits(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph, c2: Classification,
                                       P: np.ndarray, correspondence: Correspondence,
                                       shows=None) -> tuple[SoftAssignment, SoftAssignment]:
    """:func:`soft_assign` with ``side_branch_exits`` and without: the same two results (the second
    the first itself when no side branch was counted from its exit), the chains they share (the
    trunks, the legs, every branch not counted from its exit) computed once."""
    chains = _AssignmentChains(g3, c3, g2, c2, P, correspondence, shows, True)
    with_exits = chains.assembled(True)
    return with_exits, (chains.assembled(False) if with_exits.counted_from_exits else with_exits)


class _AssignmentChains:
    """The chains of :func:`soft_assign` in the order they are added, each with eq. (4)-(5)'s arc
    weights (:func:`_assign_by_arc_length`) and, for a side branch counted from its exit
    (``side_branch_exits``), the weights counted from there as well."""

    def __init__(self, g3, c3, g2, c2, P, correspondence, shows, side_branch_exits: bool):
        self.g2, self.n3, self.correspondence = g2, len(g3.positions), correspondence
        self.chains = []        # (nodes3, weights of the paper's rule, weights from the exit or None, branch)
        for segments in _trunk_chains(correspondence.trunk_pairs):
            nodes3, s2 = _sliding_trunk_lengths(g3, g2, segments, P)
            self._add(nodes3, s2, _joined([n2 for _, n2 in segments]))
        rows, cols, vals, _, _ = self.weights(False)
        junction_targets = _targets_so_far(rows, vals, cols, g2, self.n3)
        chains = correspondence.branch_chains or {i3: c2.branches[i2].nodes for i3, i2 in correspondence.branch_pairs}
        starts = {i3: _branch_start(g2, np.asarray(nodes2), junction_targets.get(int(c3.branches[i3].nodes[0])))
                  for i3, nodes2 in chains.items()}
        forks = Counter(int(chains[i3][0]) for i3, (start, _) in starts.items() if start > 0)
        trunk2 = [np.asarray(n2) for _, n2 in correspondence.trunk_pairs]
        trunk3 = [project(P, g3.positions[np.asarray(n3)]) for n3, _ in correspondence.trunk_pairs]
        segments = _trunk_segments(g2, trunk2, trunk3)          # shared by every side branch
        for i3, nodes2 in chains.items():
            nodes3, nodes2 = np.asarray(c3.branches[i3].nodes), np.asarray(nodes2)
            start, lead = starts[i3] if forks[int(nodes2[0])] >= 2 else (0, 0.0)
            # eq. (4): projected 3D path length equals 2D path length, from where eq. (5) put the junction
            s3 = _cumulative_length(project(P, g3.positions[nodes3]))
            exits = None
            if start > 0:
                s3 = s3 * _leg_scale(g2, nodes2[start:], lead, s3[-1], shows,
                                     _largest_leg_scale(g3.positions[nodes3], P, s3[-1]))
                s3 = _through_crotch(s3, lead, _cumulative_length(g2.positions[nodes2])[start])
                s3 = _off_the_bridges(g2, nodes2[start:], s3, _cumulative_length(g2.positions[nodes2])[start])
            elif side_branch_exits and c3.branches[i3].label not in _MAIN_COURSE:    # a side branch (a renal)
                exits = _outline_exit(g2, nodes2, project(P, g3.positions[nodes3]), trunk2, trunk3,
                                      segments=segments)
            self._add(nodes3, s3, nodes2, exits, int(i3))

    def _add(self, nodes3, s3, nodes2, exits=None, branch: int = -1) -> None:
        x2 = self.g2.positions[nodes2]
        from_exit = None if exits is None else _assign_by_arc_length(_counted_from_exit(s3, exits), nodes2, x2)
        self.chains.append((nodes3, _assign_by_arc_length(s3, nodes2, x2), from_exit, branch))

    def weights(self, from_exits: bool):
        """``(rows, cols, vals, assigned, branches counted from their exits)`` of the chains added so
        far, each 3D node weighted by the first chain that assigns it; ``from_exits``: the side
        branches' weights counted from their exits where they have them."""
        rows, cols, vals, counted = [], [], [], []
        assigned = np.zeros(self.n3, dtype=bool)
        for nodes3, paper, from_exit, branch in self.chains:
            use_exit = from_exits and from_exit is not None
            inside, lo, hi, w_lo, w_hi = from_exit if use_exit else paper
            fresh = inside & ~assigned[nodes3]
            j = nodes3[fresh]
            rows.extend([lo[fresh], hi[fresh]])
            cols.extend([j, j])
            vals.extend([w_lo[fresh], w_hi[fresh]])
            assigned[j] = True
            counted += [branch] if use_exit else []
        return rows, cols, vals, assigned, counted

    def assembled(self, from_exits: bool) -> SoftAssignment:
        """The soft assignment of the chains (:meth:`weights`)."""
        rows, cols, vals, assigned, counted = self.weights(from_exits)
        if not vals:
            raise ValueError("the correspondence assigns no 3D node")
        M = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(self.g2.positions), self.n3))
        M.sum_duplicates()
        return SoftAssignment(M, targets_of(M, self.g2.positions, assigned), assigned, self.correspondence,
                              tuple(counted))


def targets_of(M, positions: np.ndarray, assigned: np.ndarray) -> np.ndarray:
    """The targets ``t_j = X M[:, j]`` (eqs. 4-5) of the ``assigned`` 3D nodes for the 2D node
    ``positions`` X, (n3, 2); NaN for the nodes not assigned."""
    targets = np.full((M.shape[1], 2), np.nan)
    targets[assigned] = (M.T @ np.asarray(positions, dtype=float))[assigned]
    return targets

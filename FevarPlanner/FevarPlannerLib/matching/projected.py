"""Matching against the projected pre-operative tree (:func:`match_by_projection`, beyond the
paper). Algorithm 1 in 2D keeps the five longest branches, and a frame often shows
branches that the 3D tree lacks: the internal / external iliac fork below a common iliac,
accessory renal arteries, side branches off the aorta, spurs from a wide sac. Ranked by
length, one of them is matched as a main vessel and a whole iliac lands on the wrong
vessel. The rigid pre-alignment ``P`` says where each 3D branch must appear, so each 3D
branch is scored against the 2D path from the 2D junction nearest its projected junction
to every 2D end node of the kept 2D graph (:func:`_branch_costs`): over their common arc
length, the mean closest distance between the projected branch (moved to start there)
and the path and the residual after turning it about the junction, the angle of that
turn, and the share of the projected branch that the path does not cover (less
``TIP_RADII`` radii: thinning eats a tip by about its radius). A path through a fork the
3D tree lacks continues along the arm that continues the projection best. The Hungarian
assignment (``linear_sum_assignment``) pairs 3D branches with distinct 2D ends, with a
"no partner" column per 3D branch at :data:`NO_PARTNER_PX`; 2D ends left over stay
unmatched. The 3D tree's omitted branches (side vessels the CT shows: internal iliacs,
accessory renals, visceral and lumbar branches) take part in the assignment as rivals: a
2D end that one of them explains better goes to it, not to a main vessel (a patient's
external iliac, swung by the wire onto where the frame's internal iliac ends, kept the
internal one's end). The junctions, trunks and branch chains are then read off the 2D tree spanned
by the matched ends, so a 2D branch hanging off the wrong junction costs the stretch of
aorta between the two junctions. These candidates join the paper's
(:func:`matching.candidates.candidate_correspondences`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csgraph

from ..graph import Classification, SkeletonGraph
from ..projection import project
from .paper import _FORBIDDEN, Correspondence

__all__ = ["match_by_projection", "NO_PARTNER_PX"]

#: Cost (px) of leaving a 3D branch without a 2D partner: a pairing whose projected branch
#: and 2D path lie further apart than this (:func:`_branch_costs`) is worse than none (the
#: branch then follows its neighbours by TPS). Measured on the phantoms: the right partner
#: costs 1-10 px, up to 38 px for the iliacs of the strong-deformation and extra-branch
#: cases given a misaligned ``P``; a wrong one 45-130 px.
NO_PARTNER_PX = 45.0
#: Cost (px) of a 2D path that covers none of its projected 3D branch; scaled by the share
#: left uncovered.
COVERAGE_PX = 15.0
#: A 2D path that ends short of its projected 3D branch by up to this many vessel radii
#: (at the 2D end) covers it: thinning retracts a tip by about one radius.
TIP_RADII = 1.5
#: A second free 2D end costing at most this much (px) more than a branch's chosen one
#: makes a second projection candidate (:func:`match_by_projection`); at most
#: ``MAX_ALTERNATIVES`` of them, each one more deformation to run.
AMBIGUOUS_PX = 2.0
MAX_ALTERNATIVES = 1
#: Cost (px) per radian that a projected branch must be turned about its junction to lie
#: along a 2D path (:func:`_turned_residual`): 10 degrees cost 3.5 px.
TURN_PX_PER_RAD = 20.0
#: Samples per curve in the mean closest distance of :func:`_curve_distances`.
_SAMPLES = 16


class _Polylines:
    """Several polylines stored end to end, for arc lengths and resampling in one pass each."""

    def __init__(self, polylines: list):
        sizes = np.array([len(p) for p in polylines])
        self.first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self.last = self.first + sizes - 1
        self.points = np.concatenate(polylines)
        steps = np.sqrt((np.diff(self.points, axis=0) ** 2).sum(axis=1))
        steps[self.last[:-1]] = 1.0  # a gap between consecutive polylines keeps the search inside each
        self.arc = np.concatenate([[0.0], np.cumsum(steps)])
        self.lengths = self.arc[self.last] - self.arc[self.first]

    def resample(self, which: np.ndarray, at: np.ndarray) -> np.ndarray:
        """Points of polyline ``which[k]`` at arc lengths ``at[k]`` (shape (k, m) -> (k, m, d))."""
        base = self.arc[self.first[which]][:, None]
        query = base + np.clip(at, 0.0, self.lengths[which][:, None])
        i = np.searchsorted(self.arc, query, side="right") - 1
        i = np.clip(i, self.first[which][:, None], np.maximum(self.last[which] - 1, self.first[which])[:, None])
        step = self.arc[i + 1] - self.arc[i]
        t = np.clip((query - self.arc[i]) / np.where(step > 0, step, 1.0), 0.0, 1.0)[..., None]
        return self.points[i] + t * (self.points[i + 1] - self.points[i])


def _point_to_polyline(points: np.ndarray, polylines: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest segment of its polyline, batched.

    ``points`` (k, m, 2) and ``polylines`` (k, n, 2) give (k, m).
    """
    a, ab = polylines[:, :-1], np.diff(polylines, axis=1)
    offset = points[:, :, None, :] - a[:, None]
    t = np.clip(np.einsum("kmnd,knd->kmn", offset, ab) / np.maximum(np.einsum("knd,knd->kn", ab, ab), 1e-12)[:, None],
                0.0, 1.0)
    gap = offset - t[..., None] * ab[:, None]
    return np.sqrt(np.einsum("kmnd,kmnd->kmn", gap, gap)).min(axis=2)


def _curve_distances(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Mean closest distance between paired curves sampled at equal arc lengths, both ways.

    ``first`` and ``second`` are (k, samples, 2): the first ``length`` of two curves each.
    """
    both = _point_to_polyline(np.concatenate([first, second]), np.concatenate([second, first])).mean(axis=1)
    return 0.5 * (both[:len(first)] + both[len(first):])


def _turned_residual(first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean distance between paired curves (equal arc lengths) after the best in-plane turn
    of the first about its start onto the second, about the second's start; and the angle.

    Deformation swings a vessel about its junction (iliac swing and straightening, renal
    tilt); turned, the projected branch lies along the 2D path it became, and past a fork
    the 3D tree lacks, along the arm that continues it.
    """
    a, b = first - first[:, :1], second - second[:, :1]
    dot = np.einsum("ksd,ksd->k", a, b)
    cross = np.einsum("ks,ks->k", a[..., 0], b[..., 1]) - np.einsum("ks,ks->k", a[..., 1], b[..., 0])
    angle = np.arctan2(cross, dot)
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    turned = np.stack([c * a[..., 0] - s * a[..., 1], s * a[..., 0] + c * a[..., 1]], axis=-1)
    return np.linalg.norm(turned - b, axis=2).mean(axis=1), angle


def _coverage_cost(length3: np.ndarray, length2: np.ndarray, tip_radius: np.ndarray) -> np.ndarray:
    """:data:`COVERAGE_PX` times the share of a projected 3D branch that its 2D chain leaves
    uncovered by more than ``TIP_RADII`` radii of the 2D tip (thinning eats a tip by one)."""
    uncovered = np.maximum(0.0, length3 - length2 - TIP_RADII * tip_radius)
    return COVERAGE_PX * uncovered / np.maximum(length3, 1e-9)


class _ContractedGraph:
    """A skeleton graph contracted to its key nodes, for shortest paths as node chains.

    Key nodes are the end and junction nodes (degree other than 2) and any ``forced`` node;
    each run of connection nodes between two key nodes becomes one weighted edge that
    remembers its nodes. Dijkstra then runs on a few dozen key nodes instead of every pixel,
    and a path is a handful of runs joined, not a walk node by node.
    """

    def __init__(self, graph: SkeletonGraph, forced=()):
        adjacency, degrees = graph.adjacency, graph.degrees
        is_key = (degrees > 0) & (degrees != 2)
        is_key[np.asarray(forced, dtype=np.int64)] = True
        self.keys = np.flatnonzero(is_key)
        self.index = np.full(len(degrees), -1, dtype=np.int64)
        self.index[self.keys] = np.arange(len(self.keys))
        self.runs: dict = {}
        rows = np.repeat(np.arange(len(degrees)), degrees)
        cols, weights = adjacency.indices, adjacency.data
        direct = is_key[rows] & is_key[cols] & (rows < cols)
        for a, b, weight in zip(rows[direct].tolist(), cols[direct].tolist(), weights[direct].tolist()):
            self._add(int(self.index[a]), int(self.index[b]), np.array([a, b]), weight)
        inner = np.flatnonzero((degrees == 2) & ~is_key)
        local = np.full(len(degrees), -1, dtype=np.int64)
        local[inner] = np.arange(len(inner))
        both = (local[rows] >= 0) & (local[cols] >= 0)
        inner_adjacency = sp.csr_matrix((weights[both], (local[rows[both]], local[cols[both]])),
                                        shape=(len(inner), len(inner)))
        for run in self._runs(inner_adjacency):
            nodes = inner[run]
            first = self._key_neighbours(adjacency, is_key, nodes[0])
            last = self._key_neighbours(adjacency, is_key, nodes[-1])
            if len(nodes) == 1:
                first, last = first[:1], first[1:]
            if len(first) and len(last):
                chain = np.concatenate([first[:1], nodes, last[:1]])
                steps = np.diff(graph.positions[chain], axis=0)
                self._add(int(self.index[first[0]]), int(self.index[last[0]]), chain,
                          float(np.sqrt((steps ** 2).sum(axis=1)).sum()))
        rows, cols, weights = [], [], []
        for (a, b), (_, weight) in self.runs.items():
            rows += [a, b]
            cols += [b, a]
            weights += [max(weight, 1e-9)] * 2
        self.matrix = sp.csr_matrix((weights, (rows, cols)), shape=(len(self.keys), len(self.keys)))

    @staticmethod
    def _runs(inner_adjacency: sp.csr_matrix) -> list:
        """Each run of connection nodes in order along it (local indices); closed loops dropped."""
        if inner_adjacency.shape[0] == 0:
            return []
        _, run_of = csgraph.connected_components(inner_adjacency, directed=True)
        tips = np.flatnonzero(np.diff(inner_adjacency.indptr) < 2)
        _, first = np.unique(run_of[tips], return_index=True)
        along = csgraph.dijkstra(inner_adjacency, directed=True, indices=tips[first], min_only=True)
        local = np.flatnonzero(np.isfinite(along))
        local = local[np.lexsort((along[local], run_of[local]))]
        return np.split(local, np.flatnonzero(np.diff(run_of[local])) + 1)

    @staticmethod
    def _key_neighbours(adjacency: sp.csr_matrix, is_key: np.ndarray, node: int) -> np.ndarray:
        neighbours = adjacency.indices[adjacency.indptr[node]:adjacency.indptr[node + 1]]
        return neighbours[is_key[neighbours]]

    def _add(self, a: int, b: int, chain: np.ndarray, weight: float) -> None:
        if a == b:
            return
        pair, chain = ((a, b), chain) if a < b else ((b, a), chain[::-1])
        if pair not in self.runs or weight < self.runs[pair][1]:
            self.runs[pair] = (chain, weight)

    def paths(self, source: int, targets) -> dict:
        """Shortest node chains from ``source`` to each reachable key node of ``targets`` (source first)."""
        start = int(self.index[source])
        if start < 0:
            raise ValueError(f"node {source} is not a key node of the contracted graph")
        _, pred = csgraph.dijkstra(self.matrix, directed=True, indices=start, return_predecessors=True)
        pred = pred.tolist()
        found = {}
        for target in targets:
            hops = [int(self.index[target])]
            if hops[0] < 0:
                continue
            while pred[hops[-1]] >= 0:
                hops.append(pred[hops[-1]])
            if hops[-1] != start:
                continue
            hops.reverse()
            pieces = [self._oriented(a, b)[1:] for a, b in zip(hops[:-1], hops[1:])]
            found[int(target)] = np.concatenate([[source]] + pieces).astype(np.int64)
        return found

    def _oriented(self, a: int, b: int) -> np.ndarray:
        chain = self.runs[(a, b) if a < b else (b, a)][0]
        return chain if a < b else chain[::-1]


def _branch_starts(g3: SkeletonGraph, branches: list, g2: SkeletonGraph, P: np.ndarray) -> dict:
    """3D branch junction -> the 2D junction node nearest its projection (where its 2D paths start).

    Any kept node where the 2D graph has no junction.
    """
    forks = np.flatnonzero(g2.degrees >= 3)
    pool = forks if len(forks) else np.flatnonzero(g2.degrees > 0)
    return {j3: _nearest(g2, pool, project(P, g3.positions[[j3]])[0])
            for j3 in sorted({int(b.junction) for b in branches})}


def _branch_costs(g3: SkeletonGraph, branches3: list, g2: SkeletonGraph, P: np.ndarray, ends2: np.ndarray,
                  starts: dict, contracted: _ContractedGraph):
    """Cost (px) of pairing each 3D branch of ``branches3`` with the 2D path to each 2D end,
    shape (branches, ends).

    The path runs from ``starts[junction]``, the 2D node nearest the projected 3D junction.
    Cost: the mean of the closest distance (:func:`_curve_distances`) and of the distance
    after turning the projection about its junction (:func:`_turned_residual`) between the
    projected branch and the path over their common arc length, plus
    :data:`TURN_PX_PER_RAD` per radian of that turn and :func:`_coverage_cost`.
    Unreachable ends cost ``inf``.
    """
    keys, chains = [], []
    for source in sorted(set(starts.values())):
        for end, path in contracted.paths(source, ends2).items():
            if len(path) > 1:
                keys.append((source, end))
                chains.append(g2.positions[path])
    chain_row = {key: k for k, key in enumerate(keys)}
    # each projected branch moved to start where its 2D paths start: a bend of the aorta
    # carries a whole junction with its branches across the frame
    branches = [project(P, g3.positions[b.nodes]) for b in branches3]
    branches = [q - q[0] + g2.positions[starts[int(b.junction)]] for q, b in zip(branches, branches3)]
    bundle = _Polylines(branches + chains)
    n3 = len(branches)
    radii = g2.radii if g2.radii is not None else np.zeros(len(g2.positions))
    pairs = [(i3, column, n3 + chain_row[(starts[int(b.junction)], int(end))]) for i3, b in enumerate(branches3)
             for column, end in enumerate(ends2.tolist())
             if (starts[int(b.junction)], int(end)) in chain_row and bundle.lengths[i3] > 0]
    costs = np.full((n3, len(ends2)), np.inf)
    if pairs:
        rows, cols, chain = np.array(pairs).T
        length3, length2, tip = bundle.lengths[rows], bundle.lengths[chain], radii[ends2[cols]]
        common = np.minimum(length3, length2)[:, None] * np.linspace(0.0, 1.0, _SAMPLES)
        first, second = bundle.resample(rows, common), bundle.resample(chain, common)
        residual, angle = _turned_residual(first, second)
        costs[rows, cols] = (0.5 * (_curve_distances(first, second) + residual) + TURN_PX_PER_RAD * np.abs(angle)
                             + _coverage_cost(length3, length2, tip))
    return costs


def _spanned_tree(g2: SkeletonGraph, ends: list[int], contracted: _ContractedGraph):
    """Junctions of the 2D tree spanned by ``ends`` and each end's chain from its junction.

    Returns None when the ends are not connected or span no junction (a single path).
    """
    paths = contracted.paths(ends[0], ends[1:])
    if len(paths) < len(ends) - 1:
        return None
    n = len(g2.positions)
    steps = np.concatenate([np.sort(np.stack([path[:-1], path[1:]], axis=1), axis=1) for path in paths.values()])
    steps = np.unique(steps[:, 0] * n + steps[:, 1])
    degree = np.bincount(np.concatenate([steps // n, steps % n]), minlength=n)
    junctions = np.flatnonzero(degree >= 3)
    if len(junctions) == 0:
        return None
    chains = {}
    for end, path in paths.items():
        on_path = np.flatnonzero(degree[path] >= 3)
        if len(on_path) == 0:  # only where a cycle the graph kept joins the ends
            return None
        chains[end] = path[on_path.max():]
    first_path = next(iter(paths.values()))
    chains[ends[0]] = first_path[:np.flatnonzero(degree[first_path] >= 3).min() + 1][::-1]
    return junctions, chains


def _nearest(g2: SkeletonGraph, nodes: np.ndarray, at: np.ndarray) -> int:
    return int(nodes[np.argmin(np.sum((g2.positions[nodes] - at) ** 2, axis=1))])


def _from_matched_ends(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph, c2: Classification, P: np.ndarray,
                       matched: dict, contracted: _ContractedGraph) -> Correspondence | None:
    """The correspondence read off the 2D tree spanned by the matched 2D ends (3D branch -> end)."""
    if len(matched) < 3:
        return None
    spanned = _spanned_tree(g2, list(matched.values()), contracted)
    if spanned is None:
        return None
    junctions2, chains = spanned
    junction_pairs = {}
    for j3 in np.asarray(c3.junction_nodes).tolist():
        at = project(P, g3.positions[[j3]])[0]
        starts = [chains[matched[i3]][0] for i3, b in enumerate(c3.branches) if b.junction == j3 and i3 in matched]
        junction_pairs[int(j3)] = _nearest(g2, np.array(starts) if starts else junctions2, at)
    trunk_pairs = _trunks_between(c3, g3, junction_pairs, contracted)
    ends_of_preserved = {int(b.end): i2 for i2, b in enumerate(c2.branches)}
    branch_pairs = [(i3, ends_of_preserved.get(end)) for i3, end in sorted(matched.items())]
    branch_chains = {i3: chains[end] for i3, end in sorted(matched.items())}
    return Correspondence(branch_pairs, trunk_pairs, junction_pairs, "projection", branch_chains)


def _trunks_between(c3: Classification, g3: SkeletonGraph, junction_pairs: dict, contracted: _ContractedGraph) -> list:
    """3D trunks paired with the 2D paths between their junctions' 2D partners.

    3D junctions sharing one 2D partner (renal arteries that leave the aorta apart in 3D and
    at one point in the view) act as one: a trunk between them is not paired on its own but
    runs on to the one of them farthest from the trunk's other end, so that eq. (5)
    spreads the whole 3D chain over the 2D path.
    """
    pairs, seen = [], set()
    for trunk in c3.trunks:
        a3, b3 = int(trunk.nodes[0]), int(trunk.nodes[-1])
        a2, b2 = junction_pairs.get(a3), junction_pairs.get(b3)
        if a2 is None or b2 is None or a2 == b2 or (a2, b2) in seen or (b2, a2) in seen:
            continue
        seen.add((a2, b2))
        path2 = contracted.paths(a2, [b2]).get(b2)
        if path2 is None:
            continue
        a3_far = _farthest(g3, [j for j, k in junction_pairs.items() if k == a2], g3.positions[b3])
        b3_far = _farthest(g3, [j for j, k in junction_pairs.items() if k == b2], g3.positions[a3])
        path3 = trunk.nodes if (a3_far, b3_far) == (a3, b3) else g3.shortest_path(a3_far, b3_far)
        pairs.append((np.asarray(path3), path2))
    return pairs


def _farthest(graph: SkeletonGraph, nodes: list, at: np.ndarray) -> int:
    return int(nodes[int(np.argmax(np.sum((graph.positions[nodes] - at) ** 2, axis=1)))])


def _close_seconds(costs: np.ndarray, matched_columns: dict) -> list[tuple[int, int]]:
    """(3D branch, 2D end column) swaps worth deforming with: a free end whose cost is within
    :data:`AMBIGUOUS_PX` of the branch's chosen one, closest first, at most :data:`MAX_ALTERNATIVES`."""
    taken = set(matched_columns.values())
    found = []
    for i3, column in matched_columns.items():
        for other in np.argsort(costs[i3]).tolist():
            if other != column and other not in taken and costs[i3, other] < costs[i3, column] + AMBIGUOUS_PX:
                found.append((costs[i3, other] - costs[i3, column], i3, other))
                break
    return [(i3, other) for _, i3, other in sorted(found)[:MAX_ALTERNATIVES]]


def match_by_projection(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph, c2: Classification,
                        P: np.ndarray) -> list[Correspondence]:
    """Branches, junctions and trunks matched against the 3D tree projected through ``P``.

    See the module docstring. Every 2D end node of the kept 2D graph (Algorithm 1's spurs
    removed; its omitted branches kept) is a candidate partner of each 3D branch, at the
    cost of :func:`_branch_costs`, and :data:`NO_PARTNER_PX` buys no partner; the 3D
    omitted branches compete for the same ends, and the ends they take are no main
    branch's (nor a variant's). The 3D
    junctions map to the junctions of the 2D tree spanned by the matched ends (nearest to
    their projection), trunks to the 2D paths between those.

    Returns
    -------
    list of Correspondence
        The assignment of least cost first, then a variant for each branch whose second
        best free end costs nearly as much (the two arms of a fork the 3D tree lacks, when
        the deformation leaves the projection half-way between them): the deformation
        energy decides. Empty when fewer than three 3D branches find a partner (no 2D
        junction to anchor the trunks).
    """
    ends2 = np.flatnonzero(g2.degrees == 1)
    n3 = len(c3.branches)
    if len(ends2) == 0 or n3 == 0:
        return []
    candidates = list(c3.branches) + list(c3.omitted)
    starts = _branch_starts(g3, candidates, g2, P)
    contracted = _ContractedGraph(g2, forced=list(starts.values()))
    costs = _branch_costs(g3, candidates, g2, P, ends2, starts, contracted)
    no_partner = np.full((len(candidates), len(candidates)), _FORBIDDEN)
    np.fill_diagonal(no_partner, NO_PARTNER_PX)
    rows, cols = linear_sum_assignment(np.hstack([np.where(np.isfinite(costs), costs, _FORBIDDEN), no_partner]))
    matched = {int(r): int(c) for r, c in zip(rows, cols) if c < len(ends2) and costs[r, c] < NO_PARTNER_PX}
    # the 2D ends that the 3D tree's own side branches explain best are no main vessel's
    columns = {r: c for r, c in matched.items() if r < n3}
    costs = costs[:n3]
    costs[:, [c for r, c in matched.items() if r >= n3]] = np.inf
    variants = [columns] + [{**columns, i3: other} for i3, other in _close_seconds(costs, columns)]
    found = [_from_matched_ends(g3, c3, g2, c2, P, {i3: int(ends2[c]) for i3, c in v.items()}, contracted)
             for v in variants]
    return [c for c in found if c is not None]

"""Repairs before Algorithm 1 on a copy of the graph: gaps bridged, short loops broken (departure 6)."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from .skeleton_graph import SkeletonGraph, _MIN_WEIGHT, _walk_back, upper_entries

#: A cycle's arc whose median lumen radius is at most this share of the widest arc's is a
#: narrower vessel touching the wider one (an internal iliac's tip on the external iliac in
#: a CT mask): :func:`_break_cycle` drops it rather than the longest arc, which would cut
#: the wide vessel and route it through the narrow one.
NARROW_ARC_SHARE = 0.8


class _Repair:
    """A mutable copy of a graph's adjacency with a record of what was changed."""

    def __init__(self, graph: SkeletonGraph):
        self.positions = graph.positions
        self.radii = graph.radii
        self.adjacency = graph.adjacency.tocsr(copy=True)
        self.alive = np.ones(len(graph), dtype=bool)
        self.bridges: list[tuple[int, int]] = []
        self.loop_nodes: list[int] = []
        self.dropped_nodes: list[int] = []
        self.notes: list[str] = []

    def remove_nodes(self, nodes) -> None:
        nodes = np.asarray(nodes, dtype=np.int64)
        if len(nodes) == 0:
            return
        self.alive[nodes] = False
        keep = sp.diags(self.alive.astype(float))
        self.adjacency = (keep @ self.adjacency @ keep).tocsr()
        self.adjacency.eliminate_zeros()

    def set_edges(self, pairs, weights) -> None:
        """Add (weight > 0) or remove (weight 0) undirected edges."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        lil = self.adjacency.tolil()
        for (a, b), w in zip(pairs, weights):
            lil[a, b] = w
            lil[b, a] = w
        self.adjacency = lil.tocsr()
        self.adjacency.eliminate_zeros()

    def graph(self, template: SkeletonGraph) -> SkeletonGraph:
        return SkeletonGraph(self.positions, self.adjacency, template.grid_indices, template.unit_mm, template.radii)


def _bridge_gaps(repair: _Repair, max_gap: float) -> None:
    """Join skeleton pieces to the largest one across gaps up to ``max_gap`` (nearest nodes)."""
    count, labels = csgraph.connected_components(repair.adjacency, directed=True)
    if count == 1:
        return
    sizes = np.bincount(labels)
    main = labels == int(np.argmax(sizes))
    pending = [c for c in np.argsort(-sizes) if not main[np.flatnonzero(labels == c)[0]]]
    while pending:
        main_nodes = np.flatnonzero(main)
        tree = cKDTree(repair.positions[main_nodes])
        best = None
        for component in pending:
            members = np.flatnonzero(labels == component)
            dist, nearest = tree.query(repair.positions[members])
            k = int(np.argmin(dist))
            if best is None or dist[k] < best[0]:
                best = (float(dist[k]), component, int(members[k]), int(main_nodes[nearest[k]]))
        gap, component, a, b = best
        if gap > max_gap:
            break
        repair.set_edges([(a, b)], [max(gap, _MIN_WEIGHT)])
        repair.bridges.append((b, a))
        repair.notes.append(f"bridged a gap of {gap:.3g} between nodes {b} and {a}")
        main |= labels == component
        pending.remove(component)
    if pending:
        dropped = np.flatnonzero(np.isin(labels, pending))
        message = (f"skeleton has {len(pending)} piece(s) ({len(dropped)} nodes) farther than "
                   f"max_gap={max_gap:.3g} from the main piece; dropped them")
        warnings.warn(message, stacklevel=3)
        repair.notes.append(message)
        repair.dropped_nodes.extend(dropped.tolist())
        repair.remove_nodes(dropped)


def _chords(adjacency: sp.csr_matrix) -> np.ndarray:
    """Edges outside a shortest-path spanning forest: each closes one independent cycle."""
    _, labels = csgraph.connected_components(adjacency, directed=True)
    roots = np.unique(labels, return_index=True)[1]
    _, pred = csgraph.dijkstra(adjacency, directed=True, indices=roots, min_only=True,
                               return_predecessors=True)[:2]
    rows, cols, _ = upper_entries(adjacency)
    chord = (pred[cols] != rows) & (pred[rows] != cols)       # a forest edge joins a node to its predecessor
    return np.stack([rows[chord], cols[chord]], axis=1).astype(np.int64)


def _without_edge(adjacency: sp.csr_matrix, a: int, b: int) -> sp.csr_matrix:
    """The adjacency with the edge a-b made impassable (infinite weight); the structure is kept."""
    blocked = adjacency.copy()
    for row, col in ((a, b), (b, a)):
        span = slice(blocked.indptr[row], blocked.indptr[row + 1])
        blocked.data[span][blocked.indices[span] == col] = np.inf
    return blocked


def _shortest_cycle_through(adjacency: sp.csr_matrix, a: int, b: int, limit: float):
    """(length, ordered cycle nodes) of the shortest cycle using edge a-b, or None above ``limit``."""
    weight = adjacency[a, b]
    dist, pred = csgraph.dijkstra(_without_edge(adjacency, a, b), directed=True, indices=a, limit=limit,
                                  return_predecessors=True)
    if not np.isfinite(dist[b]) or dist[b] + weight > limit:
        return None
    return float(dist[b] + weight), _walk_back(pred, b)


def _cycle_intact(repair: "_Repair", cycle: np.ndarray) -> bool:
    """Whether every node of ``cycle`` is alive and joined to the next one."""
    if not repair.alive[cycle].all():
        return False
    return bool(np.all(np.asarray(repair.adjacency[cycle, np.roll(cycle, -1)]).ravel() != 0))


def _narrow_arc(repair: _Repair, cycle: np.ndarray, marks: np.ndarray):
    """Index of the arc (between consecutive ``marks``) of clearly the narrowest vessel, or None.

    The arc with the smallest median radius of its inner nodes, when that is at most
    :data:`NARROW_ARC_SHARE` of the largest arc's; None without radii or when the arcs are
    of one calibre (two paths through one wide sac).
    """
    if repair.radii is None:
        return None
    medians = np.array([np.median(repair.radii[cycle[a + 1:b]]) if b > a + 1 else np.nan
                        for a, b in zip(marks[:-1], marks[1:])])
    if np.sum(np.isfinite(medians)) < 2:
        return None
    narrowest = int(np.nanargmin(medians))
    return narrowest if medians[narrowest] <= NARROW_ARC_SHARE * np.nanmax(medians) else None


def _break_cycle(repair: _Repair, cycle: np.ndarray) -> None:
    """Break one cycle: drop its arc of clearly the narrowest vessel (:func:`_narrow_arc`),
    else its longest arc, between consecutive attachment nodes."""
    degrees = np.diff(repair.adjacency.indptr)
    attached = np.flatnonzero(degrees[cycle] > 2)
    steps = np.linalg.norm(repair.positions[np.roll(cycle, -1)] - repair.positions[cycle], axis=1)
    if len(attached) == 0:
        repair.set_edges([(cycle[-1], cycle[0])], [0.0])
        return
    start = int(attached[0])
    cycle, steps = np.roll(cycle, -start), np.roll(steps, -start)
    if len(attached) == 1:
        # a lasso: keep the half of the loop next to its attachment node
        half = np.searchsorted(np.cumsum(steps), steps.sum() / 2.0) + 1
        drop = cycle[half:]
    else:
        marks = np.r_[np.sort((attached - start) % len(cycle)), len(cycle)]
        arc_lengths = [steps[marks[i]:marks[i + 1]].sum() for i in range(len(marks) - 1)]
        longest = _narrow_arc(repair, cycle, marks)
        longest = int(np.argmax(arc_lengths)) if longest is None else longest
        drop = cycle[marks[longest] + 1:marks[longest + 1]]
        if len(drop) == 0:
            repair.set_edges([(cycle[marks[longest]], cycle[marks[longest + 1] % len(cycle)])], [0.0])
            return
    repair.loop_nodes.extend(drop.tolist())
    repair.remove_nodes(drop)


def _break_short_loops(repair: _Repair, max_loop: float) -> None:
    """Break cycles shorter than ``max_loop``, shortest first; note the longer ones."""
    broken = 0
    while True:
        chords = _chords(repair.adjacency)
        if len(chords) == 0:
            break
        found = [_shortest_cycle_through(repair.adjacency, a, b, max_loop) for a, b in chords]
        found = sorted((f for f in found if f is not None), key=lambda f: f[0])
        if not found:
            repair.notes.append(f"kept {len(chords)} cycle(s) longer than max_loop={max_loop:.3g}")
            break
        # shortest first; breaking a cycle only lengthens or removes the others, so every
        # cycle still intact afterwards is still the shortest through its chord
        for _, cycle in found:
            if _cycle_intact(repair, cycle):
                _break_cycle(repair, cycle)
                broken += 1
    if broken:
        repair.notes.append(f"broke {broken} loop(s) shorter than {max_loop:.3g}")

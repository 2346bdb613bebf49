"""Skeleton node classification: paper Algorithm 1 (rows 1-31), with the departures listed in :mod:`graph`."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from ..conventions import BRANCH_LABELS
from .anatomy import anatomical_roles
from .repair import _Repair, _break_short_loops, _bridge_gaps
from .skeleton_graph import (DEFAULT_IOTA_MM, DEFAULT_MAX_GAP_MM, DEFAULT_MAX_LOOP_MM, SPUR_RADIUS_FACTOR, Branch,
                             Classification, SkeletonGraph, Trunk, _path_length, _walk_back, upper_entries)

def _junction_clusters(graph: SkeletonGraph):
    """Rows 1-4: quasi-junction clusters, one junction (largest degree) and arm count each."""
    n = len(graph)
    quasi = np.flatnonzero(graph.degrees >= 3)
    cluster_of = np.full(n, -1, dtype=np.int64)
    if len(quasi) == 0:
        return cluster_of, np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    count, labels = csgraph.connected_components(graph.induced_adjacency(quasi), directed=True)
    cluster_of[quasi] = labels
    order = np.lexsort((quasi, -graph.degrees[quasi], labels))
    first = np.r_[True, labels[order][1:] != labels[order][:-1]]
    junctions = quasi[order][first]
    coo = graph.adjacency.tocoo()
    boundary = (cluster_of[coo.row] >= 0) & (cluster_of[coo.row] != cluster_of[coo.col])
    arms = np.bincount(cluster_of[coo.row[boundary]], minlength=count)
    return cluster_of, junctions, arms


def _between(adjacency: sp.csr_matrix, alive: np.ndarray) -> sp.csr_matrix:
    """The entries of ``adjacency`` (canonical: sorted, no zeros) between ``alive`` nodes: ``diag(alive)
    A diag(alive)`` without its zeros, read off the stored entries (each kept one times 1.0 twice)."""
    rows = np.repeat(np.arange(adjacency.shape[0]), np.diff(adjacency.indptr))
    kept = alive[rows] & alive[adjacency.indices]
    indptr = np.zeros(adjacency.shape[0] + 1, dtype=adjacency.indptr.dtype)
    np.cumsum(np.bincount(rows[kept], minlength=adjacency.shape[0]), out=indptr[1:])
    return sp.csr_matrix((adjacency.data[kept], adjacency.indices[kept], indptr), shape=adjacency.shape)


class _BranchSearch:
    """Rows 5-19 of Algorithm 1: branches in order of growing geodesic length."""

    def __init__(self, graph: SkeletonGraph, tau: int, iota: float, spur_radius_factor: float = SPUR_RADIUS_FACTOR):
        self.graph = graph
        self.tau = tau
        self.iota = iota
        self.spur_radius_factor = spur_radius_factor
        self.cluster_of, junctions, self.arms = _junction_clusters(graph)
        self.junction_of_cluster = junctions
        self.active = np.ones(len(junctions), dtype=bool)
        self.kept_degree = graph.degrees.copy()
        self.deleted: list[int] = []
        self.preserved: list[Branch] = []
        self.omitted: list[Branch] = []

    def _nearest_junctions(self):
        sources = self.junction_of_cluster[self.active]
        if len(sources) == 0:
            n = len(self.graph)
            return np.full(n, np.inf), np.full(n, -9999), np.full(n, -1)
        return csgraph.dijkstra(self.graph.adjacency, directed=True, indices=sources, min_only=True,
                                return_predecessors=True)

    def _delete_spur(self, path_from_junction: np.ndarray) -> None:
        """Remove the dangling part of a short branch, from its end node inwards."""
        adjacency = self.graph.adjacency
        for node in path_from_junction[:0:-1]:
            if self.kept_degree[node] > 1:
                break
            self.deleted.append(int(node))
            self.kept_degree[node] = 0
            self.kept_degree[adjacency.indices[adjacency.indptr[node]:adjacency.indptr[node + 1]]] -= 1

    def run(self, ends: np.ndarray, protected=()) -> None:
        """Find, preserve, omit or delete the branches; ``protected`` ends are taken last.

        Taking an end last preserves its branch (the paper preserves the last ``tau``); the
        others go in order of growing geodesic length, as in Algorithm 1.
        """
        marked = list(int(e) for e in ends)
        protected = set(int(e) for e in protected)
        dist, pred, source = self._nearest_junctions()
        while marked:
            end = min(marked, key=lambda e: (e in protected, dist[e], e))
            if not np.isfinite(dist[end]):
                break
            junction = int(source[end])
            nodes = _walk_back(pred, end)[::-1]
            branch = Branch(nodes, junction, end, _path_length(self.graph.positions, nodes))
            marked_before = len(marked)
            marked.remove(end)
            if marked_before <= self.tau:
                self.preserved.append(branch)
                continue
            if branch.length < spur_length(self.graph, junction, self.iota, self.spur_radius_factor):
                self._delete_spur(nodes)
            else:
                self.omitted.append(branch)
            cluster = self.cluster_of[junction]
            self.arms[cluster] -= 1
            if self.arms[cluster] <= 2:
                self.active[cluster] = False
                dist, pred, source = self._nearest_junctions()

    def junctions(self) -> np.ndarray:
        return np.sort(self.junction_of_cluster[self.active])


def _trunks(graph: SkeletonGraph, junctions: np.ndarray) -> list[Trunk]:
    """Rows 20-31: shortest paths between neighbouring junctions (where their waves meet)."""
    if len(junctions) < 2:
        return []
    adjacency = graph.adjacency
    dist, pred, source = csgraph.dijkstra(adjacency, directed=True, indices=junctions, min_only=True,
                                          return_predecessors=True)
    a, b, w = upper_entries(adjacency)
    meet = (source[a] >= 0) & (source[b] >= 0) & (source[a] != source[b])
    best: dict[tuple[int, int], tuple[float, int, int]] = {}
    for u, v, cost in zip(a[meet], b[meet], dist[a[meet]] + w[meet] + dist[b[meet]]):
        if source[u] > source[v]:
            u, v = v, u
        key = (int(source[u]), int(source[v]))
        if key not in best or cost < best[key][0]:
            best[key] = (float(cost), int(u), int(v))
    trunks = []
    for (ja, jb), (cost, u, v) in sorted(best.items()):
        nodes = np.concatenate([_walk_back(pred, u)[::-1], _walk_back(pred, v)])
        trunks.append(Trunk(nodes, (ja, jb), _path_length(graph.positions, nodes)))
    return trunks


def spur_length(graph: SkeletonGraph, junction, iota: float, factor: float = SPUR_RADIUS_FACTOR):
    """Length below which a branch leaving ``junction`` is a spur: ``max(iota, factor * radius)``.

    ``iota`` alone where the graph has no radii. ``junction`` may be an array of nodes.
    """
    if graph.radii is None:
        return np.full(np.shape(junction), float(iota)) if np.ndim(junction) else float(iota)
    return np.maximum(float(iota), factor * graph.radii[junction])


def _fork_waves(graph: SkeletonGraph):
    """Distance, predecessor and source of every node from its nearest quasi-junction node
    (one multi-source Dijkstra), or None without quasi-junctions."""
    forks = np.flatnonzero(graph.degrees >= 3)
    if len(forks) == 0:
        return None
    return csgraph.dijkstra(graph.adjacency, directed=False, indices=forks, min_only=True, return_predecessors=True)


def _ends_beyond_spurs(graph: SkeletonGraph, ends: np.ndarray, iota: float,
                       factor: float = SPUR_RADIUS_FACTOR, waves=None) -> np.ndarray:
    """The end nodes farther along the skeleton from every quasi-junction node than a spur reaches.

    A vessel whose tip the thinning split (a wide rounded end: two prongs of a few pixels)
    keeps its farthest prong's end: at a fork all of whose arms but one end as spurs
    (:func:`_tip_fork_ends`). ``waves``: :func:`_fork_waves` of ``graph``, when already computed.
    """
    waves = _fork_waves(graph) if waves is None else waves
    if waves is None:
        return ends
    reach, _, source = waves
    reachable = source[ends] >= 0
    limit = np.full(len(ends), float(iota))
    limit[reachable] = spur_length(graph, source[ends][reachable], iota, factor)
    beyond = reach[ends] >= limit
    return np.sort(np.r_[ends[beyond], _tip_fork_ends(graph, ends[~beyond], reach, source)])


def _tip_fork_ends(graph: SkeletonGraph, spur_ends: np.ndarray, reach: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Of the spur ends, the farthest one of each fork where every arm but one ends in a spur:
    the fork is a vessel's split tip, and its longest prong is that vessel's end."""
    found = []
    forks = source[spur_ends]
    for fork in np.unique(forks[forks >= 0]):
        prongs = spur_ends[forks == fork]
        if graph.degrees[fork] - len(prongs) <= 1:
            found.append(prongs[np.argmax(reach[prongs])])
    return np.asarray(found, dtype=spur_ends.dtype)


def _branch_calibres(graph: SkeletonGraph, ends: np.ndarray, waves=None) -> np.ndarray | None:
    """Median lumen radius of each end's branch, from where it leaves the nearest
    quasi-junction's lumen to the end (None where the graph has no radii).

    ``waves``: :func:`_fork_waves` of ``graph``, when already computed.
    """
    waves = _fork_waves(graph) if waves is None and graph.radii is not None else waves
    if graph.radii is None or waves is None:
        return None
    reach, pred, source = waves
    pred = pred.tolist()
    calibres = np.empty(len(ends))
    for k, end in enumerate(ends.tolist()):
        path = [end]
        while pred[path[-1]] >= 0:
            path.append(pred[path[-1]])
        nodes = np.array(path)
        if source[end] >= 0:
            outside = nodes[reach[nodes] > graph.radii[source[end]]]
            nodes = outside if len(outside) else nodes
        calibres[k] = float(np.median(graph.radii[nodes]))
    return calibres


def _describe(graph: SkeletonGraph, search: _BranchSearch, ends: np.ndarray) -> str:
    lengths = sorted((round(b.length, 1) for b in search.preserved + search.omitted), reverse=True)
    return (f"{len(graph)} nodes, {len(ends)} end nodes, {len(search.junction_of_cluster)} junctions, "
            f"branch lengths {lengths}")


def _sorted_nodes(nodes) -> np.ndarray:
    return np.array(sorted(nodes), dtype=np.int64)


def classify(graph: SkeletonGraph, *, tau: int = 5, iota: float | None = None,
             max_gap: float | None = None, max_loop: float | None = None,
             directions: dict | None = None, spur_radius_factor: float = SPUR_RADIUS_FACTOR) -> Classification:
    """Classify skeleton nodes into branches, trunks and junctions (paper Algorithm 1).

    Parameters
    ----------
    graph : SkeletonGraph
    tau : int
        Number of branches to preserve (the paper's 5: upper aorta, two renals, two iliacs).
    iota : float, optional
        Branches found while more than ``tau`` end nodes remain are deleted when shorter than
        this, omitted otherwise. In graph units; default ``DEFAULT_IOTA_MM / graph.unit_mm``
        (10 mm in 3D; in 2D pass the pixel size to ``from_image`` or give pixels here).
        Where ``graph.radii`` is known the limit is ``max(iota, spur_radius_factor * r)``
        with ``r`` the radius at the branch's junction (:func:`spur_length`).
    max_gap, max_loop : float, optional
        Gap bridging and loop breaking lengths in graph units (defaults from
        :data:`DEFAULT_MAX_GAP_MM` and :data:`DEFAULT_MAX_LOOP_MM`).
    directions : dict, optional
        ``{"left": ..., "superior": ..., "anterior": ...}`` in the graph's frame (anterior
        only in 3D). Departure from Algorithm 1, which preserves the ``tau`` longest
        branches: with directions, the five ends that play the anatomical roles
        (:func:`anatomical_roles`) are preserved whatever their length, so a coeliac
        trunk or an SMA longer than the stub of upper aorta above it cannot take its place.
        Where the graph knows its radii, the branches' calibres (:func:`_branch_calibres`)
        make the widest of near-tied renal candidates the renal (an accessory renal artery
        beside the main one is narrower).
    spur_radius_factor : float
        Spurs are also branches shorter than this many radii of the vessel they leave
        (where ``graph.radii`` is known; :data:`SPUR_RADIUS_FACTOR`).

    Returns
    -------
    Classification
        Labels are all 'other' until :func:`label_anatomy`.

    Raises
    ------
    ValueError
        When fewer than ``tau`` branches or no trunk can be found; the message says what was.
    """
    if tau < 1:
        raise ValueError(f"tau must be >= 1, got {tau}")
    if len(graph) == 0:
        raise ValueError("skeleton graph has no nodes")
    scale = 1.0 / graph.unit_mm
    iota = DEFAULT_IOTA_MM * scale if iota is None else float(iota)
    max_gap = DEFAULT_MAX_GAP_MM * scale if max_gap is None else float(max_gap)
    max_loop = DEFAULT_MAX_LOOP_MM * scale if max_loop is None else float(max_loop)

    repair = _Repair(graph)
    _bridge_gaps(repair, max_gap)
    _break_short_loops(repair, max_loop)
    repaired = repair.graph(graph)

    ends = np.flatnonzero(repaired.degrees == 1)
    search = _BranchSearch(repaired, tau, iota, spur_radius_factor)
    if len(ends) < tau:
        raise ValueError(f"skeleton has only {len(ends)} end nodes, need {tau} branches "
                         f"(upper aorta, renal and iliac arteries): {_describe(repaired, search, ends)}")
    protected = ()
    if directions is not None and tau == len(BRANCH_LABELS):
        waves = _fork_waves(repaired)
        candidates = _ends_beyond_spurs(repaired, ends, iota, spur_radius_factor, waves)
        if len(candidates) >= tau:
            roles = anatomical_roles(repaired.positions[candidates], **directions,
                                     sizes=_branch_calibres(repaired, candidates, waves))
            protected = candidates[list(roles.values())]
    search.run(ends, protected)
    if len(search.preserved) < tau:
        raise ValueError(f"found only {len(search.preserved)} of {tau} branches: {_describe(repaired, search, ends)}")

    alive = repair.alive.copy()
    alive[search.deleted] = False
    final = SkeletonGraph(graph.positions, _between(repaired.adjacency, alive), graph.grid_indices, graph.unit_mm,
                          graph.radii)
    junctions = search.junctions()
    trunks = _trunks(final, junctions)
    if not trunks:
        raise ValueError(f"no trunk: the {tau} branches meet at {len(junctions)} junction(s), "
                         f"need two or more joined by the aorta: {_describe(repaired, search, ends)}")
    return Classification(
        branches=search.preserved,
        omitted=search.omitted,
        trunks=trunks,
        end_nodes=ends,
        junction_nodes=junctions,
        deleted_nodes=np.flatnonzero(~alive),
        node_labels=["other"] * len(graph),
        graph=final,
        spur_nodes=_sorted_nodes(search.deleted),
        loop_nodes=_sorted_nodes(repair.loop_nodes),
        dropped_nodes=_sorted_nodes(repair.dropped_nodes),
        bridges=np.array(repair.bridges, dtype=np.int64).reshape(-1, 2),
        notes=repair.notes,
    )

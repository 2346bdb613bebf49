"""Skeleton graphs (paper Definition 1) and skeleton node classification (Definitions 2-4, Alg. 1).

A :class:`SkeletonGraph` has one node per skeleton voxel (3D, positions in LPS mm) or pixel
(2D, positions ``(u, v)`` in pixels), edges between grid points at Chebyshev distance 1
(Definition 1) weighted by the Euclidean distance of their positions, and a sparse
symmetric adjacency matrix. :func:`classify` runs Algorithm 1 on it and
:func:`label_anatomy` names the five preserved branches and the trunks.

Where this departs from Algorithm 1, and why
--------------------------------------------
1. Geodesic lengths are physical (Dijkstra on Euclidean edge weights: mm in 3D, pixels in
   2D) instead of hop counts; branches are still found in order of growing geodesic length
   and ``iota`` is a length, not a node count. Hop counts make a diagonal run of voxels look
   shorter than an axial one of the same length and tie ``iota`` to the voxel size.
2. Preservation counts the current end node: a branch is omitted/deleted while more than
   ``tau`` end nodes are still marked *including its own*. Taken literally (count after
   unmarking) the rule preserves ``tau + 1`` branches whenever there are spurs.
3. A junction turns into a connection node only when fewer than three of its arms are left
   (arms that are neither deleted nor omitted). The paper converts it unconditionally; that
   is the same for the usual degree-3 junction, but where a spur leaves a four-armed junction
   (both renals and a spur at one point of a 2D projection) converting it would make a
   renal branch swallow the whole aortic trunk.
4. A deleted spur loses its nodes from the end node up to, not including, the first node
   that still has two other neighbours; the paper deletes the whole path including the
   junction node, which would cut the skeleton there.
5. Trunks are the shortest paths between junctions whose geodesic "waves" meet (multi-source
   Dijkstra); this is the bidirectional BFS of rows 20-31, with each pair reported once.
6. Repairs that the paper does not need on hand-segmented phantoms but real skeletons do,
   all applied before Algorithm 1 on a copy of the graph (``Classification.graph``):
   * triangle pruning in the graph constructors (see :func:`skeleton.grid_edges`);
   * gaps: components whose nearest nodes lie within ``max_gap`` of the main component are
     bridged by one straight edge; farther ones are dropped with a warning;
   * loops: every cycle shorter than ``max_loop`` is broken by removing its longest arc
     between consecutive attachment nodes (a loop closing on itself at one node keeps the
     half next to that node), so two parallel paths through a sac become the shorter one;
     longer cycles are kept (noted).
7. Spurs relative to the vessel: when the graph knows its local radii (the mask it was
   thinned from was given), a branch is a spur when it is shorter than
   ``max(iota, spur_radius_factor * r)``, ``r`` the radius at its junction. Thinning grows a
   branch of one to two radii from every bump of a wide vessel (an aneurysm sac in a raw
   DSA frame: 15-25 mm from a 13 mm lumen), longer than a fixed ``iota`` of one small
   vessel's diameter; a real side branch is several parent radii long.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from . import skeleton as _skeleton
from .conventions import BRANCH_LABELS, IOTA_MM
from .io import Volume

__all__ = [
    "SkeletonGraph",
    "Branch",
    "Trunk",
    "Classification",
    "classify",
    "label_anatomy",
    "anatomical_roles",
    "smooth_positions",
    "centre_in_lumen",
    "spur_length",
    "skeleton_graph_3d",
    "skeleton_graph_2d",
    "DEFAULT_IOTA_MM",
    "SPUR_RADIUS_FACTOR",
    "DEFAULT_MAX_GAP_MM",
    "DEFAULT_MAX_LOOP_MM",
    "BRANCH_LABELS",
]

#: Spurs shorter than this are deleted: the one :data:`conventions.IOTA_MM`.
DEFAULT_IOTA_MM = IOTA_MM
#: Where the graph knows its radii, a branch shorter than this many radii of the vessel at
#: its junction is a spur too (departure 7 above). A bump of height ``h`` on the wall thins
#: to a branch from the centreline of about ``r + h`` (measured: 1.5 r for a bump of a
#: quarter radius on a projected sac); real branches are three radii of their parent or
#: more (renals 40-70 mm off an aorta of 10-12 mm, an internal iliac 35 mm off 5 mm).
SPUR_RADIUS_FACTOR = 2.0
#: Skeleton pieces closer than this to the main piece are bridged, mm. Thinning pulls each
#: side of a cut back by about a vessel radius, so this is a gap plus two radii.
DEFAULT_MAX_GAP_MM = 15.0
#: Cycles shorter than this are broken (loops from thinning a wide sac), mm.
DEFAULT_MAX_LOOP_MM = 100.0

_MIN_WEIGHT = 1e-9
# Every adjacency here is symmetric by construction, so csgraph calls pass directed=True:
# the result is the same and scipy skips building the transpose.


class SkeletonGraph:
    """Nodes, positions and the weighted adjacency of a 2D or 3D skeleton (Definition 1).

    Attributes
    ----------
    positions : numpy.ndarray, shape (n, d)
        LPS mm (3D) or ``(u, v)`` pixels (2D, u = column, v = row).
    grid_indices : numpy.ndarray of int, shape (n, d)
        ``(k, j, i)`` or ``(row, col)``; -1 where the nodes do not come from a grid.
    adjacency : scipy.sparse.csr_matrix, shape (n, n)
        Symmetric; entry = Euclidean distance between the two node positions.
    degrees : numpy.ndarray of int, shape (n,)
    dim : int
        2 or 3.
    unit_mm : float
        Millimetres per position unit (1 in 3D, the pixel size in 2D); sets default lengths.
    radii : numpy.ndarray, shape (n,), or None
        Local vessel radius at each node in position units (the distance to the wall of the
        mask the skeleton was thinned from), when that mask was given; spurs are then
        judged against the radius of the vessel they leave (:func:`classify`).
    """

    def __init__(self, positions, adjacency, grid_indices=None, unit_mm: float = 1.0, radii=None):
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2 or positions.shape[1] not in (2, 3):
            raise ValueError(f"positions must have shape (n, 2) or (n, 3), got {positions.shape}")
        if not np.all(np.isfinite(positions)):
            raise ValueError("skeleton positions contain NaN or infinite values")
        n = len(positions)
        adjacency = sp.csr_matrix(adjacency, dtype=float)
        if adjacency.shape != (n, n):
            raise ValueError(f"adjacency shape {adjacency.shape} does not match {n} nodes")
        adjacency.eliminate_zeros()
        adjacency.sort_indices()
        self.positions = positions
        self.adjacency = adjacency
        self.grid_indices = (np.full(positions.shape, -1, dtype=np.int64) if grid_indices is None
                             else np.asarray(grid_indices, dtype=np.int64).reshape(positions.shape))
        self.degrees = np.diff(adjacency.indptr).astype(np.int64)
        self.dim = positions.shape[1]
        self.unit_mm = float(unit_mm)
        self.radii = None if radii is None else np.asarray(radii, dtype=float).reshape(n)

    def __len__(self) -> int:
        return len(self.positions)

    def __repr__(self) -> str:
        return f"SkeletonGraph(dim={self.dim}, nodes={len(self)}, edges={self.adjacency.nnz // 2})"

    @staticmethod
    def _weighted_adjacency(positions: np.ndarray, edges: np.ndarray) -> sp.csr_matrix:
        n = len(positions)
        if len(edges) == 0:
            return sp.csr_matrix((n, n))
        weights = np.linalg.norm(positions[edges[:, 0]] - positions[edges[:, 1]], axis=1)
        weights = np.maximum(weights, _MIN_WEIGHT)
        rows = np.concatenate([edges[:, 0], edges[:, 1]])
        cols = np.concatenate([edges[:, 1], edges[:, 0]])
        return sp.csr_matrix((np.concatenate([weights, weights]), (rows, cols)), shape=(n, n))

    @classmethod
    def _from_grid(cls, indices: np.ndarray, shape, positions: np.ndarray, unit_mm: float,
                   prune_triangles: bool, radii=None) -> "SkeletonGraph":
        edges = _skeleton.grid_edges(indices, shape, prune_triangles=prune_triangles)
        return cls(positions, cls._weighted_adjacency(positions, edges), indices, unit_mm, radii)

    @classmethod
    def from_volume(cls, skeleton: Volume, *, prune_triangles: bool = True, lumen: Volume | None = None) -> "SkeletonGraph":
        """Graph of the non-zero voxels of a 3D skeleton volume; positions in LPS mm.

        Nodes are in C order of ``(k, j, i)``. With the ``lumen`` mask it was thinned from
        (same grid), every node gets its local radius in mm (``radii``).
        """
        array = np.asarray(skeleton.array)
        if array.ndim != 3:
            raise ValueError(f"skeleton volume must be 3D, got shape {array.shape}")
        flat = _skeleton.nonzero_linear(array)
        if len(flat) == 0:
            raise ValueError(f"skeleton volume of shape {array.shape} is empty (no non-zero voxel)")
        indices = np.stack(np.unravel_index(flat, array.shape), axis=1)
        radii = None
        if lumen is not None:
            if tuple(lumen.shape) != array.shape:
                raise ValueError(f"lumen mask of shape {tuple(lumen.shape)} is not on the skeleton's grid {array.shape}")
            radii = _skeleton.local_radius(lumen.array, indices, np.asarray(lumen.spacing, dtype=float)[::-1])
        return cls._from_grid(indices, array.shape, skeleton.index_to_lps(indices), 1.0, prune_triangles, radii)

    @classmethod
    def from_image(cls, skeleton2d: np.ndarray, pixel_size: float = 1.0, *,
                   prune_triangles: bool = True, mask: np.ndarray | None = None) -> "SkeletonGraph":
        """Graph of the non-zero pixels of a 2D skeleton; positions ``(u, v)`` in pixels.

        ``pixel_size`` (mm per pixel) only scales the default lengths of :func:`classify`.
        With the vessel ``mask`` it was thinned from, every node gets its local radius in
        pixels (``radii``).
        """
        array = np.asarray(skeleton2d)
        if array.ndim != 2:
            raise ValueError(f"2D skeleton must be a 2D array, got shape {array.shape}")
        if not pixel_size > 0:
            raise ValueError(f"pixel_size must be positive, got {pixel_size}")
        indices = np.stack(np.unravel_index(_skeleton.nonzero_linear(array), array.shape), axis=1)
        if len(indices) == 0:
            raise ValueError(f"2D skeleton of shape {array.shape} is empty (no non-zero pixel)")
        positions = indices[:, ::-1].astype(float)
        radii = None
        if mask is not None:
            if np.shape(mask) != array.shape:
                raise ValueError(f"vessel mask of shape {np.shape(mask)} does not match the skeleton's {array.shape}")
            radii = _skeleton.local_radius(mask, indices)
        return cls._from_grid(indices, array.shape, positions, pixel_size, prune_triangles, radii)

    @classmethod
    def from_points(cls, positions, edges, *, grid_indices=None, unit_mm: float = 1.0) -> "SkeletonGraph":
        """Graph from arbitrary node positions and undirected edges (e.g. a projected 3D skeleton).

        Self-loops and repeated edges are dropped. For 2D positions without ``grid_indices``
        the grid index is the nearest pixel ``(round(v), round(u))``; for 3D it is -1.
        """
        positions = np.asarray(positions, dtype=float)
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        n = len(positions)
        if len(edges) and (edges.min() < 0 or edges.max() >= n):
            raise ValueError(f"edge index out of range for {n} nodes")
        edges = np.unique(np.sort(edges[edges[:, 0] != edges[:, 1]], axis=1), axis=0)
        if grid_indices is None and positions.ndim == 2 and positions.shape[1] == 2 and np.all(np.isfinite(positions)):
            grid_indices = np.rint(positions[:, ::-1]).astype(np.int64)
        return cls(positions, cls._weighted_adjacency(positions, edges) if n else sp.csr_matrix((0, 0)),
                   grid_indices, unit_mm)

    def with_positions(self, positions) -> "SkeletonGraph":
        """The same nodes and edges at new positions (edge lengths recomputed)."""
        positions = np.asarray(positions, dtype=float)
        return SkeletonGraph(positions, self._weighted_adjacency(positions, self.edges()), self.grid_indices,
                             self.unit_mm, self.radii)

    def edges(self) -> np.ndarray:
        """Undirected edges as an (m, 2) array with ``i < j``, sorted."""
        upper = sp.triu(self.adjacency, k=1).tocoo()
        pairs = np.stack([upper.row, upper.col], axis=1).astype(np.int64)
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    def subgraph(self, nodes) -> "SkeletonGraph":
        """The induced subgraph on ``nodes`` (new node ``t`` is old node ``nodes[t]``)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        adjacency = self.adjacency[nodes][:, nodes]
        radii = None if self.radii is None else self.radii[nodes]
        return SkeletonGraph(self.positions[nodes], adjacency, self.grid_indices[nodes], self.unit_mm, radii)

    def components(self) -> tuple[int, np.ndarray]:
        """Number of connected components and the component label of each node."""
        return csgraph.connected_components(self.adjacency, directed=True)

    def geodesic_from(self, sources, *, nearest: bool = False) -> np.ndarray:
        """Geodesic distances along the skeleton (Dijkstra on the edge lengths).

        Returns shape (n,) for one source or with ``nearest=True`` (distance to the nearest
        source), else (len(sources), n). Unreachable nodes get ``inf``.
        """
        single = np.ndim(sources) == 0
        return csgraph.dijkstra(self.adjacency, directed=True, indices=sources,
                                min_only=nearest and not single)

    def shortest_path(self, a: int, b: int) -> np.ndarray:
        """Node indices on a shortest path from ``a`` to ``b``, both included."""
        dist, pred = csgraph.dijkstra(self.adjacency, directed=True, indices=int(a), return_predecessors=True)
        if not np.isfinite(dist[b]):
            raise ValueError(f"nodes {a} and {b} are not connected in the skeleton graph")
        return _walk_back(pred, int(b))[::-1]


def _walk_back(predecessors: np.ndarray, node: int) -> np.ndarray:
    """Nodes from ``node`` back to the source of a Dijkstra predecessor array."""
    path = [node]
    while predecessors[path[-1]] >= 0:
        path.append(int(predecessors[path[-1]]))
    return np.array(path, dtype=np.int64)


def _path_length(positions: np.ndarray, path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(positions[path], axis=0), axis=1).sum())


@dataclass
class Branch:
    """A branch (Definition 4): nodes from its junction to its end node, both included."""

    nodes: np.ndarray
    junction: int
    end: int
    length: float
    label: str = "other"


@dataclass
class Trunk:
    """A trunk (Definition 4): nodes from junction ``a`` to junction ``b``, both included."""

    nodes: np.ndarray
    junctions: tuple
    length: float
    label: str = "aorta"


@dataclass
class Classification:
    """Output of Algorithm 1 (and of :func:`label_anatomy`).

    Attributes
    ----------
    branches : list of Branch
        The ``tau`` preserved branches, in the order found (growing length).
    omitted : list of Branch
        Branches kept in the graph but not matched (extra arteries, long spurs).
    trunks : list of Trunk
    end_nodes : numpy.ndarray
        All end nodes (degree 1) of the repaired graph, ``I_e``.
    junction_nodes : numpy.ndarray
        Final junction nodes ``I_c`` after conversions.
    deleted_nodes : numpy.ndarray
        Nodes removed: short spurs (``I_d``), broken loop arcs and dropped components.
    node_labels : list of str
        One anatomy label per node of the input graph ('other' until labelled).
    graph : SkeletonGraph
        The repaired graph (same nodes; bridges added, loops broken, deleted nodes isolated).
    spur_nodes, loop_nodes, dropped_nodes : numpy.ndarray
        ``deleted_nodes`` split by reason.
    bridges : numpy.ndarray, shape (k, 2)
        Edges added across gaps.
    notes : list of str
        What was repaired, in words.
    """

    branches: list
    omitted: list
    trunks: list
    end_nodes: np.ndarray
    junction_nodes: np.ndarray
    deleted_nodes: np.ndarray
    node_labels: list
    graph: SkeletonGraph | None = None
    spur_nodes: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    loop_nodes: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    dropped_nodes: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    bridges: np.ndarray = field(default_factory=lambda: np.empty((0, 2), dtype=np.int64))
    notes: list = field(default_factory=list)

    def kept_nodes(self) -> np.ndarray:
        """Indices of every node not deleted, ascending."""
        return np.setdiff1d(np.arange(len(self.node_labels)), self.deleted_nodes)

    def branch(self, label: str) -> Branch:
        """The preserved branch carrying ``label`` (after :func:`label_anatomy`)."""
        for branch in self.branches:
            if branch.label == label:
                return branch
        raise KeyError(f"no preserved branch labelled {label!r}")


# ---------------------------------------------------------------------------------------
# Repairs before Algorithm 1: gaps and loops
# ---------------------------------------------------------------------------------------

class _Repair:
    """A mutable copy of a graph's adjacency with a record of what was changed."""

    def __init__(self, graph: SkeletonGraph):
        self.positions = graph.positions
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
    n = adjacency.shape[0]
    _, labels = csgraph.connected_components(adjacency, directed=True)
    roots = np.unique(labels, return_index=True)[1]
    _, pred = csgraph.dijkstra(adjacency, directed=True, indices=roots, min_only=True,
                               return_predecessors=True)[:2]
    child = np.flatnonzero(pred >= 0)
    tree_keys = np.minimum(child, pred[child]) * n + np.maximum(child, pred[child])
    upper = sp.triu(adjacency, k=1).tocoo()
    keys = upper.row.astype(np.int64) * n + upper.col
    chord = ~np.isin(keys, tree_keys)
    return np.stack([upper.row[chord], upper.col[chord]], axis=1).astype(np.int64)


def _shortest_cycle_through(adjacency: sp.csr_matrix, a: int, b: int, limit: float):
    """(length, ordered cycle nodes) of the shortest cycle using edge a-b, or None above ``limit``."""
    weight = adjacency[a, b]
    without = adjacency.tolil(copy=True)
    without[a, b] = 0
    without[b, a] = 0
    without = without.tocsr()
    without.eliminate_zeros()
    dist, pred = csgraph.dijkstra(without, directed=True, indices=a, limit=limit,
                                  return_predecessors=True)
    if not np.isfinite(dist[b]) or dist[b] + weight > limit:
        return None
    return float(dist[b] + weight), _walk_back(pred, b)


def _break_cycle(repair: _Repair, cycle: np.ndarray) -> None:
    """Break one cycle: drop its longest arc between consecutive attachment nodes."""
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
        longest = int(np.argmax(arc_lengths))
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
        found = [f for f in found if f is not None]
        if not found:
            repair.notes.append(f"kept {len(chords)} cycle(s) longer than max_loop={max_loop:.3g}")
            break
        length, cycle = min(found, key=lambda f: f[0])
        _break_cycle(repair, cycle)
        broken += 1
    if broken:
        repair.notes.append(f"broke {broken} loop(s) shorter than {max_loop:.3g}")


# ---------------------------------------------------------------------------------------
# Algorithm 1
# ---------------------------------------------------------------------------------------

def _junction_clusters(graph: SkeletonGraph):
    """Rows 1-4: quasi-junction clusters, one junction (largest degree) and arm count each."""
    n = len(graph)
    quasi = np.flatnonzero(graph.degrees >= 3)
    cluster_of = np.full(n, -1, dtype=np.int64)
    if len(quasi) == 0:
        return cluster_of, np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    count, labels = csgraph.connected_components(graph.adjacency[quasi][:, quasi], directed=True)
    cluster_of[quasi] = labels
    order = np.lexsort((quasi, -graph.degrees[quasi], labels))
    first = np.r_[True, labels[order][1:] != labels[order][:-1]]
    junctions = quasi[order][first]
    coo = graph.adjacency.tocoo()
    boundary = (cluster_of[coo.row] >= 0) & (cluster_of[coo.row] != cluster_of[coo.col])
    arms = np.bincount(cluster_of[coo.row[boundary]], minlength=count)
    return cluster_of, junctions, arms


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
    upper = sp.triu(adjacency, k=1).tocoo()
    a, b, w = upper.row, upper.col, upper.data
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


def _ends_beyond_spurs(graph: SkeletonGraph, ends: np.ndarray, iota: float,
                       factor: float = SPUR_RADIUS_FACTOR) -> np.ndarray:
    """The end nodes farther along the skeleton from every quasi-junction node than a spur reaches."""
    forks = np.flatnonzero(graph.degrees >= 3)
    if len(forks) == 0:
        return ends
    reach, _, source = csgraph.dijkstra(graph.adjacency, directed=False, indices=forks, min_only=True,
                                        return_predecessors=True)
    reachable = source[ends] >= 0
    limit = np.full(len(ends), float(iota))
    limit[reachable] = spur_length(graph, source[ends][reachable], iota, factor)
    return ends[reach[ends] >= limit]


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
        candidates = _ends_beyond_spurs(repaired, ends, iota, spur_radius_factor)
        if len(candidates) >= tau:
            roles = anatomical_roles(repaired.positions[candidates], **directions)
            protected = candidates[list(roles.values())]
    search.run(ends, protected)
    if len(search.preserved) < tau:
        raise ValueError(f"found only {len(search.preserved)} of {tau} branches: {_describe(repaired, search, ends)}")

    alive = repair.alive.copy()
    alive[search.deleted] = False
    keep = sp.diags(alive.astype(float))
    final = SkeletonGraph(graph.positions, (keep @ repaired.adjacency @ keep).tocsr(), graph.grid_indices,
                          graph.unit_mm, graph.radii)
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


# ---------------------------------------------------------------------------------------
# Anatomy
# ---------------------------------------------------------------------------------------

def _unit(vector, dim: int, name: str) -> np.ndarray:
    vector = np.asarray(vector, dtype=float).reshape(-1)
    if vector.shape != (dim,) or not np.all(np.isfinite(vector)) or np.linalg.norm(vector) == 0:
        raise ValueError(f"{name} must be a finite non-zero {dim}-vector, got {vector}")
    return vector / np.linalg.norm(vector)


#: Weights of the role scores in :func:`anatomical_roles` (dimensionless: lengths in the
#: graph's unit). Renals: lateral counts twice as much as height; a 3D end anterior of the
#: top end (coeliac, SMA) or posterior of it (internal iliac) is penalised twice its offset.
ROLE_LATERAL_WEIGHT = 2.0
DEPTH_PENALTY = 2.0


def anatomical_roles(end_positions, *, left, superior, anterior=None) -> dict:
    """Which end node plays which of the five roles: label -> row of ``end_positions``.

    With ``p`` an end's offset from the most superior end (the upper aorta's):

    * the iliacs are the pair of other ends with the largest
      ``-(p_a + p_b).superior + |p_a - p_b|.left - 2 max(0, p.posterior)`` summed: low and
      far apart, so that an internal iliac beside its common iliac is not taken for the
      other side; the one further to the patient's left is ``iliac_left``;
    * ``renal_{side}`` is the end on its side of the top end (``s p.left > 0``, ``s = +1``
      for left) with the largest ``2 s p.left + p.superior - 2 max(0, p.anterior)``: lateral
      and high, not an anterior visceral branch.

    ``anterior`` (3D only) enables the depth terms; in a 2D view depth is not seen. Lateral
    offsets are measured across the cranio-caudal direction (in an angulated view the
    image directions of left and superior are not orthogonal).

    Raises
    ------
    ValueError
        With fewer than five ends.
    """
    points = np.asarray(end_positions, dtype=float)
    if len(points) < len(BRANCH_LABELS):
        raise ValueError(f"need {len(BRANCH_LABELS)} end nodes for the anatomy, got {len(points)}")
    dim = points.shape[1]
    superior = _unit(superior, dim, "superior")
    left = _unit(left, dim, "left")
    left = _unit(left - (left @ superior) * superior, dim, "left")
    top = int(np.argmax(points @ superior))
    offset = points - points[top]
    height, lateral = offset @ superior, offset @ left
    forward = offset @ _unit(anterior, dim, "anterior") if anterior is not None else np.zeros(len(points))
    others = np.array([i for i in range(len(points)) if i != top])
    low = -height[others] - DEPTH_PENALTY * np.maximum(0.0, -forward[others])
    pair_score = low[:, None] + low[None, :] + np.abs(lateral[others][:, None] - lateral[others][None, :])
    np.fill_diagonal(pair_score, -np.inf)
    a, b = np.unravel_index(np.argmax(pair_score), pair_score.shape)
    right_iliac, left_iliac = sorted((int(others[a]), int(others[b])), key=lambda i: lateral[i])
    roles = {"aorta": top, "iliac_left": left_iliac, "iliac_right": right_iliac}
    for side, s in (("left", 1.0), ("right", -1.0)):
        score = ROLE_LATERAL_WEIGHT * s * lateral + height - DEPTH_PENALTY * np.maximum(0.0, forward)
        order = [int(i) for i in np.argsort(-score, kind="stable") if int(i) not in roles.values()]
        on_side = [i for i in order if s * lateral[i] > 0]
        roles[f"renal_{side}"] = (on_side or order)[0]
    return roles


def label_anatomy(graph: SkeletonGraph, classification: Classification, *, left, superior,
                  anterior=None) -> Classification:
    """Name the five preserved branches and the trunks; fill ``node_labels`` (in place).

    Parameters
    ----------
    graph : SkeletonGraph
    classification : Classification
        From :func:`classify` with ``tau=5``.
    left, superior : array_like, shape (d,)
        The patient's left and superior directions in the graph's frame: in 3D LPS
        ``(1, 0, 0)`` and ``(0, 0, 1)``; in 2D from ``projection.image_directions(P, at)``
        (a mirrored view flips ``left``).

    anterior : array_like, shape (3,), optional
        The patient's anterior direction (3D only: ``(0, -1, 0)`` in LPS).

    Rule: :func:`anatomical_roles` on the five branch ends (the most superior end is the
    upper aorta; iliacs low and on their side; renals lateral and high). Trunks are aorta.

    Returns
    -------
    Classification
        The same object, labelled.
    """
    branches = classification.branches
    if len(branches) != len(BRANCH_LABELS):
        raise ValueError(f"labelling needs exactly {len(BRANCH_LABELS)} preserved branches, got {len(branches)}")
    _unit(left, graph.dim, "left")
    _unit(superior, graph.dim, "superior")
    roles = anatomical_roles(graph.positions[[b.end for b in branches]], left=left, superior=superior,
                             anterior=anterior)
    for label, index in roles.items():
        branches[index].label = label
    labels = ["other"] * len(graph)
    for branch in branches:
        for node in branch.nodes[1:]:
            labels[node] = branch.label
    for trunk in classification.trunks:
        trunk.label = "aorta"
        for node in trunk.nodes:
            labels[node] = "aorta"
    for branch in branches:
        labels[branch.junction] = "aorta"
    for node in classification.deleted_nodes:
        labels[node] = "other"
    classification.node_labels = labels
    return classification


def smooth_positions(graph: SkeletonGraph, iterations: int = 10, weight: float = 0.5) -> SkeletonGraph:
    """Laplacian smoothing of the connection nodes' positions (topology unchanged).

    Thinning leaves a voxel staircase around the true centreline; moving every degree-2
    node ``weight`` of the way to the mean of its neighbours, ``iterations`` times, takes
    most of it out. End and junction nodes stay where they are, so branch lengths shrink
    only by the staircase they lose.

    Returns
    -------
    SkeletonGraph
        Same nodes, edges and grid indices; new positions and edge lengths.
    """
    hops = graph.adjacency.copy()
    hops.data[:] = 1.0
    degrees = np.asarray(hops.sum(axis=1)).ravel()
    movable = degrees == 2
    mean_of_neighbours = sp.diags(1.0 / np.maximum(degrees, 1.0)) @ hops
    positions = np.array(graph.positions, dtype=float)
    for _ in range(iterations):
        step = mean_of_neighbours @ positions - positions
        positions[movable] += weight * step[movable]
    return graph.with_positions(positions)


def _lumen_distance_map(lumen: Volume) -> tuple[np.ndarray, np.ndarray]:
    """Inside distance to the wall (mm) on the lumen's bounding box, and the box's first index."""
    array = _skeleton.as_binary(lumen.array, "lumen mask")
    if not array.any():
        raise ValueError("lumen mask is empty: nothing to centre the skeleton in")
    box = _skeleton.bounding_box(array, pad=1)
    spacing_kji = lumen.spacing[::-1]
    return ndimage.distance_transform_edt(array[box], sampling=spacing_kji), np.array([b.start for b in box])


def _cross_section_offset(position, tangent, radius, inside_lps, slab_mm, margin_mm) -> np.ndarray | None:
    """Mean in-plane offset of the lumen voxels in a thin slab across the vessel at ``position``."""
    offset = inside_lps - position
    along = offset @ tangent
    across = offset - along[:, None] * tangent
    section = (np.abs(along) <= slab_mm) & (np.linalg.norm(across, axis=1) <= radius + margin_mm)
    if section.sum() < 4:
        return None
    return across[section].mean(axis=0)


def centre_in_lumen(graph: SkeletonGraph, lumen: Volume, *, slab_mm: float = 0.75,
                    margin_mm: float = 1.5) -> SkeletonGraph:
    """Move the connection nodes of a 3D skeleton to the centroid of the lumen's cross-section.

    Thinning puts the skeleton on voxel centres, up to half a voxel from the true axis, and
    :func:`smooth_positions` only averages that staircase along the vessel. Here every
    degree-2 node moves, within the plane normal to its tangent, to the mean of the lumen
    voxels in a slab ``2 slab_mm`` thick across the vessel and within the local radius (the
    inside distance to the wall) plus ``margin_mm``: for a round lumen that is its axis, to
    a small fraction of a voxel, because it averages the whole wall. The margin keeps
    neighbouring vessels out of the section except right at an ostium. End and junction
    nodes stay where they are; a node whose correction would exceed one voxel diagonal
    (a section that is not one vessel) is left alone. On the 1 mm phantom CT this takes the
    mean distance to the true centreline from 0.39 to 0.16 mm (after smoothing).

    Parameters
    ----------
    graph : SkeletonGraph
        A 3D skeleton graph, positions in LPS mm (after :func:`smooth_positions`, so that
        the tangents are not staircase directions).
    lumen : Volume
        The binary lumen mask the skeleton was thinned from.
    slab_mm, margin_mm : float
        Half thickness of the cross-section and how far beyond the local radius it reaches.

    Returns
    -------
    SkeletonGraph
        Same nodes and edges; new positions and edge lengths.
    """
    if graph.dim != 3:
        raise ValueError(f"centre_in_lumen needs a 3D skeleton graph, got dim={graph.dim}")
    distance, box_start = _lumen_distance_map(lumen)
    inside = distance > 0
    spacing_kji = lumen.spacing[::-1]
    max_shift = float(np.linalg.norm(lumen.spacing))
    positions = np.array(graph.positions, dtype=float)
    grid = np.round(lumen.lps_to_index(graph.positions)).astype(int) - box_start
    adjacency = graph.adjacency
    for node in np.flatnonzero(graph.degrees == 2):
        voxel = grid[node]
        if np.any(voxel < 0) or np.any(voxel >= distance.shape) or not inside[tuple(voxel)]:
            continue
        radius = float(distance[tuple(voxel)])
        reach = np.ceil((radius + margin_mm) / spacing_kji).astype(int) + 1
        low, high = np.maximum(voxel - reach, 0), np.minimum(voxel + reach + 1, distance.shape)
        window = tuple(slice(a, b) for a, b in zip(low, high))
        inside_lps = lumen.index_to_lps(np.argwhere(inside[window]) + low + box_start)
        first, second = graph.positions[adjacency.indices[adjacency.indptr[node]:adjacency.indptr[node + 1]]]
        tangent = (first - second) / max(float(np.linalg.norm(first - second)), _MIN_WEIGHT)
        shift = _cross_section_offset(graph.positions[node], tangent, radius, inside_lps, slab_mm, margin_mm)
        if shift is not None and np.linalg.norm(shift) <= max_shift:
            positions[node] += shift
    return graph.with_positions(positions)


# ---------------------------------------------------------------------------------------
# Conveniences
# ---------------------------------------------------------------------------------------

def skeleton_graph_3d(mask_or_skeleton: Volume, is_skeleton: bool = False, *,
                      smooth_sigma: float = 0.0) -> SkeletonGraph:
    """3D skeleton graph of a lumen mask (thinned here) or of a given skeleton volume."""
    skeleton = mask_or_skeleton if is_skeleton else _skeleton.skeletonize_3d(mask_or_skeleton,
                                                                              smooth_sigma=smooth_sigma)
    return SkeletonGraph.from_volume(skeleton)


def skeleton_graph_2d(mask: np.ndarray, *, pixel_size: float = 1.0, smooth_sigma: float = 1.0,
                      downsample: int | None = None, is_skeleton: bool = False) -> SkeletonGraph:
    """2D skeleton graph of a vessel mask (thinned here) or of a given 2D skeleton."""
    skeleton = mask if is_skeleton else _skeleton.skeletonize_2d(mask, smooth_sigma=smooth_sigma,
                                                                 downsample=downsample)
    return SkeletonGraph.from_image(skeleton, pixel_size)

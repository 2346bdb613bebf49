"""The skeleton graph (paper Definition 1) and the types Algorithm 1 returns (Definitions 2-4)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from .. import skeleton as _skeleton
from ..conventions import IOTA_MM
from ..io import Volume

#: Spurs shorter than this are deleted: the one :data:`conventions.IOTA_MM`.
DEFAULT_IOTA_MM = IOTA_MM
#: Where the graph knows its radii, a branch shorter than this many radii of the vessel at
#: its junction is a spur too (departure 7 in :mod:`graph`). A bump of height ``h`` on the wall thins
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
        weights = row_norms(positions[edges[:, 0]] - positions[edges[:, 1]])
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
        return cls.from_image_box((slice(0, array.shape[0]), slice(0, array.shape[1])), array, array.shape,
                                  pixel_size, prune_triangles=prune_triangles, mask=mask)

    @classmethod
    def from_image_box(cls, box, skeleton_in_box: np.ndarray, shape, pixel_size: float = 1.0, *,
                       prune_triangles: bool = True, mask: np.ndarray | None = None) -> "SkeletonGraph":
        """:meth:`from_image` of a skeleton on a grid of ``shape`` that is empty outside ``box``
        (slices), given as its part inside ``box`` (``skeleton.skeleton_2d_box``): the same graph,
        nodes in the same order, without the full grid."""
        array = np.asarray(skeleton_in_box)
        shape = tuple(int(n) for n in shape)
        if not pixel_size > 0:
            raise ValueError(f"pixel_size must be positive, got {pixel_size}")
        start = np.array([b.start for b in box], dtype=np.int64)
        # C order inside the box is C order on the whole grid: every pixel lies in the box
        indices = np.stack(np.unravel_index(_skeleton.nonzero_linear(array), array.shape), axis=1) + start
        if len(indices) == 0:
            raise ValueError(f"2D skeleton of shape {shape} is empty (no non-zero pixel)")
        positions = indices[:, ::-1].astype(float)
        radii = None
        if mask is not None:
            if np.shape(mask) != shape:
                raise ValueError(f"vessel mask of shape {np.shape(mask)} does not match the skeleton's {shape}")
            radii = _skeleton.local_radius(mask, indices)
        return cls._from_grid(indices, shape, positions, pixel_size, prune_triangles, radii)

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
        """The same nodes and edges at new positions (edge lengths recomputed).

        The adjacency keeps its sparsity structure (it is already canonical: sorted, no
        zeros, weights >= ``_MIN_WEIGHT``); only its entries are recomputed, each stored
        entry ``(i, j)`` as ``|positions[i] - positions[j]|``: the same numbers as building
        it again from the edges, without the sparse matrix conversions.
        """
        positions = np.asarray(positions, dtype=float)
        if positions.shape != self.positions.shape:
            raise ValueError(f"positions must have shape {self.positions.shape}, got {positions.shape}")
        if not np.all(np.isfinite(positions)):
            raise ValueError("skeleton positions contain NaN or infinite values")
        rows = np.repeat(np.arange(len(positions)), np.diff(self.adjacency.indptr))
        weights = np.maximum(row_norms(positions[rows] - positions[self.adjacency.indices]), _MIN_WEIGHT)
        adjacency = sp.csr_matrix((weights, self.adjacency.indices.copy(), self.adjacency.indptr.copy()),
                                  shape=self.adjacency.shape)
        return SkeletonGraph._canonical(positions, adjacency, self.grid_indices, self.unit_mm, self.radii,
                                        self.degrees.copy())

    @classmethod
    def _canonical(cls, positions, adjacency, grid_indices, unit_mm, radii, degrees) -> "SkeletonGraph":
        """A graph from parts already in the constructor's canonical form (no checks, no copies)."""
        graph = cls.__new__(cls)
        graph.positions, graph.adjacency, graph.grid_indices = positions, adjacency, grid_indices
        graph.degrees, graph.dim, graph.unit_mm, graph.radii = degrees, positions.shape[1], unit_mm, radii
        return graph

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

    def induced_adjacency(self, nodes) -> sp.csr_matrix:
        """``adjacency[nodes][:, nodes]`` for ascending ``nodes``: the same matrix (entries, order),
        read off the stored rows in one gather instead of two sparse fancy indexings (a quarter
        to a half of their time on a frame's 2D graph)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        indptr, indices = self.adjacency.indptr, self.adjacency.indices
        local = np.full(len(self), -1, dtype=np.int64)
        local[nodes] = np.arange(len(nodes))
        starts = indptr[nodes]
        counts = indptr[nodes + 1] - starts
        slots = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum()))
        columns = local[indices[slots]]
        inside = columns >= 0
        row_ptr = np.zeros(len(nodes) + 1, dtype=indptr.dtype)
        np.cumsum(np.bincount(np.repeat(np.arange(len(nodes)), counts)[inside], minlength=len(nodes)), out=row_ptr[1:])
        return sp.csr_matrix((self.adjacency.data[slots[inside]], columns[inside].astype(indices.dtype), row_ptr),
                             shape=(len(nodes), len(nodes)))

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


def upper_entries(adjacency: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, values)`` of the stored entries above the diagonal, in storage order: those of
    ``sp.triu(adjacency, k=1).tocoo()``, without building the matrix."""
    rows = np.repeat(np.arange(adjacency.shape[0], dtype=adjacency.indices.dtype), np.diff(adjacency.indptr))
    upper = rows < adjacency.indices
    return rows[upper], adjacency.indices[upper], adjacency.data[upper]


def row_norms(vectors: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(vectors, axis=-1)`` of a real float array, to the bit (its square, sum along
    the last axis and root), without its argument handling (a few microseconds a call, and the
    per-frame path calls it hundreds of times)."""
    return np.sqrt(np.add.reduce(vectors * vectors, axis=-1))


def _walk_back(predecessors: np.ndarray, node: int) -> np.ndarray:
    """Nodes from ``node`` back to the source of a Dijkstra predecessor array."""
    path = [node]
    before = predecessors.item          # Python ints: no NumPy scalar per step
    previous = before(node)
    while previous >= 0:
        path.append(previous)
        previous = before(previous)
    return np.array(path, dtype=np.int64)


def _path_length(positions: np.ndarray, path: np.ndarray) -> float:
    return float(row_norms(np.diff(positions[path], axis=0)).sum())


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

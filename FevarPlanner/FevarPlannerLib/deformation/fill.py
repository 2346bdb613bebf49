"""Algorithm 2 row 16: the unassigned nodes follow branch-wise 3D thin-plate splines."""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import scipy.sparse
from scipy.sparse import csgraph
from scipy.spatial.distance import cdist

from ..centerline import as_points
from .tps import FixedControlsTPS

__all__ = ["fill_unassigned"]


def _stored_edges(adjacency) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the stored off-diagonal entries of ``adjacency``, in storage order."""
    coo = scipy.sparse.coo_matrix(adjacency)
    mask = coo.row != coo.col
    return coo.row[mask], coo.col[mask]


def _edge_weighted_graph(points: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> scipy.sparse.csr_matrix:
    """The undirected skeleton graph with Euclidean edge lengths (mm) as weights."""
    lengths = np.linalg.norm(points[rows] - points[cols], axis=1)
    lengths = np.maximum(lengths, 1e-9)          # csgraph treats an explicit 0 as "no edge"
    n = len(points)
    graph = scipy.sparse.csr_matrix((lengths, (rows, cols)), shape=(n, n))
    return graph.maximum(graph.T).tocsr()


#: Largest (sources x nodes) distance table computed in one Dijkstra call.
_DISTANCE_TABLE_LIMIT = 4_000_000


def _nearest_assigned(graph, sources: np.ndarray, assigned: np.ndarray, limit: float,
                      distance=None) -> tuple[np.ndarray, np.ndarray]:
    """Assigned nodes reachable from ``sources`` within ``limit`` mm, and their distances.

    ``distance`` (n,) may hold these geodesic distances already.
    """
    if distance is None:
        distance = csgraph.dijkstra(graph, directed=False, indices=sources, min_only=True, limit=limit)
    found = np.flatnonzero(assigned & np.isfinite(distance))
    return found, distance[found]


def _choose_controls(points, graph, nodes, assigned, candidates, neighbourhood_mm, max_controls, min_controls,
                     distance=None):
    """Control nodes for the unassigned ``nodes``: assigned ``candidates`` nearest along the skeleton.

    Geodesic neighbourhood of ``neighbourhood_mm`` first (``distance``, if given, holds the
    geodesic distances from ``nodes`` within it); if that holds fewer than ``min_controls``,
    the nearest reachable assigned nodes at any distance; if still too few, the
    Euclidean-nearest assigned nodes. At most ``max_controls`` are kept, nearest first.
    """
    allowed = assigned & candidates
    found, distance = _nearest_assigned(graph, nodes, allowed, neighbourhood_mm, distance)
    if len(found) < min_controls:
        found, distance = _nearest_assigned(graph, nodes, allowed, np.inf)
    if len(found) < min_controls:
        pool = np.flatnonzero(assigned)
        distance = cdist(points[pool], points[nodes]).min(axis=1)
        found = pool
    order = np.argsort(distance, kind="stable")[:max_controls]
    return found[order]


def _connected_vessels(piece: np.ndarray, rows: np.ndarray, cols: np.ndarray, vessels: np.ndarray) -> np.ndarray:
    """Nodes of the vessels an unassigned ``piece`` is connected to (the paper's "connected branches or trunks").

    A side branch seen nowhere in the frame (a superior mesenteric artery) then follows the
    aorta it leaves, not a renal beside it that the frame moved on its own. The vessels are
    those of the nodes one edge outside the piece; with none (a piece on its own), every node.
    """
    inside = np.zeros(len(vessels), dtype=bool)
    inside[piece] = True
    outward = np.r_[cols[inside[rows] & ~inside[cols]], rows[inside[cols] & ~inside[rows]]]
    touching = np.unique(vessels[outward])
    if touching.size == 0:
        return np.ones(len(vessels), dtype=bool)
    return np.isin(vessels, touching)


class _FillPlan:
    """Which unassigned nodes follow which controls, with each spline's fixed part (Algorithm 2 row 16).

    All of it depends only on the pre-operative points, the skeleton, the assigned mask and
    the options, never on where the assigned nodes moved: a frame's nearest-point passes
    (and the frames of a patient with the same assignment) reuse it (:func:`_plan_for`).
    """

    def __init__(self, points, rows, cols, assigned, groups, max_controls, neighbourhood_mm, regularization,
                 min_extent_ratio, vessels=None):
        n = len(points)
        self.splines = []                  # (unassigned nodes, their controls, FixedControlsTPS)
        graph = _edge_weighted_graph(points, rows, cols)
        pending = ~assigned
        everywhere = np.ones(n, dtype=bool)
        for group in groups:
            if group.size and (group.min() < 0 or group.max() >= n):
                raise ValueError(f"groups: node indices must lie in [0, {n})")
            nodes = group[pending[group]]
            members = np.zeros(n, dtype=bool)
            members[group] = True
            if nodes.size == 0 or np.count_nonzero(assigned & members) < 4:
                continue
            controls = _choose_controls(points, graph, nodes, assigned, members, np.inf, max_controls, 4)
            self._add(points, controls, nodes, regularization, min_extent_ratio)
            pending[nodes] = False

        remaining = np.flatnonzero(pending)
        if remaining.size == 0:
            return
        sub = graph[remaining][:, remaining]
        _, component_of = csgraph.connected_components(sub, directed=False)
        table = None
        if remaining.size * n <= _DISTANCE_TABLE_LIMIT:      # one Dijkstra call for all components
            table = csgraph.dijkstra(graph, directed=False, indices=remaining, limit=neighbourhood_mm)
        for label in np.unique(component_of):
            members = np.flatnonzero(component_of == label)
            nodes = remaining[members]
            near = None if table is None else table[members].min(axis=0)
            candidates = everywhere if vessels is None else _connected_vessels(nodes, rows, cols, vessels)
            controls = _choose_controls(points, graph, nodes, assigned, candidates, neighbourhood_mm,
                                        max_controls, 4, near)
            self._add(points, controls, nodes, regularization, min_extent_ratio)

    def _add(self, points, controls, nodes, regularization, min_extent_ratio) -> None:
        spline = FixedControlsTPS(points[controls], points[nodes], regularization, min_extent_ratio=min_extent_ratio)
        self.splines.append((nodes, controls, spline))

    def apply(self, result: np.ndarray, moved: np.ndarray) -> None:
        """Move the planned nodes of ``result`` (in place) by the splines through ``moved`` controls."""
        for nodes, controls, spline in self.splines:
            result[nodes] = spline.apply(moved[controls])


#: Fill plans kept (most recently used last): a few frames' passes and candidates.
_PLAN_CACHE_SIZE = 16
_plan_cache: OrderedDict = OrderedDict()
_plan_lock = threading.Lock()


def _plan_for(points, adjacency, assigned, groups, max_controls, neighbourhood_mm, regularization,
              min_extent_ratio, vessels=None) -> _FillPlan:
    """The :class:`_FillPlan` of these inputs, from a small LRU cache keyed by their content."""
    rows, cols = _stored_edges(adjacency)
    groups = [np.unique(np.asarray(group, dtype=np.int64).reshape(-1)) for group in groups or ()]
    key = (points.shape, points.tobytes(), rows.tobytes(), cols.tobytes(), assigned.tobytes(),
           tuple(group.tobytes() for group in groups), int(max_controls), float(neighbourhood_mm),
           float(regularization), float(min_extent_ratio), None if vessels is None else vessels.tobytes())
    with _plan_lock:
        plan = _plan_cache.get(key)
        if plan is not None:
            _plan_cache.move_to_end(key)
            return plan
    plan = _FillPlan(points, rows, cols, assigned, groups, max_controls, neighbourhood_mm, regularization,
                     min_extent_ratio, vessels)
    with _plan_lock:
        _plan_cache[key] = plan
        while len(_plan_cache) > _PLAN_CACHE_SIZE:
            _plan_cache.popitem(last=False)
    return plan


def fill_unassigned(points, deformed_assigned, assigned, adjacency, *, groups=None, max_controls=80,
                    neighbourhood_mm=40.0, regularization=0.0, min_extent_ratio=0.05, vessels=None) -> np.ndarray:
    """Move the unassigned skeleton nodes with branch-wise 3D TPS (Algorithm 2 row 16).

    Each connected piece of unassigned nodes (in the skeleton restricted to them) follows a
    TPS whose controls are the assigned nodes within ``neighbourhood_mm`` of it along the
    skeleton: the assigned parts of the branches and trunks it is connected to (with
    ``vessels``, only those: not a sibling branch reached through the trunk). With fewer
    than 4 such controls the nearest assigned nodes further away are used. Where ``groups``
    are given, the unassigned nodes of a group use that group's assigned nodes instead.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Pre-operative skeleton nodes (LPS mm).
    deformed_assigned : array_like, shape (n, 3)
        Deformed positions, read only where ``assigned`` is True.
    assigned : array_like of bool, shape (n,)
    adjacency : scipy.sparse matrix, shape (n, n)
        Skeleton adjacency (non-zero = edge; weights are ignored, lengths come from ``points``).
    groups : sequence of int arrays, optional
        Explicit branch/trunk node groups; a node in several groups uses the first.
    max_controls : int
        Most control points of one spline (the nearest along the skeleton are kept).
    neighbourhood_mm : float
        Geodesic radius of the control neighbourhood (mm).
    regularization : float
        TPS ``lambda`` (see :meth:`ThinPlateSpline3D.fit`).
    min_extent_ratio : float
        Affine directions with less relative spread of the controls are dropped, so that
        near-collinear controls (a straight branch) do not extrapolate wildly sideways.
    vessels : array_like, shape (n,), optional
        The vessel (any label or code) of each node.

    Returns
    -------
    numpy.ndarray, shape (n, 3)
        All nodes: assigned ones exactly at ``deformed_assigned``, the rest TPS-moved. With no
        assigned node at all, ``points`` unchanged.
    """
    points = as_points(points, "points", 3)
    n = len(points)
    assigned = np.asarray(assigned, dtype=bool).reshape(-1)
    if len(assigned) != n:
        raise ValueError(f"assigned: {len(assigned)} flags for {n} points")
    moved = np.asarray(deformed_assigned, dtype=float)
    if moved.shape != (n, 3):
        raise ValueError(f"deformed_assigned: expected shape ({n}, 3), got {moved.shape}")
    if not np.all(np.isfinite(moved[assigned])):
        raise ValueError("deformed_assigned: NaN or infinite values at assigned nodes")
    if adjacency.shape != (n, n):
        raise ValueError(f"adjacency: expected shape ({n}, {n}), got {adjacency.shape}")
    if max_controls < 1:
        raise ValueError(f"max_controls must be >= 1 (got {max_controls})")
    result = points.copy()
    result[assigned] = moved[assigned]
    if assigned.all() or not assigned.any():
        return result

    if vessels is not None:
        vessels = np.unique(np.asarray(vessels).reshape(-1), return_inverse=True)[1]
        if len(vessels) != n:
            raise ValueError(f"vessels: {len(vessels)} labels for {n} points")
    plan = _plan_for(points, adjacency, assigned, groups, max_controls, neighbourhood_mm, regularization,
                     min_extent_ratio, vessels)
    plan.apply(result, moved)
    return result

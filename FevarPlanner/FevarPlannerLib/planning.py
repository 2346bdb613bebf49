"""3D catheter path planning on the (deformed) centreline graph.

The path runs from the access point, the distal end of the start vessel (by default the
right iliac artery, where the catheter enters), along the centreline graph to the target:
the ostium of the target branch (the first node of that branch next to the aorta) or its
distal end. It is the shortest path on the graph with Euclidean edge lengths (Dijkstra),
so it follows the vessel tree and never cuts across the lumen.

All points are LPS millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from .centerline import ANATOMY_LABELS, Centerline

__all__ = ["CatheterPath", "VESSEL_LABELS", "check_labels", "plan_path", "path_length", "resample_path", "smooth_path"]

TARGET_POINTS = ("ostium", "end")


@dataclass
class CatheterPath:
    """A planned catheter path.

    Attributes
    ----------
    points : numpy.ndarray, shape (k, 3)
        Path points, LPS mm, from the access point to the target.
    nodes : numpy.ndarray of int, shape (k,)
        Indices of the path points in the centreline they were planned on.
    start_label, target_label : str
        Vessel labels of the access vessel and the target vessel.
    length_mm : float
        Arc length of the path.
    """

    points: np.ndarray
    nodes: np.ndarray
    start_label: str
    target_label: str
    length_mm: float

    def to_dict(self) -> dict:
        """The ``path`` entry of result.json: ``{"points", "from", "to", "length_mm"}``."""
        return {"points": np.asarray(self.points, dtype=float).tolist(), "from": self.start_label,
                "to": self.target_label, "length_mm": float(self.length_mm)}


def path_length(points: np.ndarray) -> float:
    """Arc length (mm) of a polyline given as (k, 3) points."""
    points = np.asarray(points, dtype=float)
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def _edge_graph(centerline: Centerline) -> sparse.csr_matrix:
    """Symmetric sparse graph of the centreline with Euclidean edge lengths as weights.

    Self-loops and repeated edges are dropped. A zero-length edge (two nodes at the same
    position) gets a tiny positive weight, because csgraph reads stored zeros as no edge.
    """
    edges = np.sort(centerline.edges, axis=1)
    edges = np.unique(edges[edges[:, 0] != edges[:, 1]], axis=0)
    lengths = np.linalg.norm(centerline.points[edges[:, 1]] - centerline.points[edges[:, 0]], axis=1)
    lengths = np.maximum(lengths, 1e-12)
    n = len(centerline)
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    return sparse.csr_matrix((np.concatenate([lengths, lengths]), (rows, cols)), shape=(n, n))


def _label_nodes(centerline: Centerline, label: str) -> np.ndarray:
    nodes = np.flatnonzero(np.asarray(centerline.labels) == label)
    if len(nodes) == 0:
        present = sorted(set(centerline.labels))
        raise ValueError(f"no '{label}' nodes in the centreline; labels present: {present}")
    return nodes


def _distal_end(graph: sparse.csr_matrix, nodes: np.ndarray, from_aorta: np.ndarray, label: str) -> int:
    """The node of ``nodes`` farthest (along the graph) from the aorta, preferring degree-1 nodes."""
    reachable = nodes[np.isfinite(from_aorta[nodes])]
    if len(reachable) == 0:
        raise ValueError(f"the '{label}' nodes are not connected to the aorta in the centreline graph")
    degree = np.diff(graph.indptr)
    ends = reachable[degree[reachable] == 1]
    candidates = ends if len(ends) else reachable
    return int(candidates[np.argmax(from_aorta[candidates])])


def _ostium_candidates(graph: sparse.csr_matrix, nodes: np.ndarray, aorta: np.ndarray,
                       from_aorta: np.ndarray, label: str) -> np.ndarray:
    """Nodes of the target branch next to an aorta node; else its node nearest the aorta."""
    is_aorta = np.zeros(graph.shape[0], dtype=bool)
    is_aorta[aorta] = True
    adjacent = np.array([n for n in nodes if is_aorta[graph.indices[graph.indptr[n]:graph.indptr[n + 1]]].any()],
                        dtype=np.int64)
    if len(adjacent):
        return adjacent
    if not np.isfinite(from_aorta[nodes]).any():
        raise ValueError(f"the '{label}' nodes are not connected to the aorta in the centreline graph")
    return np.array([nodes[np.argmin(from_aorta[nodes])]], dtype=np.int64)


def _trace(predecessors: np.ndarray, source: int, target: int) -> np.ndarray:
    """Node sequence source -> target from a Dijkstra predecessor array rooted at ``source``."""
    nodes = [target]
    while nodes[-1] != source:
        nodes.append(int(predecessors[nodes[-1]]))
    return np.array(nodes[::-1], dtype=np.int64)


#: The vessels a path may start or end in (every anatomy label but the aorta).
VESSEL_LABELS = tuple(name for name in ANATOMY_LABELS if name != "aorta")


def check_labels(start: str, target: str) -> None:
    """Raise ``ValueError`` unless ``start`` and ``target`` are vessel labels (before any work starts)."""
    for role, label in (("start", start), ("target", target)):
        if label not in VESSEL_LABELS:
            raise ValueError(f"{role} vessel must be one of {list(VESSEL_LABELS)}, got {label!r}")


def plan_path(centerline: Centerline, *, start: str = "iliac_right", target: str = "renal_left",
              to: str = "ostium") -> CatheterPath:
    """Shortest path along the centreline graph from the access point to the target.

    Parameters
    ----------
    centerline : Centerline
        The labelled (deformed) centreline graph; it must hold 'aorta' nodes and nodes of the
        start and target vessels, connected to each other.
    start : str
        Label of the access vessel; the path starts at its distal end, the degree-1 node
        of that vessel farthest from the aorta along the graph.
    target : str
        Label of the target vessel (e.g. the renal artery to be fenestrated).
    to : {"ostium", "end"}
        End the path at the target's ostium (its node next to an aorta node; if several,
        the one reached first from the access point) or at its distal end.

    Returns
    -------
    CatheterPath

    Raises
    ------
    ValueError
        A label is unknown or absent, or the vessels are not connected.
    """
    check_labels(start, target)
    if to not in TARGET_POINTS:
        raise ValueError(f"'to' must be one of {list(TARGET_POINTS)}, got {to!r}")
    aorta = _label_nodes(centerline, "aorta")
    start_nodes = _label_nodes(centerline, start)
    target_nodes = _label_nodes(centerline, target)

    graph = _edge_graph(centerline)
    from_aorta = csgraph.dijkstra(graph, directed=False, indices=aorta, min_only=True)
    access = _distal_end(graph, start_nodes, from_aorta, start)
    if to == "end":
        goals = np.array([_distal_end(graph, target_nodes, from_aorta, target)])
    else:
        goals = _ostium_candidates(graph, target_nodes, aorta, from_aorta, target)

    distance, predecessors = csgraph.dijkstra(graph, directed=False, indices=access, return_predecessors=True)
    goal = int(goals[np.argmin(distance[goals])])
    if not np.isfinite(distance[goal]):
        raise ValueError(f"no path along the centreline from '{start}' to '{target}': the graph is disconnected")
    nodes = _trace(predecessors, access, goal)
    points = centerline.points[nodes].copy()
    return CatheterPath(points, nodes, start, target, path_length(points))


def _drop_repeated_points(points: np.ndarray) -> np.ndarray:
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([points[:1], points[1:][steps > 0]])


def resample_path(points: np.ndarray, step_mm: float = 1.0) -> np.ndarray:
    """Resample a polyline at equal arc-length steps, keeping both end points exactly.

    The spacing is ``L / ceil(L / step_mm)``: the largest spacing not above ``step_mm``
    that divides the length ``L`` evenly.

    Parameters
    ----------
    points : array_like, shape (k, 3)
    step_mm : float
        Largest allowed distance (along the curve) between consecutive output points.

    Returns
    -------
    numpy.ndarray, shape (m, 3)
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"expected (k, 3) points, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("path points contain NaN or infinite values")
    if not step_mm > 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")
    points = _drop_repeated_points(points)
    if len(points) == 1:
        return points.copy()
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    count = int(np.ceil(arc[-1] / step_mm))
    samples = np.linspace(0.0, arc[-1], count + 1)
    resampled = np.column_stack([np.interp(samples, arc, points[:, axis]) for axis in range(3)])
    resampled[0], resampled[-1] = points[0], points[-1]
    return resampled


def smooth_path(points: np.ndarray, sigma_mm: float = 2.0, step_mm: float = 0.5) -> np.ndarray:
    """A smooth, catheter-friendly version of a path, with exactly the same end points.

    The path is resampled every ``step_mm`` and filtered with a Gaussian of width
    ``sigma_mm`` along its arc length. Beyond each end the curve is continued by its point
    reflection through the end point, so the filter leaves both end points (and straight
    stretches) where they are instead of pulling them inwards.

    Parameters
    ----------
    points : array_like, shape (k, 3)
    sigma_mm : float
        Standard deviation of the smoothing kernel along the curve, mm (0 = no smoothing).
    step_mm : float
        Sampling step of the returned curve, mm.

    Returns
    -------
    numpy.ndarray, shape (m, 3)
    """
    if sigma_mm < 0:
        raise ValueError(f"sigma_mm must be non-negative, got {sigma_mm}")
    curve = resample_path(points, step_mm)
    if sigma_mm == 0 or len(curve) < 3:
        return curve
    step = np.linalg.norm(curve[1] - curve[0])
    sigma = sigma_mm / step
    pad = min(len(curve) - 1, int(np.ceil(4 * sigma)))
    head = 2 * curve[0] - curve[pad:0:-1]
    tail = 2 * curve[-1] - curve[-2:-pad - 2:-1]
    padded = np.concatenate([head, curve, tail])
    smoothed = ndimage.gaussian_filter1d(padded, sigma, axis=0, mode="nearest")[pad:pad + len(curve)]
    smoothed[0], smoothed[-1] = curve[0], curve[-1]
    return smoothed

"""The paper's evaluation metrics: 2D and 3D point-to-curve distances (Sec. III, Figs. 4-6,
Tables I-II).

The paper measured errors with MATLAB's ``distance2curve`` (File Exchange): the distance from
each point to the *nearest point on a curve made of straight segments*, not to the nearest
vertex. Here a curve is any centreline graph: every edge is one segment, and an isolated
node is a segment of length zero.

* **2D error** (pixels): every node of the result, projected with ``P`` (eq. 1), to the 2D
  skeleton graph of the fluoroscopic frame. ``2d_reverse_px`` is the other way round
  (skeleton points to the projected result graph); it exposes a result whose projection
  covers only part of the skeleton, but it also counts skeleton pieces the 3D centreline
  has no counterpart for (catheters, small side branches).
* **3D error** (mm): every node of the result to the ground-truth 3D centreline graph
  (``forward``, the paper's measure), every ground-truth node to the result
  (``reverse``), so that a collapsed or shrunken result cannot look good, and
  ``symmetric``: the statistics of both sets of distances pooled (its ``max`` is the
  Hausdorff distance between the two graphs).

Every statistic is a dict ``{"mean", "std", "median", "max"}``; ``std`` is the sample
standard deviation (``ddof = 1``, MATLAB's default) and 0 for a single distance.

Restricting the comparison to vessels present in both
-----------------------------------------------------
A ground-truth centreline may hold vessels that the result does not (or the other way
round), and a fluoroscopic frame may not show every vessel of the CT. :func:`evaluate`
therefore compares only nodes whose anatomy labels occur in the chosen label set: by
default the labels that the result and the ground truth *both* carry; a caller that knows
which vessels the frame shows passes them as ``labels`` (:func:`restrict_to_labels` does
the cut: the subgraph of the kept nodes and of the edges between them). The 2D skeleton
carries no labels and is never cut.

Depth (issue 10)
----------------
One view fixes each point's ray but not its depth along it. :func:`depth_floor` scores the
oracle that puts every true intra-operative point on its true ray at its pre-operative
depth, with the same metric (oracle points to the true graph): a method that does not
recover depth cannot go below it. :func:`depth_analysis` splits each result node's error
into its along-ray and in-plane parts (:func:`ray_components`), overall and per vessel,
and reports the fraction of the true along-ray motion recovered. With two views the
floor is reported for the main view's rays.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.spatial import cKDTree

from .centerline import ANATOMY_LABELS, Centerline, as_points
from .conventions import BRANCH_LABELS
from .projection import project, source_position, validate_projection_matrix

__all__ = [
    "point_to_segments",
    "SegmentIndex",
    "point_to_graph",
    "graph_index",
    "distance_statistics",
    "error_2d",
    "error_3d",
    "restrict_to_labels",
    "common_labels",
    "evaluate",
    "closest_points_on_graph",
    "depth_floor_points",
    "depth_floor",
    "ray_components",
    "depth_analysis",
    "MAIN_VESSELS",
]

#: Segments scanned per KD-tree query before the exactness check (see point_to_segments).
_CANDIDATES = 8
#: Below this many segments the plain all-pairs computation is as fast as the tree.
_BRUTE_FORCE_SEGMENTS = 64
#: Most segments scanned per point (growing 4x from _CANDIDATES) before the all-pairs fallback.
_MAX_CANDIDATES = 512


def _nearest_on_segments(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray,
                         chunk_elements: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance of every point to the nearest of all segments and that nearest point,
    in memory-bounded chunks."""
    ab = seg_b - seg_a
    length2 = np.einsum("md,md->m", ab, ab)
    safe_length2 = np.where(length2 > 0, length2, 1.0)
    chunk = max(1, chunk_elements // max(1, seg_a.size))
    distances = np.empty(len(points))
    nearest = np.empty_like(points, dtype=float)
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk]
        ap = p[:, None, :] - seg_a[None, :, :]
        t = np.clip(np.einsum("cmd,md->cm", ap, ab) / safe_length2, 0.0, 1.0)
        t[:, length2 == 0] = 0.0
        offset = ap - t[..., None] * ab[None]
        squared = np.einsum("cmd,cmd->cm", offset, offset)
        best = squared.argmin(axis=1)
        rows = np.arange(len(p))
        distances[start:start + chunk] = np.sqrt(squared[rows, best])
        nearest[start:start + chunk] = seg_a[best] + t[rows, best][:, None] * ab[best]
    return distances, nearest


def _segment_distances_all_pairs(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray,
                                 chunk_elements: int) -> np.ndarray:
    """Exact distance of every point to the nearest of all segments, in memory-bounded chunks."""
    return _nearest_on_segments(points, seg_a, seg_b, chunk_elements)[0]


def _segment_distances_candidates(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray,
                                  candidates: np.ndarray) -> np.ndarray:
    """Distance of point ``i`` to the nearest of the segments ``candidates[i]`` (n, k)."""
    a = seg_a[candidates]
    ab = seg_b[candidates] - a
    ap = points[:, None, :] - a
    length2 = np.einsum("nkd,nkd->nk", ab, ab)
    t = np.where(length2 > 0, np.einsum("nkd,nkd->nk", ap, ab) / np.where(length2 > 0, length2, 1.0), 0.0)
    offset = ap - np.clip(t, 0.0, 1.0)[..., None] * ab
    return np.sqrt(np.einsum("nkd,nkd->nk", offset, offset).min(axis=1))


def point_to_segments(points, seg_a, seg_b, *, chunk_elements: int = 2_000_000) -> np.ndarray:
    """Distance from each point to the nearest point of a set of straight segments.

    Parameters
    ----------
    points : array_like, shape (n, d)
        Query points, ``d`` = 2 or 3 (any ``d`` works).
    seg_a, seg_b : array_like, shape (m, d)
        Segment end points; a segment with ``seg_a[i] == seg_b[i]`` is a single point.
    chunk_elements : int
        Upper bound on the number of floats of one temporary (point, segment, coordinate)
        block; bounds the memory of the all-pairs fallback.

    Returns
    -------
    numpy.ndarray, shape (n,)

    Notes
    -----
    See :class:`SegmentIndex`, which this builds and queries once; build the index yourself
    to measure many point sets against the same segments.
    """
    points = as_points(points, "points")
    return SegmentIndex(seg_a, seg_b, points.shape[1], chunk_elements=chunk_elements).distances(points)


class SegmentIndex:
    """A set of straight segments, prepared for repeated nearest-distance queries.

    Parameters
    ----------
    seg_a, seg_b : array_like, shape (m, d)
        Segment end points; a segment with ``seg_a[i] == seg_b[i]`` is a single point.
    dim : int, optional
        The dimension the segments must have (that of the query points).
    chunk_elements : int
        As in :func:`point_to_segments`.

    Notes
    -----
    A KD-tree on the segment midpoints proposes the ``8`` nearest segments of each point.
    The answer is exact whenever the best of them is no farther than ``d_k - h_max``
    (``d_k`` the distance to the k-th nearest midpoint, ``h_max`` the largest half-length):
    every other segment lies at least that far. The points that fail the check are asked
    again with four times as many candidates, and so on; those still unresolved at
    :data:`_MAX_CANDIDATES` are computed against all segments. Every answer is the
    minimum of the same per-segment distances, so it does not depend on the stage that
    resolved it.
    """

    def __init__(self, seg_a, seg_b, dim: int | None = None, *, chunk_elements: int = 2_000_000):
        self.seg_a = as_points(seg_a, "segment starts", dim)
        self.seg_b = as_points(seg_b, "segment ends", self.seg_a.shape[1] if dim is None else dim)
        if len(self.seg_a) != len(self.seg_b):
            raise ValueError(f"{len(self.seg_a)} segment starts but {len(self.seg_b)} segment ends")
        if len(self.seg_a) == 0:
            raise ValueError("no segments to measure the distance to")
        self.chunk_elements = chunk_elements
        self.tree = None
        if len(self.seg_a) > _BRUTE_FORCE_SEGMENTS:
            self.tree = cKDTree(0.5 * (self.seg_a + self.seg_b))
            self.half_length_max = 0.5 * np.sqrt(((self.seg_b - self.seg_a) ** 2).sum(axis=1)).max()

    def distances(self, points) -> np.ndarray:
        """Distance from each point (n, d) to the nearest point of the segments, shape (n,)."""
        points = as_points(points, "points", self.seg_a.shape[1])
        if len(points) == 0:
            return np.empty(0)
        if self.tree is None:
            return _segment_distances_all_pairs(points, self.seg_a, self.seg_b, self.chunk_elements)
        best = np.empty(len(points))
        pending = np.arange(len(points))
        k = _CANDIDATES
        while len(pending) and k < min(len(self.seg_a), _MAX_CANDIDATES + 1):
            midpoint_distance, candidates = self.tree.query(points[pending], k=k)
            found = _segment_distances_candidates(points[pending], self.seg_a, self.seg_b, candidates)
            resolved = found <= midpoint_distance[:, -1] - self.half_length_max
            best[pending[resolved]] = found[resolved]
            pending = pending[~resolved]
            k *= 4
        if len(pending):
            best[pending] = _segment_distances_all_pairs(points[pending], self.seg_a, self.seg_b,
                                                         self.chunk_elements)
        return best


def _graph_segments(graph_points: np.ndarray, graph_edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The segments of a graph: one per edge, plus a zero-length one per isolated node."""
    n = len(graph_points)
    if len(graph_edges) and (graph_edges.min() < 0 or graph_edges.max() >= n):
        raise ValueError(f"graph edge index out of range for {n} nodes")
    isolated = np.setdiff1d(np.arange(n), graph_edges.ravel())
    starts = np.concatenate([graph_edges[:, 0], isolated])
    ends = np.concatenate([graph_edges[:, 1], isolated])
    return graph_points[starts], graph_points[ends]


def point_to_graph(points, graph_points, graph_edges) -> np.ndarray:
    """Distance from each point to the nearest point of a graph drawn with straight edges.

    Parameters
    ----------
    points : array_like, shape (n, d)
    graph_points : array_like, shape (k, d)
    graph_edges : array_like of int, shape (m, 2)
        Node index pairs; nodes without edges count as single points.

    Returns
    -------
    numpy.ndarray, shape (n,)
    """
    return graph_index(graph_points, graph_edges).distances(points)


def graph_index(graph_points, graph_edges, dim: int | None = None) -> SegmentIndex:
    """The :class:`SegmentIndex` of a graph drawn with straight edges (see :func:`point_to_graph`)."""
    graph_points = as_points(graph_points, "graph points", dim)
    if len(graph_points) == 0:
        raise ValueError("the graph has no nodes")
    graph_edges = np.asarray(graph_edges, dtype=np.int64).reshape(-1, 2)
    return SegmentIndex(*_graph_segments(graph_points, graph_edges), dim)


def distance_statistics(distances) -> dict:
    """``{"mean", "std", "median", "max"}`` of a set of distances (sample std, MATLAB's)."""
    distances = np.asarray(distances, dtype=float).ravel()
    if len(distances) == 0:
        raise ValueError("no distances to summarise")
    return {
        "mean": float(distances.mean()),
        "std": float(distances.std(ddof=1)) if len(distances) > 1 else 0.0,
        "median": float(np.median(distances)),
        "max": float(distances.max()),
    }


def error_2d(deformed_points3d, P, skeleton2d_points, skeleton2d_edges) -> dict:
    """2D error (pixels): projected result nodes to the 2D skeleton graph.

    Parameters
    ----------
    deformed_points3d : array_like, shape (n, 3)
        Result nodes, LPS mm.
    P : array_like, shape (3, 4)
        Projection matrix (eq. 1).
    skeleton2d_points : array_like, shape (k, 2)
        2D skeleton nodes ``(u, v)``, pixels.
    skeleton2d_edges : array_like of int, shape (m, 2)

    Returns
    -------
    dict
        ``{"mean", "std", "median", "max"}`` in pixels.
    """
    P = validate_projection_matrix(P)
    projected = project(P, as_points(deformed_points3d, "deformed points", 3))
    skeleton = as_points(skeleton2d_points, "2D skeleton points", 2)
    return distance_statistics(point_to_graph(projected, skeleton, skeleton2d_edges))


def _graph_of(curve, name: str) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(curve, Centerline):
        return curve.points, curve.edges
    try:
        points, edges = curve
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a Centerline or a (points, edges) pair") from None
    return as_points(points, f"{name} points", 3), np.asarray(edges, dtype=np.int64).reshape(-1, 2)


def error_3d(deformed, gt) -> dict:
    """3D error (mm) between a result and the ground-truth centreline, both ways.

    Parameters
    ----------
    deformed, gt : Centerline or tuple (points (n, 3), edges (m, 2))

    Returns
    -------
    dict
        ``forward`` (result nodes to the ground-truth graph, the paper's measure),
        ``reverse`` (ground-truth nodes to the result graph) and ``symmetric`` (both pooled),
        each ``{"mean", "std", "median", "max"}`` in mm.
    """
    result_points, result_edges = _graph_of(deformed, "deformed centreline")
    gt_points, gt_edges = _graph_of(gt, "ground-truth centreline")
    forward = point_to_graph(result_points, gt_points, gt_edges)
    reverse = point_to_graph(gt_points, result_points, result_edges)
    return {
        "forward": distance_statistics(forward),
        "reverse": distance_statistics(reverse),
        "symmetric": distance_statistics(np.concatenate([forward, reverse])),
    }


def restrict_to_labels(centerline: Centerline, labels: Iterable[str]) -> Centerline:
    """The subgraph of the nodes whose anatomy label is in ``labels`` (node order kept).

    Raises
    ------
    ValueError
        On an unknown label, or when no node carries any of the labels.
    """
    labels = set(labels)
    unknown = labels - set(ANATOMY_LABELS)
    if unknown:
        raise ValueError(f"unknown anatomy labels: {sorted(unknown)}")
    keep = np.array([label in labels for label in centerline.labels], dtype=bool)
    if not keep.any():
        raise ValueError(f"no centreline node carries any of the labels {sorted(labels)}")
    new_index = np.full(len(centerline), -1, dtype=np.int64)
    new_index[keep] = np.arange(int(keep.sum()))
    edges = new_index[centerline.edges]
    edges = edges[(edges >= 0).all(axis=1)]
    kept_labels = [label for label, k in zip(centerline.labels, keep) if k]
    return Centerline(centerline.points[keep], edges, kept_labels)


def common_labels(first: Centerline, second: Centerline) -> list[str]:
    """The anatomy labels that both centrelines carry, in :data:`ANATOMY_LABELS` order."""
    shared = set(first.labels) & set(second.labels)
    return [label for label in ANATOMY_LABELS if label in shared]


def evaluate(deformed: Centerline, gt: Centerline | None, P, skeleton2d_points, skeleton2d_edges,
             *, labels: Iterable[str] | None = None) -> dict:
    """All metrics of the paper for one result.

    Parameters
    ----------
    deformed : Centerline
        The registered (deformed) 3D centreline.
    gt : Centerline or None
        The intra-operative ground-truth 3D centreline, when known (simulation, phantom).
    P : array_like, shape (3, 4)
        Projection matrix of the frame.
    skeleton2d_points, skeleton2d_edges : array_like
        The 2D skeleton graph of the frame (pixels).
    labels : iterable of str, optional
        Compare only these vessels. Default: the labels both ``deformed`` and ``gt`` carry
        (all of ``deformed``'s when there is no ground truth).

    Returns
    -------
    dict
        ``2d_px`` and ``2d_reverse_px`` (pixels), ``3d_mm``, ``3d_reverse_mm`` and
        ``3d_symmetric_mm`` (mm; ``None`` without ground truth), each
        ``{"mean", "std", "median", "max"}``, and ``labels``, the labels compared.
    """
    P = validate_projection_matrix(P)
    skeleton = as_points(skeleton2d_points, "2D skeleton points", 2)
    skeleton_edges = np.asarray(skeleton2d_edges, dtype=np.int64).reshape(-1, 2)
    if labels is None:
        labels = common_labels(deformed, gt) if gt is not None else common_labels(deformed, deformed)
    unknown = set(labels) - set(ANATOMY_LABELS)
    if unknown:
        raise ValueError(f"unknown anatomy labels: {sorted(unknown)}")
    labels = [label for label in ANATOMY_LABELS if label in set(labels)]
    if not labels:
        raise ValueError("nothing to compare: the result and the ground truth share no anatomy label")
    result = restrict_to_labels(deformed, labels)
    projected = project(P, result.points)
    metrics = {
        "2d_px": distance_statistics(point_to_graph(projected, skeleton, skeleton_edges)),
        "2d_reverse_px": distance_statistics(point_to_graph(skeleton, projected, result.edges)),
        "3d_mm": None,
        "3d_reverse_mm": None,
        "3d_symmetric_mm": None,
        "labels": labels,
    }
    if gt is not None:
        errors = error_3d(result, restrict_to_labels(gt, labels))
        metrics.update({"3d_mm": errors["forward"], "3d_reverse_mm": errors["reverse"],
                        "3d_symmetric_mm": errors["symmetric"]})
    return metrics


# --------------------------------------------------------------------------- depth (issue 10)

#: The five vessels every case holds; the depth analysis compares these ("other" branches
#: have no counterpart to compare in general).
MAIN_VESSELS = BRANCH_LABELS
#: Below this mean true along-ray displacement (mm) a vessel has no out-of-plane motion worth
#: a recovered fraction (it would divide by almost nothing).
MIN_OUT_OF_PLANE_MM = 0.5


def closest_points_on_graph(points, graph_points, graph_edges) -> tuple[np.ndarray, np.ndarray]:
    """Distance from each point to a graph drawn with straight edges, and the nearest graph point.

    Parameters
    ----------
    points : array_like, shape (n, d)
    graph_points : array_like, shape (k, d)
    graph_edges : array_like of int, shape (m, 2)

    Returns
    -------
    distances : numpy.ndarray, shape (n,)
        The same numbers as :func:`point_to_graph`.
    nearest : numpy.ndarray, shape (n, d)
        The nearest point of the graph (on an edge or an isolated node).
    """
    points = as_points(points, "points")
    graph_points = as_points(graph_points, "graph points", points.shape[1])
    if len(graph_points) == 0:
        raise ValueError("the graph has no nodes")
    seg_a, seg_b = _graph_segments(graph_points, np.asarray(graph_edges, dtype=np.int64).reshape(-1, 2))
    return _nearest_on_segments(points, seg_a, seg_b, 2_000_000)


def depth_floor_points(intraop_points, preop_points, P) -> np.ndarray:
    """The depth oracle: each true intra-operative point on its own ray, at its pre-operative depth.

    The ray runs from the source of ``P`` (:func:`projection.source_position`) through the
    intra-operative point; the oracle point lies on it at the distance from the source of
    the corresponding pre-operative point. It projects exactly where the truth does (a
    perfect 2D fit) and keeps the pre-operative depth: what a single view cannot tell.

    Parameters
    ----------
    intraop_points, preop_points : array_like, shape (n, 3)
        Corresponding points (row ``i`` of one is row ``i`` of the other), LPS mm.
    P : array_like, shape (3, 4)
        The true projection of the frame.
    """
    intra = as_points(intraop_points, "intra-operative points", 3)
    pre = as_points(preop_points, "pre-operative points", 3)
    if len(intra) != len(pre):
        raise ValueError(f"{len(intra)} intra-operative but {len(pre)} pre-operative points: no correspondence")
    source = source_position(validate_projection_matrix(P))
    rays = intra - source
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return source + unit * np.linalg.norm(pre - source, axis=1)[:, None]


def _main_labels(*centerlines: Centerline, labels=None) -> list[str]:
    wanted = set(MAIN_VESSELS if labels is None else labels)
    unknown = wanted - set(ANATOMY_LABELS)
    if unknown:
        raise ValueError(f"unknown anatomy labels: {sorted(unknown)}")
    for centerline in centerlines:
        wanted &= set(centerline.labels)
    chosen = [label for label in ANATOMY_LABELS if label in wanted]
    if not chosen:
        raise ValueError("nothing to compare: no vessel label is shared")
    return chosen


def depth_floor(gt_preop: Centerline, gt_intraop: Centerline, P, labels=None) -> dict:
    """The single-view depth floor of a case (mm): the error of :func:`depth_floor_points`.

    Scored as the methods are: every oracle point to the nearest segment of the true
    intra-operative centreline (restricted to ``labels``; default the main vessels).

    Parameters
    ----------
    gt_preop, gt_intraop : Centerline
        The ground truth's corresponding dense centrelines (same nodes, same order).
    P : array_like, shape (3, 4)
        The true projection of the view (for two views: the main one, whose floor it is).
    labels : iterable of str, optional

    Returns
    -------
    dict
        ``{"mean", "std", "median", "max"}`` over all compared nodes, ``per_vessel``
        (label -> the same statistics) and ``labels``.
    """
    if len(gt_preop) != len(gt_intraop) or list(gt_preop.labels) != list(gt_intraop.labels):
        raise ValueError("the pre- and intra-operative ground truths do not correspond node for node")
    labels = _main_labels(gt_intraop, labels=labels)
    truth = restrict_to_labels(gt_intraop, labels)
    keep = np.array([label in labels for label in gt_intraop.labels])
    oracle = depth_floor_points(gt_intraop.points[keep], gt_preop.points[keep], P)
    distances = point_to_graph(oracle, truth.points, truth.edges)
    node_labels = np.array(truth.labels)
    per_vessel = {label: distance_statistics(distances[node_labels == label]) for label in labels}
    return {**distance_statistics(distances), "per_vessel": per_vessel, "labels": labels}


def ray_components(points, gt_points, gt_edges, P) -> dict:
    """Split each point's 3D error into its along-ray and in-plane parts.

    The error of point ``p`` is ``p - q`` with ``q`` the nearest point of the true graph;
    its along-ray part is its component along the unit ray from the source of ``P``
    through ``q`` (positive: farther from the source than the truth), the in-plane part
    the rest, so that ``distance**2 == along**2 + in_plane**2`` for every point.

    Returns
    -------
    dict
        ``distance``, ``in_plane``, ``along`` (signed), arrays of shape (n,), and
        ``nearest`` (n, 3).
    """
    points = as_points(points, "points", 3)
    distance, nearest = closest_points_on_graph(points, gt_points, gt_edges)
    source = source_position(validate_projection_matrix(P))
    rays = nearest - source
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    error = points - nearest
    along = np.einsum("nd,nd->n", error, unit)
    in_plane = np.linalg.norm(error - along[:, None] * unit, axis=1)
    return {"distance": distance, "in_plane": in_plane, "along": along, "nearest": nearest}


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _recovered(along_error: np.ndarray, true_along: np.ndarray):
    """1 - |along-ray error| / |true along-ray displacement| (None without such a displacement)."""
    if np.mean(true_along) < MIN_OUT_OF_PLANE_MM:
        return None
    return float(1.0 - np.abs(along_error).sum() / true_along.sum())


def depth_analysis(deformed: Centerline, preop: Centerline, gt_preop: Centerline, gt_intraop: Centerline, P,
                   labels=None) -> dict:
    """In-plane / along-ray split of a result's 3D error, the depth floor and the recovered depth.

    Parameters
    ----------
    deformed : Centerline
        The result (its nodes are scored, as in :func:`evaluate`).
    preop : Centerline
        The pre-operative centreline the result was deformed from (node ``i`` of one is node
        ``i`` of the other), to find each node's true displacement.
    gt_preop, gt_intraop : Centerline
        The ground truth's corresponding dense centrelines.
    P : array_like, shape (3, 4)
        The TRUE projection of the (main) view: rays and the floor are geometric facts of
        the frame, not of the pose a method was given.
    labels : iterable of str, optional
        Default: the main vessels that the result and the truth both hold.

    Returns
    -------
    dict
        ``3d_mm``, ``in_plane_mm``, ``along_ray_mm`` (of ``|along|``), ``true_along_ray_mm``
        (each ``{"mean", "std", "median", "max"}``), ``rms_mm`` (``3d``, ``in_plane``,
        ``along_ray``: ``3d**2 == in_plane**2 + along_ray**2``), ``depth_floor_mm`` (the
        statistics of :func:`depth_floor`), ``out_of_plane_recovered`` (``1 - sum |along
        error| / sum |true along displacement|``; None without out-of-plane motion) and
        ``per_vessel``: label -> means (``nodes``, ``3d_mm``, ``in_plane_mm``,
        ``along_ray_mm``, ``true_along_ray_mm``, ``depth_floor_mm``,
        ``out_of_plane_recovered``).

    Notes
    -----
    A node's true along-ray displacement is that of the nearest dense pre-operative
    ground-truth node ``n``: ``|(gt_intraop[n] - gt_preop[n]) . r|`` with ``r`` the unit
    ray through ``gt_intraop[n]``. The rigid (undeformed) result recovers about 0, a
    result at the true depth 1, one that moved the wrong way less than 0.
    """
    if len(deformed) != len(preop):
        raise ValueError(f"the result has {len(deformed)} nodes but its pre-operative centreline {len(preop)}")
    labels = _main_labels(deformed, gt_intraop, labels=labels)
    floor = depth_floor(gt_preop, gt_intraop, P, labels)
    result, result_pre = restrict_to_labels(deformed, labels), restrict_to_labels(preop, labels)
    truth = restrict_to_labels(gt_intraop, labels)
    parts = ray_components(result.points, truth.points, truth.edges, P)
    truth_pre = restrict_to_labels(gt_preop, labels)
    _, nearest_node = cKDTree(truth_pre.points).query(result_pre.points)
    displacement = truth.points[nearest_node] - truth_pre.points[nearest_node]
    rays = truth.points[nearest_node] - source_position(P)
    true_along = np.abs(np.einsum("nd,nd->n", displacement, rays / np.linalg.norm(rays, axis=1, keepdims=True)))
    along = np.abs(parts["along"])
    node_labels = np.array(result.labels)
    per_vessel = {}
    for label in labels:
        sel = node_labels == label
        if not sel.any():
            continue
        per_vessel[label] = {"nodes": int(sel.sum()), "3d_mm": float(parts["distance"][sel].mean()),
                             "in_plane_mm": float(parts["in_plane"][sel].mean()), "along_ray_mm": float(along[sel].mean()),
                             "true_along_ray_mm": float(true_along[sel].mean()),
                             "depth_floor_mm": floor["per_vessel"][label]["mean"],
                             "out_of_plane_recovered": _recovered(parts["along"][sel], true_along[sel])}
    return {
        "labels": labels,
        "3d_mm": distance_statistics(parts["distance"]),
        "in_plane_mm": distance_statistics(parts["in_plane"]),
        "along_ray_mm": distance_statistics(along),
        "true_along_ray_mm": distance_statistics(true_along),
        "rms_mm": {"3d": _rms(parts["distance"]), "in_plane": _rms(parts["in_plane"]), "along_ray": _rms(along)},
        "depth_floor_mm": {k: v for k, v in floor.items() if k not in ("labels",)},
        "out_of_plane_recovered": _recovered(parts["along"], true_along),
        "per_vessel": per_vessel,
    }

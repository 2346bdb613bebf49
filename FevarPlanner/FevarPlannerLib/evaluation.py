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
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.spatial import cKDTree

from .centerline import ANATOMY_LABELS, Centerline, as_points
from .projection import project, validate_projection_matrix

__all__ = [
    "point_to_segments",
    "point_to_graph",
    "distance_statistics",
    "error_2d",
    "error_3d",
    "restrict_to_labels",
    "common_labels",
    "evaluate",
]

#: Segments scanned per KD-tree query before the exactness check (see point_to_segments).
_CANDIDATES = 8
#: Below this many segments the plain all-pairs computation is as fast as the tree.
_BRUTE_FORCE_SEGMENTS = 64


def _segment_distances_all_pairs(points: np.ndarray, seg_a: np.ndarray, seg_b: np.ndarray,
                                 chunk_elements: int) -> np.ndarray:
    """Exact distance of every point to the nearest of all segments, in memory-bounded chunks."""
    ab = seg_b - seg_a
    length2 = np.einsum("md,md->m", ab, ab)
    safe_length2 = np.where(length2 > 0, length2, 1.0)
    chunk = max(1, chunk_elements // max(1, seg_a.size))
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk]
        ap = p[:, None, :] - seg_a[None, :, :]
        t = np.clip(np.einsum("cmd,md->cm", ap, ab) / safe_length2, 0.0, 1.0)
        t[:, length2 == 0] = 0.0
        offset = ap - t[..., None] * ab[None]
        out[start:start + chunk] = np.sqrt(np.einsum("cmd,cmd->cm", offset, offset).min(axis=1))
    return out


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
    A KD-tree on the segment midpoints proposes the ``8`` nearest segments of each point.
    The answer is exact whenever the best of them is no farther than ``d_k - h_max``
    (``d_k`` the distance to the 8th nearest midpoint, ``h_max`` the largest half-length):
    every other segment lies at least that far. The points that fail the check are
    computed against all segments.
    """
    points = as_points(points, "points")
    seg_a = as_points(seg_a, "segment starts", points.shape[1])
    seg_b = as_points(seg_b, "segment ends", points.shape[1])
    if len(seg_a) != len(seg_b):
        raise ValueError(f"{len(seg_a)} segment starts but {len(seg_b)} segment ends")
    if len(seg_a) == 0:
        raise ValueError("no segments to measure the distance to")
    if len(points) == 0:
        return np.empty(0)
    if len(seg_a) <= _BRUTE_FORCE_SEGMENTS:
        return _segment_distances_all_pairs(points, seg_a, seg_b, chunk_elements)
    midpoints = 0.5 * (seg_a + seg_b)
    half_length_max = 0.5 * np.sqrt(((seg_b - seg_a) ** 2).sum(axis=1)).max()
    midpoint_distance, candidates = cKDTree(midpoints).query(points, k=_CANDIDATES)
    best = _segment_distances_candidates(points, seg_a, seg_b, candidates)
    unresolved = best > midpoint_distance[:, -1] - half_length_max
    if np.any(unresolved):
        best[unresolved] = _segment_distances_all_pairs(points[unresolved], seg_a, seg_b, chunk_elements)
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
    graph_points = as_points(graph_points, "graph points")
    if len(graph_points) == 0:
        raise ValueError("the graph has no nodes")
    graph_edges = np.asarray(graph_edges, dtype=np.int64).reshape(-1, 2)
    seg_a, seg_b = _graph_segments(graph_points, graph_edges)
    return point_to_segments(points, seg_a, seg_b)


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

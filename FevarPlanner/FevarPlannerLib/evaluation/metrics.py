"""The paper's 2D and 3D errors (Sec. III, Tables I-II) and their statistics, restricted to
the vessels present in both centrelines (package docstring).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..centerline import ANATOMY_LABELS, Centerline, as_points
from ..projection import project, validate_projection_matrix
from .distances import point_to_graph

__all__ = [
    "distance_statistics",
    "error_2d",
    "error_3d",
    "restrict_to_labels",
    "common_labels",
    "evaluate",
]


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

"""Depth (issue 10): the single-view depth floor, the along-ray / in-plane split of each
result node's error, per vessel, and the fraction of the true along-ray motion recovered
(package docstring).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..centerline import ANATOMY_LABELS, Centerline, as_points
from ..conventions import BRANCH_LABELS
from ..projection import source_position, validate_projection_matrix
from .distances import _graph_segments, _nearest_on_segments, point_to_graph
from .metrics import distance_statistics, restrict_to_labels

__all__ = [
    "MAIN_VESSELS",
    "MIN_OUT_OF_PLANE_MM",
    "closest_points_on_graph",
    "DEPTH_MEASURES",
    "depth_floor_points",
    "depth_floor",
    "ray_components",
    "depth_analysis",
]


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


#: How :func:`depth_floor_points` measures depth: distance from the source ("range", the
#: benchmarks' floor) or along the principal axis ("axial", the pinhole's own depth).
DEPTH_MEASURES = ("range", "axial")


def depth_floor_points(intraop_points, preop_points, P, depth: str = "range") -> np.ndarray:
    """The depth oracle: each true intra-operative point on its own ray, at its pre-operative depth.

    The ray runs from the source of ``P`` (:func:`projection.source_position`) through the
    intra-operative point; the oracle point lies on it at the pre-operative point's depth.
    It projects exactly where the truth does (a perfect 2D fit) and keeps the pre-operative
    depth: what a single view cannot tell.

    Parameters
    ----------
    intraop_points, preop_points : array_like, shape (n, 3)
        Corresponding points (row ``i`` of one is row ``i`` of the other), LPS mm.
    P : array_like, shape (3, 4)
        The true projection of the frame.
    depth : {"range", "axial"}
        "range" (the default, the benchmarks' floor): the distance from the source.
        "axial": the distance along the principal axis (the plane parallel to the detector),
        which a move parallel to the detector keeps. The two differ by about ``d x / D`` for
        a move ``d`` parallel to the detector at ``x`` mm off the axis and ``D`` from the
        source: a few tenths of a mm at a clinical SOD, up to mm under a short bench pinhole.
    """
    intra = as_points(intraop_points, "intra-operative points", 3)
    pre = as_points(preop_points, "pre-operative points", 3)
    if len(intra) != len(pre):
        raise ValueError(f"{len(intra)} intra-operative but {len(pre)} pre-operative points: no correspondence")
    if depth not in DEPTH_MEASURES:
        raise ValueError(f"unknown depth measure {depth!r}; choose one of {', '.join(DEPTH_MEASURES)}")
    P = validate_projection_matrix(P)
    source = source_position(P)
    rays = intra - source
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    if depth == "range":
        return source + unit * np.linalg.norm(pre - source, axis=1)[:, None]
    axis = P[2, :3] / np.linalg.norm(P[2, :3])
    axis = axis if np.mean(rays @ axis) > 0 else -axis        # P is defined up to sign
    return source + unit * ((pre - source) @ axis / (unit @ axis))[:, None]


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


def depth_floor(gt_preop: Centerline, gt_intraop: Centerline, P, labels=None, depth: str = "range") -> dict:
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
    depth : {"range", "axial"}
        How the oracle keeps the pre-operative depth (:func:`depth_floor_points`).

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
    oracle = depth_floor_points(gt_intraop.points[keep], gt_preop.points[keep], P, depth)
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

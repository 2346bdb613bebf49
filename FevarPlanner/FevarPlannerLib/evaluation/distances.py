"""Distances from points to curves made of straight segments, as MATLAB's ``distance2curve``
(package docstring): :func:`point_to_segments`, :func:`point_to_graph`, and
:class:`SegmentIndex` (a graph's segments indexed once, queried many times).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..centerline import as_points

__all__ = [
    "point_to_segments",
    "SegmentIndex",
    "point_to_graph",
    "graph_index",
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

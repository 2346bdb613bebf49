"""The centreline graph that flows from the skeleton stage to planning and export."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .conventions import ANATOMY_LABELS

__all__ = ["ANATOMY_LABELS", "Centerline", "as_points"]


def as_points(array, name: str, dim: int | None = None, min_count: int = 0) -> np.ndarray:
    """``array`` as a finite float (n, dim) array, or a ValueError naming ``name`` and the problem."""
    array = np.asarray(array, dtype=float)
    if array.ndim != 2 or (dim is not None and array.shape[1] != dim):
        want = f"(n, {dim})" if dim is not None else "(n, d)"
        raise ValueError(f"{name}: expected an array of shape {want}, got {array.shape}")
    if len(array) < min_count:
        raise ValueError(f"{name}: needs at least {min_count} points, got {len(array)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return array


@dataclass
class Centerline:
    """Nodes (LPS mm), undirected edges between node indices and one anatomy label per node.

    Attributes
    ----------
    points : numpy.ndarray, shape (n, 3)
    edges : numpy.ndarray of int, shape (m, 2)
    labels : list of str, length n, each one of :data:`ANATOMY_LABELS`
    """

    points: np.ndarray
    edges: np.ndarray
    labels: list = field(default_factory=list)

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=float).reshape(-1, 3)
        self.edges = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)
        if not self.labels:
            self.labels = ["other"] * len(self.points)
        self.labels = list(self.labels)
        if len(self.labels) != len(self.points):
            raise ValueError(f"{len(self.labels)} labels for {len(self.points)} points")
        unknown = set(self.labels) - set(ANATOMY_LABELS)
        if unknown:
            raise ValueError(f"unknown anatomy labels: {sorted(unknown)}")
        if len(self.edges) and (self.edges.min() < 0 or self.edges.max() >= len(self.points)):
            raise ValueError("edge index out of range")

    def __len__(self) -> int:
        return len(self.points)

    def with_points(self, points: np.ndarray) -> "Centerline":
        """The same graph and labels at new node positions."""
        return Centerline(points, self.edges.copy(), list(self.labels))

    def to_dict(self) -> dict:
        return {"points": self.points.tolist(), "edges": self.edges.tolist(), "labels": list(self.labels)}

    @classmethod
    def from_dict(cls, data: dict) -> "Centerline":
        return cls(np.asarray(data["points"], dtype=float), np.asarray(data.get("edges", []), dtype=np.int64),
                   list(data.get("labels", [])))

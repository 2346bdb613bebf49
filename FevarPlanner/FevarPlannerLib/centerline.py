"""The centreline graph that flows from the skeleton stage to planning and export."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ANATOMY_LABELS", "Centerline"]

#: Anatomical labels, as result.json and the exports name them (DESIGN.md section 4).
ANATOMY_LABELS = ("aorta", "renal_left", "renal_right", "iliac_left", "iliac_right", "other")


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

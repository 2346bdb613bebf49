"""JSON inputs with points: the phantom's ground-truth centreline (``gt.json``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..files import InputError, display_path, read_json_file


def _json_points(value, path: Path, key: str) -> np.ndarray:
    """``value`` as an (n, 3) array of finite numbers, or :class:`InputError` naming ``key``."""
    if not isinstance(value, list) or not value:
        raise InputError(f"{display_path(path)}: key '{key}' must be a non-empty list of [x, y, z] points")
    for i, point in enumerate(value):
        if (not isinstance(point, list) or len(point) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in point)):
            raise InputError(f"{display_path(path)}: key '{key}[{i}]' must be 3 numbers, got {str(point)[:40]}")
    points = np.array(value, dtype=float)
    if not np.all(np.isfinite(points)):
        raise InputError(f"{display_path(path)}: key '{key}' holds NaN or infinite values")
    return points


def read_ground_truth(path, key: str = "intraop_centerline"):
    """The ground-truth centreline ``key`` of a phantom's ``gt.json``, validated."""
    from ..centerline import Centerline

    path = Path(path)
    data = read_json_file(path, "ground-truth JSON")
    if not isinstance(data, dict) or not isinstance(data.get(key), dict):
        raise InputError(f"{display_path(path)}: key '{key}' missing or not an object")
    entry = data[key]
    points = _json_points(entry.get("points"), path, f"{key}.points")
    edges = entry.get("edges", [])
    if (not isinstance(edges, list) or not all(isinstance(e, list) and len(e) == 2 and
                                               all(isinstance(i, int) and 0 <= i < len(points) for i in e)
                                               for e in edges)):
        raise InputError(f"{display_path(path)}: key '{key}.edges' must be pairs of node indices below {len(points)}")
    labels = entry.get("labels", [])
    if not isinstance(labels, list) or not all(isinstance(v, str) for v in labels) or (
            labels and len(labels) != len(points)):
        raise InputError(f"{display_path(path)}: key '{key}.labels' must be one string per point")
    return Centerline(points, np.array(edges, dtype=np.int64).reshape(-1, 2), list(labels))

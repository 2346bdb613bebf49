"""``result.json`` (:data:`RESULT_VERSION` 1, docs/DESIGN.md section 4): built, validated and
read back. :func:`validate_result` is its schema, written out by hand; a file is only
replaced by a complete, validated one.
"""

from __future__ import annotations

import json
import math
from numbers import Real
from pathlib import Path

import numpy as np

from ..centerline import Centerline
from ..conventions import ANATOMY_LABELS
from ..files import InputError, check_readable, write_text_atomic
from ..projection import validate_projection_matrix


RESULT_VERSION = 1


CORE_KEYS = ("version", "method", "preop_centerline", "deformed_centerline", "path", "timings_s")
REQUIRED_TIMINGS = ("total", "registration")


def _jsonable(value):
    """``value`` with numpy arrays / scalars, tuples and paths turned into JSON types."""
    if isinstance(value, dict):
        return {str(key): _jsonable(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(item) for item in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def build_result_dict(method: str, preop: Centerline, deformed: Centerline, path, timings: dict,
                      **extra) -> dict:
    """Assemble (and validate) the result.json document of docs/DESIGN.md section 4.

    Parameters
    ----------
    method : str
        ``"proposed"``, ``"icp-tps"``, ``"rigid"``, ...
    preop, deformed : Centerline
        The pre-operative centreline and the deformed one (same nodes, same order).
    path : CatheterPath or dict
        The planned path (anything with ``to_dict()``, or its dict).
    timings : dict
        Seconds per stage; ``total`` and ``registration`` are required.
    **extra
        Further JSON-serialisable entries, e.g. ``projection_matrix``, ``errors``, ``inputs``.

    Returns
    -------
    dict
        Plain JSON types only.
    """
    clash = sorted(set(extra) & set(CORE_KEYS))
    if clash:
        raise ValueError(f"extra result entries may not replace core keys: {clash}")
    path_dict = path.to_dict() if hasattr(path, "to_dict") else dict(path)
    data = _jsonable({
        "version": RESULT_VERSION,
        "method": method,
        "preop_centerline": preop.to_dict(),
        "deformed_centerline": deformed.to_dict(),
        "path": path_dict,
        "timings_s": dict(timings),
        **extra,
    })
    validate_result(data)
    return data


def _is_number(value) -> bool:
    return isinstance(value, (Real, np.number)) and not isinstance(value, (bool, np.bool_))


def _first_non_finite(value, where: str):
    """Location (e.g. ``errors.per_node[3]``) of the first NaN / infinity in ``value``, or None."""
    if isinstance(value, dict):
        items = ((f"{where}.{key}", item) for key, item in value.items())
    elif isinstance(value, (list, tuple)):
        items = ((f"{where}[{i}]", item) for i, item in enumerate(value))
    elif isinstance(value, np.ndarray) and value.dtype.kind in "fc":
        bad = np.argwhere(~np.isfinite(value))
        return f"{where}[{', '.join(map(str, bad[0]))}]" if len(bad) else None
    else:
        return where if _is_number(value) and not math.isfinite(value) else None
    for name, item in items:
        found = _first_non_finite(item, name)
        if found:
            return found
    return None


def _points_array(value, where: str, min_count: int) -> np.ndarray:
    try:
        points = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where} is not a numeric (n, 3) array") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{where} must have shape (n, 3), got {points.shape}")
    if len(points) < min_count:
        raise ValueError(f"{where} needs at least {min_count} points, got {len(points)}")
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if len(bad):
        raise ValueError(f"{where}[{bad[0]}] is not finite: {points[bad[0]].tolist()}")
    return points


def _edges_array(value, count: int, where: str) -> np.ndarray:
    edges = np.asarray(value)
    if edges.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if edges.ndim != 2 or edges.shape[1] != 2 or edges.dtype.kind not in "iu":
        raise ValueError(f"{where} must be an (m, 2) array of integer node indices")
    if edges.min() < 0 or edges.max() >= count:
        raise ValueError(f"{where} refers to nodes outside 0..{count - 1}")
    return edges


def _labels_list(value, count: int, where: str) -> list:
    if not isinstance(value, (list, tuple)) or len(value) != count:
        raise ValueError(f"{where} must be a list of {count} labels")
    for i, label in enumerate(value):
        if label not in ANATOMY_LABELS:
            raise ValueError(f"{where}[{i}] = {label!r} is not one of {list(ANATOMY_LABELS)}")
    return list(value)


def _check_centerline_keys(data, where: str) -> None:
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be an object with points, edges and labels")
    missing = [key for key in ("points", "edges", "labels") if key not in data]
    if missing:
        raise ValueError(f"{where} lacks {missing}")


def _check_centerlines(preop: dict, deformed: dict) -> None:
    """Both centrelines well formed, with the same nodes in the same order and the same edges."""
    _check_centerline_keys(preop, "preop_centerline")
    _check_centerline_keys(deformed, "deformed_centerline")
    p_points = _points_array(preop["points"], "preop_centerline.points", 1)
    d_points = _points_array(deformed["points"], "deformed_centerline.points", 1)
    if len(p_points) != len(d_points):
        raise ValueError(f"deformed_centerline has {len(d_points)} nodes, preop_centerline has {len(p_points)}:"
                         " they must list the same nodes in the same order")
    count = len(p_points)
    p_edges = _edges_array(preop["edges"], count, "preop_centerline.edges")
    d_edges = _edges_array(deformed["edges"], count, "deformed_centerline.edges")
    p_labels = _labels_list(preop["labels"], count, "preop_centerline.labels")
    d_labels = _labels_list(deformed["labels"], count, "deformed_centerline.labels")
    if p_labels != d_labels:
        first = next(i for i, (a, b) in enumerate(zip(p_labels, d_labels)) if a != b)
        raise ValueError(f"node {first} is {p_labels[first]!r} in preop_centerline but {d_labels[first]!r} in"
                         " deformed_centerline: the nodes must be in the same order")
    if p_edges.shape != d_edges.shape or not np.array_equal(p_edges, d_edges):
        raise ValueError("deformed_centerline.edges differ from preop_centerline.edges")


def _check_path(path) -> None:
    if not isinstance(path, dict):
        raise ValueError("path must be an object with points, from and to")
    missing = [key for key in ("points", "from", "to") if key not in path]
    if missing:
        raise ValueError(f"path lacks {missing}")
    _points_array(path["points"], "path.points", 2)
    for key in ("from", "to"):
        if path[key] not in ANATOMY_LABELS:
            raise ValueError(f"path.{key} = {path[key]!r} is not one of {list(ANATOMY_LABELS)}")
    if "length_mm" in path and not (_is_number(path["length_mm"]) and path["length_mm"] >= 0):
        raise ValueError(f"path.length_mm must be a non-negative number, got {path['length_mm']!r}")


def _check_timings(timings) -> None:
    if not isinstance(timings, dict):
        raise ValueError("timings_s must be an object of seconds per stage")
    missing = [key for key in REQUIRED_TIMINGS if key not in timings]
    if missing:
        raise ValueError(f"timings_s lacks {missing}")
    for key, value in timings.items():
        if not (_is_number(value) and value >= 0):
            raise ValueError(f"timings_s.{key} must be a non-negative number of seconds, got {value!r}")


def validate_result(data: dict) -> None:
    """Check a result.json document against the version-1 contract (docs/DESIGN.md section 4).

    Raises
    ------
    ValueError
        One line naming the first problem found: wrong version, missing key, bad shape,
        unknown label, NaN / infinity anywhere, pre-op and deformed centrelines that do not
        list the same nodes in the same order, a bad projection matrix.
    """
    if not isinstance(data, dict):
        raise ValueError(f"result must be a JSON object, got {type(data).__name__}")
    missing = [key for key in CORE_KEYS if key not in data]
    if missing:
        raise ValueError(f"result lacks {missing}")
    version = data["version"]
    if not (isinstance(version, int) and not isinstance(version, bool)) or version != RESULT_VERSION:
        raise ValueError(f"result version must be {RESULT_VERSION}, got {version!r}")
    if not isinstance(data["method"], str) or not data["method"]:
        raise ValueError(f"method must be a non-empty string, got {data['method']!r}")
    _check_centerlines(data["preop_centerline"], data["deformed_centerline"])
    _check_path(data["path"])
    _check_timings(data["timings_s"])
    if "projection_matrix" in data:
        validate_projection_matrix(data["projection_matrix"], name="projection_matrix")
    bad = _first_non_finite(data, "result")
    if bad:
        raise ValueError(f"{bad} is not finite (NaN or infinity)")


def write_result_json(path, data: dict) -> None:
    """Validate ``data`` and write it to ``path`` atomically.

    Nothing is written when validation or serialisation fails, so an existing file stays
    as it was.
    """
    path = Path(path)
    data = _jsonable(data)
    try:
        validate_result(data)
        text = json.dumps(data, indent=2, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not written: {exc}") from None
    write_text_atomic(path, text + "\n")


def read_result_json(path) -> dict:
    """Read and validate a result.json; :class:`files.InputError` names the file and problem."""
    path = Path(path)
    check_readable(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a readable JSON file ({exc})") from None
    try:
        validate_result(data)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    return data

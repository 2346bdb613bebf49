"""Exports of a planning result: result.json, centreline .vtp, Slicer markups, PNG pictures.

Everything is written in DICOM LPS millimetres and goes through a temporary file beside
the target and a rename (:func:`io.atomic_path`), so a failure never leaves a half-written
file, and an existing file is only replaced by a complete, validated one.

* ``result.json`` (:data:`RESULT_VERSION` 1) follows docs/DESIGN.md section 4;
  :func:`validate_result` is its schema, written out by hand.
* ``*.vtp``: the centreline graph as vtkPolyData, one line cell per edge, point data
  ``label`` (index into :data:`ANATOMY_LABELS`) and ``label_name``, and the coordinate
  system the way 3D Slicer's model storage writes and reads it: field data ``SPACE`` =
  ``"LPS"`` (a legacy ``.vtk`` says ``SPACE=LPS`` in its header line instead). Slicer
  removes ``SPACE`` when it loads a file and writes its own when it saves one, so that tag
  is never stale; the older ``coordinateSystem`` array is read only when ``SPACE`` is absent.
* ``*.mrk.json``: a Slicer markups curve (schema v1.0.3) with an explicit coordinate system.
* ``overlay.png``: the fluoroscopic frame with projected centrelines, pixel for pixel.
* a 3D picture of centrelines (and optionally the aorta surface), rendered offscreen.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass
from numbers import Real
from pathlib import Path

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import (vtkLogger, vtkOutputWindow, vtkPoints, vtkStringArray,
                                      vtkStringOutputWindow)
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkIOLegacy import vtkPolyDataReader
from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLPolyDataWriter

from .centerline import Centerline
from .conventions import ANATOMY_LABELS, PALETTE
from .files import InputError, atomic_path, check_readable, write_text_atomic
from .projection import depth, image_directions, project, validate_projection_matrix, view_label

__all__ = [
    "RESULT_VERSION",
    "ROLE_NAMES",
    "MARKUPS_SCHEMA",
    "build_result_dict",
    "validate_result",
    "write_result_json",
    "read_result_json",
    "centerline_to_polydata",
    "polydata_to_centerline",
    "coordinate_system_of",
    "write_centerline_vtp",
    "read_centerline_vtp",
    "write_path_markups",
    "read_path_markups",
    "OverlayLayer",
    "centerline_layer",
    "path_layer",
    "render_overlay",
    "view_name",
    "render_centerlines_3d",
    "tube_actor",
    "polydata_actor",
]

RESULT_VERSION = 1
MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
                  "Resources/Schema/markups-schema-v1.0.3.json#")
CORE_KEYS = ("version", "method", "preop_centerline", "deformed_centerline", "path", "timings_s")
REQUIRED_TIMINGS = ("total", "registration")
# Slicer's default control point orientation (identity in RAS) written in each system
IDENTITY_ORIENTATION = {"LPS": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                        "RAS": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}
LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])
#: Slicer's model files name their coordinate system with this field-data array (.vtp) or
#: ``SPACE=LPS`` / ``SPACE=RAS`` in the header line (legacy .vtk), after the NRRD key.
SPACE_TAG = "SPACE"
#: The tag this project wrote before it followed Slicer; read only when ``SPACE`` is absent.
LEGACY_SPACE_TAG = "coordinateSystem"
COORDINATE_SYSTEMS = ("LPS", "RAS")
#: What the display calls each role ("recovered", not "deformed": the result.json key
#: ``deformed_centerline`` stays, as the contract says).
ROLE_NAMES = {"preop": "pre-operative", "recovered": "recovered", "deformed": "recovered", "path": "catheter path",
              "skeleton2d": "2D skeleton", "truth": "intra-operative truth"}


# ----------------------------------------------------------------------------- result.json

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


# ----------------------------------------------------------------------------- .vtp

def centerline_to_polydata(centerline: Centerline, arrays: dict | None = None, *,
                           space: str | None = "LPS") -> vtkPolyData:
    """vtkPolyData of a centreline: points, one line per edge, label arrays, extra arrays.

    Parameters
    ----------
    centerline : Centerline
        Points in LPS mm.
    arrays : dict of str -> array_like, optional
        Extra point data, each of shape (n,) or (n, k) (e.g. a per-node error in mm).
    space : {"LPS", "RAS", None}
        The points are written in this system and the field data ``SPACE`` names it, as
        Slicer's model storage does. ``None``: RAS points and no tag, which is what a Slicer
        model node holds in memory (its scene is RAS; a tag there would go stale when Slicer
        saves the model in LPS).
    """
    if space not in COORDINATE_SYSTEMS + (None,):
        raise ValueError(f"space must be 'LPS', 'RAS' or None, got {space!r}")
    n = len(centerline)
    polydata = vtkPolyData()
    points = vtkPoints()
    xyz = centerline.points if space == "LPS" else centerline.points * LPS_TO_RAS
    points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(xyz, dtype=float), deep=True))
    polydata.SetPoints(points)
    lines = vtkCellArray()
    offsets = np.arange(0, 2 * len(centerline.edges) + 1, 2, dtype=np.int64)
    lines.SetData(numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(np.ascontiguousarray(centerline.edges.ravel()), deep=True))
    polydata.SetLines(lines)

    codes = np.array([ANATOMY_LABELS.index(label) for label in centerline.labels], dtype=np.int32)
    label_codes = numpy_support.numpy_to_vtk(codes, deep=True)
    label_codes.SetName("label")
    polydata.GetPointData().AddArray(label_codes)
    names = vtkStringArray()
    names.SetName("label_name")
    for label in centerline.labels:
        names.InsertNextValue(label)
    polydata.GetPointData().AddArray(names)
    for name, values in (arrays or {}).items():
        polydata.GetPointData().AddArray(_point_array(name, values, n))

    if space is not None:
        system = vtkStringArray()
        system.SetName(SPACE_TAG)
        system.InsertNextValue(space)
        polydata.GetFieldData().AddArray(system)
    return polydata


def _point_array(name: str, values, count: int):
    if name in ("label", "label_name"):
        raise ValueError(f"point array name {name!r} is reserved for the anatomy labels")
    values = np.asarray(values)
    if values.dtype.kind not in "iuf" or values.ndim not in (1, 2) or len(values) != count:
        raise ValueError(f"point array {name!r} must be numeric with {count} rows, got shape {values.shape}")
    array = numpy_support.numpy_to_vtk(np.ascontiguousarray(values), deep=True)
    array.SetName(name)
    return array


def _line_edges(polydata: vtkPolyData) -> np.ndarray:
    """Edges (consecutive point pairs) of every line / polyline cell."""
    lines = polydata.GetLines()
    if lines is None or lines.GetNumberOfCells() == 0:
        return np.zeros((0, 2), dtype=np.int64)
    offsets = numpy_support.vtk_to_numpy(lines.GetOffsetsArray()).astype(np.int64)
    connectivity = numpy_support.vtk_to_numpy(lines.GetConnectivityArray()).astype(np.int64)
    pairs = [np.column_stack([connectivity[a:b - 1], connectivity[a + 1:b]])
             for a, b in zip(offsets[:-1], offsets[1:]) if b - a >= 2]
    return np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)


def _point_labels(polydata: vtkPolyData, count: int) -> list:
    point_data = polydata.GetPointData()
    names = point_data.GetAbstractArray("label_name")
    if isinstance(names, vtkStringArray):
        return [names.GetValue(i) for i in range(names.GetNumberOfValues())]
    codes = point_data.GetArray("label")
    if codes is None:
        return ["other"] * count
    codes = numpy_support.vtk_to_numpy(codes).astype(np.int64)
    if codes.size and (codes.min() < 0 or codes.max() >= len(ANATOMY_LABELS)):
        raise ValueError(f"label codes must lie in 0..{len(ANATOMY_LABELS) - 1}")
    return [ANATOMY_LABELS[code] for code in codes]


def _space_value(text: str, where: str) -> str:
    value = str(text).strip().upper()
    if value not in COORDINATE_SYSTEMS:
        raise ValueError(f"unknown {where} {text!r} (expected LPS or RAS)")
    return value


def _field_string(polydata: vtkPolyData, name: str) -> str | None:
    array = polydata.GetFieldData().GetAbstractArray(name)
    if array is None or array.GetNumberOfValues() == 0:
        return None
    return str(array.GetVariantValue(0).ToString())


def coordinate_system_of(polydata: vtkPolyData, header: str | None = None, default: str = "LPS") -> str:
    """The coordinate system a model file's points are in, decided the way Slicer decides it.

    Slicer's ``vtkMRMLModelStorageNode`` reads ``SPACE=RAS`` / ``SPACE=LPS`` from a legacy
    .vtk header line, or the field-data string ``SPACE`` of a .vtp, and assumes LPS when the
    file says nothing. Here ``SPACE`` (or the header) wins; this project's older
    ``coordinateSystem`` field array is used only when neither is present, since Slicer keeps
    that array unchanged (and so stale) when it re-saves a model in another system.
    """
    if header:
        for system in COORDINATE_SYSTEMS:
            if f"{SPACE_TAG}={system}" in header:
                return system
    for name in (SPACE_TAG, LEGACY_SPACE_TAG):
        value = _field_string(polydata, name)
        if value is not None:
            return _space_value(value, name)
    return default


def polydata_to_centerline(polydata: vtkPolyData, coordinate_system: str | None = None) -> Centerline:
    """The :class:`Centerline` held by a vtkPolyData, points returned in LPS.

    Parameters
    ----------
    polydata : vtkPolyData
    coordinate_system : {"LPS", "RAS", None}
        The system of the points; None reads it from the field data
        (:func:`coordinate_system_of`). A Slicer model node's polydata is RAS whatever its
        arrays say: pass ``"RAS"`` for it.
    """
    if polydata.GetPoints() is None or polydata.GetNumberOfPoints() == 0:
        raise ValueError("the polydata has no points")
    system = coordinate_system_of(polydata) if coordinate_system is None else _space_value(coordinate_system,
                                                                                          "coordinate system")
    points = numpy_support.vtk_to_numpy(polydata.GetPoints().GetData()).astype(float)
    if system == "RAS":
        points = points * LPS_TO_RAS
    return Centerline(points, _line_edges(polydata), _point_labels(polydata, len(points)))


@contextlib.contextmanager
def _vtk_errors_captured():
    """Collect VTK error text (instead of printing it) while the block runs."""
    previous_window = vtkOutputWindow.GetInstance()
    previous_cutoff = vtkLogger.GetCurrentVerbosityCutoff()
    window = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(window)
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    try:
        yield window
    finally:
        vtkOutputWindow.SetInstance(previous_window)
        vtkLogger.SetStderrVerbosity(vtkLogger.ConvertToVerbosity(previous_cutoff))


def _vtk_error_line(window: vtkStringOutputWindow) -> str:
    """The message of the first ERROR block in captured VTK output ('' if none; warnings ignored)."""
    for block in window.GetOutput().split("\n\n"):
        lines = [line.strip() for line in block.strip().splitlines() if line.strip()]
        if len(lines) >= 2 and lines[0].startswith("ERROR"):
            return lines[1].split("): ", 1)[-1]
    return ""


def write_centerline_vtp(path, centerline: Centerline, *, arrays: dict | None = None) -> None:
    """Write a centreline as a VTK XML PolyData file (.vtp) in LPS, atomically.

    See :func:`centerline_to_polydata` for the content; ``arrays`` adds point data. The
    field data ``SPACE`` = ``LPS`` makes Slicer load it in the right place.
    """
    path = Path(path)
    polydata = centerline_to_polydata(centerline, arrays)
    with atomic_path(path, suffix=".vtp") as tmp, _vtk_errors_captured() as errors:
        writer = vtkXMLPolyDataWriter()
        writer.SetFileName(str(tmp))
        writer.SetInputData(polydata)
        if writer.Write() != 1:
            raise OSError(f"{path}: cannot write VTK polydata ({_vtk_error_line(errors) or 'write failed'})")


def _read_model_file(path: Path):
    """(polydata, legacy header or None) of a .vtp or legacy .vtk file."""
    legacy = path.suffix.lower() == ".vtk"
    reader = vtkPolyDataReader() if legacy else vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    if legacy:
        reader.ReadAllFieldsOn()
    with _vtk_errors_captured() as errors:
        reader.Update()
    message = _vtk_error_line(errors)
    if message or (legacy and not reader.IsFilePolyData()):
        raise InputError(f"{path}: cannot read VTK polydata ({message or 'not polydata'})")
    return reader.GetOutput(), (reader.GetHeader() if legacy else None)


def read_centerline_vtp(path) -> Centerline:
    """Read a centreline model file (.vtp, or a legacy .vtk as Slicer saves by default) into LPS mm.

    The points' coordinate system is read as Slicer reads it (:func:`coordinate_system_of`),
    so a model that Slicer saved (LPS points, ``SPACE`` = ``LPS``) comes back unchanged.
    """
    path = Path(path)
    check_readable(path)
    polydata, header = _read_model_file(path)
    try:
        return polydata_to_centerline(polydata, coordinate_system_of(polydata, header))
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


# ----------------------------------------------------------------------------- Slicer markups

def write_path_markups(path, points, *, name: str = "CatheterPath", coordinate_system: str = "LPS",
                       color=PALETTE["path"]) -> None:
    """Write a path as a Slicer markups curve (``.mrk.json``, schema v1.0.3), atomically.

    Parameters
    ----------
    path : path-like
        Output file, conventionally ``*.mrk.json``.
    points : array_like, shape (k, 3)
        Control points in LPS mm (k >= 2).
    name : str
        Markup name; control points are labelled ``name-1``, ``name-2``, ...
    coordinate_system : {"LPS", "RAS"}
        System the file is written in (stated in the file; Slicer reads both).
    color : color
        Curve colour (matplotlib colour name or RGB in 0..1); default the path colour.

    A ``.mrk.json`` cannot say a curve is linear (Slicer keeps the curve type in the scene
    file), so Slicer draws the loaded path as a spline through these points: the points are
    dense and smooth, so its length stays within 0.5 % of ``path.length_mm``.
    """
    if coordinate_system not in IDENTITY_ORIENTATION:
        raise ValueError(f"coordinate_system must be 'LPS' or 'RAS', got {coordinate_system!r}")
    points = _points_array(points, "path points", 2)
    if coordinate_system == "RAS":
        points = points * LPS_TO_RAS
    rgb = _rgb(color)
    control_points = [{"id": str(i + 1), "label": f"{name}-{i + 1}", "description": "", "associatedNodeID": "",
                       "position": position.tolist(), "orientation": IDENTITY_ORIENTATION[coordinate_system],
                       "selected": True, "locked": False, "visibility": True, "positionStatus": "defined"}
                      for i, position in enumerate(points)]
    markup = {"type": "Curve", "name": name, "coordinateSystem": coordinate_system, "coordinateUnits": "mm",
              "locked": False, "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d",
              "lastUsedControlPointNumber": len(points), "controlPoints": control_points,
              "measurements": [{"name": "length", "enabled": True, "units": "mm", "printFormat": "%-#4.4g%s"}],
              "display": {"visibility": True, "opacity": 1.0, "color": rgb, "selectedColor": rgb,
                          "propertiesLabelVisibility": True, "pointLabelsVisibility": False,
                          "glyphType": "Sphere3D", "glyphScale": 1.0, "lineThickness": 0.5}}
    write_text_atomic(path, json.dumps({"@schema": MARKUPS_SCHEMA, "markups": [markup]}, indent=2) + "\n")


def read_path_markups(path) -> np.ndarray:
    """Control points (LPS mm, shape (k, 3)) of the first markup in a ``.mrk.json`` file."""
    path = Path(path)
    check_readable(path)
    try:
        markup = json.loads(path.read_text(encoding="utf-8"))["markups"][0]
        positions = [point["position"] for point in markup["controlPoints"]]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, IndexError, TypeError) as exc:
        raise InputError(f"{path}: not a Slicer markups file ({type(exc).__name__}: {exc})") from None
    system = markup.get("coordinateSystem", "LPS")
    if system not in IDENTITY_ORIENTATION:
        raise InputError(f"{path}: unknown coordinateSystem {system!r}")
    try:
        points = _points_array(positions, "controlPoints", 1)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    return points * LPS_TO_RAS if system == "RAS" else points


# ----------------------------------------------------------------------------- overlay PNG

def _rgb(color) -> list:
    from matplotlib.colors import to_rgb

    return [float(c) for c in to_rgb(color)]


@dataclass
class OverlayLayer:
    """One coloured layer of the overlay, in image coordinates (u = column, v = row).

    Attributes
    ----------
    name : str
        Legend entry.
    points_uv : numpy.ndarray, shape (k, 2)
    color : color
        Matplotlib colour name or RGB in 0..1.
    edges : numpy.ndarray of int, shape (m, 2), optional
        Segments between point indices (a projected graph).
    polyline : bool
        Without ``edges``: join consecutive points (a path) instead of drawing dots.
    """

    name: str
    points_uv: np.ndarray
    color: object = "red"
    edges: np.ndarray | None = None
    polyline: bool = False

    def __post_init__(self):
        self.points_uv = np.asarray(self.points_uv, dtype=float).reshape(-1, 2)
        if self.edges is not None:
            self.edges = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)
            if len(self.edges) and (self.edges.min() < 0 or self.edges.max() >= len(self.points_uv)):
                raise ValueError(f"overlay layer {self.name!r}: edge index out of range")

    def segments(self) -> np.ndarray:
        """Finite line segments (s, 2, 2) to draw; empty for a layer of dots."""
        if self.edges is not None:
            segments = self.points_uv[self.edges]
        elif self.polyline and len(self.points_uv) > 1:
            segments = np.stack([self.points_uv[:-1], self.points_uv[1:]], axis=1)
        else:
            return np.zeros((0, 2, 2))
        return segments[np.isfinite(segments).all(axis=(1, 2))]

    def dots(self) -> np.ndarray:
        """Finite points (k, 2) to draw as dots."""
        return self.points_uv[np.isfinite(self.points_uv).all(axis=1)]


def centerline_layer(name: str, P: np.ndarray, centerline: Centerline, color) -> OverlayLayer:
    """A centreline projected with ``P`` (eq. 1), drawn as its graph edges."""
    return OverlayLayer(name, project(P, centerline.points), color, edges=centerline.edges)


def path_layer(name: str, P: np.ndarray, points: np.ndarray, color) -> OverlayLayer:
    """A 3D path projected with ``P`` (eq. 1), drawn as a polyline."""
    return OverlayLayer(name, project(P, np.asarray(points, dtype=float)), color, polyline=True)


def _grey_limits(image: np.ndarray) -> tuple[float, float]:
    low, high = np.percentile(image, [1.0, 99.0])
    if high <= low:
        low, high = float(image.min()), float(image.max())
    return float(low), float(high if high > low else low + 1.0)


def _squares(points_uv: np.ndarray, side: float) -> np.ndarray:
    """Corners (k, 4, 2) of squares of ``side`` pixels centred on each point (data = pixels)."""
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * (side / 2.0)
    return points_uv[:, None, :] + corners[None, :, :]


def _layer_artist(layer: OverlayLayer, line_width_pt: float, dot_px: float):
    """Matplotlib collection of a layer: unsnapped lines, or squares of ``dot_px`` pixels."""
    from matplotlib.collections import LineCollection, PolyCollection

    if layer.edges is not None or layer.polyline:
        return LineCollection(layer.segments(), colors=[_rgb(layer.color)], linewidths=line_width_pt, snap=False)
    return PolyCollection(_squares(layer.dots(), dot_px), facecolors=[_rgb(layer.color)], edgecolors="none")


def view_name(P: np.ndarray, at) -> str:
    """The C-arm view of ``P`` seen from ``at`` (LPS), e.g. ``"LAO 30 / CRA 15"``.

    The angles follow projection.py's convention: the viewing direction (source to
    detector) is ``(sin a cos b, -cos a cos b, sin b)`` with ``a`` LAO positive and ``b``
    cranial positive. ``P``'s overall sign is fixed so that ``at`` lies in front of the source.
    """
    P = np.asarray(P, dtype=float)
    direction = P[2, :3] * np.sign(depth(P, np.asarray(at, dtype=float)))
    direction = direction / np.linalg.norm(direction)
    return view_label(np.degrees(np.arctan2(direction[0], -direction[1])),
                      np.degrees(np.arcsin(np.clip(direction[2], -1.0, 1.0))))


def _scale_bar_mm(pixels_per_mm: float, cols: int) -> float:
    """A round length (mm) whose bar is at most a quarter of the image width."""
    for length in (200.0, 100.0, 50.0, 20.0, 10.0, 5.0, 2.0, 1.0):
        if length * pixels_per_mm <= cols / 4.0:
            return length
    return 1.0


def _orientation_marks(axes, P, at, rows: int, cols: int) -> None:
    """R / L letters on the image edges where the patient's right and left project, and a mm scale bar."""
    left, _ = image_directions(P, at)
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
    reach = 0.45 * min(rows, cols)
    style = {"color": "white", "fontsize": 11, "fontweight": "bold", "ha": "center", "va": "center",
             "bbox": {"facecolor": "black", "alpha": 0.5, "pad": 1.5, "edgecolor": "none"}}
    for letter, sign in (("L", 1.0), ("R", -1.0)):
        u, v = centre + sign * reach * left
        axes.text(u, v, letter, **style)
    at = np.asarray(at, dtype=float)
    pixels_per_mm = float(np.linalg.norm(project(P, at + [1.0, 0.0, 0.0]) - project(P, at)))
    length = _scale_bar_mm(pixels_per_mm, cols)
    x1, y = cols - 0.04 * cols, rows - 0.05 * rows
    x0 = x1 - length * pixels_per_mm
    axes.plot([x0, x1], [y, y], color="white", linewidth=3, solid_capstyle="butt")
    axes.text((x0 + x1) / 2.0, y - 0.015 * rows, f"{length:g} mm", color="white", fontsize=8, ha="center",
              va="bottom")


def render_overlay(path, image: np.ndarray, *, skeleton2d: np.ndarray | None = None,
                   layers=(), line_px: float = 2.0, dot_px: float = 3.0, legend_height_px: int = 28,
                   min_width_px: int = 480, title: str | None = None, P: np.ndarray | None = None,
                   anchor=None, skeleton_color=PALETTE["skeleton2d"]) -> None:
    """Draw the frame in grey with coloured layers on top and save it as a PNG (atomically).

    The frame fills the top-left ``rows x cols`` pixels of the PNG at 1:1, so the layer
    point ``(u, v)`` is drawn at PNG pixel ``(row v, column u)``. The legend sits in a strip
    below the frame (and the PNG is widened to ``min_width_px`` for it if needed).

    Parameters
    ----------
    path : path-like
        Output ``.png``.
    image : numpy.ndarray, shape (rows, cols)
        The fluoroscopic frame (any real values; shown from its 1st to 99th percentile).
    skeleton2d : numpy.ndarray, shape (k, 2), optional
        2D skeleton points (u, v), drawn as dots (:data:`conventions.PALETTE` "skeleton2d") under the other layers.
    layers : sequence of OverlayLayer
        Drawn in order (later on top).
    line_px, dot_px : float
        Line width and dot size in PNG pixels (antialiased, not snapped to the pixel grid,
        so a line or dot is centred exactly on its ``(u, v)``).
    title : str, optional
        Drawn at the top left (e.g. the method, the view and the 2D fit).
    P, anchor : (3, 4) and (3,), optional
        With both: R and L where the patient's right and left project (through ``anchor``,
        LPS, e.g. the anatomy's centre) and a millimetre scale bar at ``anchor``'s depth.
    skeleton_color : color
        Colour of the 2D skeleton dots.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    image = np.asarray(image, dtype=float)
    if image.ndim != 2 or min(image.shape) < 1:
        raise ValueError(f"overlay image must be 2D (rows, cols), got shape {image.shape}")
    if not np.all(np.isfinite(image)):
        raise ValueError("overlay image contains NaN or infinite values")
    layers = list(layers)
    if skeleton2d is not None:
        layers.insert(0, OverlayLayer("2D skeleton", skeleton2d, skeleton_color))

    rows, cols = image.shape
    width, height = max(cols, min_width_px), rows + legend_height_px
    dpi = 100.0
    points_per_px = 72.0 / dpi  # matplotlib sizes are in points
    figure = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="black")
    FigureCanvasAgg(figure)
    axes = figure.add_axes((0.0, legend_height_px / height, cols / width, rows / height))
    axes.set_axis_off()
    low, high = _grey_limits(image)
    axes.imshow(image, cmap="gray", vmin=low, vmax=high, interpolation="nearest",
                extent=(-0.5, cols - 0.5, rows - 0.5, -0.5))
    handles = []
    for layer in layers:
        axes.add_collection(_layer_artist(layer, line_px * points_per_px, dot_px))
        handles.append(Line2D([], [], color=_rgb(layer.color), linewidth=3, label=layer.name))
    if P is not None and anchor is not None:
        _orientation_marks(axes, P, anchor, rows, cols)
    if title:
        axes.text(0.01 * cols, 0.01 * rows, title, color="white", fontsize=9, ha="left", va="top",
                  bbox={"facecolor": "black", "alpha": 0.55, "pad": 2.0, "edgecolor": "none"})
    axes.set_xlim(-0.5, cols - 0.5)
    axes.set_ylim(rows - 0.5, -0.5)
    if handles:
        figure.legend(handles=handles, loc="lower left", ncol=len(handles), frameon=False, fontsize=8,
                      labelcolor="white", bbox_to_anchor=(0.0, 0.0), borderaxespad=0.2, handlelength=1.5,
                      columnspacing=1.0)
    with atomic_path(path, suffix=".png") as tmp:
        figure.savefig(tmp, dpi=dpi, format="png", facecolor="black")


# ----------------------------------------------------------------------------- 3D picture

def _as_centerline(item) -> Centerline:
    """A Centerline as is; (k, 3) points (a path) as a polyline."""
    if isinstance(item, Centerline):
        return item
    points = _points_array(item, "3D picture path points", 2)
    edges = np.column_stack([np.arange(len(points) - 1), np.arange(1, len(points))])
    return Centerline(points, edges, ["other"] * len(points))


def polydata_actor(polydata_or_port, color, opacity: float = 1.0):
    """A VTK actor drawing ``polydata`` (or a filter's output port) in one colour, no scalars.

    The shared base of every actor in the pictures here and the workstation's views.
    """
    from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

    mapper = vtkPolyDataMapper()
    if hasattr(polydata_or_port, "GetNumberOfPoints"):
        mapper.SetInputData(polydata_or_port)
    else:
        mapper.SetInputConnection(polydata_or_port)
    mapper.ScalarVisibilityOff()
    actor = vtkActor()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetColor(*_rgb(color))
    prop.SetOpacity(opacity)
    return actor


def tube_actor(polydata, color, radius: float, opacity: float = 1.0, sides: int = 16):
    """A VTK actor drawing the lines of ``polydata`` as capped tubes of ``radius`` (mm)."""
    from vtkmodules.vtkFiltersCore import vtkStripper, vtkTubeFilter

    stripper = vtkStripper()
    stripper.SetInputData(polydata)
    tubes = vtkTubeFilter()
    tubes.SetInputConnection(stripper.GetOutputPort())
    tubes.SetRadius(radius)
    tubes.SetNumberOfSides(sides)
    tubes.CappingOn()
    actor = polydata_actor(tubes.GetOutputPort(), color, opacity)
    actor.GetProperty().SetSpecular(0.35)
    actor.GetProperty().SetSpecularPower(30)
    return actor


def _text_actor(text: str, color, position, size: int, justify_right: bool = False):
    from vtkmodules.vtkRenderingCore import vtkTextActor

    actor = vtkTextActor()
    actor.SetInput(text)
    actor.GetTextProperty().SetColor(*_rgb(color))
    actor.GetTextProperty().SetFontSize(size)
    if justify_right:
        actor.GetTextProperty().SetJustificationToRight()
    actor.SetDisplayPosition(*position)
    return actor


def _anterior_camera(renderer, bounds) -> None:
    """Look from the front (-y in LPS) with the head (+z) up: patient's right on the left."""
    center = np.array([(bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2, (bounds[4] + bounds[5]) / 2])
    camera = renderer.GetActiveCamera()
    camera.SetFocalPoint(*center)
    camera.SetPosition(*(center - [0.0, 1000.0, 0.0]))
    camera.SetViewUp(0.0, 0.0, 1.0)
    renderer.ResetCamera(bounds)
    camera.Zoom(0.85)  # leave a margin for the legend and the R / L marks


def render_centerlines_3d(path, centerlines, *, surface=None, size=(800, 800)) -> None:
    """Render centrelines as tubes (and a translucent surface) offscreen and save a PNG.

    Parameters
    ----------
    path : path-like
        Output ``.png``, written atomically.
    centerlines : sequence of (Centerline or (k, 3) points, color, name)
        Each drawn as tubes in its colour and named in the legend; points (a planned
        path) are drawn as a polyline. Later entries are drawn slightly thicker.
    surface : vtkPolyData, optional
        E.g. the aorta lumen surface (LPS mm), drawn translucent.
    size : (width, height)
        Picture size in pixels.

    The view is anterior with the patient's head up (the patient's right on the left).
    """
    from vtkmodules.vtkIOImage import vtkPNGWriter
    from vtkmodules.vtkRenderingCore import vtkRenderer, vtkRenderWindow, vtkWindowToImageFilter
    import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (registers the OpenGL render window)
    import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text rendering)

    centerlines = [(_as_centerline(item), color, name) for item, color, name in centerlines]
    if not centerlines and surface is None:
        raise ValueError("nothing to render: give at least one centreline or a surface")
    width, height = (int(s) for s in size)
    if width < 16 or height < 16:
        raise ValueError(f"picture size must be at least 16 x 16 pixels, got {size}")
    renderer = vtkRenderer()
    renderer.SetBackground(0.08, 0.09, 0.12)
    extent = max((np.ptp(c.points, axis=0).max() for c, _, _ in centerlines), default=100.0)
    radius = max(0.5, 0.005 * float(extent))
    for index, (centerline, color, name) in enumerate(centerlines):
        # later entries are drawn a little thicker, so they stay visible where they coincide
        renderer.AddActor(tube_actor(centerline_to_polydata(centerline), color, radius * (1.0 + 0.3 * index)))
        renderer.AddViewProp(_text_actor(name, color, (10, height - 24 - 20 * index), 16))
    if surface is not None:
        renderer.AddActor(polydata_actor(surface, PALETTE["surface"], 0.25))
    renderer.AddViewProp(_text_actor("R", "white", (10, height // 2), 18))
    renderer.AddViewProp(_text_actor("L", "white", (width - 10, height // 2), 18, justify_right=True))
    renderer.AddViewProp(_text_actor("anterior view", "lightgrey", (10, 10), 12))
    renderer.ResetCamera()
    _anterior_camera(renderer, renderer.ComputeVisiblePropBounds())

    with _vtk_errors_captured() as errors:
        window = vtkRenderWindow()
        window.SetOffScreenRendering(1)
        window.SetSize(width, height)
        window.AddRenderer(renderer)
        window.Render()
    if _vtk_error_line(errors):
        raise RuntimeError(f"{path}: offscreen rendering failed ({_vtk_error_line(errors)})")
    grab = vtkWindowToImageFilter()
    grab.SetInput(window)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    with atomic_path(path, suffix=".png") as tmp:
        writer = vtkPNGWriter()
        writer.SetFileName(str(tmp))
        writer.SetInputConnection(grab.GetOutputPort())
        writer.Write()
        if writer.GetErrorCode():
            raise OSError(f"{path}: cannot write PNG (VTK error code {writer.GetErrorCode()})")
    window.Finalize()

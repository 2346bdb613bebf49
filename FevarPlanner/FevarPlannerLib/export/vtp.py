"""Centrelines as vtkPolyData (``.vtp``, legacy ``.vtk``), the way 3D Slicer's model storage
writes and reads them.

One line cell per edge, point data ``label`` (index into ``ANATOMY_LABELS``) and
``label_name``, and the coordinate system as field data ``SPACE`` = ``"LPS"`` (a legacy
``.vtk`` says ``SPACE=LPS`` in its header line instead). Slicer removes ``SPACE`` when it
loads a file and writes its own when it saves one, so that tag is never stale; the older
``coordinateSystem`` array is read only when ``SPACE`` is absent.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkPoints, vtkStringArray, vtkStringOutputWindow
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkIOLegacy import vtkPolyDataReader
from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLPolyDataWriter

from ..centerline import Centerline
from ..conventions import ANATOMY_LABELS
from ..files import InputError, atomic_path, check_readable


LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])
#: Slicer's model files name their coordinate system with this field-data array (.vtp) or
#: ``SPACE=LPS`` / ``SPACE=RAS`` in the header line (legacy .vtk), after the NRRD key.
SPACE_TAG = "SPACE"
#: The tag this project wrote before it followed Slicer; read only when ``SPACE`` is absent.
LEGACY_SPACE_TAG = "coordinateSystem"
COORDINATE_SYSTEMS = ("LPS", "RAS")


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

"""The catheter path as a Slicer markups curve (``*.mrk.json``, schema v1.0.3) with an explicit
coordinate system.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..conventions import PALETTE
from ..files import InputError, check_readable, write_text_atomic
from .overlay import _rgb
from .result import _points_array
from .vtp import LPS_TO_RAS


MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
                  "Resources/Schema/markups-schema-v1.0.3.json#")


# Slicer's default control point orientation (identity in RAS) written in each system
IDENTITY_ORIENTATION = {"LPS": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                        "RAS": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}


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

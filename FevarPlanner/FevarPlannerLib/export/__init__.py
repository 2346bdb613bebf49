"""Exports of a planning result: result.json, centreline .vtp, Slicer markups, PNG pictures.

Everything is written in DICOM LPS millimetres and goes through a temporary file beside
the target and a rename (:func:`files.atomic_path`), so a failure never leaves a half-written
file, and an existing file is only replaced by a complete, validated one. One module per
format (every name is re-exported here):

    result      ``result.json`` (:data:`RESULT_VERSION` 1, docs/DESIGN.md section 4) and
                :func:`validate_result`, its schema written out by hand
    vtp         ``*.vtp`` / ``*.vtk``: the centreline graph as vtkPolyData, coordinate system
                tagged the way 3D Slicer's model storage writes and reads it (``SPACE``)
    markups     ``*.mrk.json``: a Slicer markups curve (schema v1.0.3) with an explicit
                coordinate system
    overlay     ``overlay.png``: the fluoroscopic frame with projected centrelines, pixel for pixel
    picture3d   a 3D picture of centrelines (and optionally the aorta surface), rendered offscreen
    summary     the results table's rows (:func:`summary_rows`), shared by the front ends
"""

from __future__ import annotations

from .markups import IDENTITY_ORIENTATION, MARKUPS_SCHEMA, read_path_markups, write_path_markups
from .overlay import (OverlayLayer, ROLE_NAMES, centerline_layer, path_layer, render_overlay, view_name,
                      warning_lines)
from .overlay import _orientation_marks  # the tests draw the marks alone
from .picture3d import polydata_actor, render_centerlines_3d, tube_actor
from .summary import FIT_NAMES, METRIC_NAMES, format_metric, summary_rows
from .result import (CORE_KEYS, REQUIRED_TIMINGS, RESULT_VERSION, build_result_dict, read_result_json,
                     validate_result, write_result_json)
from .vtp import (COORDINATE_SYSTEMS, LEGACY_SPACE_TAG, LPS_TO_RAS, SPACE_TAG, centerline_to_polydata,
                  coordinate_system_of, polydata_to_centerline, read_centerline_vtp, write_centerline_vtp)

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
    "warning_lines",
    "render_centerlines_3d",
    "tube_actor",
    "polydata_actor",
    "format_metric",
    "summary_rows",
]


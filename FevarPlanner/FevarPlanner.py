"""FevarPlanner: the 3D Slicer scripted module.

The only file of the project that imports ``slicer`` (and, inside the Slicer application,
``qt``). It is a thin adapter around the pure core:

* module-level functions move data between the core and MRML nodes: volumes (a CT loaded
  from DICOM, labelmaps) and segmentations both ways, centrelines as model nodes with a
  ``Radius`` array (as SlicerVMTK's Extract Centerline gives them), the catheter path as a
  locked linear markups curve, the frame in its own slice view with the projected tree as
  an overlay that only that view shows; a case with several views (further frames at other
  C-arm angles) gets one frame and one overlay set per view, and :func:`show_view` puts one
  of them in the frame view. They need nothing but the MRML classes, so they run
  under the ``slicer-core`` wheel (pip) as well as in Slicer, and the pytest suite checks
  them there;
* :class:`FevarPlannerParameters`: the module's parameter node (inputs and results as node
  references, options as parameters), saved with the scene. Inside Slicer the widget binds
  the same fields through ``parameterNodeWrapper``;
* :class:`FevarPlannerLogic` builds a case from loaded nodes (or reads a case folder), runs
  :func:`FevarPlannerLib.pipeline.run_case` (the same entry point as the CLI and the
  workstation) on the cached pre-operative model, and puts the result into the scene;
* inside the Slicer application only: the module description, the widget (the shared
  ``Resources/UI/FevarPlanner.ui`` panel plus node selectors), with enter / exit / cleanup
  handlers, and the self-test.

Coordinates: the core works in DICOM LPS millimetres; Slicer's scene is RAS. The conversion
``RAS = (-x, -y, z)`` happens here and nowhere else.

Why one file of about a thousand lines: Slicer loads a scripted module from one
``<Module>.py`` that holds the module, widget, logic and test classes side by side (its
scripted-module template and the ``slicerMacroBuildScriptedModule`` convention); splitting
the MRML adapters into a package beside it would put a second ``slicer``-importing file in
the core's reach. Everything that is not Slicer glue lives in :mod:`FevarPlannerLib`.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import slicer
import vtk
from vtk.util import numpy_support

from FevarPlannerLib import RESEARCH_USE_STATEMENT
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.conventions import PALETTE
from FevarPlannerLib.export import LPS_TO_RAS, summary_rows

try:
    from slicer.ScriptedLoadableModule import (ScriptedLoadableModule, ScriptedLoadableModuleLogic,
                                               ScriptedLoadableModuleTest, ScriptedLoadableModuleWidget)
    import ctk
    import qt

    SLICER_APPLICATION = True
except ImportError:
    # slicer-core (pip) outside the Slicer application: MRML classes only. The logic then
    # works on a scene it is given; the module, widget and self-test classes need the
    # application and are not defined.
    ScriptedLoadableModuleLogic = object
    SLICER_APPLICATION = False

try:
    from slicer.parameterNodeWrapper import parameterNodeWrapper
except ImportError:  # slicer-core, or a Slicer older than 5.2
    parameterNodeWrapper = None

__all__ = [
    "ROLE_ATTRIBUTE",
    "STYLE",
    "CORE_REQUIREMENTS",
    "missing_requirements",
    "lps_to_ras",
    "ras_to_lps",
    "module_resource_path",
    "centerline_polydata_ras",
    "model_node_to_centerline",
    "centerline_to_model_node",
    "path_to_curve_node",
    "fluoro_to_volume_node",
    "picture_to_volume_node",
    "volume_to_node",
    "node_to_volume",
    "mask_to_segmentation_node",
    "segmentation_node_to_mask",
    "lumen_radii",
    "frame_view_nodes",
    "show_frame",
    "overlay_to_model_node",
    "result_views",
    "show_view",
    "extra_views",
    "add_extra_view",
    "remove_extra_view",
    "result_nodes",
    "remove_result_nodes",
    "FevarPlannerParameters",
    "FevarPlannerLogic",
    "run_phantom_check",
    "run_node_check",
]

#: Node attribute naming what a node shows; nodes carrying it belong to this module.
ROLE_ATTRIBUTE = "FevarPlanner.role"

#: Display colour (RGB 0..1, the project's one palette) and line width per role.
STYLE = {
    "preop": (PALETTE["preop"], 2.0),
    "deformed": (PALETTE["recovered"], 3.0),
    "path": (PALETTE["path"], 4.0),
    "skeleton2d": (PALETTE["skeleton2d"], 2.0),
}
#: Node attribute naming the view (``main``, ``lao30``, ...) a frame or overlay node belongs to.
VIEW_ATTRIBUTE = "FevarPlanner.view"
#: Node reference from an overlay node to the frame node it is drawn on.
FRAME_REFERENCE = "FevarPlanner.frame"
#: The first view's name (the case folder's own frame, or the parameter node's ``fluoroVolume``):
#: the core's ``io.MAIN_VIEW``, not imported here since the readers need packages a fresh Slicer may lack.
MAIN_VIEW_NAME = "main"
#: Roles whose nodes a new run keeps: the aorta segmentation may have been edited by hand.
KEPT_ROLES = ("aorta",)
#: Layout name of the slice view that shows the frame (never the CT's views).
FRAME_VIEW = "FevarFrame"


#: Third-party modules the core imports at planning time (module -> pip requirement).
#: Slicer ships some of them; torch is left out: only CT segmentation without a given aorta
#: mask needs it, and Slicer users get it from the PyTorch extension.
CORE_REQUIREMENTS = {
    "numpy": "numpy",
    "scipy": "scipy",
    "skimage": "scikit-image",
    "SimpleITK": "SimpleITK",
    "pydicom": "pydicom",
    "PIL": "Pillow",
    "matplotlib": "matplotlib",
    "threadpoolctl": "threadpoolctl",
}


def missing_requirements(requirements: dict = CORE_REQUIREMENTS) -> list:
    """pip requirements whose module cannot be imported here (nothing is imported to check)."""
    return [pip_name for module, pip_name in requirements.items() if importlib.util.find_spec(module) is None]


def lps_to_ras(points) -> np.ndarray:
    """DICOM LPS points (n, 3) or (3,) as Slicer RAS points: ``(-x, -y, z)``."""
    return np.asarray(points, dtype=float) * LPS_TO_RAS


def ras_to_lps(points) -> np.ndarray:
    """Slicer RAS points as DICOM LPS points (the same sign flip, its own inverse)."""
    return np.asarray(points, dtype=float) * LPS_TO_RAS


def module_resource_path(relative) -> Path:
    """A file under the module's ``Resources`` folder.

    A built extension has ``Resources/`` next to this file (the CMake build copies it
    there); the source tree has it one level up, at the repository root.
    """
    here = Path(__file__).resolve().parent
    candidates = [here / "Resources" / relative, here.parent / "Resources" / relative]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"FevarPlanner resource {relative} not found in {candidates[0].parent} "
                            f"or {candidates[1].parent}")


def _vtk_points(points: np.ndarray) -> vtk.vtkPoints:
    result = vtk.vtkPoints()
    result.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(points, dtype=float), deep=True))
    return result


def centerline_polydata_ras(centerline: Centerline, radius=None) -> vtk.vtkPolyData:
    """The centreline as export's vtkPolyData (line per edge, label arrays) with RAS points.

    It carries no coordinate-system tag: a model node's data is RAS by definition, and
    Slicer's model storage converts it and writes its own ``SPACE`` tag when it saves it.
    ``radius`` (mm per node) becomes the point array ``Radius``, as SlicerVMTK names it.
    """
    # imported here, not at the top: export pulls in the readers (pydicom, Pillow), which a
    # fresh Slicer may lack until the widget has offered to install them
    from FevarPlannerLib import export

    arrays = {"Radius": np.asarray(radius, dtype=float)} if radius is not None else None
    return export.centerline_to_polydata(centerline, arrays, space=None)


def lumen_radii(lumen, points_lps) -> np.ndarray:
    """Lumen radius (mm) at each point: the distance from its voxel to the nearest background voxel."""
    from scipy import ndimage

    inside = np.asarray(lumen.array) > 0
    distance = ndimage.distance_transform_edt(inside, sampling=lumen.spacing[::-1])
    index = np.rint(lumen.lps_to_index(np.asarray(points_lps, dtype=float))).astype(int)
    index = np.clip(index, 0, np.array(inside.shape) - 1)
    return distance[tuple(index.T)]


def model_node_to_centerline(node) -> Centerline:
    """The centreline a model node shows, back in LPS mm (the node's points are RAS)."""
    from FevarPlannerLib import export

    return export.polydata_to_centerline(node.GetPolyData(), "RAS")


#: Homogeneous LPS <-> RAS (its own inverse).
LPS_TO_RAS_4X4 = np.diag([-1.0, -1.0, 1.0, 1.0])


def _vtk_matrix(array: np.ndarray) -> vtk.vtkMatrix4x4:
    matrix = vtk.vtkMatrix4x4()
    for row in range(4):
        for col in range(4):
            matrix.SetElement(row, col, float(array[row, col]))
    return matrix


def _numpy_matrix(matrix: vtk.vtkMatrix4x4) -> np.ndarray:
    return np.array([[matrix.GetElement(row, col) for col in range(4)] for row in range(4)])


def volume_to_node(scene, volume, name: str, role: str | None = None,
                   node_class: str = "vtkMRMLScalarVolumeNode"):
    """Add a core :class:`FevarPlannerLib.io.Volume` (LPS) to ``scene`` as a volume node (RAS).

    The voxel array keeps its ``(k, j, i)`` layout; the node's IJK-to-RAS matrix is the
    volume's index-to-LPS matrix with x and y negated.
    """
    array = np.ascontiguousarray(volume.array)
    if array.dtype == bool:
        array = array.astype(np.uint8)
    data = vtk.vtkImageData()
    data.SetDimensions(array.shape[2], array.shape[1], array.shape[0])  # i, j, k
    data.GetPointData().SetScalars(numpy_support.numpy_to_vtk(array.ravel(), deep=True,
                                                              array_type=numpy_support.get_vtk_array_type(array.dtype)))
    node = scene.AddNewNodeByClass(node_class)
    node.SetName(name)
    if role:
        node.SetAttribute(ROLE_ATTRIBUTE, role)
    node.SetIJKToRASMatrix(_vtk_matrix(LPS_TO_RAS_4X4 @ volume.index_to_lps_matrix))
    node.SetAndObserveImageData(data)
    return node


def node_to_volume(node):
    """A volume node (a CT loaded from DICOM, a labelmap) as a core ``Volume`` in LPS mm."""
    from FevarPlannerLib.io import Volume

    data = node.GetImageData()
    if data is None or data.GetNumberOfPoints() == 0:
        raise ValueError(f"volume node {node.GetName()!r} holds no image data")
    matrix = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(matrix)
    index_to_lps = LPS_TO_RAS_4X4 @ _numpy_matrix(matrix)
    columns = index_to_lps[:3, :3]
    spacing = np.linalg.norm(columns, axis=0)
    dims = data.GetDimensions()
    array = numpy_support.vtk_to_numpy(data.GetPointData().GetScalars()).reshape(dims[2], dims[1], dims[0])
    return Volume(array.copy(), spacing, index_to_lps[:3, 3], columns / spacing)


def mask_to_segmentation_node(scene, mask, reference_node, name: str = "FevarPlanner aorta",
                              segment_name: str = "aorta", color=(0.85, 0.32, 0.30)):
    """The binary lumen mask (core ``Volume``, LPS) as a segmentation node, editable in Segment Editor.

    The segmentation's reference geometry is ``reference_node`` (the CT), so Segment Editor
    paints on the CT's grid and :func:`segmentation_node_to_mask` reads it back on that grid.
    """
    labelmap = volume_to_node(scene, mask.with_array(np.asarray(mask.array) > 0), "FevarPlanner lumen labelmap",
                              node_class="vtkMRMLLabelMapVolumeNode")
    segmentation = scene.AddNewNodeByClass("vtkMRMLSegmentationNode")
    segmentation.SetName(name)
    segmentation.SetAttribute(ROLE_ATTRIBUTE, "aorta")
    segmentation.SetReferenceImageGeometryParameterFromVolumeNode(reference_node)
    ok = slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelmap, segmentation)
    scene.RemoveNode(labelmap)
    if not ok or segmentation.GetSegmentation().GetNumberOfSegments() != 1:
        raise RuntimeError("could not turn the lumen mask into a segmentation")
    segment = segmentation.GetSegmentation().GetNthSegment(0)
    segment.SetName(segment_name)
    segment.SetColor(*color)
    return segmentation


def segmentation_node_to_mask(segmentation, reference_node, segment_name: str | None = None):
    """A segmentation node (as edited in Segment Editor) as a binary core ``Volume`` on the CT grid.

    ``segment_name`` picks one segment (default: every segment, merged).
    """
    ids = vtk.vtkStringArray()
    segments = segmentation.GetSegmentation()
    for index in range(segments.GetNumberOfSegments()):
        if segment_name is None or segments.GetNthSegment(index).GetName() == segment_name:
            ids.InsertNextValue(segments.GetNthSegmentID(index))
    if ids.GetNumberOfValues() == 0:
        raise ValueError(f"segmentation {segmentation.GetName()!r} has no segment {segment_name!r}")
    scene = segmentation.GetScene()
    labelmap = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode")
    try:
        if not slicer.vtkSlicerSegmentationsModuleLogic.ExportSegmentsToLabelmapNode(segmentation, ids, labelmap,
                                                                                     reference_node):
            raise RuntimeError(f"could not export segmentation {segmentation.GetName()!r} to a labelmap")
        volume = node_to_volume(labelmap)
    finally:
        scene.RemoveNode(labelmap)
    return volume.with_array(volume.array > 0)


def _tag(node, role: str, name: str) -> None:
    node.SetName(name)
    node.SetAttribute(ROLE_ATTRIBUTE, role)


def centerline_to_model_node(scene, centerline: Centerline, name: str, role: str = "deformed", radius=None):
    """Add a centreline to ``scene`` as a vtkMRMLModelNode of lines (RAS), with a display node.

    Parameters
    ----------
    scene : vtkMRMLScene
    centerline : Centerline
        Points in LPS mm.
    name : str
        Node name shown in Slicer.
    role : {"preop", "deformed"}
        Sets the colour and line width (:data:`STYLE`) and the :data:`ROLE_ATTRIBUTE`.
    radius : array_like, optional
        Lumen radius (mm) per node, stored as the point array ``Radius``.
    """
    if role not in STYLE:
        raise ValueError(f"unknown display role {role!r}; expected one of {sorted(STYLE)}")
    node = scene.AddNewNodeByClass("vtkMRMLModelNode")
    _tag(node, role, name)
    node.SetAndObservePolyData(centerline_polydata_ras(centerline, radius))
    node.CreateDefaultDisplayNodes()
    color, width = STYLE[role]
    display = node.GetDisplayNode()
    display.SetColor(*color)
    display.SetLineWidth(width)
    display.SetScalarVisibility(False)
    display.SetVisibility2D(True)
    return node


def path_to_curve_node(scene, path, name: str | None = None):
    """Add a planned path to ``scene`` as a locked, linear vtkMRMLMarkupsCurveNode (RAS).

    Parameters
    ----------
    scene : vtkMRMLScene
    path : FevarPlannerLib.planning.CatheterPath
        Points in LPS mm, from the access point to the target.
    name : str, optional
        Default ``"<start> to <target>"``.
    """
    points = np.asarray(path.points, dtype=float).reshape(-1, 3)
    if len(points) < 2:
        raise ValueError(f"a catheter path needs at least 2 points, got {len(points)}")
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsCurveNode")
    _tag(node, "path", name or f"{path.start_label} to {path.target_label}")
    node.SetCurveTypeToLinear()  # the planner already resampled and smoothed the path
    node.SetControlPointPositionsWorld(_vtk_points(lps_to_ras(points)))
    node.SetLocked(True)
    node.CreateDefaultDisplayNodes()
    color, _ = STYLE["path"]
    display = node.GetDisplayNode()
    display.SetSelectedColor(*color)
    display.SetColor(*color)
    display.SetPointLabelsVisibility(False)
    display.SetPropertiesLabelVisibility(False)
    display.SetGlyphScale(1.0)
    return node


def fluoro_to_volume_node(scene, image: np.ndarray, name: str = "FevarPlanner fluoroscopy"):
    """Add the fluoroscopic frame (rows, cols) to ``scene`` as a single-slice scalar volume.

    The frame keeps its pixel grid (1 mm per pixel, origin at the first pixel) and lies in
    the axial plane oriented so that Slicer's axial view shows it as the C-arm monitor
    does: columns (``u``) to the screen's right, rows (``v``) down.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2 or min(image.shape) < 1:
        raise ValueError(f"fluoroscopic frame must be a 2D array, got shape {image.shape}")
    return _picture_node(scene, image, "vtkMRMLScalarVolumeNode", "fluoro", name)


def _picture_node(scene, pixels: np.ndarray, node_class: str, role: str, name: str):
    """A single-slice volume of ``pixels`` (rows, cols[, components]) laid as the C-arm monitor shows it.

    Columns run to the screen's right and rows down in the axial view (1 mm per pixel,
    origin at the first pixel).
    """
    rows, cols = pixels.shape[:2]
    data = vtk.vtkImageData()
    data.SetDimensions(cols, rows, 1)  # i = column (u), j = row (v)
    flat = np.ascontiguousarray(pixels).reshape(rows * cols, -1)
    data.GetPointData().SetScalars(numpy_support.numpy_to_vtk(flat if flat.shape[1] > 1 else flat.ravel(), deep=True,
                                                              array_type=numpy_support.get_vtk_array_type(flat.dtype)))
    node = scene.AddNewNodeByClass(node_class)
    _tag(node, role, name)
    node.SetIJKToRASDirections(-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0)
    node.SetAndObserveImageData(data)
    node.CreateDefaultDisplayNodes()
    return node


def picture_to_volume_node(scene, path, name: str = "FevarPlanner refusal (QC picture)"):
    """Add a PNG picture (a refusal's ``segmentation_qc.png``) to ``scene`` as an RGB vector volume.

    It is laid as the frame is (:func:`fluoro_to_volume_node`), so :func:`show_frame` shows
    it upright in the frame view. Its role is ``refusal``: the next run's results replace it.

    Raises
    ------
    OSError
        ``path`` is not a readable PNG picture.
    """
    reader = vtk.vtkPNGReader()
    if not reader.CanReadFile(str(path)):
        raise OSError(f"{path}: not a readable PNG picture")
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    cols, rows, _ = image.GetDimensions()
    scalars = image.GetPointData().GetScalars()
    pixels = numpy_support.vtk_to_numpy(scalars).reshape(rows, cols, scalars.GetNumberOfComponents())
    if pixels.shape[2] < 3:
        pixels = np.repeat(pixels[:, :, :1], 3, axis=2)
    return _picture_node(scene, pixels[::-1, :, :3], "vtkMRMLVectorVolumeNode", "refusal", name)  # VTK rows run up


def frame_view_nodes(scene):
    """The slice node and slice composite node of the frame's own view (layout name :data:`FRAME_VIEW`).

    Created on first use. Inside Slicer the widget adds a view with this layout name to the
    layout, so the frame appears there and the CT keeps the Red / Yellow / Green views.
    """
    slice_node = next((node for node in _nodes_of_class(scene, "vtkMRMLSliceNode")
                       if node.GetLayoutName() == FRAME_VIEW), None)
    if slice_node is None:
        slice_node = scene.AddNewNodeByClass("vtkMRMLSliceNode")
        slice_node.SetName("FevarPlanner frame view")
        slice_node.SetLayoutName(FRAME_VIEW)
        slice_node.SetSingletonTag(FRAME_VIEW)
    composite = next((node for node in _nodes_of_class(scene, "vtkMRMLSliceCompositeNode")
                      if node.GetLayoutName() == FRAME_VIEW), None)
    if composite is None:
        composite = scene.AddNewNodeByClass("vtkMRMLSliceCompositeNode")
        composite.SetLayoutName(FRAME_VIEW)
        composite.SetSingletonTag(FRAME_VIEW)
    return slice_node, composite


def _nodes_of_class(scene, class_name: str) -> list:
    return [scene.GetNthNodeByClass(i, class_name) for i in range(scene.GetNumberOfNodesByClass(class_name))]


def _frame_ijk_to_ras(frame_node) -> np.ndarray:
    matrix = vtk.vtkMatrix4x4()
    frame_node.GetIJKToRASMatrix(matrix)
    return _numpy_matrix(matrix)


def show_frame(scene, frame_node):
    """Show the frame volume in its own view, facing it as the C-arm monitor does (u right, v down).

    Only the frame view's composite node is changed: the views showing the CT keep it.
    Returns the frame view's slice node.
    """
    slice_node, composite = frame_view_nodes(scene)
    composite.SetBackgroundVolumeID(frame_node.GetID())
    ijk_to_ras = _frame_ijk_to_ras(frame_node)
    cols, rows, _ = frame_node.GetImageData().GetDimensions()
    u_axis, v_axis = ijk_to_ras[:3, 0], ijk_to_ras[:3, 1]
    normal = np.cross(u_axis, -v_axis)  # screen x = +u, screen y = -v (rows run down the screen)
    centre = (ijk_to_ras @ [(cols - 1) / 2.0, (rows - 1) / 2.0, 0.0, 1.0])[:3]
    slice_node.SetSliceToRASByNTP(*(normal / np.linalg.norm(normal)), *(u_axis / np.linalg.norm(u_axis)), *centre, 0)
    spacing = np.linalg.norm(ijk_to_ras[:3, :2], axis=0)
    slice_node.SetFieldOfView(cols * spacing[0], rows * spacing[1], 1.0)
    return slice_node


def overlay_to_model_node(scene, frame_node, points_uv, edges, name: str, role: str, view_node=None):
    """Lines drawn on the frame (image points ``(u, v)``) as a model node in the frame's plane.

    Shown in 2D only, projected onto the slice, and only in ``view_node`` (the frame view)
    when given: never over the CT's slice views or in 3D.
    """
    uv = np.asarray(points_uv, dtype=float).reshape(-1, 2)
    ijk = np.column_stack([uv, np.zeros(len(uv)), np.ones(len(uv))])
    ras = (ijk @ _frame_ijk_to_ras(frame_node).T)[:, :3]
    polydata = vtk.vtkPolyData()
    polydata.SetPoints(_vtk_points(ras))
    lines = vtk.vtkCellArray()
    for a, b in np.asarray(edges, dtype=np.int64).reshape(-1, 2):
        lines.InsertNextCell(2)
        lines.InsertCellPoint(int(a))
        lines.InsertCellPoint(int(b))
    polydata.SetLines(lines)
    node = scene.AddNewNodeByClass("vtkMRMLModelNode")
    _tag(node, role, name)
    node.SetAndObservePolyData(polydata)
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    color, width = STYLE[_base_role(role).replace("overlay_", "")]
    display.SetColor(*color)
    display.SetLineWidth(width)
    display.SetVisibility3D(False)
    display.SetVisibility2D(True)
    display.SetSliceDisplayModeToProjection()
    if view_node is not None:
        display.SetViewNodeIDs([view_node.GetID()])
    return node


def _view_role(role: str, view: str) -> str:
    """The role of a per-view node: ``role`` for the first view, ``role:view`` for the others."""
    return role if view == MAIN_VIEW_NAME else f"{role}:{view}"


def _base_role(role: str) -> str:
    """``overlay_deformed`` of ``overlay_deformed:lao30``."""
    return role.split(":", 1)[0]


def result_views(scene) -> list:
    """The names of the views whose overlays are in ``scene``, in the order they were added (``main`` first)."""
    names = []
    for node in _nodes_of_class(scene, "vtkMRMLModelNode"):
        name = node.GetAttribute(VIEW_ATTRIBUTE)
        if name and node.GetAttribute(ROLE_ATTRIBUTE) and name not in names:
            names.append(name)
    return names


def show_view(scene, name: str):
    """Put view ``name``'s frame in the frame view and show only that view's overlays there.

    Every view's overlay nodes stay in the scene (saved with it); those of the other views
    are hidden. Returns the frame view's slice node.

    Raises
    ------
    ValueError
        ``scene`` holds no overlay of a view ``name``.
    """
    overlays = [node for node in _nodes_of_class(scene, "vtkMRMLModelNode")
                if node.GetAttribute(VIEW_ATTRIBUTE) and node.GetAttribute(ROLE_ATTRIBUTE)]
    chosen = [node for node in overlays if node.GetAttribute(VIEW_ATTRIBUTE) == name]
    if not chosen:
        raise ValueError(f"no view {name!r} in the scene; the views are {', '.join(result_views(scene)) or 'none'}")
    for node in overlays:
        node.GetDisplayNode().SetVisibility(node.GetAttribute(VIEW_ATTRIBUTE) == name)
    return show_frame(scene, chosen[0].GetNodeReference(FRAME_REFERENCE))


def result_nodes(scene) -> dict:
    """This module's nodes in ``scene`` by role (``preop``, ``deformed``, ``path``, ``fluoro``, ...).

    Per-view nodes of a view other than the first carry ``:<view>`` after the role
    (``fluoro:lao30``, ``overlay_deformed:lao30``).
    """
    nodes = {}
    for index in range(scene.GetNumberOfNodes()):
        node = scene.GetNthNode(index)
        role = node.GetAttribute(ROLE_ATTRIBUTE)
        if role:
            nodes[role] = node
    return nodes


def remove_result_nodes(scene) -> int:
    """Remove the nodes of an earlier run from ``scene`` (not the aorta segmentation); returns how many."""
    nodes = [node for role, node in result_nodes(scene).items() if role not in KEPT_ROLES]
    for node in nodes:
        scene.RemoveNode(node)
    return len(nodes)


class FevarPlannerParameters:
    """The module's parameter node: a ``vtkMRMLScriptedModuleNode`` saved with the scene.

    Node-valued fields are node references named after the field, the others are string
    parameters, which is how ``parameterNodeWrapper`` stores them too; inside Slicer the
    widget binds the same fields through it, here (slicer-core) this class reads and writes
    them. Inputs: ``ctVolume``, ``aortaSegmentation`` (optional: used instead of segmenting
    the CT, and the segmentation a run creates is put here, so an edit in Segment Editor is
    used on the next run), ``fluoroVolume`` (the frame), ``geometryFile`` /
    ``fluoroFile`` (geometry.json, or the XA file whose C-arm tags give ``P``). Further views
    of the same anatomy at other C-arm angles, one entry per view in three lists of the same
    length: ``extraFrameVolumes`` (the frames, each view named after its node),
    ``extraGeometryFiles`` and ``extraFluoroFiles`` (as ``geometryFile`` / ``fluoroFile``,
    ``""`` for none). Lists are stored as ``parameterNodeWrapper``'s ``list[...]`` fields are
    (``<field>_len`` and ``<field>_<i>``); assign a whole list to change one. Results:
    ``preopModel``, ``recoveredModel``, ``pathCurve``, and ``shownView`` (the view in the
    frame view).
    """

    NODE_FIELDS = {"ctVolume": "vtkMRMLScalarVolumeNode", "aortaSegmentation": "vtkMRMLSegmentationNode",
                   "fluoroVolume": "vtkMRMLScalarVolumeNode", "preopModel": "vtkMRMLModelNode",
                   "recoveredModel": "vtkMRMLModelNode", "pathCurve": "vtkMRMLMarkupsCurveNode"}
    VALUE_FIELDS = {"method": "proposed", "start": "iliac_right", "target": "renal_left", "geometryFile": "",
                    "fluoroFile": "", "shownView": MAIN_VIEW_NAME}
    NODE_LIST_FIELDS = {"extraFrameVolumes": "vtkMRMLScalarVolumeNode"}
    VALUE_LIST_FIELDS = ("extraGeometryFiles", "extraFluoroFiles")
    MODULE_NAME = "FevarPlanner"

    def __init__(self, node):
        object.__setattr__(self, "node", node)

    @classmethod
    def of_scene(cls, scene) -> "FevarPlannerParameters":
        """The scene's FevarPlanner parameter node (created with the defaults on first use)."""
        for node in _nodes_of_class(scene, "vtkMRMLScriptedModuleNode"):
            if node.GetAttribute("ModuleName") == cls.MODULE_NAME:
                return cls(node)
        node = scene.AddNewNodeByClass("vtkMRMLScriptedModuleNode")
        node.SetName("FevarPlanner parameters")
        node.SetAttribute("ModuleName", cls.MODULE_NAME)
        for key, value in cls.VALUE_FIELDS.items():
            node.SetParameter(key, value)
        return cls(node)

    def __getattr__(self, name):
        if name in self.NODE_FIELDS:
            return self.node.GetNodeReference(name)
        if name in self.VALUE_FIELDS:
            value = self.node.GetParameter(name)
            return self.VALUE_FIELDS[name] if value is None else value
        if name in self.NODE_LIST_FIELDS or name in self.VALUE_LIST_FIELDS:
            return [self._read_item(name, f"{name}_{index}") for index in range(self._list_length(name))]
        raise AttributeError(name)

    def __setattr__(self, name, value):
        if name in self.NODE_FIELDS:
            self.node.SetNodeReferenceID(name, value.GetID() if value is not None else None)
        elif name in self.VALUE_FIELDS:
            self.node.SetParameter(name, str(value))
        elif name in self.NODE_LIST_FIELDS or name in self.VALUE_LIST_FIELDS:
            self._write_list(name, list(value))
        else:
            raise AttributeError(f"FevarPlanner parameters have no field {name!r}")

    def _list_length(self, name: str) -> int:
        length = self.node.GetParameter(f"{name}_len")
        return int(length) if length else 0

    def _read_item(self, name: str, key: str):
        return self.node.GetNodeReference(key) if name in self.NODE_LIST_FIELDS else self.node.GetParameter(key)

    def _write_list(self, name: str, values: list) -> None:
        for index in range(len(values), self._list_length(name)):  # entries beyond the new end
            self.node.UnsetParameter(f"{name}_{index}")
            self.node.RemoveNodeReferenceIDs(f"{name}_{index}")
        for index, value in enumerate(values):
            key = f"{name}_{index}"
            if name in self.NODE_LIST_FIELDS:
                self.node.SetParameter(key, "")
                self.node.SetNodeReferenceID(key, value.GetID() if value is not None else None)
            else:
                self.node.SetParameter(key, str(value))
        self.node.SetParameter(f"{name}_len", str(len(values)))


class FevarPlannerLogic(ScriptedLoadableModuleLogic):
    """Run a case through the core and show the result as MRML nodes.

    Usable without the widget, inside Slicer (``FevarPlannerLogic().process(parameters)``)
    and outside it on any vtkMRMLScene (``FevarPlannerLogic(scene)``). Two routes share
    :meth:`add_result`: :meth:`process` (inputs from loaded nodes, the Slicer way) and
    :meth:`run` (a case folder, as the CLI reads it).
    """

    def __init__(self, scene=None):
        if ScriptedLoadableModuleLogic is not object:
            ScriptedLoadableModuleLogic.__init__(self)
        self._scene = scene

    @property
    def scene(self):
        """The scene given to the constructor, else Slicer's ``slicer.mrmlScene``."""
        return self._scene if self._scene is not None else slicer.mrmlScene

    def getParameterNode(self) -> FevarPlannerParameters:  # noqa: N802  (Slicer naming)
        """The scene's parameter node (see :class:`FevarPlannerParameters`)."""
        return FevarPlannerParameters.of_scene(self.scene)

    def case_from_nodes(self, parameters):
        """A core :class:`FevarPlannerLib.io.Case` from the parameter node's input nodes (RAS -> LPS here).

        ``case.views`` holds the frame (``fluoroVolume`` / ``fluoroFile``, the view ``main``)
        and each further view (``extraFrameVolumes`` with ``extraGeometryFiles`` /
        ``extraFluoroFiles``, named after its node), each a :class:`FevarPlannerLib.io.View`
        with its own ``P``, as :func:`FevarPlannerLib.io.load_case` builds them from
        ``views/<name>/`` folders.
        """
        from FevarPlannerLib.io import Case, InputError

        ct_node = parameters.ctVolume
        if ct_node is None:
            raise InputError("choose the CT volume (ctVolume)")
        ct = node_to_volume(ct_node)
        mask = None
        if parameters.aortaSegmentation is not None:
            mask = segmentation_node_to_mask(parameters.aortaSegmentation, ct_node)
            if not mask.array.any():
                raise InputError(f"segmentation {parameters.aortaSegmentation.GetName()!r} is empty")
        reference = mask if mask is not None else ct
        if parameters.fluoroVolume is None and not parameters.fluoroFile:
            raise InputError("choose the frame (fluoroVolume) or its DICOM file (fluoroFile)")
        views = [_frame_view(MAIN_VIEW_NAME, parameters.fluoroVolume, parameters.fluoroFile, parameters.geometryFile,
                             reference)]
        for node, geometry, fluoro_file in extra_views(parameters):
            views.append(_frame_view(node.GetName(), node, fluoro_file, geometry, reference))
        paths = {"ct": Path(ct_node.GetName())}
        return Case(case_dir=None, ct=ct if mask is None else None, aorta_mask=mask, skeleton3d=None,
                    fluoro=views[0].fluoro, fluoro_mask=None, P=views[0].P, paths=paths, available=dict(paths),
                    geometry=views[0].geometry, views=views)

    def process(self, parameters=None, *, progress=None, cache=True):
        """Plan from the loaded nodes of ``parameters`` (default the scene's parameter node).

        Every view (the frame and ``extraFrameVolumes``) takes part in one registration; each
        gets its overlays, drawn on its own frame node, and the first view is shown. The
        pre-operative model comes from the cache (:mod:`FevarPlannerLib.cache`) when the
        same CT / segmentation were seen. Returns ``(PlanResult, nodes by role)``. A refusal
        shows its QC picture in the frame view (:meth:`show_refusal`) and is raised on.
        """
        parameters = parameters or self.getParameterNode()
        case = self.case_from_nodes(parameters)
        result, model = self._gated_run(case, use_cache=cache, method=parameters.method, start=parameters.start,
                                        target=parameters.target, progress=progress, drr=False)
        loaded = {view.name: node for view, node in zip(case.views, [parameters.fluoroVolume,
                                                                     *parameters.extraFrameVolumes])}
        nodes = self.add_result(result, model=model, case=case,
                                frame_nodes={name: node for name, node in loaded.items() if node is not None})
        if parameters.aortaSegmentation is None and model.lumen is not None:
            nodes["aorta"] = mask_to_segmentation_node(self.scene, model.lumen, parameters.ctVolume)
            parameters.aortaSegmentation = nodes["aorta"]
        parameters.preopModel, parameters.recoveredModel = nodes["preop"], nodes["deformed"]
        parameters.pathCurve = nodes["path"]
        parameters.shownView = result_views(self.scene)[0]
        return result, nodes

    def run(self, case_dir, *, method: str = "proposed", start: str = "iliac_right", target: str = "renal_left",
            out_dir=None, overrides: dict | None = None, progress=None, show_fluoro: bool = True):
        """Plan one case folder (docs/DESIGN.md section 4) and add the result to the scene.

        Parameters
        ----------
        case_dir : path
        method : {"proposed", "icp-tps", "rigid"}
        start, target : str
            Access vessel and target vessel labels.
        out_dir : path, optional
            Also write result.json, the .vtp, the .mrk.json and the overlay PNG there.
        overrides : dict, optional
            Input files replacing the folder's (``ct``, ``aorta_mask``, ``skeleton3d``,
            ``fluoro``, ``fluoro_mask``, ``geometry``).
        progress : callable, optional
            ``progress(fraction, message)``.
        show_fluoro : bool
            Also add each view's frame (the folder's own and every ``views/<name>/``) as a
            scalar volume with the projected tree; the first is shown in the frame view.

        Returns
        -------
        (PlanResult, dict)
            The core's result and the nodes added, by role.

        Raises
        ------
        FevarPlannerLib.files.InputError
            One line naming the file and the problem; a refusal by a quality gate first
            shows its QC picture in the frame view (:meth:`show_refusal`).
        """
        from FevarPlannerLib.io import load_case
        from FevarPlannerLib.pipeline import write_outputs

        case = load_case(case_dir, **{key: value for key, value in (overrides or {}).items() if value})
        result, model = self._gated_run(case, out_dir=out_dir, method=method, start=start, target=target,
                                        progress=progress)
        if out_dir is not None:
            write_outputs(result, out_dir)
        return result, self.add_result(result, model=model, show_fluoro=show_fluoro, case=case)

    def _gated_run(self, case, out_dir=None, use_cache=True, progress=None, **options):
        """The pre-operative model (cached), then :func:`run_case` with the mirror test and the
        gates ``plan`` runs after it (refuse, or warn); ``(PlanResult, model)``.

        A refusal that has a QC picture (:meth:`show_refusal`) replaces the earlier run's
        results in the scene with the picture, then is raised on.
        """
        from FevarPlannerLib import cache as preop_cache
        from FevarPlannerLib.files import InputError
        from FevarPlannerLib.pipeline import check_result, run_case

        try:
            model = preop_cache.preop_model(case, progress=progress, use_cache=use_cache)
            result = run_case(case, preop=model, progress=progress, mirror_test=True, **options)
            result.warnings.extend(check_result(case, result))
        except InputError as failure:
            self.show_refusal(failure, out_dir)
            raise
        return result, model

    def show_refusal(self, failure, out_dir=None):
        """Show why a plan was refused: its QC picture in the frame view, the earlier results removed.

        The picture is written where ``plan --out`` writes it (``out_dir``), or to a temporary
        folder, and the failure's message then names it. Returns the picture's node, or None
        when ``failure`` carries no picture (a file that cannot be read, say).
        """
        from FevarPlannerLib.pipeline import refusal_picture

        picture = refusal_picture(failure, out_dir)
        if picture is None:
            return None
        remove_result_nodes(self.scene)    # a refused case must not leave another result on show
        node = picture_to_volume_node(self.scene, picture)
        show_frame(self.scene, node)
        return node

    def add_result(self, result, *, show_fluoro: bool = True, model=None, frame_nodes=None, case=None) -> dict:
        """Replace the nodes of an earlier run by this result's; returns the nodes by role.

        Parameters
        ----------
        result : FevarPlannerLib.pipeline.PlanResult
        show_fluoro : bool
            Add a frame volume node for each view that ``frame_nodes`` does not give.
        model : FevarPlannerLib.cache.PreopModel, optional
            Gives the centrelines their ``Radius``.
        frame_nodes : dict, optional
            View name -> a loaded frame node to draw that view's overlays on.
        case : FevarPlannerLib.io.Case, optional
            The planned case: its views give the further views' frames
            (:meth:`~FevarPlannerLib.pipeline.PlanResult.view_drawings`); without it only the
            first view is drawn.

        Each drawn view's frame carries its 2D skeleton and the pre-operative tree, the
        recovered tree and the path projected through its own ``P`` (roles ``overlay_*``,
        with ``:<view>`` for views after the first), shown in the frame view only; the first
        view is put there (:func:`show_view` shows another).
        """
        scene = self.scene
        remove_result_nodes(scene)
        radius = lumen_radii(model.lumen, result.preop.points) if model is not None and model.lumen is not None \
            else None
        nodes = {
            "preop": centerline_to_model_node(scene, result.preop, "FevarPlanner pre-operative centreline", "preop",
                                              radius),
            "deformed": centerline_to_model_node(scene, result.deformed,
                                                 f"FevarPlanner recovered centreline ({result.method})", "deformed",
                                                 radius),
            "path": path_to_curve_node(scene, result.path),
        }
        frame_nodes = frame_nodes or {}
        for drawing in result.view_drawings(case):
            frame_node = frame_nodes.get(drawing.name)
            if frame_node is None and show_fluoro:
                role = _view_role("fluoro", drawing.name)
                frame_node = nodes[role] = fluoro_to_volume_node(scene, drawing.image, _view_title("fluoroscopy",
                                                                                                    drawing.name))
                _tag(frame_node, role, frame_node.GetName())
                frame_node.SetAttribute(VIEW_ATTRIBUTE, drawing.name)
            if frame_node is not None:
                nodes.update(self._frame_overlays(result, drawing, frame_node))
        views = result_views(scene)
        if views:
            show_view(scene, views[0])
        return nodes

    def _frame_overlays(self, result, drawing, frame_node) -> dict:
        """One view's overlay model nodes on ``frame_node``, projected through the view's own ``P`` (eq. 1)."""
        from FevarPlannerLib.projection import project

        scene = self.scene
        view, _ = frame_view_nodes(scene)
        path_edges = np.column_stack([np.arange(len(result.path.points) - 1), np.arange(1, len(result.path.points))])
        layers = (("overlay_skeleton2d", "2D skeleton", drawing.skeleton_points, drawing.skeleton_edges),
                  ("overlay_preop", "pre-operative, projected", project(drawing.P, result.preop.points),
                   result.preop.edges),
                  ("overlay_deformed", "recovered, projected", project(drawing.P, result.deformed.points),
                   result.deformed.edges),
                  ("overlay_path", "catheter path, projected", project(drawing.P, result.path.points), path_edges))
        overlays = {}
        for role, name, uv, edges in layers:
            node = overlay_to_model_node(scene, frame_node, uv, edges, _view_title(name, drawing.name),
                                         _view_role(role, drawing.name), view)
            node.SetAttribute(VIEW_ATTRIBUTE, drawing.name)
            node.SetNodeReferenceID(FRAME_REFERENCE, frame_node.GetID())
            overlays[_view_role(role, drawing.name)] = node
        return overlays

    def show_view(self, name: str, parameters=None):
        """Show view ``name`` in the frame view (:func:`show_view`) and keep it in the parameter node."""
        slice_node = show_view(self.scene, name)
        (parameters or self.getParameterNode()).shownView = name
        return slice_node


def _view_title(text: str, view: str) -> str:
    """A node name: ``FevarPlanner <text>``, with the view's name for views after the first."""
    return f"FevarPlanner {text}" if view == MAIN_VIEW_NAME else f"FevarPlanner {text} ({view})"


def extra_views(parameters) -> list:
    """The further views of a parameter node: ``(frame node, geometry file, XA file)`` per view.

    Raises
    ------
    InputError
        The three lists differ in length, a frame node is missing, or two views share a name
        (or one is called ``main``, the first view's name).
    """
    from FevarPlannerLib.io import InputError

    frames, geometries, files = (list(parameters.extraFrameVolumes), list(parameters.extraGeometryFiles),
                                 list(parameters.extraFluoroFiles))
    if not len(frames) == len(geometries) == len(files):
        raise InputError(f"further views: {len(frames)} frame nodes (extraFrameVolumes), {len(geometries)} "
                         f"geometry files (extraGeometryFiles) and {len(files)} XA files (extraFluoroFiles); "
                         "give one of each per view ('' for none)")
    names = [MAIN_VIEW_NAME]
    for index, node in enumerate(frames):
        if node is None:
            raise InputError(f"further view {index + 1}: its frame node (extraFrameVolumes) is missing from the scene")
        if node.GetName() in names:
            raise InputError(f"further view {index + 1}: frame node {node.GetName()!r} has the name of another "
                             f"view ({', '.join(names)}); rename it, its name names the view")
        names.append(node.GetName())
    return list(zip(frames, geometries, files))


def add_extra_view(parameters, frame_node, geometry_file: str = "", fluoro_file: str = "") -> None:
    """Append a further view to the parameter node: its frame node, geometry.json and/or XA file."""
    if frame_node is None:
        raise ValueError("a further view needs its frame node")
    parameters.extraFrameVolumes = [*parameters.extraFrameVolumes, frame_node]
    parameters.extraGeometryFiles = [*parameters.extraGeometryFiles, str(geometry_file or "")]
    parameters.extraFluoroFiles = [*parameters.extraFluoroFiles, str(fluoro_file or "")]


def remove_extra_view(parameters, index: int) -> None:
    """Drop further view ``index`` (0 = the first after ``main``) from the parameter node."""
    for field in ("extraFrameVolumes", "extraGeometryFiles", "extraFluoroFiles"):
        values = list(getattr(parameters, field))
        if 0 <= index < len(values):
            del values[index]
        setattr(parameters, field, values)


def _frame_view(name: str, frame_node, fluoro_file: str, geometry_file: str, reference):
    """One view (:class:`FevarPlannerLib.io.View`) from a frame node and/or an XA file, with its ``P``.

    The image comes from ``frame_node`` when given, else from ``fluoro_file``; ``P`` from
    ``geometry_file`` (geometry.json) or the XA file's C-arm tags, the isocentre at the
    centre of ``reference`` (:func:`FevarPlannerLib.io.projection_for_frame`: a case
    folder's rules).
    """
    from FevarPlannerLib.io import Fluoro, InputError, View, projection_for_frame, read_fluoro

    tagged = read_fluoro(fluoro_file) if fluoro_file else None
    if frame_node is not None:
        image = node_to_volume(frame_node).array[0].astype(np.float32)
        fluoro = Fluoro(image, None, tagged.carm if tagged is not None else None,
                        Path(fluoro_file) if tagged is not None else Path(frame_node.GetName()),
                        missing_tags=tagged.missing_tags if tagged is not None else ("all C-arm tags",))
    elif tagged is not None:
        fluoro = tagged
    else:
        raise InputError(f"view {name}: no frame node and no XA file")
    P, source = projection_for_frame(fluoro, reference, geometry_file or None)
    paths = {key: Path(value) for key, value in (("fluoro", fluoro_file), ("geometry", geometry_file)) if value}
    return View(name, fluoro, None, P, paths, source)


def _distance_to_label(centerline: Centerline, point_lps: np.ndarray, label: str) -> float:
    """Distance (mm) from a point to the nearest node of ``centerline`` carrying ``label``."""
    nodes = centerline.points[np.asarray(centerline.labels) == label]
    return float(np.linalg.norm(nodes - point_lps, axis=1).min()) if len(nodes) else float("inf")


def _phantom_folder(work_dir, seed: int, mask_only: bool = True) -> Path:
    from FevarPlannerLib import phantom

    return phantom.write_phantom_set(Path(work_dir) / "phantom", n=1, seed=seed, preset="random",
                                     mask_only=mask_only)[0]


def _path_check(folder: Path, result, curve) -> dict:
    """Where the path curve's ends lie against the ground truth (see :func:`run_phantom_check`)."""
    import json

    ras = np.array([curve.GetNthControlPointPositionWorld(i) for i in range(curve.GetNumberOfControlPoints())])
    truth = Centerline.from_dict(json.loads((folder / "gt.json").read_text())["intraop_centerline"])
    aorta = truth.points[np.asarray(truth.labels) == "aorta"]
    start, end = ras_to_lps(ras[0]), ras_to_lps(ras[-1])
    return {"result": result, "path_ras": ras,
            "start_right_of_aorta_mm": float(aorta[:, 0].mean() - start[0]),
            "start_below_aorta_mm": float(aorta[:, 2].min() - start[2]),
            "end_mm": _distance_to_label(truth, end, "renal_left")}


def run_phantom_check(scene, work_dir, *, seed: int = 0, mask_only: bool = True) -> dict:
    """Generate one phantom case, run it through :class:`FevarPlannerLogic` on ``scene``, measure.

    Used by the Slicer self-test and the pytest suite alike. The path is planned from the
    right iliac to the left renal artery. Returns numbers to assert on: node counts by MRML
    class, the path's control points read back from the curve node (RAS), and where its
    ends lie against the ground-truth intra-operative centreline (LPS mm):
    ``start_right_of_aorta_mm`` (aorta's mean x minus the start's x: positive on the
    patient's right), ``start_below_aorta_mm`` (lowest aorta node's z minus the start's z:
    positive below the bifurcation) and ``end_mm`` (distance from the end to the left renal
    artery). ``mask_only`` skips writing the CT series and the DICOM frame, which the
    planner does not read when the aorta mask is there.
    """
    folder = _phantom_folder(work_dir, seed, mask_only)
    result, nodes = FevarPlannerLogic(scene).run(folder, start="iliac_right", target="renal_left")
    check = _path_check(folder, result, nodes["path"])
    check.update({"nodes": nodes,
                  "models": scene.GetNumberOfNodesByClass("vtkMRMLModelNode"),
                  "curves": scene.GetNumberOfNodesByClass("vtkMRMLMarkupsCurveNode"),
                  "volumes": scene.GetNumberOfNodesByClass("vtkMRMLScalarVolumeNode")})
    return check


def _two_view_folder(work_dir, seed: int) -> Path:
    """A two-view case of the independent scenario family (AP and a second C-arm angle), masks only."""
    from FevarPlannerLib import scenarios

    scenario = scenarios.plan_scenarios("two_views", 1, seed=seed)[0]
    return scenarios.write_scenario(scenario, Path(work_dir) / "two_views")


def _loaded_frame_node(scene, mask_png: Path, name: str):
    """A frame volume node as a user would load it, drawn from a vessel mask (dark vessels on grey)."""
    from FevarPlannerLib import io

    node = fluoro_to_volume_node(scene, np.where(io.read_mask_2d(mask_png), 0.25, 0.75), name=name)
    node.RemoveAttribute(ROLE_ATTRIBUTE)  # a loaded input, not a result
    return node


def run_node_check(scene, work_dir, *, seed: int = 0, two_views: bool = False) -> dict:
    """The Slicer route on a phantom: inputs as loaded nodes, through the parameter node.

    The phantom's lumen mask stands in for a CT (lumen 300 HU in soft tissue), its vessel
    mask for the frame, its geometry.json for ``P``. A CT view ("Red") shows the CT before
    the run. With ``two_views`` the case is a two-view scenario (:mod:`FevarPlannerLib.scenarios`)
    and its second view is a further frame node, named after the view, with its own
    geometry.json. Returns :func:`run_phantom_check`'s path numbers plus the parameter
    node, the nodes and the CT view's composite node.
    """
    from FevarPlannerLib import io

    folder = _two_view_folder(work_dir, seed) if two_views else _phantom_folder(work_dir, seed)
    mask = io.read_mask(folder / "aorta_mask.nrrd")
    ct_node = volume_to_node(scene, mask.with_array(np.where(mask.array, 300.0, 40.0).astype(np.float32)), "CT")
    frame_node = _loaded_frame_node(scene, folder / "fluoro_mask.png", "XA frame")
    red = scene.AddNewNodeByClass("vtkMRMLSliceCompositeNode")
    red.SetLayoutName("Red")
    red.SetBackgroundVolumeID(ct_node.GetID())
    logic = FevarPlannerLogic(scene)
    parameters = logic.getParameterNode()
    parameters.ctVolume, parameters.fluoroVolume = ct_node, frame_node
    parameters.aortaSegmentation = mask_to_segmentation_node(scene, mask, ct_node)
    parameters.geometryFile = str(folder / "geometry.json")
    view_folders = sorted(path for path in (folder / "views").iterdir()) if two_views else []
    for view_folder in view_folders:
        add_extra_view(parameters, _loaded_frame_node(scene, view_folder / "fluoro_mask.png", view_folder.name),
                       str(view_folder / "geometry.json"))
    result, nodes = logic.process(parameters)
    check = _path_check(folder, result, nodes["path"])
    check.update({"parameters": parameters, "nodes": nodes, "ct_view": red, "folder": folder, "mask": mask,
                  "view_folders": view_folders})
    return check


#: The layout with the frame's own view beside the 3D view and the CT's axial view.
FRAME_LAYOUT_ID = 50412
FRAME_LAYOUT_XML = f"""
<layout type="horizontal" split="true">
 <item><view class="vtkMRMLViewNode" singletontag="1"><property name="viewlabel" action="default">1</property></view></item>
 <item><layout type="vertical">
  <item><view class="vtkMRMLSliceNode" singletontag="Red">
   <property name="orientation" action="default">Axial</property>
   <property name="viewlabel" action="default">R</property>
   <property name="viewcolor" action="default">#F34A33</property></view></item>
  <item><view class="vtkMRMLSliceNode" singletontag="{FRAME_VIEW}">
   <property name="orientation" action="default">Axial</property>
   <property name="viewlabel" action="default">XA</property>
   <property name="viewcolor" action="default">#1AC0CF</property></view></item>
 </layout></item>
</layout>"""


if SLICER_APPLICATION:

    class FevarPlanner(ScriptedLoadableModule):
        """Module description shown in Slicer's module list and help panel."""

        def __init__(self, parent):
            ScriptedLoadableModule.__init__(self, parent)
            self.parent.title = "FEVAR Planner"
            self.parent.categories = ["Vascular"]
            self.parent.dependencies = ["Markups", "Segmentations"]
            self.parent.contributors = ["FevarPlanner developers"]
            self.parent.helpText = (
                "Recovers the intra-operative 3D shape of an abdominal aortic aneurysm from the "
                "pre-operative CT and one fluoroscopic frame, and plans a catheter path from the "
                "femoral access to a renal ostium for fenestrated endovascular aortic repair "
                "(Zheng, Zhou, Riga and Yang, ICRA 2019). Choose the CT volume (e.g. from the DICOM "
                "module), optionally an aorta segmentation (edit it in Segment Editor: the next run "
                "uses it), the frame as a volume and its geometry (geometry.json or the XA file with "
                "C-arm tags), or a case folder, and press Plan path. Further frames of the same "
                "anatomy at other C-arm angles (Further views, or views/&lt;name&gt;/ in a case "
                "folder) are registered together with it. The frame appears in its own view (XA) "
                "with the projected tree; Frame shown picks the view; the CT keeps its views.<br><br><b>"
                + RESEARCH_USE_STATEMENT + "</b>")
            self.parent.acknowledgementText = (
                "Implements J.-Q. Zheng, X.-Y. Zhou, C. Riga and G.-Z. Yang, 'Towards 3D Path "
                "Planning from a Single 2D Fluoroscopic Image for Robot Assisted Fenestrated "
                "Endovascular Aortic Repair', ICRA 2019. Built on the Slicer scripted module "
                "template by Jean-Christophe Fillion-Robin (Kitware) and Steve Pieper (Isomics).")

    if parameterNodeWrapper is not None:
        # built from FevarPlannerParameters' fields, with real types (this file postpones annotations)
        FevarPlannerParameterNode = parameterNodeWrapper(type("FevarPlannerParameterNode", (), {
            "__doc__": "The fields of FevarPlannerParameters on the same node, typed and validated by Slicer.",
            "__annotations__": {**{field: getattr(slicer, node_class)
                                   for field, node_class in FevarPlannerParameters.NODE_FIELDS.items()},
                                **{field: str for field in FevarPlannerParameters.VALUE_FIELDS},
                                **{field: list[getattr(slicer, node_class)]
                                   for field, node_class in FevarPlannerParameters.NODE_LIST_FIELDS.items()},
                                **{field: list[str] for field in FevarPlannerParameters.VALUE_LIST_FIELDS}},
            **FevarPlannerParameters.VALUE_FIELDS}))

    class FevarPlannerWidget(ScriptedLoadableModuleWidget, slicer.util.VTKObservationMixin):
        """The shared .ui panel plus node selectors; every computation goes through :class:`FevarPlannerLogic`."""

        OVERRIDES = ("ct", "aortaMask", "skeleton3d", "fluoro", "fluoroMask", "geometry")
        DISPLAY = {"showPreopCheckBox": "preop", "showDeformedCheckBox": "deformed", "showPathCheckBox": "path"}
        SELECTORS = {"ctVolume": "CT volume:", "aortaSegmentation": "Aorta segmentation:", "fluoroVolume": "Frame (XA):"}

        def __init__(self, parent=None):
            ScriptedLoadableModuleWidget.__init__(self, parent)
            slicer.util.VTKObservationMixin.__init__(self)
            self.logic = None
            self.parameters = None
            self.nodes = {}

        def setup(self):
            ScriptedLoadableModuleWidget.setup(self)
            self.logic = FevarPlannerLogic()
            self.layout.addWidget(self._scene_inputs())
            panel = slicer.util.loadUI(str(module_resource_path("UI/FevarPlanner.ui")))
            self.layout.addWidget(panel)
            self.ui = slicer.util.childWidgetVariables(panel)
            self.ui.showSurfaceCheckBox.visible = False  # the aorta is a segmentation node here
            self.ui.caseDirBrowseButton.connect("clicked()", lambda: self._browse_folder(self.ui.caseDirLineEdit))
            self.ui.outputDirBrowseButton.connect("clicked()", lambda: self._browse_folder(self.ui.outputDirLineEdit))
            for key in self.OVERRIDES:
                line_edit = getattr(self.ui, f"{key}LineEdit")
                getattr(self.ui, f"{key}BrowseButton").connect(
                    "clicked()", lambda edit=line_edit: self._browse_file(edit))
            self.ui.caseDirLineEdit.connect("textChanged(QString)", self._update_run_button)
            self.ui.runButton.connect("clicked()", self.onRunButton)
            for box in self.DISPLAY:
                getattr(self.ui, box).connect("toggled(bool)", self._update_visibility)
            self.ui.viewComboBox.connect("currentIndexChanged(int)", self._on_view_chosen)
            self._view_names = []
            for combo, field in (("methodComboBox", "method"), ("startComboBox", "start"),
                                 ("targetComboBox", "target")):
                getattr(self.ui, combo).connect("currentTextChanged(QString)",
                                                lambda text, name=field: self._set_parameter(name, text))
            self.layout.addStretch(1)
            self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
            self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
            self.initializeParameterNode()

        def _scene_inputs(self):
            """Node selectors for the inputs loaded in the scene (the Slicer route)."""
            box = qt.QGroupBox("Inputs from the scene")
            form = qt.QFormLayout(box)
            self.selectors = {}
            for field, label in self.SELECTORS.items():
                selector = slicer.qMRMLNodeComboBox()
                selector.nodeTypes = [FevarPlannerParameters.NODE_FIELDS[field]]
                selector.noneEnabled = field == "aortaSegmentation"
                selector.addEnabled = selector.removeEnabled = False
                selector.setMRMLScene(slicer.mrmlScene)
                selector.connect("currentNodeChanged(vtkMRMLNode*)",
                                 lambda node, name=field: self._set_parameter(name, node))
                form.addRow(label, selector)
                self.selectors[field] = selector
            self.geometryPathLineEdit = ctk.ctkPathLineEdit()
            self.geometryPathLineEdit.connect("currentPathChanged(QString)",
                                              lambda path: self._set_parameter("geometryFile", path))
            form.addRow("Geometry (geometry.json):", self.geometryPathLineEdit)
            self.fluoroFileLineEdit = ctk.ctkPathLineEdit()
            self.fluoroFileLineEdit.connect("currentPathChanged(QString)",
                                            lambda path: self._set_parameter("fluoroFile", path))
            form.addRow("or XA file (C-arm tags):", self.fluoroFileLineEdit)
            form.addRow(self._further_views())
            self.planNodesButton = qt.QPushButton("Plan path from these nodes")
            self.planNodesButton.connect("clicked()", self.onPlanNodesButton)
            form.addRow(self.planNodesButton)
            return box

        def _further_views(self):
            """Further frames of the same anatomy at other C-arm angles, each with its own geometry."""
            box = qt.QGroupBox("Further views (other C-arm angles)")
            box.toolTip = ("Frames taken while the wire stays in, at other C-arm angles (e.g. LAO 30): all views "
                           "are registered together, which fixes the depth one view cannot see. Each view is "
                           "named after its frame node.")
            form = qt.QFormLayout(box)
            self.extraFrameSelector = slicer.qMRMLNodeComboBox()
            self.extraFrameSelector.nodeTypes = [FevarPlannerParameters.NODE_LIST_FIELDS["extraFrameVolumes"]]
            self.extraFrameSelector.noneEnabled = True
            self.extraFrameSelector.addEnabled = self.extraFrameSelector.removeEnabled = False
            self.extraFrameSelector.setMRMLScene(slicer.mrmlScene)
            form.addRow("Frame (XA):", self.extraFrameSelector)
            self.extraGeometryLineEdit = ctk.ctkPathLineEdit()
            form.addRow("Geometry (geometry.json):", self.extraGeometryLineEdit)
            self.extraFluoroLineEdit = ctk.ctkPathLineEdit()
            form.addRow("or XA file (C-arm tags):", self.extraFluoroLineEdit)
            buttons = qt.QHBoxLayout()
            self.addViewButton = qt.QPushButton("Add view")
            self.addViewButton.connect("clicked()", self.onAddViewButton)
            self.removeViewButton = qt.QPushButton("Remove selected")
            self.removeViewButton.connect("clicked()", self.onRemoveViewButton)
            buttons.addWidget(self.addViewButton)
            buttons.addWidget(self.removeViewButton)
            form.addRow(buttons)
            self.extraViewsList = qt.QListWidget()
            self.extraViewsList.maximumHeight = 80
            form.addRow(self.extraViewsList)
            return box

        def onAddViewButton(self):  # noqa: N802
            node = self.extraFrameSelector.currentNode()
            if node is None or self.parameters is None:
                return
            add_extra_view(self.parameters, node, self.extraGeometryLineEdit.currentPath,
                           self.extraFluoroLineEdit.currentPath)
            self._parameters_to_gui()

        def onRemoveViewButton(self):  # noqa: N802
            if self.parameters is not None and self.extraViewsList.currentRow >= 0:
                remove_extra_view(self.parameters, self.extraViewsList.currentRow)
                self._parameters_to_gui()

        # ---------------------------------------------------------------- parameter node
        def initializeParameterNode(self):  # noqa: N802  (Slicer naming)
            """Take the scene's parameter node (through parameterNodeWrapper where Slicer has it) and show it."""
            node = self.logic.getParameterNode().node
            wrapped = parameterNodeWrapper is not None
            self.parameters = FevarPlannerParameterNode(node) if wrapped else FevarPlannerParameters(node)
            if self.parameters.ctVolume is None:
                first = slicer.mrmlScene.GetFirstNodeByClass("vtkMRMLScalarVolumeNode")
                if first is not None:
                    self.parameters.ctVolume = first
            self._parameters_to_gui()
            self._fill_views()

        def _parameters_to_gui(self):
            for field, selector in self.selectors.items():
                selector.setCurrentNode(getattr(self.parameters, field))
            self.geometryPathLineEdit.currentPath = self.parameters.geometryFile
            self.fluoroFileLineEdit.currentPath = self.parameters.fluoroFile
            self.extraViewsList.clear()
            for node, geometry, fluoro_file in zip(self.parameters.extraFrameVolumes,
                                                   self.parameters.extraGeometryFiles,
                                                   self.parameters.extraFluoroFiles):
                source = Path(geometry).name if geometry else (Path(fluoro_file).name + " (C-arm tags)"
                                                               if fluoro_file else "no geometry")
                self.extraViewsList.addItem(f"{node.GetName() if node is not None else '(missing node)'}: {source}")
            for combo, field in (("methodComboBox", "method"), ("startComboBox", "start"),
                                 ("targetComboBox", "target")):
                getattr(self.ui, combo).currentText = getattr(self.parameters, field)

        def _set_parameter(self, name, value):
            if self.parameters is not None:
                setattr(self.parameters, name, value)

        def enter(self):
            """Module shown: (re)read the parameter node."""
            self.initializeParameterNode()

        def exit(self):
            """Module hidden: nothing runs in the background, so nothing to stop."""

        def onSceneStartClose(self, caller, event):  # noqa: N802
            self.parameters = None
            self.nodes = {}

        def onSceneEndClose(self, caller, event):  # noqa: N802
            if self.parent.isEntered:
                self.initializeParameterNode()

        def cleanup(self):
            """Module reloaded or Slicer closing: drop the scene observers."""
            self.removeObservers()

        # ---------------------------------------------------------------- helpers
        def _browse_folder(self, line_edit):
            folder = qt.QFileDialog.getExistingDirectory(self.parent, "Choose a folder", line_edit.text)
            if folder:
                line_edit.text = folder

        def _browse_file(self, line_edit):
            path = qt.QFileDialog.getOpenFileName(self.parent, "Choose an input file", line_edit.text)
            if path:
                line_edit.text = path

        def _update_run_button(self, *_):
            self.ui.runButton.enabled = os.path.isdir(self.ui.caseDirLineEdit.text.strip())

        def _overrides(self) -> dict:
            if not self.ui.overridesGroupBox.checked:
                return {}
            names = {"aortaMask": "aorta_mask", "fluoroMask": "fluoro_mask"}
            return {names.get(key, key): getattr(self.ui, f"{key}LineEdit").text.strip() for key in self.OVERRIDES}

        def _progress(self, fraction: float, message: str) -> None:
            self.ui.progressBar.value = int(round(100 * fraction))
            self.ui.statusLabel.text = message
            slicer.app.processEvents()

        def _update_visibility(self, *_):
            for box, role in self.DISPLAY.items():
                node = self.nodes.get(role)
                if node is not None and node.GetDisplayNode() is not None:
                    node.GetDisplayNode().SetVisibility(getattr(self.ui, box).checked)

        def _fill_table(self, result) -> None:
            rows = summary_rows(result)
            table = self.ui.resultsTableWidget
            table.setRowCount(len(rows))
            for row, (quantity, value) in enumerate(rows):
                table.setItem(row, 0, qt.QTableWidgetItem(quantity))
                table.setItem(row, 1, qt.QTableWidgetItem(value))
            table.resizeColumnToContents(0)

        def _ensure_requirements(self) -> bool:
            missing = missing_requirements()
            if not missing:
                return True
            if not slicer.util.confirmOkCancelDisplay(
                    f"FevarPlanner needs these Python packages: {', '.join(missing)}. Install them now?"):
                return False
            slicer.util.pip_install(" ".join(missing))
            return not missing_requirements()

        def _fill_views(self, result=None) -> None:
            """The view selector: one entry per view drawn in the scene (with its 2D fit when
            ``result`` is given), the parameter node's ``shownView`` selected, enabled for several."""
            fits = {view["name"]: view.get("2d_px") for view in result.views} if result is not None else {}
            self._view_names = result_views(slicer.mrmlScene)
            combo = self.ui.viewComboBox
            combo.blockSignals(True)
            combo.clear()
            for name in self._view_names:
                fit = fits.get(name)
                combo.addItem(f"{name}  (2D fit {fit['mean']:.2f} px)" if fit else name)
            shown = self.parameters.shownView if self.parameters is not None else MAIN_VIEW_NAME
            combo.currentIndex = self._view_names.index(shown) if shown in self._view_names else 0
            combo.blockSignals(False)
            combo.enabled = len(self._view_names) > 1

        def _on_view_chosen(self, index):
            if 0 <= index < len(self._view_names):
                self.logic.show_view(self._view_names[index], self.parameters)
                frame = slicer.app.layoutManager().sliceWidget(FRAME_VIEW)
                if frame is not None:
                    frame.sliceLogic().FitSliceToAll()

        def _show(self, result) -> None:
            """Table, views, visibility, the frame layout (frame in its own view; the CT keeps Red) and the status."""
            self._fill_table(result)
            self._fill_views(result)
            self._update_visibility()
            layout_node = slicer.app.layoutManager().layoutLogic().GetLayoutNode()
            if not layout_node.IsLayoutDescription(FRAME_LAYOUT_ID):
                layout_node.AddLayoutDescription(FRAME_LAYOUT_ID, FRAME_LAYOUT_XML)
            layout_node.SetViewArrangement(FRAME_LAYOUT_ID)
            frame = slicer.app.layoutManager().sliceWidget(FRAME_VIEW)
            if frame is not None:
                frame.sliceLogic().FitSliceToAll()
            slicer.util.resetThreeDViews()
            views = f"; {len(result.views)} views ({', '.join(v['name'] for v in result.views)})" \
                if len(result.views) > 1 else ""
            self.ui.statusLabel.text = (f"{result.path.start_label} → {result.path.target_label}: "
                                        f"{result.path.length_mm:.1f} mm in {result.timings['total']:.2f} s{views}")

        def onPlanNodesButton(self):  # noqa: N802
            if not self._ensure_requirements():
                return
            with slicer.util.tryWithErrorDisplay("FevarPlanner could not plan from these nodes.", waitCursor=True):
                result, self.nodes = self.logic.process(self.parameters, progress=self._progress)
                self._parameters_to_gui()
                self._show(result)

        def onRunButton(self):
            if not self._ensure_requirements():
                return
            self.ui.runButton.enabled = False
            try:
                with slicer.util.tryWithErrorDisplay("FevarPlanner could not plan this case.", waitCursor=True):
                    result, self.nodes = self.logic.run(
                        self.ui.caseDirLineEdit.text.strip(), method=self.ui.methodComboBox.currentText,
                        start=self.ui.startComboBox.currentText, target=self.ui.targetComboBox.currentText,
                        out_dir=self.ui.outputDirLineEdit.text.strip() or None, overrides=self._overrides(),
                        progress=self._progress)
                    self._show(result)
            finally:
                self._update_run_button()

    class FevarPlannerTest(ScriptedLoadableModuleTest):
        """Self-test: phantom cases through both routes of the logic, with numbers checked."""

        def setUp(self):
            slicer.mrmlScene.Clear(0)

        def runTest(self):
            self.setUp()
            self.test_lps_to_ras()
            self.setUp()
            self.test_phantom_case()
            self.setUp()
            self.test_nodes_route()
            self.setUp()
            self.test_two_view_nodes_route()

        def test_lps_to_ras(self):
            self.assertEqual(lps_to_ras([10.0, 20.0, 30.0]).tolist(), [-10.0, -20.0, 30.0])
            self.assertEqual(ras_to_lps(lps_to_ras([1.5, -2.0, 3.0])).tolist(), [1.5, -2.0, 3.0])

        def _assert_path(self, check):
            self.assertGreaterEqual(len(check["path_ras"]), 10)
            self.assertGreater(check["start_right_of_aorta_mm"], 5.0)
            self.assertGreater(check["start_below_aorta_mm"], 20.0)
            self.assertLess(check["end_mm"], 10.0)
            expected = lps_to_ras(check["result"].path.points)
            self.assertLess(float(np.abs(check["path_ras"] - expected).max()), 1e-6)

        def test_phantom_case(self):
            self.delayDisplay("Planning a phantom case folder")
            with tempfile.TemporaryDirectory() as work_dir:
                check = run_phantom_check(slicer.mrmlScene, work_dir)
            self.assertEqual(check["curves"], 1)
            self.assertEqual(check["volumes"], 1)
            self._assert_path(check)
            logging.info("FevarPlanner self-test: path %.1f mm", check["result"].path.length_mm)

        def test_nodes_route(self):
            self.delayDisplay("Planning from loaded nodes")
            with tempfile.TemporaryDirectory() as work_dir:
                check = run_node_check(slicer.mrmlScene, work_dir)
            self._assert_path(check)
            self.assertEqual(check["ct_view"].GetBackgroundVolumeID(), check["parameters"].ctVolume.GetID())
            curve = check["nodes"]["path"]
            self.assertTrue(curve.GetLocked())
            self.assertAlmostEqual(curve.GetCurveLengthWorld(), check["result"].path.length_mm, places=3)
            self.delayDisplay("Test passed")

        def test_two_view_nodes_route(self):
            self.delayDisplay("Planning from two frame nodes at different C-arm angles")
            with tempfile.TemporaryDirectory() as work_dir:
                check = run_node_check(slicer.mrmlScene, work_dir, two_views=True)
            self._assert_path(check)
            second = check["view_folders"][0].name
            self.assertEqual([view["name"] for view in check["result"].views], ["main", second])
            self.assertEqual(result_views(slicer.mrmlScene), ["main", second])
            frame_view, composite = frame_view_nodes(slicer.mrmlScene)
            show_view(slicer.mrmlScene, second)
            self.assertEqual(composite.GetBackgroundVolumeID(), check["parameters"].extraFrameVolumes[0].GetID())
            self.assertFalse(check["nodes"]["overlay_deformed"].GetDisplayNode().GetVisibility())
            self.assertTrue(check["nodes"][f"overlay_deformed:{second}"].GetDisplayNode().GetVisibility())
            self.delayDisplay("Test passed")

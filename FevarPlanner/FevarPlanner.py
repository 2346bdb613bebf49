"""FevarPlanner: the 3D Slicer scripted module.

The only file of the project that imports ``slicer`` (and, inside the Slicer application,
``qt``). It is a thin adapter around the pure core:

* module-level functions turn a :class:`FevarPlannerLib.pipeline.PlanResult` into MRML
  nodes (centrelines as model nodes, the catheter path as a markups curve, the frame as a
  scalar volume). They need nothing but the MRML classes, so they run under the
  ``slicer-core`` wheel (pip) as well as in Slicer, and the pytest suite checks them there;
* :class:`FevarPlannerLogic` runs :func:`FevarPlannerLib.pipeline.plan_case` (the same entry
  point as the CLI and the workstation) and adds the result to a scene;
* inside the Slicer application only: the module description, the widget (the shared
  ``Resources/UI/FevarPlanner.ui`` panel) and the self-test.

Coordinates: the core works in DICOM LPS millimetres; Slicer's scene is RAS. The conversion
``RAS = (-x, -y, z)`` happens here and nowhere else.
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

from FevarPlannerApp.summary import summary_rows
from FevarPlannerLib.centerline import Centerline

try:
    from slicer.ScriptedLoadableModule import (ScriptedLoadableModule, ScriptedLoadableModuleLogic,
                                               ScriptedLoadableModuleTest, ScriptedLoadableModuleWidget)
    import qt

    SLICER_APPLICATION = True
except ImportError:
    # slicer-core (pip) outside the Slicer application: MRML classes only. The logic then
    # works on a scene it is given; the module, widget and self-test classes need the
    # application and are not defined.
    ScriptedLoadableModuleLogic = object
    SLICER_APPLICATION = False

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
    "volume_to_node",
    "node_to_volume",
    "mask_to_segmentation_node",
    "segmentation_node_to_mask",
    "result_nodes",
    "remove_result_nodes",
    "FevarPlannerLogic",
    "run_phantom_check",
]

#: Node attribute naming what a node shows; nodes carrying it belong to this module.
ROLE_ATTRIBUTE = "FevarPlanner.role"

#: Display colour (RGB 0..1) and line width per role; the same colours as the overlay PNG.
STYLE = {
    "preop": ((1.0, 0.50, 0.05), 2.0),
    "deformed": ((0.09, 0.75, 0.81), 3.0),
    "path": ((0.20, 0.95, 0.20), 4.0),
}

LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])

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


def centerline_polydata_ras(centerline: Centerline) -> vtk.vtkPolyData:
    """The centreline as export's vtkPolyData (line per edge, label arrays) with RAS points.

    It carries no coordinate-system tag: a model node's data is RAS by definition, and
    Slicer's model storage converts it and writes its own ``SPACE`` tag when it saves it.
    """
    # imported here, not at the top: export pulls in the readers (pydicom, Pillow), which a
    # fresh Slicer may lack until the widget has offered to install them
    from FevarPlannerLib import export

    return export.centerline_to_polydata(centerline, space=None)


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


def centerline_to_model_node(scene, centerline: Centerline, name: str, role: str = "deformed"):
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
    """
    if role not in STYLE:
        raise ValueError(f"unknown display role {role!r}; expected one of {sorted(STYLE)}")
    node = scene.AddNewNodeByClass("vtkMRMLModelNode")
    _tag(node, role, name)
    node.SetAndObservePolyData(centerline_polydata_ras(centerline))
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
    data = vtk.vtkImageData()
    data.SetDimensions(image.shape[1], image.shape[0], 1)  # i = column (u), j = row (v)
    data.GetPointData().SetScalars(numpy_support.numpy_to_vtk(np.ascontiguousarray(image).ravel(), deep=True))
    node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode")
    _tag(node, "fluoro", name)
    node.SetIJKToRASDirections(-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0)
    node.SetAndObserveImageData(data)
    node.CreateDefaultDisplayNodes()
    return node


def result_nodes(scene) -> dict:
    """This module's nodes in ``scene`` by role (``preop``, ``deformed``, ``path``, ``fluoro``)."""
    nodes = {}
    for index in range(scene.GetNumberOfNodes()):
        node = scene.GetNthNode(index)
        role = node.GetAttribute(ROLE_ATTRIBUTE)
        if role:
            nodes[role] = node
    return nodes


def remove_result_nodes(scene) -> int:
    """Remove the nodes of an earlier run from ``scene``; returns how many were removed."""
    nodes = list(result_nodes(scene).values())
    for node in nodes:
        scene.RemoveNode(node)
    return len(nodes)


class FevarPlannerLogic(ScriptedLoadableModuleLogic):
    """Run a case through the core and show the result as MRML nodes.

    Usable without the widget, inside Slicer (``FevarPlannerLogic().run(case_dir)``) and
    outside it on any vtkMRMLScene (``FevarPlannerLogic(scene).run(case_dir)``).
    """

    def __init__(self, scene=None):
        if ScriptedLoadableModuleLogic is not object:
            ScriptedLoadableModuleLogic.__init__(self)
        self._scene = scene

    @property
    def scene(self):
        """The scene given to the constructor, else Slicer's ``slicer.mrmlScene``."""
        return self._scene if self._scene is not None else slicer.mrmlScene

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
            Also add the frame as a scalar volume.

        Returns
        -------
        (PlanResult, dict)
            The core's result and the nodes added, by role.
        """
        from FevarPlannerLib.pipeline import plan_case

        result = plan_case(case_dir, out_dir, method=method, progress=progress, start=start, target=target,
                           **{key: value for key, value in (overrides or {}).items() if value})
        return result, self.add_result(result, show_fluoro=show_fluoro)

    def add_result(self, result, *, show_fluoro: bool = True) -> dict:
        """Replace the nodes of an earlier run by this result's; returns the nodes by role."""
        scene = self.scene
        remove_result_nodes(scene)
        nodes = {
            "preop": centerline_to_model_node(scene, result.preop, "FevarPlanner pre-operative centreline", "preop"),
            "deformed": centerline_to_model_node(scene, result.deformed,
                                                 f"FevarPlanner deformed centreline ({result.method})", "deformed"),
            "path": path_to_curve_node(scene, result.path),
        }
        if show_fluoro:
            nodes["fluoro"] = fluoro_to_volume_node(scene, result.fluoro_image)
        return nodes


def _distance_to_label(centerline: Centerline, point_lps: np.ndarray, label: str) -> float:
    """Distance (mm) from a point to the nearest node of ``centerline`` carrying ``label``."""
    nodes = centerline.points[np.asarray(centerline.labels) == label]
    return float(np.linalg.norm(nodes - point_lps, axis=1).min()) if len(nodes) else float("inf")


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
    import json

    from FevarPlannerLib import phantom

    folder = phantom.write_phantom_set(Path(work_dir) / "phantom", n=1, seed=seed, preset="random",
                                        mask_only=mask_only)[0]
    logic = FevarPlannerLogic(scene)
    result, nodes = logic.run(folder, start="iliac_right", target="renal_left")
    curve = nodes["path"]
    ras = np.array([curve.GetNthControlPointPositionWorld(i) for i in range(curve.GetNumberOfControlPoints())])
    truth = Centerline.from_dict(json.loads((folder / "gt.json").read_text())["intraop_centerline"])
    aorta = truth.points[np.asarray(truth.labels) == "aorta"]
    start, end = ras_to_lps(ras[0]), ras_to_lps(ras[-1])
    return {
        "result": result,
        "models": scene.GetNumberOfNodesByClass("vtkMRMLModelNode"),
        "curves": scene.GetNumberOfNodesByClass("vtkMRMLMarkupsCurveNode"),
        "volumes": scene.GetNumberOfNodesByClass("vtkMRMLScalarVolumeNode"),
        "path_ras": ras,
        "start_right_of_aorta_mm": float(aorta[:, 0].mean() - start[0]),
        "start_below_aorta_mm": float(aorta[:, 2].min() - start[2]),
        "end_mm": _distance_to_label(truth, end, "renal_left"),
    }


if SLICER_APPLICATION:

    class FevarPlanner(ScriptedLoadableModule):
        """Module description shown in Slicer's module list and help panel."""

        def __init__(self, parent):
            ScriptedLoadableModule.__init__(self, parent)
            self.parent.title = "FEVAR Planner"
            self.parent.categories = ["Vascular"]
            self.parent.dependencies = ["Markups"]
            self.parent.contributors = ["FevarPlanner developers"]
            self.parent.helpText = (
                "Recovers the intra-operative 3D shape of an abdominal aortic aneurysm from the "
                "pre-operative CT and one fluoroscopic frame, and plans a catheter path from the "
                "femoral access to a renal ostium for fenestrated endovascular aortic repair "
                "(Zheng, Zhou, Riga and Yang, ICRA 2019). Choose a case folder (ct/ or ct.nrrd, "
                "fluoro.dcm or fluoro.png, optional masks and geometry.json) and press Plan path.")
            self.parent.acknowledgementText = (
                "Implements J.-Q. Zheng, X.-Y. Zhou, C. Riga and G.-Z. Yang, 'Towards 3D Path "
                "Planning from a Single 2D Fluoroscopic Image for Robot Assisted Fenestrated "
                "Endovascular Aortic Repair', ICRA 2019. Built on the Slicer scripted module "
                "template by Jean-Christophe Fillion-Robin (Kitware) and Steve Pieper (Isomics).")

    class FevarPlannerWidget(ScriptedLoadableModuleWidget):
        """The shared .ui panel; every computation goes through :class:`FevarPlannerLogic`."""

        OVERRIDES = ("ct", "aortaMask", "skeleton3d", "fluoro", "fluoroMask", "geometry")
        DISPLAY = {"showPreopCheckBox": "preop", "showDeformedCheckBox": "deformed", "showPathCheckBox": "path"}

        def setup(self):
            ScriptedLoadableModuleWidget.setup(self)
            panel = slicer.util.loadUI(str(module_resource_path("UI/FevarPlanner.ui")))
            self.layout.addWidget(panel)
            self.ui = slicer.util.childWidgetVariables(panel)
            self.logic = FevarPlannerLogic()
            self.nodes = {}
            self.ui.showSurfaceCheckBox.visible = False  # Slicer users load the segmentation themselves
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
            self.layout.addStretch(1)
            self._update_run_button()

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
                    self._fill_table(result)
                    self._update_visibility()
                    slicer.util.setSliceViewerLayers(background=self.nodes.get("fluoro"), fit=True)
                    slicer.util.resetThreeDViews()
                    self.ui.statusLabel.text = (f"{result.path.start_label} → {result.path.target_label}: "
                                                f"{result.path.length_mm:.1f} mm in {result.timings['total']:.2f} s")
            finally:
                self._update_run_button()

    class FevarPlannerTest(ScriptedLoadableModuleTest):
        """Self-test: a phantom case through the logic, with numbers checked."""

        def setUp(self):
            slicer.mrmlScene.Clear(0)

        def runTest(self):
            self.setUp()
            self.test_lps_to_ras()
            self.setUp()
            self.test_phantom_case()

        def test_lps_to_ras(self):
            self.assertEqual(lps_to_ras([10.0, 20.0, 30.0]).tolist(), [-10.0, -20.0, 30.0])
            self.assertEqual(ras_to_lps(lps_to_ras([1.5, -2.0, 3.0])).tolist(), [1.5, -2.0, 3.0])

        def test_phantom_case(self):
            self.delayDisplay("Planning a phantom case")
            with tempfile.TemporaryDirectory() as work_dir:
                check = run_phantom_check(slicer.mrmlScene, work_dir)
            self.assertEqual(check["models"], 2)
            self.assertEqual(check["curves"], 1)
            self.assertEqual(check["volumes"], 1)
            self.assertGreaterEqual(len(check["path_ras"]), 10)
            self.assertGreater(check["start_right_of_aorta_mm"], 5.0)
            self.assertGreater(check["start_below_aorta_mm"], 20.0)
            self.assertLess(check["end_mm"], 10.0)
            expected = lps_to_ras(check["result"].path.points)
            self.assertLess(float(np.abs(check["path_ras"] - expected).max()), 1e-6)
            logging.info("FevarPlanner self-test: path %.1f mm", check["result"].path.length_mm)
            self.delayDisplay("Test passed")

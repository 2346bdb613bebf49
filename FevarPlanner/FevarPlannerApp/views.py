"""The workstation's two VTK views: the 3D scene and the fluoroscopic frame.

Both are :class:`QVTKRenderWindowInteractor` widgets. The scene is rebuilt from a
:class:`FevarPlannerLib.pipeline.PlanResult` (plus an optional surface) by
:meth:`set_result`; layers are switched on and off by name with :meth:`set_layer_visible`.
A case with several views (``views/<name>/``) gives one
:class:`FevarPlannerLib.pipeline.ViewDrawing` per view
(:meth:`FevarPlannerLib.pipeline.PlanResult.view_drawings`); the 2D view draws one at a time.

Colours and names are the overlay PNG's (:data:`FevarPlannerLib.conventions.PALETTE` and
``FevarPlannerLib.export.ROLE_NAMES``): pre-operative orange, recovered cyan, catheter path green, 2D skeleton yellow.
"""

from __future__ import annotations

import numpy as np
import vtkmodules.qt

vtkmodules.qt.PyQtImpl = "PySide6"

import vtkmodules.vtkInteractionStyle  # noqa: E402,F401  (registers the interactor styles)
import vtkmodules.vtkRenderingFreeType  # noqa: E402,F401  (text rendering)
import vtkmodules.vtkRenderingOpenGL2  # noqa: E402,F401  (registers the OpenGL render window)
from vtkmodules.qt.QVTKRenderWindowInteractor import QVTKRenderWindowInteractor  # noqa: E402
from vtkmodules.util import numpy_support  # noqa: E402
from vtkmodules.vtkCommonCore import vtkPoints  # noqa: E402
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData  # noqa: E402
from vtkmodules.vtkFiltersSources import vtkSphereSource  # noqa: E402
from vtkmodules.vtkInteractionStyle import vtkInteractorStyleImage, vtkInteractorStyleTrackballCamera  # noqa: E402
from vtkmodules.vtkInteractionWidgets import vtkOrientationMarkerWidget  # noqa: E402
from vtkmodules.vtkRenderingAnnotation import vtkAnnotatedCubeActor  # noqa: E402
from vtkmodules.vtkRenderingCore import (vtkActor, vtkBillboardTextActor3D, vtkImageSlice,  # noqa: E402
                                         vtkImageSliceMapper, vtkRenderer, vtkTextActor,
                                         vtkWindowToImageFilter)

from FevarPlannerLib.conventions import PALETTE  # noqa: E402
from FevarPlannerLib.export import ROLE_NAMES, centerline_to_polydata, polydata_actor, tube_actor  # noqa: E402
from FevarPlannerLib.projection import project  # noqa: E402

__all__ = ["COLORS", "polyline_polydata", "segments_polydata", "View3D", "FluoroView", "render_to_array"]

#: RGB (0..1) of each layer, shared by both views and the legend.
COLORS = {**{layer: PALETTE[layer] for layer in ("preop", "deformed", "path", "skeleton2d", "surface")},
          "text": (0.90, 0.92, 0.95)}
BACKGROUND_TOP = (0.16, 0.18, 0.24)
BACKGROUND_BOTTOM = (0.05, 0.06, 0.08)


def polyline_polydata(points: np.ndarray) -> vtkPolyData:
    """One polyline through ``points`` (k, 2 or 3); 2D points get z = 0."""
    points = np.asarray(points, dtype=float)
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
    return segments_polydata(points, np.column_stack([np.arange(len(points) - 1), np.arange(1, len(points))]))


def segments_polydata(points: np.ndarray, edges: np.ndarray, z: float | None = None) -> vtkPolyData:
    """Line segments between ``points`` (n, 2 or 3) for each edge (m, 2); 2D points get z = ``z``."""
    points = np.asarray(points, dtype=float)
    if points.shape[1] == 2:
        points = np.column_stack([points, np.full(len(points), 0.0 if z is None else z)])
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    polydata = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(points), deep=True))
    polydata.SetPoints(vtk_points)
    lines = vtkCellArray()
    lines.SetData(numpy_support.numpy_to_vtkIdTypeArray(np.arange(0, 2 * len(edges) + 1, 2, dtype=np.int64), deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(np.ascontiguousarray(edges.ravel()), deep=True))
    polydata.SetLines(lines)
    return polydata


def _line_actor(polydata: vtkPolyData, color, width: float, opacity: float = 1.0) -> vtkActor:
    actor = polydata_actor(polydata, color, opacity)
    actor.GetProperty().SetLineWidth(width)
    actor.GetProperty().LightingOff()
    return actor


def _sphere_actor(center, radius: float, color) -> vtkActor:
    sphere = vtkSphereSource()
    sphere.SetCenter(*center)
    sphere.SetRadius(radius)
    sphere.SetThetaResolution(24)
    sphere.SetPhiResolution(24)
    return polydata_actor(sphere.GetOutputPort(), color)


def _text(text: str, color, size: int, bold: bool = False) -> vtkTextActor:
    actor = vtkTextActor()
    actor.SetInput(text)
    prop = actor.GetTextProperty()
    prop.SetColor(*color)
    prop.SetFontSize(size)
    prop.SetBold(bold)
    prop.SetShadow(True)
    return actor


def _label_3d(text: str, position, color) -> vtkBillboardTextActor3D:
    actor = vtkBillboardTextActor3D()
    actor.SetInput(text)
    actor.SetPosition(*position)
    actor.SetDisplayOffset(10, 6)
    prop = actor.GetTextProperty()
    prop.SetColor(*color)
    prop.SetFontSize(15)
    prop.SetBold(True)
    prop.SetShadow(True)
    return actor


def render_to_array(render_window) -> np.ndarray:
    """The render window's current pixels as an (rows, cols, 3) uint8 array, top row first."""
    render_window.Render()
    grab = vtkWindowToImageFilter()
    grab.SetInput(render_window)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    image = grab.GetOutput()
    cols, rows, _ = image.GetDimensions()
    pixels = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars()).reshape(rows, cols, -1)
    return np.ascontiguousarray(pixels[::-1, :, :3])


def _backdrop(actor: vtkTextActor, opacity: float) -> vtkTextActor:
    """Put a dark box behind ``actor``'s text, so that it reads over a bright frame too."""
    prop = actor.GetTextProperty()
    prop.SetBackgroundColor(0.0, 0.0, 0.0)
    prop.SetBackgroundOpacity(opacity)
    return actor


class _LayeredView(QVTKRenderWindowInteractor):
    """A VTK view whose actors are grouped in named layers.

    ``TEXT_BACKDROP``: opacity of a dark box behind the title and the legend (0: none).
    """

    TEXT_BACKDROP = 0.0

    def __init__(self, parent=None):
        super().__init__(parent)
        self.renderer = vtkRenderer()
        self.renderer.GradientBackgroundOn()
        self.renderer.SetBackground(*BACKGROUND_BOTTOM)
        self.renderer.SetBackground2(*BACKGROUND_TOP)
        self.GetRenderWindow().AddRenderer(self.renderer)
        self.layers: dict[str, list] = {}
        self.hidden: set[str] = set()
        self._legend_rows: list = []

    def clear(self) -> None:
        """Remove every layer."""
        for props in self.layers.values():
            for prop in props:
                self.renderer.RemoveViewProp(prop)
        self.layers = {}
        self._legend_rows = []

    def drop_layer(self, name: str) -> None:
        """Remove one layer (and its legend rows), leaving the others as they are."""
        removed = self.layers.pop(name, [])
        for prop in removed:
            self.renderer.RemoveViewProp(prop)
        self._legend_rows = [(actor, index) for actor, index in self._legend_rows if actor not in removed]

    def add_to_layer(self, name: str, prop) -> None:
        self.layers.setdefault(name, []).append(prop)
        prop.SetVisibility(name not in self.hidden)
        self.renderer.AddViewProp(prop)

    def set_layer_visible(self, name: str, visible: bool) -> None:
        """Show or hide a layer (remembered for later results)."""
        (self.hidden.discard if visible else self.hidden.add)(name)
        for prop in self.layers.get(name, []):
            prop.SetVisibility(visible)
        self.GetRenderWindow().Render()

    def pixels(self) -> np.ndarray:
        """The view as rendered now: (rows, cols, 3) uint8."""
        return render_to_array(self.GetRenderWindow())

    def _legend(self, entries, first_row: int = 0) -> None:
        """Coloured legend lines in the top-left corner, one per ``(layer, text, color)``."""
        for index, (layer, text, color) in enumerate(entries, start=first_row):
            actor = _backdrop(_text(f"\u2014 {text}", color, 15), self.TEXT_BACKDROP)
            actor.GetTextProperty().SetVerticalJustificationToTop()
            self._legend_rows.append((actor, index))
            self.add_to_layer(layer, actor)
        self._place_legend()

    def _place_legend(self) -> None:
        height = self.GetRenderWindow().GetSize()[1]
        for actor, index in self._legend_rows:
            actor.SetDisplayPosition(12, height - 40 - 21 * index)

    def resizeEvent(self, event):  # noqa: N802  (Qt naming)
        super().resizeEvent(event)
        self._place_legend()


class View3D(_LayeredView):
    """Pre-operative and recovered centrelines as tubes, the path highlighted, an optional surface.

    Seen from the front (anterior), head up: the patient's left on the screen's right, as
    on an AP fluoroscopic frame. An orientation cube names the LPS directions.
    """

    TITLE = "3D  \u2014  anterior view"

    def __init__(self, parent=None):
        super().__init__(parent)
        self.SetInteractorStyle(vtkInteractorStyleTrackballCamera())
        self._orientation = self._orientation_widget()
        self.title = _text(self.TITLE, COLORS["text"], 16, bold=True)
        self.title.SetDisplayPosition(12, 10)
        self.renderer.AddViewProp(self.title)

    def _orientation_widget(self) -> vtkOrientationMarkerWidget:
        cube = vtkAnnotatedCubeActor()
        # LPS world: +x = patient's left, +y = posterior, +z = superior
        for setter, text in (("SetXPlusFaceText", "L"), ("SetXMinusFaceText", "R"), ("SetYPlusFaceText", "P"),
                             ("SetYMinusFaceText", "A"), ("SetZPlusFaceText", "S"), ("SetZMinusFaceText", "I")):
            getattr(cube, setter)(text)
        cube.SetFaceTextScale(0.62)
        cube.GetCubeProperty().SetColor(0.30, 0.34, 0.42)
        cube.GetTextEdgesProperty().SetColor(0.8, 0.8, 0.8)
        for prop in (cube.GetXPlusFaceProperty(), cube.GetXMinusFaceProperty(), cube.GetYPlusFaceProperty(),
                     cube.GetYMinusFaceProperty(), cube.GetZPlusFaceProperty(), cube.GetZMinusFaceProperty()):
            prop.SetColor(*COLORS["text"])
        widget = vtkOrientationMarkerWidget()
        widget.SetOrientationMarker(cube)
        widget.SetInteractor(self)
        widget.SetViewport(0.86, 0.0, 1.0, 0.14)
        widget.SetEnabled(1)
        widget.InteractiveOff()
        return widget

    def set_result(self, result, surface: vtkPolyData | None = None) -> None:
        """Show a PlanResult (LPS mm) and, if given, a surface (vtkPolyData, LPS mm)."""
        self.clear()
        extent = float(np.ptp(np.vstack([result.preop.points, result.deformed.points]), axis=0).max())
        radius = max(0.4, 0.006 * extent)
        self.add_to_layer("preop", tube_actor(centerline_to_polydata(result.preop), COLORS["preop"], radius, 0.55))
        self._radius = radius
        if surface is not None and surface.GetNumberOfPoints():
            self.add_to_layer("surface", self._surface_actor(surface))
        self._legend([("preop", f"{ROLE_NAMES['preop']} centreline", COLORS["preop"])])
        self._add_recovered(result)
        self._add_path(result)
        self.reset_camera()

    def _add_recovered(self, result) -> None:
        self.add_to_layer("deformed", tube_actor(centerline_to_polydata(result.deformed), COLORS["deformed"],
                                                  self._radius * 1.25))
        self._legend([("deformed", f"{ROLE_NAMES['recovered']} centreline ({result.method})", COLORS["deformed"])],
                     first_row=1)

    def update_recovered(self, result) -> None:
        """Redraw the recovered centreline and the path only (another frame of the same run)."""
        for layer in ("deformed", "path"):
            self.drop_layer(layer)
        self._add_recovered(result)
        self._add_path(result)
        self.GetRenderWindow().Render()

    def _add_path(self, result) -> None:
        path = np.asarray(result.path.points, dtype=float)
        self.add_to_layer("path", tube_actor(polyline_polydata(path), COLORS["path"], self._radius * 2.0))
        for point, text in ((path[0], result.path.start_label), (path[-1], result.path.target_label)):
            self.add_to_layer("path", _sphere_actor(point, self._radius * 3.2, COLORS["path"]))
            self.add_to_layer("path", _label_3d(text, point, COLORS["text"]))
        self._legend([("path", f"{ROLE_NAMES['path']} {result.path.length_mm:.0f} mm", COLORS["path"])], first_row=2)

    def update_path(self, result) -> None:
        """Redraw only the path (after re-planning on the same recovered centreline)."""
        self.drop_layer("path")
        self._add_path(result)
        self.GetRenderWindow().Render()

    @staticmethod
    def _surface_actor(surface: vtkPolyData) -> vtkActor:
        actor = polydata_actor(surface, COLORS["surface"], 0.22)
        actor.GetProperty().BackfaceCullingOn()
        return actor

    def reset_camera(self) -> None:
        """Anterior view (from -y, LPS), head (+z) up, everything in frame."""
        bounds = self.renderer.ComputeVisiblePropBounds()
        center = np.array([(bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2, (bounds[4] + bounds[5]) / 2])
        camera = self.renderer.GetActiveCamera()
        camera.SetFocalPoint(*center)
        camera.SetPosition(*(center - [0.0, 1000.0, 0.0]))
        camera.SetViewUp(0.0, 0.0, 1.0)
        self.renderer.ResetCamera(bounds)
        camera.Zoom(1.1)
        self.renderer.ResetCameraClippingRange()
        self.GetRenderWindow().Render()


class FluoroView(_LayeredView):
    """The fluoroscopic frame with its 2D skeleton and the centrelines projected through P.

    Image coordinates as everywhere in the project: ``u`` = column to the right, ``v`` =
    row downwards, (0, 0) the centre of the first pixel; the view is pixel-exact.
    """

    TITLE = "Fluoroscopy  \u2014  projected through P"
    TEXT_BACKDROP = 0.6  # the frame may be bright where the text lies

    def __init__(self, parent=None):
        super().__init__(parent)
        self.renderer.GradientBackgroundOff()
        self.renderer.SetBackground(0.0, 0.0, 0.0)
        self.SetInteractorStyle(vtkInteractorStyleImage())
        self.title = _backdrop(_text(self.TITLE, COLORS["text"], 16, bold=True), self.TEXT_BACKDROP)
        self.title.SetDisplayPosition(12, 10)
        self.renderer.AddViewProp(self.title)
        self.image_shape = None
        self.frame = None  # the ViewDrawing shown

    @staticmethod
    def _image_slice(image: np.ndarray) -> vtkImageSlice:
        image = np.asarray(image, dtype=np.float32)
        data = vtkImageData()
        data.SetDimensions(image.shape[1], image.shape[0], 1)  # x = u (column), y = v (row)
        data.GetPointData().SetScalars(numpy_support.numpy_to_vtk(np.ascontiguousarray(image).ravel(), deep=True))
        mapper = vtkImageSliceMapper()
        mapper.SetInputData(data)
        actor = vtkImageSlice()
        actor.SetMapper(mapper)
        finite = image[np.isfinite(image)]
        low, high = np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0)
        actor.GetProperty().SetColorWindow(float(max(high - low, 1e-6)))
        actor.GetProperty().SetColorLevel(float((high + low) / 2))
        actor.GetProperty().SetInterpolationTypeToNearest()
        return actor

    def set_result(self, result, frame=None) -> None:
        """Show one view of a PlanResult: its frame, its 2D skeleton and the centrelines projected through its P.

        ``frame`` (one of ``result.view_drawings(case)``) picks the view; default the first.
        """
        frame = frame if frame is not None else result.view_drawings()[0]
        self.clear()
        self.frame = frame
        self.image_shape = np.asarray(frame.image).shape
        self.add_to_layer("image", self._image_slice(frame.image))
        # overlays lie between the camera (z < 0) and the image (z = 0), later ones nearer
        self.add_to_layer("skeleton2d", _line_actor(
            segments_polydata(frame.skeleton_points, frame.skeleton_edges, z=-1.0), COLORS["skeleton2d"], 5.0,
            opacity=0.75))  # wide, so it shows as a halo around the thinner projected centrelines
        for layer, centerline, width, z in (("preop", result.preop, 2.0, -2.0),
                                            ("deformed", result.deformed, 2.5, -3.0)):
            uv = project(frame.P, centerline.points)
            self.add_to_layer(layer, _line_actor(segments_polydata(uv, centerline.edges, z=z), COLORS[layer], width))
        self._legend([("skeleton2d", ROLE_NAMES["skeleton2d"], COLORS["skeleton2d"]),
                      ("preop", f"{ROLE_NAMES['preop']}, projected", COLORS["preop"]),
                      ("deformed", f"{ROLE_NAMES['recovered']}, projected", COLORS["deformed"])])
        self._add_path(result)
        self.title.SetInput(self._title_text(frame))
        self.reset_camera()

    @staticmethod
    def _title_text(frame) -> str:
        fit = f",  2D fit {frame.fit['mean']:.2f} px" if frame.fit else ""
        return f"Fluoroscopy:  view {frame.name}{fit}"

    def _add_path(self, result) -> None:
        path_uv = project(self.frame.P, result.path.points)
        path = polyline_polydata(np.column_stack([path_uv, np.full(len(path_uv), -4.0)]))
        self.add_to_layer("path", _line_actor(path, COLORS["path"], 4.0))
        self._legend([("path", f"{ROLE_NAMES['path']}, projected", COLORS["path"])], first_row=3)

    def update_path(self, result) -> None:
        """Redraw only the projected path (after re-planning on the same recovered centreline)."""
        self.drop_layer("path")
        self._add_path(result)
        self.GetRenderWindow().Render()

    def reset_camera(self) -> None:
        """Whole frame in view, u to the right and v down (camera on the -z side)."""
        if self.image_shape is None:
            return
        rows, cols = self.image_shape
        center = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0])
        camera = self.renderer.GetActiveCamera()
        camera.ParallelProjectionOn()
        camera.SetFocalPoint(*center)
        camera.SetPosition(*(center - [0.0, 0.0, 1000.0]))
        camera.SetViewUp(0.0, -1.0, 0.0)
        width, height = self.GetRenderWindow().GetSize()
        aspect = width / max(height, 1)
        camera.SetParallelScale(0.52 * max(rows, cols / max(aspect, 1e-6)))
        self.renderer.ResetCameraClippingRange()
        self.GetRenderWindow().Render()

    def resizeEvent(self, event):  # noqa: N802  (Qt naming)
        super().resizeEvent(event)
        self.reset_camera()

"""A 3D picture of centrelines (and optionally the aorta surface), rendered offscreen with VTK;
the actors are shared with the workstation's 3D view.
"""

from __future__ import annotations

import numpy as np

from ..centerline import Centerline
from ..conventions import PALETTE
from ..files import atomic_path
from .overlay import _rgb
from .result import _points_array
from .vtp import _vtk_error_line, _vtk_errors_captured, centerline_to_polydata


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

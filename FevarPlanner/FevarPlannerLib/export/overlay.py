"""``overlay.png``: the fluoroscopic frame with projected centrelines (eq. 1), pixel for pixel,
with the view's name, orientation marks and a scale bar.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

import numpy as np

from ..centerline import Centerline
from ..conventions import PALETTE
from ..files import atomic_path
from ..projection import depth, image_directions, project, view_label


#: What the display calls each role ("recovered", not "deformed": the result.json key
#: ``deformed_centerline`` stays, as the contract says).
ROLE_NAMES = {"preop": "pre-operative", "recovered": "recovered", "deformed": "recovered", "path": "catheter path",
              "skeleton2d": "2D skeleton", "truth": "intra-operative truth"}


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


#: At most this many warning lines are drawn; the rest are counted ("+N more") and stay in result.json.
MAX_WARNING_LINES = 6
#: Approximate width of one 8 pt character in pixels at the overlay's 100 dpi.
_CHAR_PX = 5.5


def warning_lines(warnings, cols: int, max_lines: int = MAX_WARNING_LINES) -> list[str]:
    """The plausibility warnings wrapped to about half the frame width (clear of the scale bar), at most ``max_lines`` lines.

    Parameters
    ----------
    warnings : sequence of str
        One entry per warning (result.json ``warnings``).
    cols : int
        Frame width in pixels.
    max_lines : int
        Lines drawn at most; a last line says how many more are in result.json.

    Returns
    -------
    list of str
        Each warning starts with "! "; its continuation lines are indented.
    """
    width = max(24, int(0.5 * cols / _CHAR_PX))
    lines = []
    for warning in warnings:
        lines += textwrap.wrap(str(warning), width=width, initial_indent="! ", subsequent_indent="  ") or ["!"]
    if len(lines) > max_lines:
        hidden = len(lines) - (max_lines - 1)
        lines = lines[:max_lines - 1] + [f"(+{hidden} more lines in result.json)"]
    return lines


def _warning_box(axes, lines: list[str], rows: int, cols: int, color) -> None:
    """The warning lines in a dark box at the frame's bottom-left corner (the title is top left,
    the scale bar bottom right)."""
    axes.text(0.01 * cols, 0.99 * rows, "\n".join(lines), color=_rgb(color), fontsize=8, ha="left",
              va="bottom", family="monospace", linespacing=1.2,
              bbox={"facecolor": "black", "alpha": 0.75, "pad": 3.0, "edgecolor": _rgb(color)})


def render_overlay(path, image: np.ndarray, *, skeleton2d: np.ndarray | None = None,
                   layers=(), line_px: float = 2.0, dot_px: float = 3.0, legend_height_px: int = 28,
                   min_width_px: int = 480, title: str | None = None, P: np.ndarray | None = None,
                   anchor=None, skeleton_color=PALETTE["skeleton2d"], warnings=(),
                   warning_color=PALETTE["warning"]) -> None:
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
    warnings : sequence of str
        Plausibility warnings (result.json ``warnings``), drawn wrapped in a box at the
        frame's bottom-left corner (:func:`warning_lines`); none: no box.
    warning_color : color
        Colour of the warning text and box edge.
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
    if warnings:
        _warning_box(axes, warning_lines(warnings, cols), rows, cols, warning_color)
    axes.set_xlim(-0.5, cols - 0.5)
    axes.set_ylim(rows - 0.5, -0.5)
    if handles:
        figure.legend(handles=handles, loc="lower left", ncol=len(handles), frameon=False, fontsize=8,
                      labelcolor="white", bbox_to_anchor=(0.0, 0.0), borderaxespad=0.2, handlelength=1.5,
                      columnspacing=1.0)
    with atomic_path(path, suffix=".png") as tmp:
        figure.savefig(tmp, dpi=dpi, format="png", facecolor="black")

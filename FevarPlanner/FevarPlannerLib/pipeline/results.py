"""What a registration and a planned case return: :class:`FrameResult` (one registration,
per view :class:`ViewFrame`) and :class:`PlanResult` (everything a caller shows or writes).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .. import export, graph, planning, projection, quality
from ..centerline import Centerline
from .visibility import Visibility


METHODS = ("proposed", "icp-tps", "rigid")
#: Views whose X-rays through the anatomy cross at this angle (degrees) or more measure depth:
#: at 20 degrees a 0.3 mm in-plane error is about 0.9 mm along the first view's ray.
DEPTH_MEASURED_SPREAD_DEG = 20.0


@dataclass
class ViewFrame:
    """One view's share of a registration (several views: :func:`register_views`)."""

    name: str
    P: np.ndarray
    skeleton2d: graph.SkeletonGraph
    classification2d: graph.Classification | None
    visibility: Visibility
    nodes_outside: int = 0
    correspondence: str = ""
    pose_correction: dict | None = None


@dataclass
class FrameResult:
    """One registration: the deformed kept nodes and how they were found.

    ``P``, ``skeleton2d`` and ``classification2d`` are those of the first view; ``views``
    holds every view, ``warnings`` what the plausibility checks changed or doubted.
    """

    deformed: Centerline
    P: np.ndarray
    skeleton2d: graph.SkeletonGraph
    classification2d: graph.Classification | None
    energy: float | None
    correspondence: str
    timings: dict
    views: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    def seen_in(self, name: str) -> "FrameResult | None":
        """The same registration with view ``name``'s ``P``, 2D skeleton and classification as
        the first view's; None if that view took no part."""
        view = next((view for view in self.views if view.name == name), None)
        if view is None:
            return None
        return dataclasses.replace(self, P=view.P, skeleton2d=view.skeleton2d, classification2d=view.classification2d)


@dataclass
class ViewDrawing:
    """What a front end draws for one view of a :class:`PlanResult` (:meth:`PlanResult.view_drawings`).

    Attributes
    ----------
    name : str
        ``main`` for the case folder's own frame, else the view's name (``views/<name>/``).
    image : numpy.ndarray, shape (rows, cols)
        The frame (a stand-in drawn from the vessel mask when the view holds only a mask).
    P : numpy.ndarray, shape (3, 4)
        The view's projection matrix (after any pose correction): LPS mm to pixels, eq. 1.
    skeleton_points : numpy.ndarray, shape (n, 2)
        The view's 2D skeleton nodes ``(u, v)``.
    skeleton_edges : numpy.ndarray, shape (m, 2)
    fit : dict or None
        The recovered tree's 2D fit to this view's skeleton (``mean``, ``std``, ... px).
    """

    name: str
    image: np.ndarray
    P: np.ndarray
    skeleton_points: np.ndarray
    skeleton_edges: np.ndarray
    fit: dict | None = None


@dataclass
class PlanResult:
    """Everything a caller shows or writes about one case (see docs/DESIGN.md section 4).

    ``P``, ``skeleton2d_*``, ``fluoro_image`` and ``errors`` are the first view's; ``views``
    has one dict per view (name, projection matrix, 2D error, visibility, inputs) and
    ``warnings`` what the plausibility checks replaced or doubted. ``view_frames`` holds, in
    the order of ``views``, each view's :class:`ViewFrame` (its ``P`` and 2D skeleton graph),
    for front ends that draw every view; it is not written to result.json. ``energy`` is the
    registration's eq. 6 energy; ``flipped`` holds, per view, the case registered with that
    view's frame flipped left-right (:func:`run_case` with ``mirror_test``; None where that
    failed), for the mirror test of the registration check.
    """

    method: str
    preop: Centerline
    deformed: Centerline
    path: planning.CatheterPath
    P: np.ndarray
    skeleton2d_points: np.ndarray
    skeleton2d_edges: np.ndarray
    fluoro_image: np.ndarray
    timings: dict
    errors: dict | None = None
    inputs: dict = field(default_factory=dict)
    qc: quality.QCData | None = None
    geometry: dict | None = None
    drr: np.ndarray | None = None
    views: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    view_frames: list = field(default_factory=list, repr=False)
    energy: float | None = None
    flipped: list | None = field(default=None, repr=False)

    def view_drawings(self, case=None) -> list[ViewDrawing]:
        """One :class:`ViewDrawing` per view the registration used, in the order of ``views``.

        The first view comes from the result itself; the others need their frames, which
        ``case`` (the :class:`io.Case` that was planned) holds. Without it, or for a result of
        one frame (a step of a multi-frame run), only the first view is given.
        """
        fits = {view["name"]: view.get("2d_px") for view in self.views}
        first = next(iter(fits), "main")
        drawings = [ViewDrawing(first, np.asarray(self.fluoro_image), np.asarray(self.P),
                                np.asarray(self.skeleton2d_points), np.asarray(self.skeleton2d_edges),
                                fits.get(first, (self.errors or {}).get("2d_px")))]
        images = {view.name: view.fluoro.image for view in getattr(case, "views", None) or []}
        drawings += [ViewDrawing(frame.name, np.asarray(images[frame.name]), np.asarray(frame.P),
                                 frame.skeleton2d.positions, frame.skeleton2d.edges(), fits.get(frame.name))
                     for frame in self.view_frames[1:] if frame.name in images]
        return drawings

    def depth_source(self) -> dict:
        """Where the depth along the X-rays comes from: ``views``, ``view_spread_deg``
        (:func:`projection.view_spread_deg` at the recovered tree's centre), ``measured``
        (at least :data:`DEPTH_MEASURED_SPREAD_DEG`) and a sentence for the reader."""
        Ps = [view["projection_matrix"] for view in self.views] or [self.P]
        spread = projection.view_spread_deg(Ps, self.deformed.points.mean(axis=0))
        measured = spread >= DEPTH_MEASURED_SPREAD_DEG
        if measured:
            note = f"measured: {len(Ps)} views whose X-rays cross at {spread:.0f} degrees"
        elif len(Ps) == 1:
            note = "from the pre-operative CT: one view does not see along its X-ray"
        else:
            note = (f"from the pre-operative CT: the {len(Ps)} views' X-rays cross at {spread:.0f} degrees, "
                    f"under {DEPTH_MEASURED_SPREAD_DEG:.0f}")
        return {"views": len(Ps), "view_spread_deg": round(spread, 1), "measured": measured, "note": note}

    def to_dict(self) -> dict:
        extra = {"projection_matrix": np.asarray(self.P).tolist(), "inputs": self.inputs,
                 "warnings": list(self.warnings), "depth": self.depth_source()}
        if self.errors is not None:
            extra["errors"] = self.errors
        if self.geometry is not None:
            extra["geometry"] = self.geometry
        if self.views:
            extra["views"] = [{k: v for k, v in view.items() if k != "visibility"} for view in self.views]
            extra["visibility"] = {view["name"]: view["visibility"] for view in self.views}
            if self.views[0].get("pose_correction") is not None:
                extra["pose_correction"] = self.views[0]["pose_correction"]
        return export.build_result_dict(self.method, self.preop, self.deformed, self.path, self.timings, **extra)

"""The one logic entry point that the CLI, the Slicer module, the workstation and the tests call.

Pre-operative work (CT side) is done once per patient by :func:`prepare_preop`; the
intra-operative side (:func:`register_frame`) runs per fluoroscopic frame and is kept
free of anything that does not depend on the frame (paper Algorithm 2):

    rows 1-2   3D skeleton graph and node classification          prepare_preop
    rows 3-4   2D skeleton graph and node classification          register_frame
    row  5     branch / trunk matching                             matching
    rows 6-12  soft assignment (eqs. 3-5)                          matching
    rows 13-15 deformation S_D + alpha S_L + beta S_S (eqs. 6-9)   deformation
    row  16    branch-wise TPS for the unassigned nodes            deformation
"""

from __future__ import annotations

import functools
import itertools
import os
import shutil
import tempfile
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy import ndimage
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from threadpoolctl import ThreadpoolController

from . import (baselines, deformation, evaluation, export, graph, io, matching, planning, plausibility, quality,
               skeleton)
from .alignment import fit_in_plane_rigid
from .centerline import Centerline
from .conventions import IOTA_MM, PALETTE
from .files import InputError, InputWarning, atomic_folder, check_inside, display_path, output_mode, swap_folder
from .io import MAIN_VIEW, Case, View, load_case
from .preop import (SMOOTHING_ITERATIONS, Preoperative, _induced_edges, _report, _skeleton3d_and_lumen, _timed,
                    build_preop, preop_from_lumen, preop_from_skeleton)
from .projection import image_directions, pixels_per_mm, project, view_label

__all__ = ["METHODS", "Preoperative", "Visibility", "ViewFrame", "FrameResult", "PlanResult", "preop_from_skeleton",
           "preop_from_lumen", "build_preop", "prepare_preop", "picture_title", "frame_visibility", "register_frame",
           "register_views", "run_case", "plan_case", "write_outputs"]

METHODS = ("proposed", "icp-tps", "rigid")


@dataclass
class Visibility:
    """What part of the image plane one frame shows (partial visibility).

    Attributes
    ----------
    shape : (rows, cols)
        The frame's pixel grid.
    exposed : (row_min, row_max, col_min, col_max)
        The exposed rectangle (inclusive pixel indices): the frame less its collimated bands.
    clipped_border : list of str
        Sides of ``exposed`` ("top", "bottom", "left", "right") that the vessel mask runs into.
    margin_px : dict
        Per clipped side, the vessel half-width there (px): within it the 2D skeleton is
        the thinning's artefact of the cut (it bends or forks towards the corners), so
        projections closer to the border than this get no data term.
    """

    shape: tuple
    exposed: tuple
    clipped_border: list
    margin_px: dict

    def shows(self, uv: np.ndarray) -> np.ndarray:
        """True for the 2D points (u, v) inside the part of the frame that shows vessels."""
        r0, r1, c0, c1 = self.exposed
        m = {side: self.margin_px.get(side, 0.0) for side in _SIDES}
        u, v = uv[:, 0], uv[:, 1]
        return ((v >= r0 - 0.5 + m["top"]) & (v <= r1 + 0.5 - m["bottom"])
                & (u >= c0 - 0.5 + m["left"]) & (u <= c1 + 0.5 - m["right"]))

    def to_dict(self, nodes_outside: int | None = None) -> dict:
        data = {"clipped_border": list(self.clipped_border), "exposed_rows_cols": list(map(int, self.exposed)),
                "margin_px": {k: round(float(v), 2) for k, v in self.margin_px.items()}}
        if nodes_outside is not None:
            data["nodes_outside"] = int(nodes_outside)
        return data


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


@dataclass
class PlanResult:
    """Everything a caller shows or writes about one case (see docs/DESIGN.md section 4).

    ``P``, ``skeleton2d_*``, ``fluoro_image`` and ``errors`` are the first view's; ``views``
    has one dict per view (name, projection matrix, 2D error, visibility, inputs) and
    ``warnings`` what the plausibility checks replaced or doubted.
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

    def to_dict(self) -> dict:
        extra = {"projection_matrix": np.asarray(self.P).tolist(), "inputs": self.inputs,
                 "warnings": list(self.warnings)}
        if self.errors is not None:
            extra["errors"] = self.errors
        if self.geometry is not None:
            extra["geometry"] = self.geometry
        if self.views:
            extra["views"] = [{k: v for k, v in view.items() if k != "visibility"} for view in self.views]
            extra["visibility"] = {view["name"]: view["visibility"] for view in self.views}
        return export.build_result_dict(self.method, self.preop, self.deformed, self.path, self.timings, **extra)


def prepare_preop(case: Case, progress=None, segmenter: str = "classical", cache=False) -> Preoperative:
    """3D skeleton graph of the pre-operative anatomy, classified (Alg. 1), centred and labelled.

    A case holding only a CT is segmented first with ``segmenter`` ("classical", "unet" or "threshold").
    ``cache``: True (the default cache folder) or a folder keeps the result on disk and
    reuses it for the same inputs (:mod:`cache`); False computes it.
    """
    if cache is False or cache is None:
        return build_preop(case, progress, segmenter)[0]
    from . import cache as preop_cache

    folder = None if cache is True else cache
    return preop_cache.preop_model(case, segmenter=segmenter, progress=progress, cache_dir=folder).preop


def _skeleton2d_graph(mask: np.ndarray, mm_per_pixel: float) -> graph.SkeletonGraph:
    return graph.SkeletonGraph.from_image(skeleton.skeletonize_2d(mask), pixel_size=mm_per_pixel, mask=mask)


def _classify_2d(g2: graph.SkeletonGraph, P: np.ndarray, at: np.ndarray) -> graph.Classification:
    """Algorithm 1 on the 2D graph (lengths scaled by ``g2.unit_mm``), labelled through ``P``."""
    left, superior = image_directions(P, at)
    # Algorithm 1's iota in pixels at the anatomy's depth (g2.unit_mm is mm per pixel there)
    c2 = graph.classify(g2, iota=IOTA_MM * (1.0 / g2.unit_mm), directions={"left": left, "superior": superior})
    return graph.label_anatomy(c2.graph, c2, left=left, superior=superior)


#: The vessels that a stiff wire moves least: the pose is refined on these alone, so that
#: the deformation of the sac and the iliacs is not mistaken for a misaligned frame.
STABLE_VESSELS = ("aorta", "renal_left", "renal_right")
#: A correction turning the frame further than this is a failed fit, not a misalignment.
MAX_POSE_ROTATION_DEG = 30.0


def _branch_nodes(classification: graph.Classification, labels) -> np.ndarray:
    nodes = [b.nodes for b in classification.branches if b.label in labels]
    return np.concatenate(nodes) if nodes else np.empty(0, dtype=np.int64)


def _refined_projection(preop: Preoperative, g2: graph.SkeletonGraph, c2: graph.Classification,
                        P: np.ndarray) -> np.ndarray:
    """``P`` corrected in-plane on the stable vessels (upper aorta and renals).

    The stable vessels' 3D nodes are soft-assigned to their 2D targets (eqs. 4-5) under the
    given ``P``; the rotation and translation of the image plane that lays their projections
    onto the targets (alignment.fit_in_plane_rigid) is folded into ``P``. A rigid in-plane
    move changes no projected length, so the assignment it was fitted on stays valid.
    """
    g3, c3 = preop.graph, preop.classification
    candidate = matching.candidate_correspondences(g3, c3, g2, c2, P)[0]
    assignment = matching.soft_assign(g3, c3, g2, c2, P, candidate)
    stable = _branch_nodes(c3, STABLE_VESSELS)
    stable = stable[assignment.assigned[stable]]
    if len(stable) < 10:
        return P
    fit = fit_in_plane_rigid(project(P, g3.positions[stable]), assignment.targets[stable], P)
    return fit.P if abs(fit.rotation_deg) <= MAX_POSE_ROTATION_DEG else P


def _frame_projection(preop: Preoperative, view: "_ViewState", P: np.ndarray) -> None:
    """Project the pre-operative kept nodes through ``P``: which of them the frame shows."""
    view.P = P
    view.visible = view.visibility.shows(project(P, preop.graph.positions))


@dataclass
class _ViewState:
    """The per-view working data of :func:`register_views`."""

    name: str
    P: np.ndarray
    g2: graph.SkeletonGraph
    c2: graph.Classification | None
    visibility: Visibility
    visible: np.ndarray | None = None
    candidates: list = field(default_factory=list)
    unclassified: str | None = None      # why Algorithm 1 failed on this view (then c2 is None)


# --------------------------------------------------------------------------- partial visibility

_SIDES = ("top", "bottom", "left", "right")
#: A border row or column whose grey values vary by less than this fraction of the frame's
#: range (1st to 99th percentile) is a collimator (shutter) band: it shows no anatomy.
FLAT_BAND_FRACTION = 0.01
#: The vessel mask runs into a border when at least this many of its pixels lie on it.
MIN_BORDER_PIXELS = 2


def _collimated_bands(image: np.ndarray) -> dict:
    """Number of flat (shutter) rows / columns on each side of a raw frame."""
    image = np.asarray(image, dtype=float)
    low, high = np.percentile(image, [1, 99])
    limit = FLAT_BAND_FRACTION * max(high - low, 1e-12)
    flat_rows, flat_cols = image.std(axis=1) < limit, image.std(axis=0) < limit

    def run(flags):
        return int(np.argmin(flags)) if not flags.all() else len(flags)

    return {"top": run(flat_rows), "bottom": run(flat_rows[::-1]), "left": run(flat_cols),
            "right": run(flat_cols[::-1])}


def frame_visibility(mask2d: np.ndarray, image: np.ndarray | None = None) -> Visibility:
    """Where a frame shows anatomy and where its vessels run out of it.

    Parameters
    ----------
    mask2d : (rows, cols) bool
        The vessel mask.
    image : (rows, cols) array, optional
        The raw frame; flat bands along its borders are collimator shutters
        (:data:`FLAT_BAND_FRACTION`) and are excluded from the exposed rectangle. Without it
        the whole frame is exposed.

    Returns
    -------
    Visibility
        The exposed rectangle, the sides of it that the vessel mask touches (the vessel
        continues beyond them unseen) and the vessel half-width at each such side.
    """
    mask = np.asarray(mask2d, dtype=bool)
    rows, cols = mask.shape
    has_image = image is not None and np.shape(image) == mask.shape
    bands = _collimated_bands(image) if has_image else dict.fromkeys(_SIDES, 0)
    r0, r1 = bands["top"], rows - 1 - bands["bottom"]
    c0, c1 = bands["left"], cols - 1 - bands["right"]
    if r0 > r1 or c0 > c1:
        r0, r1, c0, c1 = 0, rows - 1, 0, cols - 1
    shown = mask[r0:r1 + 1, c0:c1 + 1]
    sides = {"top": (0, slice(None)), "bottom": (-1, slice(None)), "left": (slice(None), 0),
             "right": (slice(None), -1)}
    clipped, margin, half_width = [], {}, None
    for side, index in sides.items():
        on_border = shown[index]
        if np.count_nonzero(on_border) >= MIN_BORDER_PIXELS:
            if half_width is None:      # only for a clipped frame: 45 ms on a 1024 x 1024 frame
                # distance to the nearest background pixel inside the exposed rectangle (its
                # edges repeated outwards): at a side the vessel runs into, its half-width there
                half_width = ndimage.distance_transform_edt(np.pad(shown, 1, mode="edge"))[1:-1, 1:-1]
            clipped.append(side)
            margin[side] = float(half_width[index][on_border].max())
    return Visibility((rows, cols), (r0, r1, c0, c1), clipped, margin)


# --------------------------------------------------------------------------- deformation over views

#: Most combinations of per-view candidate correspondences deformed (the first in order).
MAX_CANDIDATE_COMBINATIONS = 16
#: Length (mm) of the seen vessel next to an unseen piece whose direction that piece keeps.
TANGENT_MM = 15.0


def _carry_unseen(preop: Preoperative, moved: np.ndarray, assigned: np.ndarray, visible: list) -> np.ndarray:
    """Move each unassigned piece that a frame border cuts rigidly with the vessel it hangs from.

    A piece of kept nodes without a 2D target in any view that holds a node no view shows
    (outside every frame, in a collimated band, or within the vessel's half-width of a
    border it runs out of, where thinning is unreliable) and hangs from one place of the
    assigned tree has no data term: the length and smoothness terms of eq. 6 are smallest
    when it keeps its shape (a rigid motion), and it turns with
    the direction of the last :data:`TANGENT_MM` of the vessel it hangs from, so that a
    vessel leaving the frame goes on the way it left instead of the TPS extrapolating it.
    Changes ``moved`` in place and returns the carried graph nodes.
    """
    g3 = preop.graph
    n = len(g3.positions)
    free = np.zeros(n, dtype=bool)
    free[preop.kept] = ~assigned[preop.kept]
    unseen = free & ~np.logical_or.reduce(visible)
    if not unseen.any():
        return np.empty(0, dtype=np.int64)
    edges = g3.edges()
    inner = edges[free[edges[:, 0]] & free[edges[:, 1]]]
    adjacency = scipy.sparse.coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])), shape=(n, n))
    _, component = csgraph.connected_components(adjacency, directed=False)
    links = edges[free[edges[:, 0]] != free[edges[:, 1]]]
    links = np.where(free[links[:, :1]], links, links[:, ::-1])          # (free node, assigned node)
    links = links[assigned[links[:, 1]]]
    pair = edges[assigned[edges[:, 0]] & assigned[edges[:, 1]]]
    length = np.linalg.norm(g3.positions[pair[:, 0]] - g3.positions[pair[:, 1]], axis=1)
    assigned_graph = scipy.sparse.coo_matrix((length, (pair[:, 0], pair[:, 1])), shape=(n, n)).tocsr()
    carried = []
    for label in np.unique(component[unseen]):
        piece = np.flatnonzero(free & (component == label))
        anchors = np.unique(links[np.isin(links[:, 0], piece), 1])
        if len(anchors) == 0:
            continue
        if len(anchors) > 1:
            apart = csgraph.dijkstra(assigned_graph, directed=False, indices=anchors[0], limit=TANGENT_MM)
            if not np.isfinite(apart[anchors]).all():
                continue                                    # hangs between two seen parts: the TPS
        distance = csgraph.dijkstra(assigned_graph, directed=False, indices=anchors, min_only=True, limit=TANGENT_MM)
        near = np.flatnonzero(np.isfinite(distance) & (distance > 0))
        anchor_before, anchor_after = g3.positions[anchors].mean(axis=0), moved[anchors].mean(axis=0)
        rotation = np.eye(3)
        if len(near):
            rotation = _rotation_between(anchor_before - g3.positions[near].mean(axis=0),
                                         anchor_after - moved[near].mean(axis=0))
        moved[piece] = anchor_after + (g3.positions[piece] - anchor_before) @ rotation.T
        carried.append(piece)
    return np.concatenate(carried) if carried else np.empty(0, dtype=np.int64)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation turning direction ``a`` into direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, cos = np.cross(a, b), float(a @ b)
    sin = np.linalg.norm(axis)
    if sin < 1e-12:
        return np.eye(3)
    k = axis / sin
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sin * K + (1 - cos) * K @ K


def _view_data(nodes: np.ndarray, assignment, visible: np.ndarray, P: np.ndarray, positions: np.ndarray):
    """(targets, weights) of one view for the deformation ``nodes``.

    Weights are 0 where the view has no target (unassigned, or not shown by the frame) and
    otherwise scaled so that S_D stays the mean squared distance over the view's assigned
    nodes (eq. 6).
    """
    has_target = assignment.assigned[nodes] & visible[nodes]
    targets = np.where(has_target[:, None], assignment.targets[nodes], project(P, positions[nodes]))
    count = np.count_nonzero(has_target)
    weights = has_target * (len(nodes) / count) if count else np.zeros(len(nodes))
    return targets, weights


#: Most passes of nearest-point targets for a view without its own classification (ICP-like);
#: the passes stop earlier once the nodes move less than CLOSEST_POINT_SETTLED_MM on average.
CLOSEST_POINT_PASSES = 10
CLOSEST_POINT_SETTLED_MM = 0.05
#: A nearest 2D skeleton point further than this many times the median nearest distance of
#: the view is an outlier (another vessel, a part the 2D skeleton lacks) and gives no target.
CLOSEST_POINT_OUTLIER = 5.0


def _closest_point_data(view, nodes: np.ndarray, preop: Preoperative, estimate: np.ndarray):
    """(targets, weights) of a view without a classification: the nearest 2D skeleton points.

    ``estimate`` are the current kept positions; their projections through the view's P
    find the nearest node of its (smoothed) 2D skeleton; weights as in :func:`_view_data`.
    """
    positions = np.array(preop.graph.positions, dtype=float)
    positions[preop.kept] = estimate
    uv = project(view.P, positions[nodes])
    distance, index = cKDTree(view.g2.positions).query(uv)
    usable = view.visible[nodes]
    limit = CLOSEST_POINT_OUTLIER * max(float(np.median(distance[usable])) if usable.any() else 0.0, 1.0)
    has_target = usable & (distance <= limit)
    count = np.count_nonzero(has_target)
    weights = has_target * (len(nodes) / count) if count else np.zeros(len(nodes))
    return np.where(has_target[:, None], view.g2.positions[index], uv), weights


def _deform_with(preop: Preoperative, views: list, correspondences, alpha, beta, estimate=None):
    """Algorithm 2 rows 6-16 for one correspondence per view; returns (kept positions, energy, score).

    Every view soft-assigns the same 3D nodes (eqs. 3-5); one energy (eq. 6) with the data
    term averaged over the views moves them; the TPS fills the rest (row 16). A view whose
    correspondence is None (no classification) takes the nearest 2D skeleton points of the
    kept positions ``estimate`` as targets instead. The score (matching.candidate_score)
    picks between candidates: the energy plus the 3D implausibility of the result.
    """
    g3, c3 = preop.graph, preop.classification
    classified = [(v, c) for v, c in zip(views, correspondences) if c is not None]
    assignments = {v.name: matching.soft_assign(g3, c3, v.g2, v.c2, v.P, c) for v, c in classified}
    has_target = [assignments[v.name].assigned & v.visible for v, _ in classified]
    nodes = np.flatnonzero(np.logical_or.reduce(has_target))
    data = [_view_data(nodes, assignments[v.name], v.visible, v.P, g3.positions) if v.name in assignments
            else _closest_point_data(v, nodes, preop, estimate) for v in views]
    extra = {"extra_views": [(v.P, t, w) for v, (t, w) in zip(views[1:], data[1:])]} if len(views) > 1 else {}
    (targets, weights), edges = data[0], _induced_edges(g3, nodes)
    if not np.any(weights) and not extra:
        raise ValueError(f"view {views[0].name}: no 3D node has a 2D target in the frame")
    weights_arg = None if np.all(weights == 1.0) else weights
    result = deformation.deform_assigned(g3.positions[nodes], targets, edges, views[0].P, alpha=alpha, beta=beta,
                                         weights=weights_arg, **extra)
    moved = np.array(g3.positions, dtype=float)
    moved[nodes] = result.points
    in_deformation = np.zeros(len(g3.positions), dtype=bool)
    in_deformation[nodes] = True
    assigned_fraction = in_deformation[preop.kept].mean()
    in_deformation[_carry_unseen(preop, moved, in_deformation, [v.visible for v in views])] = True
    filled = deformation.fill_unassigned(g3.positions[preop.kept], moved[preop.kept], in_deformation[preop.kept],
                                         preop.kept_adjacency)
    score = matching.candidate_score(result.energy_final, assigned_fraction, preop.centerline.points, filled,
                                     preop.centerline.edges, alpha)
    return filled, float(result.energy_final), score


# --------------------------------------------------------------------------- never worse than SV

#: Largest relative change of a vessel's length that a deformation may make: vessels barely
#: stretch, and the length term (eq. 6) holds a right match to about 1 %.
LENGTH_TOLERANCE = 0.05
#: A vessel's 2D fit may be this much worse than the undeformed (SV) one before the result
#: counts as worse than SV: one pixel, the 2D skeleton's own resolution.
FIT_TOLERANCE_PX = 1.0


@dataclass
class _Vessel:
    label: str
    nodes: np.ndarray          # kept-node indices
    edges: np.ndarray          # kept-node edges inside the vessel
    attachments: np.ndarray    # (k, 2) edges (vessel node, other node)


def _vessels(centerline: Centerline) -> list:
    labels = np.asarray(centerline.labels)
    edges = centerline.edges
    vessels = []
    for label in dict.fromkeys(centerline.labels):
        member = labels == label
        inner = edges[member[edges[:, 0]] & member[edges[:, 1]]]
        cut = edges[member[edges[:, 0]] != member[edges[:, 1]]]
        cut = np.where(member[cut[:, :1]], cut, cut[:, ::-1])
        vessels.append(_Vessel(str(label), np.flatnonzero(member), inner, cut))
    return vessels


def _length(points: np.ndarray, edges: np.ndarray) -> float:
    return float(np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1).sum()) if len(edges) else 0.0


def _fit_px(points: np.ndarray, nodes: np.ndarray, views: list, kept: np.ndarray) -> float:
    """Mean over the views of the mean 2D distance (px) of the shown projected ``nodes`` to the skeleton."""
    fits = []
    for v in views:
        shown = nodes[v.visible[kept[nodes]]]
        if len(shown):
            uv = project(v.P, points[shown])
            fits.append(evaluation.point_to_graph(uv, v.g2.positions, v.g2.edges()).mean())
    return float(np.mean(fits)) if fits else 0.0


def _judge(points, vessel: _Vessel, preop_points, sv_fit: float, views, kept) -> tuple[str | None, float]:
    """Why ``points`` are implausible for ``vessel`` (None if plausible), and its 2D fit."""
    fit = _fit_px(points, vessel.nodes, views, kept)
    rest = _length(preop_points, vessel.edges)
    change = _length(points, vessel.edges) / rest - 1.0 if rest > 0 else 0.0
    if abs(change) > LENGTH_TOLERANCE:
        return f"length changed by {100 * change:+.1f}% (limit {100 * LENGTH_TOLERANCE:g}%)", fit
    if fit > sv_fit + FIT_TOLERANCE_PX:
        return f"2D fit {fit:.1f} px, worse than the undeformed {sv_fit:.1f} px", fit
    return None, fit


def _attached(option: np.ndarray, base: np.ndarray, vessel: _Vessel) -> np.ndarray:
    """``option``'s positions of ``vessel`` moved rigidly so that it stays joined to ``base``."""
    if not len(vessel.attachments):
        return option[vessel.nodes]
    outer = vessel.attachments[:, 1]
    return option[vessel.nodes] + (base[outer] - option[outer]).mean(axis=0)


SV_NAME = "the undeformed pre-operative shape (SV)"


def _replaced(result: np.ndarray, option: np.ndarray, vessel: _Vessel) -> np.ndarray:
    """``result`` with ``vessel`` taken from ``option``: the aorta as a whole tree, any other
    vessel moved rigidly so that it stays joined to ``result``."""
    if vessel.label == "aorta":
        return option.copy()
    moved = result.copy()
    moved[vessel.nodes] = _attached(option, result, vessel)
    return moved


def _never_worse_than_sv(result: np.ndarray, alternatives, preop: Preoperative, views: list) -> tuple:
    """Check each vessel of ``result`` against the undeformed (SV) start; replace implausible ones.

    A matched vessel (every label but "other") is implausible when its length changed by
    more than :data:`LENGTH_TOLERANCE` or its 2D fit (all views) is worse than SV's by more
    than :data:`FIT_TOLERANCE_PX`. It is replaced by the plausible alternative with the best
    2D fit: the same vessel from another registration (``alternatives()`` returns
    ``[(positions, name), ...]``: other candidate correspondences, each view alone), or SV,
    moved rigidly with its junction; the aorta by a whole alternative or SV. Returns
    (positions, warnings).
    """
    alternatives = functools.cache(alternatives)
    sv = preop.centerline.points
    # "other" vessels (SMA, coeliac, internal iliacs) have no 2D partner: the TPS moves them
    vessels = [v for v in _vessels(preop.centerline) if v.label != "other"]
    vessels.sort(key=lambda v: v.label != "aorta")
    result, warnings = result.copy(), []
    for vessel in vessels:
        sv_fit = _fit_px(sv, vessel.nodes, views, preop.kept)
        reason, _ = _judge(result, vessel, sv, sv_fit, views, preop.kept)
        if reason is None:
            continue
        options = list(alternatives()) + [(sv, SV_NAME)]
        best, best_fit, best_name = None, np.inf, None
        for points, name in options:
            moved = _replaced(result, points, vessel)
            why, fit = _judge(moved, vessel, sv, sv_fit, views, preop.kept)
            if why is None and fit < best_fit:
                best, best_fit, best_name = moved, fit, name
        if best is None:            # SV moved with its junction may fit worse than SV in place
            best, best_name = _replaced(result, sv, vessel), SV_NAME
        result = best
        warnings.append(f"{vessel.label}: {reason}; replaced by {best_name}")
    return result, warnings


@functools.cache
def _threadpools() -> ThreadpoolController:
    """The process's BLAS / OpenMP pools, found once (finding them costs about 3 ms a frame)."""
    return ThreadpoolController()


def register_frame(preop: Preoperative, mask2d: np.ndarray, P: np.ndarray, *, method: str = "proposed",
                   refine_pose: bool = False, alpha: float = 500.0, beta: float = 10.0,
                   image: np.ndarray | None = None, name: str = "main") -> FrameResult:
    """Register the pre-operative skeleton to one frame's 2D vessel mask (the per-frame part).

    Parameters
    ----------
    preop : Preoperative
    mask2d : (rows, cols) bool
        Vessel mask on the frame's grid.
    P : (3, 4)
        Projection matrix (rigid pre-alignment, eq. 1).
    method : {"proposed", "icp-tps", "rigid"}
    refine_pose : bool
        Correct the in-plane pose on the stable vessels first (:func:`_refined_projection`).
        Off by default: on deformed but aligned frames it mistakes the deformation for a
        misalignment (benchmark: 3D error 1.1 -> 5-11 mm); it pays off only for frames
        known to be misaligned by more than about 10 px (the robustness curves).
    alpha, beta : float
        Weights of the length and smoothness terms (eq. 6).
    image : (rows, cols) array, optional
        The raw frame, to find collimated borders (:func:`frame_visibility`).
    name : str
        The view's name in the result.
    """
    return register_views(preop, [(mask2d, P)], names=[name], images=[image], method=method,
                          refine_pose=refine_pose, alpha=alpha, beta=beta)


def register_views(preop: Preoperative, frames, *, names=None, images=None, method: str = "proposed",
                   refine_pose: bool = False, alpha: float = 500.0, beta: float = 10.0) -> FrameResult:
    """Register the pre-operative skeleton to several frames of the same anatomy at once.

    Each view gets its own 2D skeleton graph, classification, candidate correspondences and
    soft assignment (eqs. 3-5) to the same 3D nodes; one deformation (eq. 6) minimises the
    length and smoothness terms with the data term averaged over the views, so that views
    at different C-arm angles fix the depth that one view leaves open. A node gets no data
    term in a view that does not show it (outside the frame, in a collimated band, beyond a
    border the vessel runs out of: :func:`frame_visibility`). Each vessel of the result is
    then checked against the undeformed start (:func:`_never_worse_than_sv`). A view whose
    2D skeleton cannot be classified is left out with a warning while another one remains.

    Parameters
    ----------
    preop : Preoperative
    frames : sequence of (mask2d, P)
        Vessel mask and projection matrix of each view.
    names : sequence of str, optional
        View names (default "main", "view2", ...).
    images : sequence of arrays or None, optional
        Raw frames, for the collimator detection.
    method, refine_pose, alpha, beta
        As in :func:`register_frame`. ``icp-tps`` uses the first view only.

    Returns
    -------
    FrameResult
        ``P``, ``skeleton2d`` and ``classification2d`` of the first view; ``views`` of all.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    frames = list(frames)
    if not frames:
        raise ValueError("register_views: no view given")
    names = list(names) if names is not None else ["main"] + [f"view{k + 1}" for k in range(1, len(frames))]
    images = list(images) if images is not None else [None] * len(frames)
    if len(names) != len(frames) or len(images) != len(frames) or len(set(names)) != len(names):
        raise ValueError("register_views: need one distinct name (and one image or None) per view")
    # small matrices: BLAS threads only cost time here (10x in L-BFGS on 2 cores)
    with _threadpools().limit(limits=1, user_api="blas"):
        return _register_views(preop, frames, names, images, method, refine_pose, alpha, beta)


def _prepare_view(preop, mask2d, P, name, image, method, refine_pose, timings) -> _ViewState:
    """One view's 2D side: skeleton graph, classification (Alg. 1), pose, visibility."""
    with _timed(timings, "skeleton2d"):
        g2 = _skeleton2d_graph(mask2d, 1.0 / pixels_per_mm(P, preop.centre))
    c2 = unclassified = None
    if refine_pose or method == "proposed":
        with _timed(timings, "graph2d"):
            try:
                c2 = _classify_2d(g2, P, preop.centre)
                g2 = c2.graph
            except ValueError as exc:        # e.g. a lateral view: vessels overlap, ends merge
                unclassified = str(exc)
            # pixel staircase smoothed away: eq. (4) compares path lengths along it
            g2 = graph.smooth_positions(g2, SMOOTHING_ITERATIONS)
    if refine_pose and c2 is not None:
        with _timed(timings, "pose_refinement"):
            P = _refined_projection(preop, g2, c2, P)
    view = _ViewState(name, P, g2, c2, frame_visibility(mask2d, image), unclassified=unclassified)
    _frame_projection(preop, view, P)
    return view


def _alternatives(preop, views, trials, best, alpha, beta) -> list:
    """The registrations to fall back on: the other candidate combinations and, with several
    views, each view alone with its chosen correspondence."""
    found = [(positions, f"candidate {k + 1}") for k, ((positions, _, _), combo) in enumerate(trials) if combo is not best]
    if len(views) > 1:
        found += [(_deform_with(preop, [view], (chosen,), alpha, beta)[0], f"view {view.name} alone")
                  for view, chosen in zip(views, best) if chosen is not None]
    return found


def _full_combination(views, combo) -> tuple:
    """A combination over the classified views, with None for each unclassified one."""
    chosen = iter(combo)
    return tuple(None if v.c2 is None else next(chosen) for v in views)


def _with_unclassified_views(preop, views, combo, deformed, alpha, beta):
    """Add the views without a classification: passes of nearest-point targets (from the last
    result) beside the classified views' assignments, until the nodes settle."""
    full = _full_combination(views, combo)
    energy = None
    for _ in range(CLOSEST_POINT_PASSES):
        previous = deformed
        deformed, energy, _ = _deform_with(preop, views, full, alpha, beta, estimate=deformed)
        if np.linalg.norm(deformed - previous, axis=1).mean() < CLOSEST_POINT_SETTLED_MM:
            break
    return deformed, energy, full


def _register_views(preop, frames, names, images, method, refine_pose, alpha, beta) -> FrameResult:
    timings = {}
    views, warnings, failures = [], [], []
    for (mask2d, P), name, image in zip(frames, names, images):
        try:
            views.append(_prepare_view(preop, mask2d, P, name, image, method, refine_pose, timings))
        except ValueError as exc:
            # one unreadable view (vessels overlapping at a steep angle) must not sink the others
            failures.append(exc)
            warnings.append(f"view {name} not used: {exc}")
    if not views:
        raise ValueError(f"view {names[0]}: {failures[0]}" if len(frames) > 1 else str(failures[0])) from failures[0]
    points = preop.centerline.points
    energy, source = None, method
    if method == "rigid":
        deformed = points
    elif method == "icp-tps":
        if len(views) > 1:
            warnings.append(f"icp-tps registers one frame: used view {views[0].name} only")
        with _timed(timings, "registration"):
            deformed = baselines.icp_tps(points, preop.centerline.edges, views[0].g2.positions, views[0].P).points
    else:
        classified = [v for v in views if v.c2 is not None]
        if not classified:
            raise ValueError(views[0].unclassified if len(views) == 1 else
                             f"no view could be classified (view {views[0].name}: {views[0].unclassified})")
        with _timed(timings, "matching"):
            for view in views:
                view.candidates = [None] if view.c2 is None else matching.candidate_correspondences(
                    preop.graph, preop.classification, view.g2, view.c2, view.P)
        combinations = list(itertools.islice(itertools.product(*[v.candidates for v in classified]),
                                             MAX_CANDIDATE_COMBINATIONS))
        with _timed(timings, "deformation"):
            trials = [(_deform_with(preop, classified, combo, alpha, beta), combo) for combo in combinations]
            (deformed, energy, _), best = min(trials, key=lambda t: t[0][2])
            if len(classified) < len(views):
                deformed, energy, best = _with_unclassified_views(preop, views, best, deformed, alpha, beta)
                trials = [(result, _full_combination(views, combo)) for result, combo in trials]
                warnings += [f"view {v.name}: no anatomical classification ({v.unclassified}); registered to "
                             f"its nearest 2D skeleton points" for v in views if v.c2 is None]
        with _timed(timings, "plausibility"):
            deformed, doubts = _never_worse_than_sv(
                deformed, lambda: _alternatives(preop, views, trials, best, alpha, beta), preop, views)
        warnings += doubts
        source = "; ".join(f"{c.source} ({len(v.candidates)} candidate(s))" if c is not None else "nearest points"
                           for v, c in zip(views, best))
    timings["intraop"] = sum(timings.values())
    outside = [int(np.count_nonzero(~v.visible[preop.kept])) for v in views]
    frames_out = [ViewFrame(v.name, v.P, v.g2, v.c2, v.visibility, n_out,
                            (c.source if c is not None else "nearest points") if method == "proposed" else method)
                  for v, n_out, c in zip(views, outside, best if method == "proposed" else [None] * len(views))]
    first = views[0]
    return FrameResult(preop.centerline.with_points(deformed), first.P, first.g2, first.c2, energy, source, timings,
                       frames_out, warnings)


def _read_ground_truth(case: Case) -> Centerline | None:
    path = Path(case.case_dir) / "gt.json" if case.case_dir is not None else None
    if path is None or not os.path.lexists(path):
        return None
    check_inside(path, case.case_dir, "the case folder")
    return io.read_ground_truth(path)


def _vessel_mask(frame, progress=None, prior=None) -> np.ndarray:
    """The given vessel mask of a case or view, or the frame segmented."""
    if frame.fluoro_mask is not None:
        return frame.fluoro_mask
    from . import segmentation

    _report(progress, 0.4, "segmenting vessels in the frame")
    return segmentation.segment_fluoro(frame.fluoro.image, prior)


def _case_views(case: Case) -> list[View]:
    """The case's views (io.load_case), or its one frame for a Case built by hand."""
    if case.views:
        return list(case.views)
    return [View(MAIN_VIEW, case.fluoro, case.fluoro_mask, case.P,
                 {k: case.paths[k] for k in ("fluoro", "fluoro_mask") if k in case.paths})]


def _view_summary(view: View, frame: ViewFrame, deformed: Centerline) -> dict:
    """result.json's entry for one view: pose, 2D error, visibility, files.

    ``2d_px`` is over the nodes whose projection the frame shows (a node outside it has no
    2D evidence to be measured against); ``2d_all_px`` over every node, the paper's measure.
    """
    skeleton = (frame.skeleton2d.positions, frame.skeleton2d.edges())
    errors = evaluation.evaluate(deformed, None, frame.P, *skeleton)
    shown = frame.visibility.shows(project(frame.P, deformed.points))
    fit = evaluation.error_2d(deformed.points[shown], frame.P, *skeleton) if shown.any() else None
    return {"name": view.name, "projection_matrix": np.asarray(frame.P).tolist(), "2d_px": fit,
            "2d_all_px": errors["2d_px"],
            "correspondence": frame.correspondence, "inputs": {k: str(v) for k, v in view.paths.items()},
            "visibility": frame.visibility.to_dict(frame.nodes_outside)}


def _drr_volume(case: Case):
    """The volume a DRR is rendered from: the CT, else the lumen mask (an angiogram), else None."""
    return case.ct if case.ct is not None else case.aorta_mask


def _preop_of(case: Case, preop, progress, segmenter, cache) -> Preoperative:
    if preop is None:
        return prepare_preop(case, progress, segmenter, cache)
    return getattr(preop, "preop", preop)  # a cache.PreopModel or a Preoperative


def run_case(case: Case, *, method: str = "proposed", progress=None, start: str = "iliac_right",
             target: str = "renal_left", refine_pose: bool = False, alpha: float = 500.0,
             beta: float = 10.0, segmenter: str = "classical", preop=None, cache=False, drr="auto") -> PlanResult:
    """Run the whole job on a loaded case: pre-op graph, registration to every view, path, errors.

    Every view of the case (``case.views``: the top-level frame and ``views/<name>/``) takes
    part in one registration (:func:`register_views`). ``segmenter`` ("classical",
    "unet" or "threshold") segments a case that holds only a CT. ``preop`` (a :class:`Preoperative`
    or a :class:`cache.PreopModel`) skips the pre-operative work; ``cache`` keeps it on disk
    (:func:`prepare_preop`). ``drr``: render the geometry check (:mod:`drr`) of the first
    view always (True), never (False) or when its ``P`` came from C-arm tags ("auto").
    """
    planning.check_labels(start, target)
    t0 = time.perf_counter()
    _report(progress, 0.0, "pre-operative skeleton graph")
    with _blamed_on(case.paths.get(case.stage_3d)):
        preop = _preop_of(case, preop, progress, segmenter, cache)
    timings = dict(preop.timings)
    views = _case_views(case)
    by_name = {view.name: view for view in views}
    priors = [quality.FluoroPrior.from_centerline(preop.centerline, view.P) for view in views]
    qc = quality.QCData(case.ct, case.aorta_mask, views[0].fluoro.image, None, priors[0])
    with _blamed_on(case.paths.get(case.stage_3d)):
        quality.check_preop_tree(preop.centerline, case.aorta_mask, qc)     # before registering: both sides
    masks = []
    with _timed(timings, "segmentation2d"):
        for view, prior in zip(views, priors):
            with _blamed_on(_view_frame_path(view)):
                masks.append(_vessel_mask(view, progress, prior))
    qc.mask2d = masks[0]
    for view, mask, prior in zip(views, masks, priors):
        try:
            with _blamed_on(_view_frame_path(view)):
                quality.check_frame_mask(mask, prior, qc, frame=view.fluoro.image if view.has_frame else None)
        except quality.QualityError as exc:
            if view is views[0]:
                raise
            raise quality.QualityError(f"view {view.name}: {exc}", qc) from None
    _report(progress, 0.5, f"registering ({method}, {len(views)} view(s))")
    with _blamed_on(_view_frame_path(views[0])):
        frame = register_views(preop, [(mask, view.P) for mask, view in zip(masks, views)],
                               names=[view.name for view in views],
                               images=[view.fluoro.image if view.has_frame else None for view in views],
                               method=method, refine_pose=refine_pose, alpha=alpha, beta=beta)
    timings.update(frame.timings)
    timings["registration"] = frame.timings["intraop"]
    _report(progress, 0.85, "planning the catheter path")
    with _timed(timings, "planning"):
        path = planning.plan_path(frame.deformed, start=start, target=target)
    sk_edges = frame.skeleton2d.edges()
    gt = _read_ground_truth(case)
    with _blamed_on(Path(case.case_dir) / "gt.json" if gt is not None else None):
        errors = evaluation.evaluate(frame.deformed, gt, frame.P, frame.skeleton2d.positions, sk_edges)
    geometry = case.geometry.to_dict() if case.geometry is not None else None
    drr_image = None
    if (drr is True or (drr == "auto" and geometry and geometry["source"] == "dicom-tags")) and _drr_volume(case) is not None:
        from . import drr as drr_module

        _report(progress, 0.9, "rendering the DRR geometry check")
        with _timed(timings, "drr"):
            drr_image = drr_module.check_drr(_drr_volume(case), case.P, case.fluoro.shape)
    summaries = [_view_summary(by_name[vf.name], vf, frame.deformed) for vf in frame.views]
    timings["total"] = time.perf_counter() - t0
    _report(progress, 1.0, "done")
    return PlanResult(method, preop.centerline, frame.deformed, path, frame.P, frame.skeleton2d.positions,
                      sk_edges, views[0].fluoro.image, timings, errors,
                      {k: str(v) for k, v in case.paths.items()} | {"correspondence": frame.correspondence},
                      qc=qc, geometry=geometry, drr=drr_image, views=summaries, warnings=list(frame.warnings))


def _view_frame_path(view: View):
    """The file a view's frame problems are named after: its vessel mask, else its frame."""
    paths = getattr(view, "paths", None) or {}
    return paths.get("fluoro_mask", paths.get("fluoro"))


@contextmanager
def _blamed_on(path):
    """Turn a plain ``ValueError`` of the block (a skeleton without its branches, a flat frame)
    into an :class:`InputError` naming the input file it came from."""
    try:
        yield
    except ValueError as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if path is None or display_path(path) in message:
            raise
        if isinstance(exc, InputError) and type(exc) is not InputError:
            # a subclass (quality.QualityError) carries more than its message: renamed in place
            exc.args = (f"{display_path(path)}: {message}",)
            raise
        raise InputError(f"{display_path(path)}: {message}") from None


def plan_case(case_dir, out_dir=None, *, method: str = "proposed", progress=None, **overrides) -> PlanResult:
    """Load a case folder (docs/DESIGN.md section 4), run it, and write the outputs if ``out_dir``.

    ``overrides`` are the case-file flags (``ct``, ``aorta_mask``, ``skeleton3d``, ``fluoro``,
    ``fluoro_mask``, ``geometry``, ``frame``) and the options of :func:`run_case`.

    The plausibility gates (:mod:`plausibility`) run around the work: start / target and the
    output folder before anything is read, the anatomy's projection once the case is
    loaded, the frame's vessel tree and the result before anything is written. Their
    warnings, and those of the readers (:class:`InputWarning`), land in
    ``result.warnings``.
    """
    load_keys = {"ct", "aorta_mask", "skeleton3d", "fluoro", "fluoro_mask", "geometry", "frame"}
    plausibility.check_start_target(overrides.get("start") or "iliac_right", overrides.get("target") or "renal_left")
    if out_dir is not None:
        files = [overrides[k] for k in sorted(load_keys - {"frame"}) if overrides.get(k) is not None]
        check_output_folder(out_dir, folders=[case_dir] if case_dir is not None else [], files=files)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputWarning)
        case = load_case(case_dir, **{k: v for k, v in overrides.items() if k in load_keys and v is not None})
    notes = [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    for recorded in caught:      # passed on as they came: the CLI shows ours as notes
        warnings.warn_explicit(recorded.message, recorded.category, recorded.filename, recorded.lineno)
    plausibility.check_anatomy_in_view(case.P, _anatomy_points(case), case.fluoro.shape, case.paths.get("geometry", case_dir))
    try:
        result = run_case(case, method=method, progress=progress,
                          **{k: v for k, v in overrides.items() if k not in load_keys})
    except quality.QualityError as failure:    # the QC picture first, so the user sees why
        if out_dir is not None and failure.qc is not None:
            _write_failure_qc(Path(out_dir), failure)
        raise
    frame_path = case.paths.get("fluoro_mask", case.paths.get("fluoro"))
    plausibility.check_anatomy_in_view(result.P, result.preop.points, case.fluoro.shape, case.paths.get("geometry", case_dir))
    plausibility.check_vessel_tree(result.skeleton2d_points, result.skeleton2d_edges, result.P, result.preop.points,
                                   frame_path)
    gate_notes = plausibility.result_warnings(result.preop, result.deformed, frame_path, method=method)
    for note in gate_notes:
        warnings.warn(note, InputWarning, stacklevel=2)
    result.warnings.extend(notes + gate_notes)
    if out_dir is not None:
        write_outputs(result, out_dir)
    return result


def picture_title(result: PlanResult) -> str:
    """The caption of the pictures: method, view angles, and the 2D number named for what it is.

    Without ground truth the 2D number is the fit to the frame's own skeleton, not an error.
    """
    tags = (result.geometry or {}).get("tags", {})
    if "PositionerPrimaryAngle" in tags:
        view = f"{view_label(tags['PositionerPrimaryAngle'], tags['PositionerSecondaryAngle'])} (tags)"
    else:
        view = f"{export.view_name(result.P, result.deformed.points.mean(axis=0))} (from P)"
    errors = result.errors or {}
    text = f"{result.method} | {view}"
    if errors.get("2d_px"):
        mean = errors["2d_px"]["mean"]
        if errors.get("3d_mm"):
            text += f" | 2D error {mean:.2f} px, 3D error {errors['3d_mm']['mean']:.2f} mm (vs. truth)"
        else:
            text += f" | fit to the frame's own skeleton {mean:.2f} px"
    return text


#: Foreground voxels sampled to check the anatomy's projection before any work.
_ANATOMY_SAMPLES = 4000


def _anatomy_points(case: Case) -> np.ndarray:
    """LPS points of the loaded 3D input: foreground voxels of a mask / skeleton, or the CT's centre."""
    volume = case.reference_volume
    if case.stage_3d == "ct":
        return volume.center_lps()[None]
    kji = np.argwhere(volume.array)
    step = max(1, len(kji) // _ANATOMY_SAMPLES)
    return volume.index_to_lps(kji[::step])


#: The files :func:`write_outputs` writes (``segmentation_qc.png`` when the segmentation QC
#: ran); a folder holding only these, or a ``result.json``, or nothing may be replaced.
OUTPUT_NAMES = ("deformed_centerline.vtp", "path.mrk.json", "overlay.png", "result.json")
QC_NAME = "segmentation_qc.png"
DRR_NAME = "drr_check.png"


def _write_failure_qc(out_dir: Path, failure) -> None:
    """The QC picture of a failed segmentation gate, without touching a previous output set.

    A new or empty output folder gets it as its only file (swapped in whole); a folder that
    holds a previous set keeps it unchanged and the picture goes beside it, as
    ``<out>.segmentation_qc.png``.
    """
    if os.path.isdir(out_dir) and os.listdir(out_dir):
        beside = out_dir.parent / f"{out_dir.name}.{QC_NAME}"
        quality.write_segmentation_qc(beside, failure.qc, str(failure))
        failure.args = (str(failure).replace(f"see {QC_NAME}", f"see {display_path(beside)}"),)
        return
    with atomic_folder(out_dir) as staging:
        quality.write_segmentation_qc(staging / QC_NAME, failure.qc, str(failure))


def check_output_folder(out_dir, folders=(), files=()) -> Path:
    """Refuse an output folder that would overwrite or mix with something else, before any work.

    Refused: ``out_dir`` equal to, inside or containing an input (the case folder or any
    input file's folder); an existing file or special file in its place; a folder that
    holds anything but a previous output set (a ``result.json``) or nothing.
    """
    out = Path(out_dir)
    shown = display_path(out)
    if str(out).strip() == "":
        raise InputError("--out: empty path")
    try:
        str(out).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{shown}: the output folder's name is not valid UTF-8 (the writers cannot take it); "
                         f"choose another name") from None
    target = Path(os.path.realpath(out))
    inputs = [(Path(f), Path(f)) for f in folders] + [(Path(f), Path(f) if Path(f).is_dir() else Path(f).parent)
                                                      for f in files]
    for given, folder in inputs:
        folder = Path(os.path.realpath(folder))
        if target == folder:
            relation = "is the folder of"
        elif folder in target.parents:
            relation = "lies inside the folder of"
        elif target in folder.parents:
            relation = "contains"
        else:
            continue
        raise InputError(f"{shown}: the output folder {relation} the input {display_path(given)}; choose a folder "
                         f"apart from the inputs")
    if os.path.lexists(out):
        if not out.is_dir():
            raise InputError(f"{shown}: exists and is not a folder")
        entries = sorted(os.listdir(out))
        foreign = [name for name in entries if not _looks_like_an_output(out / name)]
        if entries and "result.json" not in entries and not set(entries) <= set(OUTPUT_NAMES + (QC_NAME, DRR_NAME)):
            foreign = entries
        if foreign:
            raise InputError(f"{shown}: the folder holds files that are not a FevarPlanner output set "
                             f"({', '.join(display_path(n) for n in foreign[:3])}{', ...' if len(foreign) > 3 else ''})"
                             f", which replacing the set would delete; choose a new or empty folder")
    elif not out.parent.is_dir() and out.parent.exists():
        raise InputError(f"{shown}: its parent {display_path(out.parent)} is not a folder")
    return out


#: Suffixes of the files an output set is made of; anything else in an output folder (a
#: subfolder, notes) was put there by someone else and is not deleted by a new set.
OUTPUT_SUFFIXES = (".vtp", ".json", ".png", ".csv")


def _looks_like_an_output(path: Path) -> bool:
    return path.is_file() and not path.is_symlink() and path.suffix in OUTPUT_SUFFIXES


def _write_output_set(result: PlanResult, folder: Path) -> dict:
    paths = {name: folder / name for name in OUTPUT_NAMES}
    export.write_centerline_vtp(paths["deformed_centerline.vtp"], result.deformed)
    export.write_path_markups(paths["path.mrk.json"], result.path.points)
    colors, names = PALETTE, export.ROLE_NAMES
    layers = [
        export.centerline_layer(f"{names['preop']} (projected)", result.P, result.preop, colors["preop"]),
        export.centerline_layer(f"{names['recovered']} (projected)", result.P, result.deformed, colors["recovered"]),
        export.path_layer(names["path"], result.P, result.path.points, colors["path"]),
    ]
    export.render_overlay(paths["overlay.png"], result.fluoro_image, skeleton2d=result.skeleton2d_points,
                          layers=layers, title=picture_title(result), P=result.P,
                          anchor=result.deformed.points.mean(axis=0))
    if result.qc is not None:
        paths[QC_NAME] = folder / QC_NAME
        quality.write_segmentation_qc(paths[QC_NAME], result.qc)
    if result.drr is not None:
        from . import drr

        paths[DRR_NAME] = folder / DRR_NAME
        notes = (result.geometry or {}).get("assumptions", [])
        drr.write_drr_check(paths[DRR_NAME], result.fluoro_image, result.drr,
                            title=f"geometry check, {picture_title(result)}", notes=notes)
    export.write_result_json(paths["result.json"], result.to_dict())
    return paths


def write_outputs(result: PlanResult, out_dir, extra=None) -> dict:
    """Write result.json, deformed_centerline.vtp, path.mrk.json and overlay.png into ``out_dir``.

    The whole set is written into a temporary folder beside ``out_dir`` and swapped in at
    the end (:func:`swap_folder`): until then a previous set stays as it was, and a
    failure (a full disk) or a killed process never leaves a half-written or mixed folder.
    Files and the folder get the modes the umask gives new ones. ``extra(folder)``, if
    given, writes further files of the same set into the staging folder and returns their
    paths. Returns the final paths.
    """
    out_dir = Path(out_dir)
    check_output_folder(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.writing.", dir=out_dir.parent))
    try:
        os.chmod(staging, output_mode(folder=True))
        written = _write_output_set(result, staging)
        if extra is not None:
            written.update(extra(staging))
        swap_folder(staging, out_dir)
    except OSError as exc:
        where = display_path(exc.filename) if exc.filename else display_path(out_dir)
        raise InputError(f"{where}: cannot write the outputs ({exc.strerror or exc}); {display_path(out_dir)} "
                         f"was left as it was") from None
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return {name: out_dir / path.name for name, path in written.items()}

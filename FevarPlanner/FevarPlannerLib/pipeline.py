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
import json
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import ThreadpoolController

from . import baselines, deformation, evaluation, export, graph, matching, planning, quality, skeleton
from .alignment import fit_in_plane_rigid
from .centerline import Centerline
from .conventions import IOTA_MM, LPS_DIRECTIONS, PALETTE
from .io import Case, InputError, load_case
from .projection import image_directions, pixels_per_mm, project, view_label

__all__ = ["METHODS", "Preoperative", "FrameResult", "PlanResult", "preop_from_skeleton", "preop_from_lumen",
           "build_preop", "prepare_preop", "picture_title", "register_frame", "run_case", "plan_case", "write_outputs"]

METHODS = ("proposed", "icp-tps", "rigid")
#: Laplacian smoothing passes over both skeletons (graph.smooth_positions), which takes out
#: the voxel / pixel staircase that eq. (4)'s path lengths and the targets inherit. On the
#: simulation protocol with +-1 degree out-of-plane bending, before the 3D skeleton was also
#: centred in the lumen (Testing/benchmarks/bench_registration.py), the mean 2D error fell
#: from 0.61 to 0.13 px and the 3D error from 1.06 to 0.91 mm.
SMOOTHING_ITERATIONS = 10


@contextmanager
def _timed(timings: dict, name: str):
    start = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - start


def _report(progress, fraction: float, message: str) -> None:
    if progress is not None:
        progress(fraction, message)


@dataclass
class Preoperative:
    """The pre-operative 3D skeleton graph, classified and labelled (computed once per patient)."""

    graph: graph.SkeletonGraph
    classification: graph.Classification
    kept: np.ndarray
    centerline: Centerline
    timings: dict = field(default_factory=dict)

    def __post_init__(self):
        # the kept nodes' own graph (node t is graph node kept[t]), for the per-frame TPS fill
        self.kept_adjacency = self.graph.subgraph(self.kept).adjacency
        self.centre = self.centerline.points.mean(axis=0)


@dataclass
class FrameResult:
    """One frame's registration: the deformed kept nodes and how they were found."""

    deformed: Centerline
    P: np.ndarray
    skeleton2d: graph.SkeletonGraph
    classification2d: graph.Classification | None
    energy: float | None
    correspondence: str
    timings: dict


@dataclass
class PlanResult:
    """Everything a caller shows or writes about one case (see docs/DESIGN.md section 4)."""

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

    def to_dict(self) -> dict:
        extra = {"projection_matrix": np.asarray(self.P).tolist(), "inputs": self.inputs}
        if self.errors is not None:
            extra["errors"] = self.errors
        if self.geometry is not None:
            extra["geometry"] = self.geometry
        return export.build_result_dict(self.method, self.preop, self.deformed, self.path, self.timings, **extra)


def _induced_edges(graph_: graph.SkeletonGraph, nodes: np.ndarray) -> np.ndarray:
    """Edges of ``graph_`` between ``nodes``, renumbered to positions in ``nodes``."""
    index = np.full(len(graph_.positions), -1)
    index[nodes] = np.arange(len(nodes))
    edges = index[graph_.edges()]
    return edges[np.all(edges >= 0, axis=1)]


def _skeleton3d_and_lumen(case: Case, progress=None, segmenter: str = "classical"):
    """The case's 3D skeleton volume (given, or thinned from the lumen) and its lumen mask (or None)."""
    mask = case.aorta_mask
    if case.skeleton3d is not None:
        return case.skeleton3d, mask
    if mask is None:
        from . import segmentation

        _report(progress, 0.05, "segmenting the aorta in the CT")
        # the classical route and the UNet report slice by slice: move the bar from 5 to 15 %
        kwargs = {"progress": lambda done, total: _report(progress, 0.05 + 0.1 * done / max(total, 1),
                                                          f"segmenting the aorta: slice {done}/{total}")}
        mask = segmentation.segment_ct(case.ct, segmenter, **(kwargs if segmenter != "threshold" else {}))
    _report(progress, 0.15, "thinning the 3D lumen")
    return skeleton.skeletonize_3d(mask), mask


def preop_from_skeleton(skeleton_volume, timings: dict | None = None, lumen=None) -> Preoperative:
    """Classify (Alg. 1) and label a binary 3D skeleton volume: Algorithm 2 rows 1-2.

    With the ``lumen`` mask it was thinned from, the smoothed skeleton is also centred in
    the lumen's cross-sections (graph.centre_in_lumen, sub-voxel).
    """
    timings = {} if timings is None else timings
    with _timed(timings, "preop_graph3d"):
        # with the lumen, spurs are also judged against the local radius (graph.spur_length)
        g3 = graph.SkeletonGraph.from_volume(skeleton_volume, lumen=lumen)
        c3 = graph.classify(g3, iota=IOTA_MM, directions=LPS_DIRECTIONS)
        # the repaired graph (gaps bridged, small loops broken, spurs isolated), its voxel
        # staircase smoothed away
        g3 = graph.smooth_positions(c3.graph, SMOOTHING_ITERATIONS)
    if lumen is not None:
        with _timed(timings, "preop_centring"):
            g3 = graph.centre_in_lumen(g3, lumen)
    with _timed(timings, "preop_graph3d"):
        c3 = graph.label_anatomy(g3, c3, **LPS_DIRECTIONS)
    kept = np.asarray(c3.kept_nodes())
    labels = [c3.node_labels[i] for i in kept]
    centerline = Centerline(g3.positions[kept], _induced_edges(g3, kept), labels)
    return Preoperative(g3, c3, kept, centerline, timings)


def preop_from_lumen(lumen, timings: dict | None = None) -> Preoperative:
    """Thin a binary 3D lumen mask (a Volume) and build its :class:`Preoperative`, centred in it."""
    return preop_from_skeleton(skeleton.skeletonize_3d(lumen), timings, lumen)


def build_preop(case: Case, progress=None, segmenter: str = "classical"):
    """(:class:`Preoperative`, lumen mask or None) of a case, computed (see :func:`prepare_preop`)."""
    timings = {}
    with _timed(timings, "preop_skeleton3d"):
        skeleton_volume, lumen = _skeleton3d_and_lumen(case, progress, segmenter)
    _report(progress, 0.25, "3D skeleton graph and Algorithm 1")
    return preop_from_skeleton(skeleton_volume, timings, lumen), lumen


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


def _deform_with(preop: Preoperative, g2, c2, P, correspondence, alpha, beta):
    """Algorithm 2 rows 6-16 for one correspondence; returns (kept positions, energy, score).

    The score (matching.candidate_score) picks between candidates: the energy plus the 3D
    implausibility of the result.
    """
    g3, c3 = preop.graph, preop.classification
    assignment = matching.soft_assign(g3, c3, g2, c2, P, correspondence)
    assigned = np.flatnonzero(assignment.assigned)
    result = deformation.deform_assigned(g3.positions[assigned], assignment.targets[assigned],
                                         _induced_edges(g3, assigned), P, alpha=alpha, beta=beta)
    moved = np.array(g3.positions, dtype=float)
    moved[assigned] = result.points
    keep_assigned = assignment.assigned[preop.kept]
    filled = deformation.fill_unassigned(g3.positions[preop.kept], moved[preop.kept], keep_assigned,
                                         preop.kept_adjacency)
    score = matching.candidate_score(result.energy_final, keep_assigned.mean(), preop.centerline.points, filled,
                                     preop.centerline.edges, alpha)
    return filled, float(result.energy_final), score


@functools.cache
def _threadpools() -> ThreadpoolController:
    """The process's BLAS / OpenMP pools, found once (finding them costs about 3 ms a frame)."""
    return ThreadpoolController()


def register_frame(preop: Preoperative, mask2d: np.ndarray, P: np.ndarray, *, method: str = "proposed",
                   refine_pose: bool = False, alpha: float = 500.0, beta: float = 10.0) -> FrameResult:
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
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    # small matrices: BLAS threads only cost time here (10x in L-BFGS on 2 cores)
    with _threadpools().limit(limits=1, user_api="blas"):
        return _register_frame(preop, mask2d, P, method, refine_pose, alpha, beta)


def _register_frame(preop, mask2d, P, method, refine_pose, alpha, beta) -> FrameResult:
    timings = {}
    with _timed(timings, "skeleton2d"):
        g2 = _skeleton2d_graph(mask2d, 1.0 / pixels_per_mm(P, preop.centre))
    c2 = None
    if refine_pose or method == "proposed":
        with _timed(timings, "graph2d"):
            c2 = _classify_2d(g2, P, preop.centre)
            # pixel staircase smoothed away: eq. (4) compares path lengths along it
            g2 = graph.smooth_positions(c2.graph, SMOOTHING_ITERATIONS)
    if refine_pose:
        with _timed(timings, "pose_refinement"):
            P = _refined_projection(preop, g2, c2, P)
    points = preop.centerline.points
    energy, source = None, method
    if method == "rigid":
        deformed = points
    elif method == "icp-tps":
        with _timed(timings, "registration"):
            deformed = baselines.icp_tps(points, preop.centerline.edges, g2.positions, P).points
    else:
        with _timed(timings, "matching"):
            candidates = matching.candidate_correspondences(preop.graph, preop.classification, g2, c2, P)
        with _timed(timings, "deformation"):
            trials = [(_deform_with(preop, g2, c2, P, c, alpha, beta), c) for c in candidates]
            (deformed, energy, _), best = min(trials, key=lambda t: t[0][2])
        source = f"{best.source} ({len(candidates)} candidate(s))"
    timings["intraop"] = sum(timings.values())
    return FrameResult(preop.centerline.with_points(deformed), P, g2, c2, energy, source, timings)


def _read_ground_truth(case: Case) -> Centerline | None:
    path = Path(case.case_dir) / "gt.json" if case.case_dir is not None else None
    if path is None or not path.is_file():
        return None
    try:
        return Centerline.from_dict(json.loads(path.read_text())["intraop_centerline"])
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"{path}: unreadable ground truth ({exc})") from None


def _vessel_mask(case: Case, progress=None, prior=None) -> np.ndarray:
    if case.fluoro_mask is not None:
        return case.fluoro_mask
    from . import segmentation

    _report(progress, 0.4, "segmenting vessels in the frame")
    return segmentation.segment_fluoro(case.fluoro.image, prior)


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
    """Run the whole job on a loaded case: pre-op graph, frame registration, path, errors.

    ``segmenter`` ("classical", "unet" or "threshold") segments a case that holds only a CT. ``preop``
    (a :class:`Preoperative` or a :class:`cache.PreopModel`) skips the pre-operative work;
    ``cache`` keeps it on disk (:func:`prepare_preop`). ``drr``: render the geometry check
    (:mod:`drr`) always (True), never (False) or when ``P`` came from C-arm tags ("auto").
    """
    planning.check_labels(start, target)
    t0 = time.perf_counter()
    _report(progress, 0.0, "pre-operative skeleton graph")
    preop = _preop_of(case, preop, progress, segmenter, cache)
    timings = dict(preop.timings)
    prior = quality.FluoroPrior.from_centerline(preop.centerline, case.P)
    qc = quality.QCData(case.ct, case.aorta_mask, case.fluoro.image, None, prior)
    quality.check_preop_tree(preop.centerline, case.aorta_mask, qc)     # before registering: both sides
    with _timed(timings, "segmentation2d"):
        qc.mask2d = mask2d = _vessel_mask(case, progress, prior)
    quality.check_frame_mask(mask2d, prior, qc, frame=case.fluoro.image)
    _report(progress, 0.5, f"registering ({method})")
    frame = register_frame(preop, mask2d, case.P, method=method, refine_pose=refine_pose, alpha=alpha, beta=beta)
    timings.update(frame.timings)
    timings["registration"] = frame.timings["intraop"]
    _report(progress, 0.85, "planning the catheter path")
    with _timed(timings, "planning"):
        path = planning.plan_path(frame.deformed, start=start, target=target)
    sk_edges = frame.skeleton2d.edges()
    gt = _read_ground_truth(case)
    errors = evaluation.evaluate(frame.deformed, gt, frame.P, frame.skeleton2d.positions, sk_edges)
    geometry = case.geometry.to_dict() if case.geometry is not None else None
    drr_image = None
    if (drr is True or (drr == "auto" and geometry and geometry["source"] == "dicom-tags")) and _drr_volume(case) is not None:
        from . import drr as drr_module

        _report(progress, 0.9, "rendering the DRR geometry check")
        with _timed(timings, "drr"):
            drr_image = drr_module.check_drr(_drr_volume(case), case.P, case.fluoro.shape)
    timings["total"] = time.perf_counter() - t0
    _report(progress, 1.0, "done")
    return PlanResult(method, preop.centerline, frame.deformed, path, frame.P, frame.skeleton2d.positions,
                      sk_edges, case.fluoro.image, timings, errors,
                      {k: str(v) for k, v in case.paths.items()} | {"correspondence": frame.correspondence},
                      qc=qc, geometry=geometry, drr=drr_image)


def plan_case(case_dir, out_dir=None, *, method: str = "proposed", progress=None, **overrides) -> PlanResult:
    """Load a case folder (docs/DESIGN.md section 4), run it, and write the outputs if ``out_dir``.

    ``overrides`` are the case-file flags (``ct``, ``aorta_mask``, ``skeleton3d``, ``fluoro``,
    ``fluoro_mask``, ``geometry``, ``frame``) and the options of :func:`run_case`.
    """
    load_keys = {"ct", "aorta_mask", "skeleton3d", "fluoro", "fluoro_mask", "geometry", "frame"}
    case = load_case(case_dir, **{k: v for k, v in overrides.items() if k in load_keys and v is not None})
    try:
        result = run_case(case, method=method, progress=progress,
                          **{k: v for k, v in overrides.items() if k not in load_keys})
    except quality.QualityError as failure:    # the QC picture first, so the user sees why
        if out_dir is not None and failure.qc is not None:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            quality.write_segmentation_qc(Path(out_dir) / "segmentation_qc.png", failure.qc, str(failure))
        raise
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


def write_outputs(result: PlanResult, out_dir) -> dict:
    """Write result.json, deformed_centerline.vtp, path.mrk.json and overlay.png into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {name: out_dir / name for name in
             ("deformed_centerline.vtp", "path.mrk.json", "overlay.png", "result.json")}
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
        quality.write_segmentation_qc(out_dir / "segmentation_qc.png", result.qc)
    if result.drr is not None:
        from . import drr

        paths["drr_check.png"] = out_dir / "drr_check.png"
        notes = (result.geometry or {}).get("assumptions", [])
        drr.write_drr_check(paths["drr_check.png"], result.fluoro_image, result.drr,
                            title=f"geometry check, {picture_title(result)}", notes=notes)
    # result.json last: its presence means every other output is complete
    export.write_result_json(paths["result.json"], result.to_dict())
    return paths

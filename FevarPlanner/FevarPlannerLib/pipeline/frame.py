"""The per-frame side of Algorithm 2 (rows 3-16): the 2D skeleton graph and Algorithm 1 on
it, the pose refinement, matching and soft assignment (:mod:`matching`), the deformation
(:mod:`deformation`), for one view (:func:`register_frame`) or several
(:func:`register_views`). Nothing here depends on more than the frame and the
pre-operative model, which is computed once per patient.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import ThreadpoolController

from .. import baselines, evaluation, graph, matching
from ..alignment import MIN_OFFSET_PX, PoseCheck, check_misalignment
from ..conventions import IOTA_MM
from ..preop import SMOOTHING_ITERATIONS, Preoperative, _timed
from ..projection import image_directions, pixels_per_mm, project
from .fallback import _never_worse_than_sv
from .multiview import (MAX_CANDIDATE_COMBINATIONS, _deform_with, follow_anchor, outside_silhouette_warnings,
                        score_floor)
from .results import FrameResult, METHODS, ViewFrame
from .visibility import FieldSearch, Visibility, find_field, frame_visibility, shutter_filled


def _skeleton2d_graph(mask: np.ndarray, mm_per_pixel: float) -> graph.SkeletonGraph:
    return graph.skeleton_graph_2d(mask, pixel_size=mm_per_pixel, radii=True)


def _classify_2d(g2: graph.SkeletonGraph, P: np.ndarray, at: np.ndarray) -> graph.Classification:
    """Algorithm 1 on the 2D graph (lengths scaled by ``g2.unit_mm``), labelled through ``P``."""
    left, superior = image_directions(P, at)
    # Algorithm 1's iota in pixels at the anatomy's depth (g2.unit_mm is mm per pixel there)
    c2 = graph.classify(g2, iota=IOTA_MM * (1.0 / g2.unit_mm), directions={"left": left, "superior": superior})
    return graph.label_anatomy(c2.graph, c2, left=left, superior=superior)


#: The vessels that a stiff wire moves least: the pose is checked on these alone, so that
#: the deformation of the sac and the iliacs is not mistaken for a misaligned frame. The
#: "aorta" branch of Algorithm 1 is the aorta above its highest junction (the renals).
STABLE_VESSELS = ("aorta", "renal_left", "renal_right")
#: Of a renal artery only the part this close to its ostium (mm of path from the aorta)
#: counts as stable: further out the kidney moves with breathing and the wire.
RENAL_OSTIUM_MM = 25.0
#: Pose modes of :func:`register_views`: check and correct only when the frame is
#: misaligned ("auto", the default), never ("off"), always ("on").
POSE_MODES = ("auto", "off", "on")


def _pose_mode(refine_pose) -> str:
    """``refine_pose`` as one of :data:`POSE_MODES` (True / False are "on" / "off")."""
    if refine_pose is True or refine_pose is False:
        return "on" if refine_pose else "off"
    if refine_pose not in POSE_MODES:
        raise ValueError(f"unknown pose mode {refine_pose!r}; choose one of {', '.join(POSE_MODES)}")
    return refine_pose


def _branch_nodes(classification: graph.Classification, labels) -> np.ndarray:
    nodes = [b.nodes for b in classification.branches if b.label in labels]
    return np.concatenate(nodes) if nodes else np.empty(0, dtype=np.int64)


def _ostium_part(positions: np.ndarray, nodes: np.ndarray, length_mm: float) -> np.ndarray:
    """The first nodes of a branch (ordered from its junction) within ``length_mm`` of path."""
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions[nodes], axis=0), axis=1))])
    return nodes[along <= length_mm]


def _stable_regions(preop: Preoperative) -> dict:
    """3D graph nodes of each stable region: the upper aorta and each renal ostium."""
    g3, c3 = preop.graph, preop.classification
    regions = {}
    for branch in c3.branches:
        if branch.label == "aorta":
            regions["upper_aorta"] = branch.nodes
        elif branch.label in ("renal_left", "renal_right"):
            regions[branch.label] = _ostium_part(g3.positions, branch.nodes, RENAL_OSTIUM_MM)
    return regions


def _pose_check(preop: Preoperative, g2: graph.SkeletonGraph, c2: graph.Classification, P: np.ndarray,
                visibility: "Visibility", mode: str) -> tuple[PoseCheck, list, matching.SoftAssignment]:
    """Test the given ``P`` against the frame on the stable vessels (alignment.check_misalignment).

    The stable regions' 3D nodes that the frame shows are projected through ``P`` and fitted
    in-plane onto the frame's own stable branches (the 2D aorta and renal branches of
    Algorithm 1), starting from ``P`` and from their soft-assigned targets (eqs. 4-5). The
    fit is folded into ``P`` when the regions agree on it, or always with ``mode == "on"``.
    Returns the check, the candidate correspondences under ``P`` and the first one's soft
    assignment (the registration reuses both when ``P`` is kept); the check itself fits the
    renal ostia from their 2D junctions (``side_branch_exits=False``; the same assignment
    unless a renal was counted from the aorta's outline).
    """
    g3, c3 = preop.graph, preop.classification
    candidates = matching.candidate_correspondences(g3, c3, g2, c2, P)
    candidate = candidates[0]
    registration, assignment = matching.soft_assign_with_and_without_exits(g3, c3, g2, c2, P, candidate,
                                                                           shows=visibility.shows)
    projected = project(P, g3.positions)
    regions, targets = {}, {}
    for name, nodes in _stable_regions(preop).items():
        nodes = nodes[assignment.assigned[nodes] & visibility.shows(projected[nodes])]
        regions[name], targets[name] = projected[nodes], assignment.targets[nodes]
    curve = g2.positions[_branch_nodes(c2, STABLE_VESSELS)]
    check = check_misalignment(regions, curve, P, targets=targets, reference="upper_aorta", force=mode == "on")
    return check, candidates, registration


def _held_upper_aorta(preop: Preoperative, g2: graph.SkeletonGraph, c2: graph.Classification, P: np.ndarray,
                      visibility: Visibility, assignment: matching.SoftAssignment) -> matching.SoftAssignment:
    """``assignment`` with the upper aorta's targets on the frame's aorta nearest to its projection.

    The upper aorta is the region a wire does not move (the pose check's premise): under the
    checked ``P`` its projection lies on the frame's aorta, and only its path-length targets
    (eq. 5) would slide it along itself. They do, by up to 8 mm: the 2D aorta's end and
    junction lie pixels away from the projected 3D ones, and the length term then carries
    the slide on; in a cranial or caudal view a slide along the aorta is a depth error, and
    it moves the renal ostia. So its targets are the nearest points of the frame's aorta
    branch (which still follow an aorta that a wire did bend), when the projection of its
    part the frame shows lies on that branch (mean distance up to ``alignment.MIN_OFFSET_PX``,
    where the pose check calls frame and ``P`` agreeing); an upper aorta that moved with the
    patient keeps its path-length targets.
    """
    from scipy.spatial import cKDTree

    nodes = _stable_regions(preop).get("upper_aorta")
    curve = g2.positions[_branch_nodes(c2, ("aorta",))]
    if nodes is None or len(curve) < 2:
        return assignment
    uv = project(P, preop.graph.positions[nodes])
    shown = assignment.assigned[nodes] & visibility.shows(uv)
    if not np.any(shown):
        return assignment
    nodes = nodes[shown]
    distance, nearest = cKDTree(curve).query(uv[shown])
    if distance.mean() > MIN_OFFSET_PX:
        return assignment
    targets = assignment.targets.copy()
    targets[nodes] = curve[nearest]
    return dataclasses.replace(assignment, targets=targets)


def _centred_targets(preop: Preoperative, g2: graph.SkeletonGraph, centred: graph.SkeletonGraph | None,
                     c2: graph.Classification, P: np.ndarray, visibility: Visibility,
                     assignment: matching.SoftAssignment) -> matching.SoftAssignment:
    """``assignment``'s targets taken at the 2D nodes ``centred`` between the vessel's walls
    (:func:`matching.centre_in_outline`; the matching itself stays on the skeleton as thinned),
    then the upper aorta's held (:func:`_held_upper_aorta`, on the thinned aorta: held on the
    centred one, the bench phantom's upper aorta slid by up to 13 px along itself), then moved
    by the route's own errors on the pre-operative lumen (:func:`_route_offsets`)."""
    if centred is None:
        return _held_upper_aorta(preop, g2, c2, P, visibility, assignment)
    held = _held_upper_aorta(preop, g2, c2, P, visibility, matching.targets_at(assignment, centred.positions))
    return matching.offset_targets(held, _route_offsets(preop, P, visibility), g2.radii)


#: Geometries whose route offsets (:func:`_route_offsets`) are kept on the pre-operative model.
ROUTE_OFFSETS_KEPT = 8


def _route_offsets(preop: Preoperative, P: np.ndarray, visibility: Visibility) -> matching.RouteOffsets:
    """:func:`matching.route_offsets` under ``P``, once per ``P``: the pre-operative lumen projected onto
    the frame (:func:`matching.render_lumen`, cut to what the frame exposes) and put through a
    single view's route as the frame is (thinning, Algorithm 1, every candidate match, eqs.
    (4)-(5), centring, the held upper aorta). Kept on ``preop`` for the last
    :data:`ROUTE_OFFSETS_KEPT` geometries (a tracked run keeps its geometry from frame to frame;
    a frame whose pose check corrects ``P`` uses two, and several views one each)."""
    key = (np.asarray(P, dtype=float).tobytes(),) + visibility.key()
    kept = preop.route_offsets
    if key in kept:
        kept[key] = kept.pop(key)           # the most recently used last
        return kept[key]
    assignments, radii2 = _rendered_assignments(preop, P, visibility)
    kept[key] = matching.route_offsets(preop.graph, P, assignments, preop.classification.node_labels, radii2)
    while len(kept) > ROUTE_OFFSETS_KEPT:
        del kept[next(iter(kept))]
    return kept[key]


def _rendered_assignments(preop: Preoperative, P: np.ndarray, visibility: Visibility) -> tuple:
    """The single-view route's assignments (one per candidate match) of the pre-operative tree to its
    own lumen projected through ``P``, and the 2D radii of that route's graph; empty without
    radii or where Algorithm 1 fails on it."""
    if preop.graph.radii is None:
        return [], None
    rendered = matching.render_lumen(preop.graph, P, visibility.shape) & visibility.exposed_mask()
    try:
        c2 = _classify_2d(_skeleton2d_graph(rendered, 1.0 / pixels_per_mm(P, preop.centre)), P, preop.centre)
        g2 = graph.smooth_positions(c2.graph, SMOOTHING_ITERATIONS)
        candidates = matching.candidate_correspondences(preop.graph, preop.classification, g2, c2, P)
    except ValueError:
        return [], None
    centred = matching.centre_in_outline(g2, rendered)
    found = []
    for correspondence in candidates:
        try:
            assignment = matching.soft_assign(preop.graph, preop.classification, g2, c2, P, correspondence,
                                              shows=visibility.shows)
        except ValueError:
            continue
        found.append(_held_upper_aorta(preop, g2, c2, P, visibility, matching.targets_at(assignment, centred.positions)))
    return found, g2.radii


def _uncentred(preop: Preoperative, view: "_ViewState") -> None:
    """Take ``view``'s targets back on the skeleton as thinned (in place): with several views the
    followers' nearest-point passes run on the thinned skeletons, and the anchor's centred targets
    there moved which view the registration check of a foreign second frame blamed
    (test_wrong_frames) while leaving the two-view error as it was (development seed 0: 0.634 /
    0.635 mm)."""
    if view.centred is None:
        return
    view.centred = None
    view.assignments = {key: (c, _centred_targets(preop, view.g2, None, view.c2, view.P, view.visibility,
                                                   matching.targets_at(a, view.g2.positions)))
                        for key, (c, a) in view.assignments.items()}


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
    pose: PoseCheck | None = None        # the in-plane pose check (None: not run)
    assignments: dict = field(default_factory=dict)     # id(correspondence) -> (correspondence, assignment)
    soft_assignments: dict = field(default_factory=dict)    # the same before the targets' corrections
    centred: graph.SkeletonGraph | None = None          # g2 centred between the walls: where targets lie

    def assignment(self, preop: Preoperative, correspondence) -> matching.SoftAssignment:
        """The soft assignment (eqs. 3-5) of the 3D nodes to this view under ``correspondence``.

        Computed once per view and correspondence: the candidate combinations, the
        nearest-point passes and the plausibility alternatives share it.
        """
        key = id(correspondence)
        if key not in self.assignments:     # the correspondence is kept with it: its id stays unique
            found = self._soft_assignment(preop, correspondence)
            held = _centred_targets(preop, self.g2, self.centred, self.c2, self.P, self.visibility, found)
            self.assignments[key] = (correspondence, held)
        return self.assignments[key][1]

    def assigned(self, preop: Preoperative, correspondence) -> np.ndarray:
        """Which 3D nodes :meth:`assignment` assigns (its ``assigned``), without moving its targets when
        it is not there yet: the targets' corrections (:func:`_centred_targets`) keep the nodes."""
        found = self.assignments.get(id(correspondence))
        return found[1].assigned if found is not None else self._soft_assignment(preop, correspondence).assigned

    def _soft_assignment(self, preop: Preoperative, correspondence) -> matching.SoftAssignment:
        """eqs. 3-5 of ``correspondence`` as :func:`matching.soft_assign` gives them, once per correspondence."""
        key = id(correspondence)
        if key not in self.soft_assignments:
            self.soft_assignments[key] = (correspondence, matching.soft_assign(
                preop.graph, preop.classification, self.g2, self.c2, self.P, correspondence,
                shows=self.visibility.shows))
        return self.soft_assignments[key][1]

    @functools.cached_property
    def skeleton_index(self) -> evaluation.SegmentIndex:
        """The 2D skeleton's segments, indexed once for the many 2D fits of the plausibility check;
        centred between the walls where the targets were (a result that follows them lies up to
        4 px off the thinned skeleton beside a sac)."""
        centred = self.g2 if self.centred is None else self.centred
        return evaluation.graph_index(centred.positions, self.g2.edges())


@functools.cache
def _threadpools() -> ThreadpoolController:
    """The process's BLAS / OpenMP pools, found once (finding them costs about 3 ms a frame)."""
    return ThreadpoolController()


def register_frame(preop: Preoperative, mask2d: np.ndarray, P: np.ndarray, *, method: str = "proposed",
                   refine_pose="auto", alpha: float = 500.0, beta: float = 10.0,
                   image: np.ndarray | None = None, name: str = "main",
                   search: FieldSearch | None = None) -> FrameResult:
    """Register the pre-operative skeleton to one frame's 2D vessel mask (the per-frame part).

    Parameters
    ----------
    preop : Preoperative
    mask2d : (rows, cols) bool
        Vessel mask on the frame's grid.
    P : (3, 4)
        Projection matrix (rigid pre-alignment, eq. 1).
    method : {"proposed", "icp-tps", "rigid"}
    refine_pose : {"auto", "off", "on"} or bool
        The in-plane pose check (:func:`_pose_check`, alignment.check_misalignment). "auto"
        (the default) corrects ``P`` only when the upper aorta and both renal ostia agree on
        one rigid in-plane offset of the frame (a misaligned ``P``, not a deformation) and
        only for the proposed method; "on" (True) applies the fit always and to every method;
        "off" (False) keeps ``P`` as given. What was found is in ``FrameResult.views`` and,
        when applied, in the warnings.
    alpha, beta : float
        Weights of the length and smoothness terms (eq. 6).
    image : (rows, cols) array, optional
        The raw frame, to find collimated borders (:func:`frame_visibility`).
    name : str
        The view's name in the result.
    search : FieldSearch, optional
        ``image``'s surround search when the segmentation did it already
        (:func:`segment_frame_and_field`), so that the visibility does not search the frame again.
    """
    return register_views(preop, [(mask2d, P)], names=[name], images=[image], method=method,
                          refine_pose=refine_pose, alpha=alpha, beta=beta, searches=[search])


def register_flipped(preop: Preoperative, mask2d: np.ndarray, P: np.ndarray, *, image: np.ndarray | None = None,
                     refine_pose="auto", alpha: float = 500.0, beta: float = 10.0) -> FrameResult | None:
    """The frame registered flipped left-right (proposed method), or None when that fails.

    The mirror test's other hypothesis (issue 11, :func:`plausibility.check_not_mirrored`): a
    frame shown with the wrong side convention is, flipped, the right one. ``mask2d``,
    ``image`` and ``P`` are the frame's as given (:func:`register_frame`); a flipped frame
    that cannot be registered is no evidence either way.
    """
    return register_view_flipped(preop, [(mask2d, P)], 0, images=[image], refine_pose=refine_pose, alpha=alpha,
                                 beta=beta)


def register_view_flipped(preop: Preoperative, frames, flip: int, *, names=None, images=None, refine_pose="auto",
                          alpha: float = 500.0, beta: float = 10.0) -> FrameResult | None:
    """Several views registered together (:func:`register_views`) with view ``flip``'s frame
    flipped left-right, the others as given; None when that fails.

    The mirror test of one view of several: a view shown with the wrong side convention
    is, flipped, consistent with the others in 3D, and the joint registration needs less
    non-rigid motion and energy. The result's first view is the first given.
    """
    def flipped(array):
        return None if array is None else np.ascontiguousarray(np.asarray(array)[:, ::-1])

    frames = [(flipped(mask) if k == flip else mask, P) for k, (mask, P) in enumerate(frames)]
    images = list(images) if images is not None else [None] * len(frames)
    images = [flipped(image) if k == flip else image for k, image in enumerate(images)]
    try:
        return register_views(preop, frames, names=names, images=images, refine_pose=refine_pose, alpha=alpha,
                              beta=beta)
    except Exception:       # noqa: BLE001  (any failure of the flipped frame: no evidence)
        return None


def register_views(preop: Preoperative, frames, *, names=None, images=None, method: str = "proposed",
                   refine_pose="auto", alpha: float = 500.0, beta: float = 10.0, searches=None) -> FrameResult:
    """Register the pre-operative skeleton to several frames of the same anatomy at once.

    Each view gets its own 2D skeleton graph and classification (Algorithm 1). The first
    view that Algorithm 1 classifies is the anchor: its candidate correspondences and soft
    assignment (eqs. 3-5) give the first deformation alone. Every other view follows from
    that estimate: passes of nearest-point targets on its 2D skeleton, each 3D branch on the
    2D leg assigned to it one-to-one (``multiview._closest_point_data``), beside the
    anchor's targets re-taken on its matched chains, with one deformation (eq. 6) and the
    data term averaged over the views, so that views at different C-arm angles fix the
    depth that one view leaves open. A second view's own labels are not used: they are
    found without the first view, and where its legs overlap below the bifurcation (50-70
    degrees) its 2D junction is where they part in the image, 20-30 mm below the
    anatomical one, which stretched the aorta to it. A node gets no data term in a view
    that does not show it (outside the frame, in a collimated band, beyond a border the
    vessel runs out of: :func:`frame_visibility`). Each vessel of the result is then
    checked against the undeformed start (:func:`_never_worse_than_sv`), and a main vessel
    lying outside a view's silhouette is flagged
    (``multiview.outside_silhouette_warnings``). A view whose 2D skeleton cannot be read is
    left out with a warning while another one remains; one Algorithm 1 cannot classify
    follows like any other (a warning says so).

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
    searches : sequence of FieldSearch or None, optional
        Each image's surround search when it was done already (:func:`register_frame`).

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
    searches = list(searches) if searches is not None else [None] * len(frames)
    if len(names) != len(frames) or len(images) != len(frames) or len(searches) != len(frames) \
            or len(set(names)) != len(names):
        raise ValueError("register_views: need one distinct name (and one image or None) per view")
    sources = [ViewSource(name, P, image, mask=mask2d, search=search)
               for (mask2d, P), name, image, search in zip(frames, names, images, searches)]
    return register_prepared(preop, prepare_views(preop, sources, method=method, refine_pose=refine_pose),
                             method=method, alpha=alpha, beta=beta)


def register_prepared(preop: Preoperative, outcomes, *, method: str = "proposed", alpha: float = 500.0,
                      beta: float = 10.0) -> FrameResult:
    """:func:`register_views` on views whose 2D side :func:`prepare_views` has done (same ``method``)."""
    # small matrices: BLAS threads only cost time here (10x in L-BFGS on 2 cores)
    with _threadpools().limit(limits=1, user_api="blas"):
        return _register_views(preop, outcomes, method, alpha, beta)


@dataclass
class ViewSource:
    """What one view's 2D work starts from (:func:`prepare_views`).

    Attributes
    ----------
    name : str
    P : (3, 4) array
    image : (rows, cols) array or None
        The frame: segmented when no mask is given and, when ``real_frame``, used for the
        collimator detection and the frame check's contrast.
    mask : (rows, cols) bool array or None
        The vessel mask as it is to be used; None: ``given_mask`` repaired
        (:func:`given_mask.condition_given_mask`), else ``image`` segmented with ``prior``.
    given_mask : (rows, cols) array or None
        A mask read from the case, to be repaired first.
    prior : quality.FluoroPrior or None
        The projected pre-operative tree: the segmentation's prior and the frame check's.
    check : bool
        Run the frame check (:func:`quality.check_frame_mask`) on the mask.
    real_frame : bool
        ``image`` is a real frame (not a stand-in drawn from the mask).
    search : FieldSearch or None
        ``image``'s surround search, when done already with ``mask``
        (:func:`segment_frame_and_field`).
    """

    name: str
    P: np.ndarray
    image: np.ndarray | None = None
    mask: np.ndarray | None = None
    given_mask: np.ndarray | None = None
    prior: object | None = None
    check: bool = False
    real_frame: bool = True
    search: FieldSearch | None = None

    @property
    def frame(self) -> np.ndarray | None:
        """The real frame, or None."""
        return self.image if self.real_frame else None


@dataclass
class ViewOutcome:
    """One view's 2D side as :func:`prepare_views` left it: each step's result or its error.

    The errors are kept, not raised, so that the caller raises them in the order of the
    serial work (every view's mask, then every view's frame check, then the registration).
    """

    name: str
    mask: np.ndarray | None = None
    view: _ViewState | None = None
    mask_error: Exception | None = None
    check_error: Exception | None = None
    view_error: Exception | None = None
    timings: dict = field(default_factory=dict)
    cpu_seconds: float = 0.0        # CPU time of the process that did the work, for the benchmarks
    in_worker: bool = False         # done by the worker process
    check_job: object | None = field(default=None, repr=False)     # the frame check, still running in the worker

    def finish_check(self) -> Exception | None:
        """The frame check's error (None: passed or not asked for), waiting for it if it still runs."""
        if self.check_job is not None:
            job, self.check_job = self.check_job, None
            self.check_error = job.result()
        return self.check_error


def _source_mask(source: ViewSource) -> np.ndarray:
    """The view's vessel mask: as given, a given one repaired, or the frame segmented."""
    return _source_mask_and_field(source)[0]


def _source_mask_and_field(source: ViewSource) -> tuple[np.ndarray, FieldSearch | None]:
    """:func:`_source_mask` and, when it segmented the frame, the frame's surround search
    (:func:`find_field`) the segmentation used, for the visibility to reuse; with a mask given,
    the search given with it (``ViewSource.search``); else None."""
    if source.mask is not None:
        return source.mask, source.search
    if source.given_mask is not None:
        from ..given_mask import condition_given_mask

        return condition_given_mask(source.given_mask), None
    return segment_frame_and_field(source.image, source.prior)


def segment_frame(image: np.ndarray, prior) -> np.ndarray:
    """A raw frame's vessel mask, as ``plan`` and ``track`` both take it: segmented with the
    projected tree ``prior`` (:func:`segmentation.segment_fluoro`) on the frame whose round or
    shaped field's surround is filled (:func:`shutter_filled`), and no vessel kept there."""
    return segment_frame_and_field(image, prior)[0]


def segment_frame_and_field(image: np.ndarray, prior) -> tuple[np.ndarray, FieldSearch | None]:
    """:func:`segment_frame`'s mask and the surround search its frame was filled by
    (:func:`find_field`; None for a run of frames), which :func:`register_frame` takes back
    (``search``) so that a frame's round field or shutters are searched once."""
    from .. import segmentation

    search = find_field(image)
    frame, unexposed = shutter_filled(image, search)
    mask = segmentation.segment_fluoro(frame, prior)
    return (mask & ~unexposed if unexposed is not None else mask), search


def _view_stage(preop: Preoperative, source: ViewSource, method: str, refine_pose, centre: bool = True) -> ViewOutcome:
    """One view's whole 2D side: mask, frame check, then :func:`_prepare_view`; errors kept."""
    outcome = ViewOutcome(source.name)
    start = time.process_time()
    try:
        _view_steps(preop, source, method, refine_pose, outcome, centre)
    finally:
        outcome.cpu_seconds = time.process_time() - start
    return outcome


def _view_steps(preop: Preoperative, source: ViewSource, method: str, refine_pose, outcome: ViewOutcome,
                centre: bool = True) -> None:
    """The steps of :func:`_view_stage`, each result or error written into ``outcome``."""
    try:
        with _timed(outcome.timings, "segmentation2d"):
            outcome.mask, search = _source_mask_and_field(source)
    except Exception as exc:        # noqa: BLE001  (raised by the caller, in the serial order)
        outcome.mask_error = exc
        return
    if source.check:
        from . import workers

        # the check does not feed the registration: in the worker (when idle) while this goes on
        job = workers.submit(_frame_check, preop, outcome.mask, source.prior, source.frame)
        if job.remote:
            outcome.check_job = job
        else:
            with _timed(outcome.timings, "frame_check"):
                outcome.check_error = job.result()
    try:
        with _threadpools().limit(limits=1, user_api="blas"):
            outcome.view = _prepare_view(preop, outcome.mask, source.P, source.name, source.frame, method,
                                         refine_pose, outcome.timings, centre,
                                         search if source.frame is not None else None)
    except Exception as exc:        # noqa: BLE001
        outcome.view_error = exc


def _frame_check(preop: Preoperative, mask: np.ndarray, prior, frame: np.ndarray | None) -> Exception | None:
    """:func:`quality.check_frame_mask` of a view's mask: its error, or None when it passes."""
    return _frame_check_report(preop, mask, prior, frame)[0]


def _frame_check_report(preop: Preoperative, mask: np.ndarray, prior, frame: np.ndarray | None,
                        run_dense_side: int | None = None) -> tuple[Exception | None, dict | None]:
    """:func:`quality.check_frame_mask` of a view's mask (``run_dense_side``: a run's display
    polarity, when known): (its error or None, its report when it passes)."""
    from .. import quality

    try:
        report = quality.check_frame_mask(mask, prior, None, frame=frame, run_dense_side=run_dense_side)
    except Exception as exc:        # noqa: BLE001  (raised by the caller, in the serial order)
        return exc, None
    return None, report


def _rekeyed(outcome: ViewOutcome) -> ViewOutcome:
    """An outcome from the worker with its view's assignments keyed by the ids of the unpickled
    correspondences (the cache key of :meth:`_ViewState.assignment`)."""
    if outcome.view is not None:
        outcome.view.assignments = {id(c): (c, a) for c, a in outcome.view.assignments.values()}
        outcome.view.soft_assignments = {id(c): (c, a) for c, a in outcome.view.soft_assignments.values()}
    outcome.in_worker = True
    return outcome


def prepare_views(preop: Preoperative, sources, *, method: str = "proposed", refine_pose="auto") -> list[ViewOutcome]:
    """The 2D side of every view (:func:`_view_stage`), in pairs: the second of each in the worker.

    With several views, the worker process (:mod:`workers`) does the second view of each
    pair while this process does the first; when the worker is off, not started yet or
    fails, both run here. The outcomes are the same either way, in the order of ``sources``.
    A frame check that the idle worker took (one view) may still run: the caller collects it
    (:func:`finish_checks`) before it uses or raises anything of the outcomes.
    """
    from . import workers

    sources = list(sources)
    centre = len(sources) == 1      # centred targets are a single view's (_uncentred)
    outcomes = []
    for first in range(0, len(sources), 2):
        job = (workers.submit(_view_stage, preop, sources[first + 1], method, refine_pose, centre)
               if first + 1 < len(sources) else None)
        try:
            outcomes.append(_view_stage(preop, sources[first], method, refine_pose, centre))
        except BaseException:       # interrupted: the worker's answer must not be left in its pipe
            if job is not None and job.remote:
                job.result()
            finish_checks(outcomes)
            raise
        if job is not None:
            outcomes.append(_rekeyed(job.result()) if job.remote else job.result())
    return outcomes


def finish_checks(outcomes) -> None:
    """Wait for the frame checks still running in the worker (:meth:`ViewOutcome.finish_check`)."""
    for outcome in outcomes:
        outcome.finish_check()


def _prepare_view(preop, mask2d, P, name, image, method, refine_pose, timings, centre: bool = True,
                  search: FieldSearch | None = None) -> _ViewState:
    """One view's 2D side: skeleton graph, classification (Alg. 1), pose, visibility; with
    ``centre`` the 2D nodes centred between the vessel's walls, where a single view's targets lie
    (:func:`_centred_targets`; a view of several would drop them, :func:`_uncentred`). ``search``:
    ``image``'s surround search when the segmentation did it (:func:`segment_frame_and_field`), so
    that the visibility does not search the frame a second time."""
    with _timed(timings, "skeleton2d"):
        g2 = _skeleton2d_graph(mask2d, 1.0 / pixels_per_mm(P, preop.centre))
    c2 = unclassified = centred = None
    mode = _pose_mode(refine_pose)
    if mode == "on" or method == "proposed":
        with _timed(timings, "graph2d"):
            try:
                c2 = _classify_2d(g2, P, preop.centre)
                g2 = c2.graph
            except ValueError as exc:        # e.g. a lateral view: vessels overlap, ends merge
                unclassified = str(exc)
            # pixel staircase smoothed away: eq. (4) compares path lengths along it
            g2 = graph.smooth_positions(g2, SMOOTHING_ITERATIONS)
            centred = matching.centre_in_outline(g2, mask2d) if centre else None
    visibility = frame_visibility(mask2d, image, search)
    pose = kept = None
    if c2 is not None and (mode == "on" or (mode == "auto" and method == "proposed")):
        with _timed(timings, "pose_refinement"):
            pose, candidates, assignment = _pose_check(preop, g2, c2, P, visibility, mode)
        if np.array_equal(pose.P, P):       # P kept: the check's matching under it stands
            held = _centred_targets(preop, g2, centred, c2, P, visibility, assignment)
            kept = candidates, {id(candidates[0]): (candidates[0], held)}
        P = pose.P
    view = _ViewState(name, P, g2, c2, visibility, unclassified=unclassified, pose=pose, centred=centred)
    if kept is not None and method == "proposed":
        view.candidates, view.assignments = kept
    _frame_projection(preop, view, P)
    return view


def _pose_warning(view: "_ViewState") -> str | None:
    """The warning of an applied pose correction: the geometry deserves a look."""
    if view.pose is None or not view.pose.applied:
        return None
    (du, dv), turn = view.pose.translation_px, view.pose.rotation_deg
    return (f"view {view.name}: frame and P disagreed by {view.pose.offset_px:.1f} px (shift {du:+.1f}, {dv:+.1f} px, "
            f"turn {turn:+.1f} deg): corrected in-plane; check the geometry")


def _candidate_trials(preop, anchor, alpha, beta) -> tuple[list, int]:
    """The anchor's candidate correspondences, each as (its deformation, a 1-tuple of it), and the
    index of the one with the least score (the first of equals, as ``min`` picks).

    A deformation is a cached call of :func:`_deform_with` that gives (kept positions, energy,
    score). A candidate whose score cannot go below the best so far (:func:`multiview.score_floor`)
    is not deformed here: only a fallback that asks for it (:func:`_alternatives`) deforms it.
    """
    trials, best, best_score = [], 0, None
    for c in anchor.candidates[:MAX_CANDIDATE_COMBINATIONS]:
        deform = functools.cache(functools.partial(_deform_with, preop, [anchor], (c,), alpha, beta))
        trials.append((deform, (c,)))
        if best_score is not None and not score_floor(preop, [anchor], (c,), alpha) < best_score:
            continue
        score = deform()[2]
        if best_score is None or score < best_score:
            best, best_score = len(trials) - 1, score
    return trials, best


def _alternatives(preop, views, trials, best, alpha, beta) -> list:
    """The registrations to fall back on: the other candidate combinations (deformed now if
    :func:`_candidate_trials` left them) and, with several views, each view alone with its
    chosen correspondence."""
    found = [(result()[0], f"candidate {k + 1}") for k, (result, combo) in enumerate(trials) if combo is not best]
    if len(views) > 1:
        found += [(_deform_with(preop, [view], (chosen,), alpha, beta)[0], f"view {view.name} alone")
                  for view, chosen in zip(views, best) if chosen is not None]
    return found


def _full_combination(views, anchor, combo) -> tuple:
    """The anchor's correspondence ``combo`` (a 1-tuple) spread over the views, None for every other."""
    return tuple(combo[0] if v is anchor else None for v in views)


def _with_followers(preop, views, anchor, combo, deformed, alpha, beta):
    """Add the views that follow the anchor: passes of nearest-point targets (from the last
    result) beside the anchor's assignment, until the nodes settle (:func:`register_views`)."""
    full = _full_combination(views, anchor, combo)
    deformed, energy = follow_anchor(preop, views, full, deformed, alpha, beta)
    return deformed, energy, full


def _register_views(preop, outcomes, method, alpha, beta) -> FrameResult:
    timings = {}
    views, warnings, failures = [], [], []
    for outcome in outcomes:
        for stage in ("skeleton2d", "graph2d", "pose_refinement"):
            if stage in outcome.timings:
                timings[stage] = timings.get(stage, 0.0) + outcome.timings[stage]
        error = outcome.mask_error or outcome.view_error
        if error is not None and not isinstance(error, ValueError):
            raise error
        if error is None:
            views.append(outcome.view)
        else:
            # one unreadable view (vessels overlapping at a steep angle) must not sink the others
            failures.append(error)
            warnings.append(f"view {outcome.name} not used: {error}")
    if not views:
        raise ValueError(f"view {outcomes[0].name}: {failures[0]}" if len(outcomes) > 1 else str(failures[0])) from failures[0]
    warnings += [w for w in map(_pose_warning, views) if w]
    if len(views) > 1:       # centred targets (matching.centre_in_outline) for a single view only
        for view in views:
            _uncentred(preop, view)
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
        anchor = classified[0]
        with _timed(timings, "matching"):
            if not anchor.candidates:         # not already found by the pose check under this P
                anchor.candidates = matching.candidate_correspondences(preop.graph, preop.classification, anchor.g2,
                                                                       anchor.c2, anchor.P)
        with _timed(timings, "deformation"):
            trials, best = _candidate_trials(preop, anchor, alpha, beta)
            deformed, energy, _ = trials[best][0]()
            best = trials[best][1]
            if len(views) > 1:
                deformed, energy, best = _with_followers(preop, views, anchor, best, deformed, alpha, beta)
                trials = [(result, _full_combination(views, anchor, combo)) for result, combo in trials]
                warnings += [f"view {v.name}: no anatomical classification ({v.unclassified}); registered to "
                             f"its nearest 2D skeleton points" for v in views if v.c2 is None]
        with _timed(timings, "plausibility"):
            deformed, doubts = _never_worse_than_sv(
                deformed, lambda: _alternatives(preop, views, trials, best, alpha, beta), preop, views)
        warnings += doubts
        if len(views) > 1:
            warnings += outside_silhouette_warnings(preop, views, deformed)
        source = "; ".join(f"{c.source} ({len(v.candidates)} candidate(s))" if c is not None else "nearest points"
                           for v, c in zip(views, best))
    timings["intraop"] = sum(timings.values())
    outside = [int(np.count_nonzero(~v.visible[preop.kept])) for v in views]
    frames_out = [ViewFrame(v.name, v.P, v.g2, v.c2, v.visibility, n_out,
                            (c.source if c is not None else "nearest points") if method == "proposed" else method,
                            None if v.pose is None else v.pose.to_dict())
                  for v, n_out, c in zip(views, outside, best if method == "proposed" else [None] * len(views))]
    first = views[0]
    return FrameResult(preop.centerline.with_points(deformed), first.P, first.g2, first.c2, energy, source, timings,
                       frames_out, warnings)

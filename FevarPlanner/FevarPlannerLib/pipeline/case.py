"""A whole case: read, gated (:mod:`plausibility`), registered, planned and evaluated
(:func:`run_case`), and the same from a case folder with its outputs written
(:func:`plan_case`); :func:`prepare_preop` gives the pre-operative model, cached or not.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .. import evaluation, io, planning, plausibility, quality, skeleton
from ..centerline import Centerline
from ..files import InputError, InputWarning, check_inside, display_path
from ..io import MAIN_VIEW, Case, View, load_case
from ..preop import Preoperative, _report, _timed, build_preop
from ..projection import project
from .frame import ViewSource, _source_mask, finish_checks, prepare_views, register_prepared, register_view_flipped
from .outputs import check_output_folder, refusal_picture, write_outputs
from .results import PlanResult, ViewFrame


def prepare_preop(case: Case, progress=None, segmenter: str = "classical", cache=False) -> Preoperative:
    """3D skeleton graph of the pre-operative anatomy, classified (Alg. 1), centred and labelled.

    A case holding only a CT is segmented first with ``segmenter`` ("classical", "unet" or "threshold").
    ``cache``: True (the default cache folder) or a folder keeps the result on disk and
    reuses it for the same inputs (:mod:`cache`); False computes it.
    """
    if cache is False or cache is None:
        return build_preop(case, progress, segmenter)[0]
    from .. import cache as preop_cache

    folder = None if cache is True else cache
    return preop_cache.preop_model(case, segmenter=segmenter, progress=progress, cache_dir=folder).preop


def _read_ground_truth(case: Case) -> Centerline | None:
    path = Path(case.case_dir) / "gt.json" if case.case_dir is not None else None
    if path is None or not os.path.lexists(path):
        return None
    check_inside(path, case.case_dir, "the case folder")
    return io.read_ground_truth(path)


def _vessel_mask(frame, progress=None, prior=None) -> np.ndarray:
    """The given vessel mask of a case or view (its JPEG / binarisation damage repaired), or the
    frame segmented."""
    if frame.fluoro_mask is not None:
        return _source_mask(ViewSource("", None, given_mask=frame.fluoro_mask))
    _report(progress, 0.4, "segmenting vessels in the frame")
    return _source_mask(ViewSource("", None, frame.fluoro.image, prior=prior))


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
            "visibility": frame.visibility.to_dict(frame.nodes_outside), "pose_correction": frame.pose_correction}


def _drr_volume(case: Case):
    """The volume a DRR is rendered from: the CT, else the lumen mask (an angiogram), else None."""
    return case.ct if case.ct is not None else case.aorta_mask


def _preop_of(case: Case, preop, progress, segmenter, cache):
    """(:class:`Preoperative`, the lumen it was built from or None): the given mask, else the
    segmented CT's lumen (so that the quality gate and the QC picture see it too)."""
    if preop is None and cache not in (False, None):
        from .. import cache as preop_cache

        preop = preop_cache.preop_model(case, segmenter=segmenter, progress=progress,
                                        cache_dir=None if cache is True else cache)
    elif preop is None:
        return build_preop(case, progress, segmenter)
    return getattr(preop, "preop", preop), getattr(preop, "lumen", None)  # a cache.PreopModel or a Preoperative


def run_case(case: Case, *, method: str = "proposed", progress=None, start: str = "iliac_right",
             target: str = "renal_left", refine_pose="auto", alpha: float = 500.0,
             beta: float = 10.0, segmenter: str = "classical", preop=None, cache=False, drr="auto",
             mirror_test: bool = False) -> PlanResult:
    """Run the whole job on a loaded case: pre-op graph, registration to every view, path, errors.

    Every view of the case (``case.views``: the top-level frame and ``views/<name>/``) takes
    part in one registration (:func:`register_views`). ``segmenter`` ("classical",
    "unet" or "threshold") segments a case that holds only a CT. ``preop`` (a :class:`Preoperative`
    or a :class:`cache.PreopModel`) skips the pre-operative work; ``cache`` keeps it on disk
    (:func:`prepare_preop`). ``drr``: render the geometry check (:mod:`drr`) of the first
    view always (True), never (False) or when its ``P`` came from C-arm tags ("auto").
    ``mirror_test``: register the case once more per view with that view's frame flipped
    left-right (``PlanResult.flipped``, for :func:`plausibility.check_not_mirrored`; proposed
    method only).
    """
    planning.check_labels(start, target)
    t0 = time.perf_counter()
    _report(progress, 0.0, "pre-operative skeleton graph")
    with _blamed_on(case.paths.get(case.stage_3d)):
        preop, lumen = _preop_of(case, preop, progress, segmenter, cache)
    lumen = case.aorta_mask if case.aorta_mask is not None else lumen
    timings = dict(preop.timings)
    views = _case_views(case)
    by_name = {view.name: view for view in views}
    priors = [quality.FluoroPrior.from_centerline(preop.centerline, view.P) for view in views]
    qc = quality.QCData(case.ct, lumen, views[0].fluoro.image, None, priors[0])
    with _blamed_on(case.paths.get(case.stage_3d)):
        quality.check_preop_tree(preop.centerline, lumen, qc)     # before registering: both sides
    if any(view.fluoro_mask is None for view in views):
        _report(progress, 0.4, "segmenting vessels in the frame")
    # every view's 2D side at once (the second of each pair in the worker process); its
    # errors are raised below in the serial order: every mask, every frame check, the registration
    outcomes = prepare_views(preop, [_view_source(view, prior) for view, prior in zip(views, priors)],
                             method=method, refine_pose=refine_pose)
    for stage in ("segmentation2d", "frame_check"):
        timings[stage] = sum(outcome.timings.get(stage, 0.0) for outcome in outcomes)
    try:
        for view, outcome in zip(views, outcomes):
            if outcome.mask_error is not None:
                with _blamed_on(_view_frame_path(view)):
                    raise outcome.mask_error
        qc.mask2d = outcomes[0].mask
        _report(progress, 0.5, f"registering ({method}, {len(views)} view(s))")
        # registered while a frame check may still run in the worker; its failure comes first
        try:
            with _blamed_on(_view_frame_path(views[0])):
                frame = register_prepared(preop, outcomes, method=method, alpha=alpha, beta=beta)
            failure = None
        except Exception as exc:        # noqa: BLE001  (raised after the frame checks)
            failure = exc
    finally:
        finish_checks(outcomes)
    for view, outcome in zip(views, outcomes):
        if outcome.check_error is not None:
            _raise_check_error(outcome.check_error, view, view is views[0], qc)
    if failure is not None:
        _raise_registration_failure(failure, outcomes, views[0], qc)
    timings.update(frame.timings)
    timings["registration"] = frame.timings["intraop"]
    flipped = None
    if mirror_test and method == "proposed":
        with _timed(timings, "mirror_test"):
            flipped = _flipped_registrations(preop, views, outcomes, refine_pose, alpha, beta)
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
        from .. import drr as drr_module

        _report(progress, 0.9, "rendering the DRR geometry check")
        with _timed(timings, "drr"):
            drr_image = drr_module.check_drr(_drr_volume(case), case.P, case.fluoro.shape)
    summaries = [_view_summary(by_name[vf.name], vf, frame.deformed) for vf in frame.views]
    timings["total"] = time.perf_counter() - t0
    _report(progress, 1.0, "done")
    return PlanResult(method, preop.centerline, frame.deformed, path, frame.P, frame.skeleton2d.positions,
                      sk_edges, views[0].fluoro.image, timings, errors,
                      {k: str(v) for k, v in case.paths.items()} | {"correspondence": frame.correspondence},
                      qc=qc, geometry=geometry, drr=drr_image, views=summaries, warnings=list(frame.warnings),
                      view_frames=list(frame.views), energy=frame.energy, flipped=flipped)


def _flipped_registrations(preop, views, outcomes, refine_pose, alpha, beta) -> list:
    """The mirror test's other hypotheses: per view, the case registered with that view's
    frame flipped left-right and the others as given (:func:`register_view_flipped`)."""
    frames = [(outcome.mask, view.P) for view, outcome in zip(views, outcomes)]
    names = [view.name for view in views]
    images = [view.fluoro.image if view.has_frame else None for view in views]     # as _view_source
    return [register_view_flipped(preop, frames, k, names=names, images=images, refine_pose=refine_pose, alpha=alpha,
                                  beta=beta) for k in range(len(views))]


def _view_source(view: View, prior) -> ViewSource:
    """What the view's 2D side starts from: its given mask (to be repaired) or its frame (to be
    segmented with the projected ``prior``), the frame check included."""
    return ViewSource(view.name, view.P, view.fluoro.image, given_mask=view.fluoro_mask, prior=prior, check=True,
                      real_frame=view.has_frame)


def _raise_check_error(error: Exception, view: View, first: bool, qc) -> None:
    """Raise a view's frame check failure as the check raises it, named after the view's file
    (and, but for the first view, after the view), with the case's QC data."""
    try:
        with _blamed_on(_view_frame_path(view)):
            if isinstance(error, quality.QualityError):
                error.qc = qc
            raise error
    except quality.QualityError as exc:
        if first:
            raise
        raise quality.QualityError(f"view {view.name}: {exc}", qc) from None


def _raise_registration_failure(failure: Exception, outcomes, first: View, qc) -> None:
    """Raise what the registration raised; when Algorithm 1 found the five main branches in no
    view's vessel mask, as a refusal of the frame with its QC picture (the mask over the frame
    and the projected tree show which vessel is missing or merged)."""
    states = [outcome.view for outcome in outcomes]
    if isinstance(failure, ValueError) and states and all(s is not None and s.unclassified for s in states):
        with _blamed_on(_view_frame_path(first)):
            raise quality.QualityError(f"frame check: the frame's vessels do not make the five main branches "
                                       f"({states[0].unclassified}): a vessel is missing from the vessel mask or "
                                       f"merged with another (see segmentation_qc.png)", qc) from None
    raise failure


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
        result = run_case(case, method=method, progress=progress, mirror_test=True,
                          **{k: v for k, v in overrides.items() if k not in load_keys})
        gate_notes = check_result(case, result)
    except quality.QualityError as failure:    # the QC picture first, so the user sees why
        if out_dir is not None:
            refusal_picture(failure, out_dir)
        raise
    for note in gate_notes:
        warnings.warn(note, InputWarning, stacklevel=2)
    result.warnings.extend(notes + gate_notes)
    if out_dir is not None:
        write_outputs(result, out_dir)
    return result


def check_result(case: Case, result: PlanResult) -> list[str]:
    """The plausibility gates after a registration (:mod:`plausibility`); their warnings.

    The anatomy still in front of the source and in the frame under the registration's ``P``,
    a frame whose vessel tree is at the projected tree's scale, the registered vessels'
    lengths and displacements, and for the proposed method the registration check on every
    view and, when ``result`` holds it (:func:`run_case` with ``mirror_test``), the mirror
    test. :func:`plan_case`, the workstation and the Slicer module run it on every result.

    Raises
    ------
    files.InputError
        One line naming the file and the problem; a :class:`quality.QualityError` (a
        subclass) carries the QC picture's data.
    """
    frame_path = case.paths.get("fluoro_mask", case.paths.get("fluoro", "the frame"))
    where = case.paths.get("geometry", case.case_dir if case.case_dir is not None else "the geometry")
    plausibility.check_anatomy_in_view(result.P, result.preop.points, case.fluoro.shape, where)
    plausibility.check_vessel_tree(result.skeleton2d_points, result.skeleton2d_edges, result.P,
                                   result.preop.points, frame_path)
    notes = plausibility.result_warnings(result.preop, result.deformed, frame_path, method=result.method)
    if result.method == "proposed":      # issue 11: a frame not this case's anatomy, side or view
        notes += _registration_check(case, result, frame_path)
    return notes


def _registration_check(case, result: PlanResult, frame_path) -> list[str]:
    """:func:`plausibility.check_registrations` on every view the registration used (the
    refusal's QC picture shows that view's frame; the view with the strongest evidence first),
    and on each the mirror test
    (:func:`plausibility.check_not_mirrored`) when ``result`` holds it; the warnings of those
    it lets pass."""
    views = {view.name: view for view in getattr(case, "views", None) or []}
    first = result.view_frames[0].classification2d if result.view_frames else None
    names = [frame.name for frame in result.view_frames[:1]] or [MAIN_VIEW]
    checks = [(result.P, result.skeleton2d_points, result.skeleton2d_edges, case.fluoro.shape, frame_path, result.qc,
               first)]
    for frame in result.view_frames[1:]:
        view = views.get(frame.name)
        if view is not None:
            checks.append((frame.P, frame.skeleton2d.positions, frame.skeleton2d.edges(), view.fluoro.shape,
                           view.paths.get("fluoro_mask", view.paths.get("fluoro", frame.name)),
                           _view_qc(result.qc, view, quality.FluoroPrior.from_centerline(result.preop, frame.P)),
                           frame.classification2d))
            names.append(frame.name)
    flipped = dict(zip(views or [MAIN_VIEW], result.flipped or []))      # run_case's mirror_test
    every = plausibility.check_registrations(result.preop, result.deformed, checks)
    notes = []
    for name, (P, points, edges, shape, path, qc, classification), signals in zip(names, checks, every):
        other = flipped.get(name)
        plausibility.check_not_mirrored(result.preop, result.deformed, P, result.energy, signals,
                                        other.seen_in(name) if other is not None else None, shape, path, qc)
        notes += plausibility.registration_warnings(signals)
    return notes


def _view_qc(qc: quality.QCData | None, view: View, prior: quality.FluoroPrior) -> quality.QCData:
    """The QC data of ``view``: the case's CT panels (``qc``'s), this view's frame, mask and
    projected pre-operative tree (``prior``)."""
    if qc is None:
        return quality.QCData(frame=view.fluoro.image, mask2d=view.fluoro_mask, prior=prior)
    return dataclasses.replace(qc, frame=view.fluoro.image, mask2d=view.fluoro_mask, prior=prior, notes=list(qc.notes))


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

"""``fevar-planner track``: every frame of a fluoroscopic run registered against one pre-operative model.

The pre-operative model is built (or read from the cache, :mod:`cache`) once; each frame
of the multi-frame ``fluoro.dcm`` (NumberOfFrames) is then segmented (vesselness), and
registered (:func:`pipeline.register_frame`), and its path planned. Per frame it records
the times and the fit of the recovered centreline to that frame's own 2D skeleton (the
2D distance of eq. 6's data term; a fit, not an error: a run has no ground truth).
What belongs to the run rather than to a frame is judged once: the side convention (the
mirror test, on the first registered frame) and the display's polarity (the frame check's
reading of the metal, :func:`quality.dense_side`, taken from the first frame whose check
passes with a verdict, then used for the frames after it).

Outputs in ``OUT``: ``track.csv`` (one row per frame), ``track.json`` (per-frame times,
their median / 95th percentile / maximum, the pre-operative time and whether it came from
the cache) and the last frame's ``result.json`` and pictures (:func:`pipeline.write_outputs`).
"""

from __future__ import annotations

import csv
import io as _stringio
import json
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import evaluation, planning, plausibility, quality
from .files import InputError, write_text_atomic
from .io import FluoroRun, load_case, read_fluoro

__all__ = ["FrameRecord", "TrackResult", "register_run_frame", "track_case", "write_track_outputs", "CSV_COLUMNS"]

#: Runs of at least this many frames hand each frame check to the view worker process, which
#: saves wall time only (its 10-15 ms a frame on a second core, bench_tracking.py), once the
#: worker is ready (about 0.5 s after its start, which costs about 1.5 s of CPU and 550 MB, as
#: ``plan`` notes); shorter runs keep the check in this process and start no worker.
WORKER_MIN_FRAMES = 40

CSV_COLUMNS = ("frame", "fit_2d_px", "path_length_mm", "read_ms", "segmentation_ms", "frame_check_ms",
               "registration_ms", "result_checks_ms", "planning_ms", "total_ms", "warnings")
#: The per-frame times of :func:`register_run_frame` (s), in order; ``total`` is their sum.
TIMED_STEPS = ("read", "segmentation", "frame_check", "registration", "result_checks", "planning")


@dataclass
class FrameRecord:
    """One frame's outcome: the fit to its own skeleton, the path length, times (s), warnings."""

    frame: int
    fit_2d_px: float | None
    path_length_mm: float | None
    times: dict
    warnings: list = field(default_factory=list)

    def row(self) -> dict:
        ms = {f"{key}_ms": round(1000.0 * self.times.get(key, 0.0), 2) for key in TIMED_STEPS + ("total",)}
        return {"frame": self.frame,
                "fit_2d_px": "" if self.fit_2d_px is None else round(self.fit_2d_px, 4),
                "path_length_mm": "" if self.path_length_mm is None else round(self.path_length_mm, 2),
                **ms, "warnings": " | ".join(self.warnings)}


@dataclass
class TrackResult:
    """All frames of a run, the pre-operative summary and the last frame's full result."""

    records: list
    preop_seconds: float
    preop_from_cache: bool
    method: str
    last: object = None

    def summary(self) -> dict:
        """Per-frame time statistics (ms) and the fit, for ``track.json`` (the benchmark record)."""
        totals = np.array([r.times["total"] for r in self.records]) * 1000.0
        registration = np.array([r.times.get("registration", 0.0) for r in self.records]) * 1000.0
        fits = np.array([r.fit_2d_px for r in self.records if r.fit_2d_px is not None])

        def stats(values):
            if not len(values):
                return None
            return {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)),
                    "max": float(values.max()), "mean": float(values.mean())}

        return {"method": self.method, "n_frames": len(self.records),
                "geometry": getattr(self.last, "geometry", None),
                "failed_frames": [r.frame for r in self.records if r.fit_2d_px is None],
                "preop_s": self.preop_seconds, "preop_from_cache": self.preop_from_cache,
                "per_frame_total_ms": stats(totals), "per_frame_registration_ms": stats(registration),
                "fit_2d_px": stats(fits),
                "frames": [{"frame": r.frame, "total_ms": 1000.0 * r.times["total"],
                            "registration_ms": 1000.0 * r.times.get("registration", 0.0),
                            "fit_2d_px": r.fit_2d_px} for r in self.records]}


@dataclass
class _RunPolarity:
    """The display's dense side of a run (:func:`quality.dense_side`: -1 or +1), once a frame's
    metal has shown it (None until then): the display does not change within a run, so the
    frame check of the frames after it uses it instead of reading their metal again."""

    dense_side: int | None = None

    def learn(self, side: int | None) -> None:
        """Keep the side a frame check read, when it gave a verdict and none is kept yet."""
        if self.dense_side is None and side:
            self.dense_side = side


def _frame_range(n_frames: int, first: int, count: int | None, path) -> range:
    if not 0 <= first < n_frames:
        raise InputError(f"{path}: first frame {first} out of range (the file has {n_frames} frames)")
    last = n_frames if count is None else min(n_frames, first + count)
    return range(first, last)


def _without_qc_picture(failure: quality.QualityError, prefix: str = "") -> InputError:
    """``failure`` as an InputError without its pointer to the QC picture: track writes none per frame."""
    return InputError(prefix + str(failure).replace(" (see segmentation_qc.png)", ""))


def register_run_frame(preop, case, index: int, *, method: str = "proposed", start: str = "iliac_right",
                       target: str = "renal_left", prior=None, run: FluoroRun | None = None):
    """Frame ``index`` of the case's run registered against ``preop``: ``(PlanResult, times in s)``.

    The frame is read (the loaded one when it is ``case.fluoro``'s), segmented with the
    projected pre-operative tree as prior, checked by the same gates as ``plan`` (the
    frame's mask against the projected tree, its vessel tree, the result's lengths and
    displacements, and for the proposed method the registration check: a frame that fails
    raises InputError), registered and its path planned;
    ``errors`` hold the fit to its own skeleton and ``warnings`` the result's notes. Used by
    :func:`track_case` and by the workstation to play a run back.

    The frame check runs in the view worker process (:mod:`pipeline.workers`) while this
    process registers, when the worker is ready (as ``plan`` does): its failure still comes
    first, and a registration error after it. ``times`` (:data:`TIMED_STEPS`, s): the frame
    check's is this process's wait for it (or the check itself, done here).

    ``prior`` (a :class:`quality.FluoroPrior` for ``preop`` and ``case.P``) may be built
    once per run and passed in; it caches its band on the frame grid. So may ``run``
    (:class:`io.FluoroRun` of ``case.fluoro.path``): the file is then parsed once per run.
    """
    result, times, _, _ = _registered_run_frame(preop, case, index, method=method, start=start, target=target,
                                                prior=prior, run=run)
    return result, times


def _registered_run_frame(preop, case, index: int, *, method: str, start: str, target: str, prior,
                          run: FluoroRun | None, polarity: _RunPolarity | None = None):
    """:func:`register_run_frame`, also returning the frame read and its vessel mask: ``(PlanResult,
    times, frame, mask)`` (the run's side check uses them again, :func:`_check_run_side`).
    ``polarity``: the run's display polarity, used by the frame check when known and learnt from
    it when not (:class:`_RunPolarity`)."""
    from .pipeline import PlanResult, register_frame, segment_frame_and_field

    prior = quality.FluoroPrior.from_centerline(preop.centerline, case.P) if prior is None else prior
    times = {}
    t = time.perf_counter()
    fluoro = _run_frame(case, index, run)
    frame_path = f"{case.fluoro.path} (frame {index})"
    times["read"] = time.perf_counter() - t
    t = time.perf_counter()
    mask, search = segment_frame_and_field(fluoro.image, prior)
    times["segmentation"] = time.perf_counter() - t
    check = _frame_check_job(preop, mask, prior, fluoro.image, None if polarity is None else polarity.dense_side)
    t = time.perf_counter()
    try:
        frame, failure = register_frame(preop, mask, case.P, method=method, image=fluoro.image,
                                        search=search), None
    except Exception as exc:        # noqa: BLE001  (raised after the frame check's failure)
        frame, failure = None, exc
    except BaseException:           # interrupted: the worker's answer must not be left in its pipe
        check.result()
        raise
    times["registration"] = time.perf_counter() - t
    t = time.perf_counter()
    check_error, caught, side = check.result()
    times["frame_check"] = time.perf_counter() - t
    if polarity is not None:
        polarity.learn(side)
    for category, message in caught:        # as if the check had run here
        warnings.warn(message, category, stacklevel=2)
    if isinstance(check_error, quality.QualityError):
        raise _without_qc_picture(check_error, f"{frame_path}: ") from None
    if check_error is not None:
        raise check_error
    if failure is not None:
        raise failure
    t = time.perf_counter()
    edges_2d = frame.skeleton2d.edges()
    plausibility.check_vessel_tree(frame.skeleton2d.positions, edges_2d, frame.P, preop.centerline.points, frame_path)
    notes = plausibility.result_warnings(preop.centerline, frame.deformed, frame_path, method=method)
    if method == "proposed":      # issue 11: a frame not this case's anatomy, side or view
        try:
            signals = plausibility.check_registration(preop.centerline, frame.deformed, frame.P,
                                                      frame.skeleton2d.positions, edges_2d, fluoro.image.shape,
                                                      frame_path, classification=frame.classification2d)
        except quality.QualityError as exc:
            raise _without_qc_picture(exc) from None
        notes += plausibility.registration_warnings(signals)
    times["result_checks"] = time.perf_counter() - t
    t = time.perf_counter()
    path = planning.plan_path(frame.deformed, start=start, target=target)
    times["planning"] = time.perf_counter() - t
    t = time.perf_counter()
    fit = evaluation.evaluate(frame.deformed, None, frame.P, frame.skeleton2d.positions, edges_2d)
    times["result_checks"] += time.perf_counter() - t
    times["total"] = sum(times[step] for step in TIMED_STEPS)
    result = PlanResult(method, preop.centerline, frame.deformed, path, frame.P, frame.skeleton2d.positions, edges_2d,
                        fluoro.image, {"total": times["total"], "registration": frame.timings["intraop"]}, fit,
                        {"fluoro": str(case.fluoro.path), "frame": index},
                        geometry=case.geometry.to_dict() if case.geometry is not None else None, energy=frame.energy)
    result.warnings.extend(frame.warnings + notes)
    return result, times, fluoro, mask


def _run_frame(case, index: int, run: FluoroRun | None):
    """Frame ``index`` of the case's run: the loaded one when it is ``case.fluoro``'s, else read (from ``run``)."""
    if index == case.fluoro.frame:
        return case.fluoro
    return read_fluoro(case.fluoro.path, frame=index) if run is None else run.frame(index)


def _frame_check_job(preop, mask: np.ndarray, prior, image: np.ndarray, run_dense_side: int | None = None):
    """The frame check (:func:`quality.check_frame_mask`) of ``mask`` as a job of the view worker
    (done here, when its result is asked for, if the worker is not ready): its ``result()`` is
    (the check's error or None, its warnings as (category, message), the display's dense side it
    used: None when it failed). ``run_dense_side``: the run's, when known (:class:`_RunPolarity`)."""
    from .pipeline import workers

    return workers.submit(_frame_check_and_warnings, preop, mask, prior, image, run_dense_side)


def _frame_check_and_warnings(preop, mask: np.ndarray, prior, image: np.ndarray,
                              run_dense_side: int | None = None) -> tuple:
    """``pipeline.frame._frame_check`` with the warnings it gives and the dense side it used, for
    :func:`_frame_check_job` (the worker's warnings would not reach this process's record of the frame)."""
    from .pipeline.frame import _frame_check_report

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        error, report = _frame_check_report(preop, mask, prior, image, run_dense_side)
    return error, [(w.category, str(w.message)) for w in caught], None if report is None else report.get("dense_side")


def track_case(case_dir, *, method: str = "proposed", start: str = "iliac_right", target: str = "renal_left",
               first: int = 0, count: int | None = None, segmenter: str = "classical", cache=True,
               progress=None, **case_files) -> TrackResult:
    """Register every frame of the case's multi-frame run (see the module docstring).

    Parameters
    ----------
    case_dir : path
        A case folder (DESIGN.md section 4) whose frame file holds several frames.
    method : {"proposed", "icp-tps", "rigid"}
    start, target : str
        The path's vessels, checked before any work starts.
    first, count : int
        The frames to register (default all from ``first``).
    segmenter : {"classical", "unet", "threshold"}
    cache : bool or path
        Keep the pre-operative model on disk (:mod:`cache`).
    progress : callable, optional
        ``progress(fraction, message)``.
    **case_files
        Overrides of the folder's files (``ct``, ``aorta_mask``, ... as :func:`io.load_case`).
    """
    from . import cache as preop_cache
    from .pipeline import METHODS

    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    planning.check_labels(start, target)
    case = load_case(case_dir, frame=first, **case_files)
    if case.fluoro.path is None or "fluoro" not in case.paths:
        raise InputError(f"{case_dir}: no fluoroscopy run to track (only a vessel mask)")
    frames = _frame_range(case.fluoro.n_frames, first, count, case.fluoro.path)
    t0 = time.perf_counter()
    model = preop_cache.preop_model(case, segmenter=segmenter, progress=progress,
                                    cache_dir=None if cache in (True, False, None) else cache,
                                    use_cache=cache not in (False, None))
    preop, preop_seconds = model.preop, time.perf_counter() - t0
    prior = quality.FluoroPrior.from_centerline(preop.centerline, case.P)
    with _view_worker_for(len(frames)):
        records, last = _track_frames(preop, case, frames, prior, FluoroRun(case.fluoro.path), method, start, target,
                                      progress)
    if progress is not None:
        progress(1.0, f"{len(records)} frames")
    return TrackResult(records, preop_seconds, model.from_cache, method, last)


@contextmanager
def _view_worker_for(n_frames: int):
    """The view worker as the caller set it for a run of at least :data:`WORKER_MIN_FRAMES` frames,
    off for a shorter one."""
    from .pipeline import workers

    if n_frames >= WORKER_MIN_FRAMES:
        yield
        return
    previous = workers.set_enabled(False)
    try:
        yield
    finally:
        workers.set_enabled(previous)


def _track_frames(preop, case, frames, prior, run: FluoroRun, method: str, start: str, target: str,
                  progress) -> tuple[list, object]:
    """:func:`track_case`'s loop over ``frames``: (FrameRecord per frame, the last registered frame's PlanResult)."""
    records, last, side_checked = [], None, method != "proposed"
    polarity = _RunPolarity()
    for done, index in enumerate(frames):
        if progress is not None:
            progress(0.3 + 0.7 * done / len(frames), f"frame {index} ({done + 1}/{len(frames)})")
        t = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                last, times, fluoro, mask = _registered_run_frame(preop, case, index, method=method, start=start,
                                                                  target=target, prior=prior, run=run,
                                                                  polarity=polarity)
            except (ValueError, RuntimeError) as exc:
                records.append(FrameRecord(index, None, None, {"total": time.perf_counter() - t},
                                           [str(exc).splitlines()[0]]))
                continue
        records.append(FrameRecord(index, last.errors["2d_px"]["mean"], last.path.length_mm, times,
                                   sorted({str(w.message).splitlines()[0] for w in caught} | set(last.warnings))))
        if not side_checked:        # once per run, on its first registered frame
            _check_run_side(preop, case, index, fluoro, mask, last)
            side_checked = True
    return records, last


def _check_run_side(preop, case, index: int, fluoro, mask: np.ndarray, given) -> None:
    """Refuse the whole run when frame ``index``, its first registered frame (``given``, its
    :class:`pipeline.PlanResult`; ``fluoro`` the frame as read and ``mask`` its vessel mask, as
    registered), looks mirrored left-right: the side convention is the run's, so the mirror test
    (:func:`plausibility.check_not_mirrored`) runs once, on that frame registered flipped too."""
    from .pipeline import register_flipped

    signals = plausibility.registration_signals(preop.centerline, given.deformed, given.P, given.skeleton2d_points,
                                                given.skeleton2d_edges, mask.shape)
    flipped = register_flipped(preop, mask, case.P, image=fluoro.image)
    try:
        plausibility.check_not_mirrored(preop.centerline, given.deformed, given.P, given.energy, signals, flipped,
                                        mask.shape, f"{case.fluoro.path} (frame {index})")
    except quality.QualityError as exc:
        raise InputError(f"{_without_qc_picture(exc)}; the side convention is the run's: every frame is refused") \
            from None


def write_track_outputs(result: TrackResult, out_dir) -> dict:
    """Write ``track.csv``, ``track.json`` and the last frame's outputs into ``out_dir``."""
    from .pipeline import write_outputs

    from .files import atomic_folder

    out_dir = Path(out_dir)
    buffer = _stringio.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for record in result.records:
        writer.writerow(record.row())

    def track_files(folder: Path) -> dict:
        paths = {"track.csv": folder / "track.csv", "track.json": folder / "track.json"}
        write_text_atomic(paths["track.csv"], buffer.getvalue())
        write_text_atomic(paths["track.json"], json.dumps(result.summary(), indent=2) + "\n")
        return paths

    # one output set, swapped in whole (pipeline.write_outputs)
    if result.last is not None:
        return write_outputs(result.last, out_dir, extra=track_files)
    with atomic_folder(out_dir) as staging:
        written = track_files(staging)
    return {name: out_dir / path.name for name, path in written.items()}

"""Benchmark the whole per-frame path from a raw 1024 x 1024 frame, stage by stage (issue 10).

A phantom case (random anatomy, seed ``--seed``) is rendered as a raw DSA-like 1024 x 1024
frame (:func:`phantom.render_fluoro`) in the AP view and, for the two-view variant, in a
second view of the same anatomy (LAO ``--second-angle``). The pre-operative model is built
once (thinned lumen, Algorithm 1, centred: :func:`pipeline.preop_from_lumen`). Then, per
frame and over ``--repeats`` repeats, each stage of the per-frame path is timed as the
pipeline runs it:

==============  =========================================================================
mask            the pre-operative prior projected through P (:class:`quality.FluoroPrior`)
                and :func:`segmentation.segment_fluoro` with it (``pipeline.frame._source_mask``)
frame_check     the frame check (:func:`quality.check_frame_mask`, the polarity reading
                included), as ``plan`` runs it on every view (``ViewSource(check=True)``): in this
                process, or (one view) in the idle view worker beside the registration, whose CPU
                time is read off the worker's scheduler record (Linux ``/proc/PID/schedstat``) and
                added to the total, not to ``this_process``; with two views, the second view's
                check is part of its worker stage
skeleton2d      :func:`skeleton.skeletonize_2d` and :meth:`graph.SkeletonGraph.from_image`
                (with the mask's radii)
graph2d         Algorithm 1, anatomical labels and smoothing of the 2D graph
matching        :func:`matching.candidate_correspondences`
deformation     soft assignment, deformation (eq. 6, L-BFGS) and TPS fill, per candidate
plausibility    the never-worse-than-SV check of every vessel
pose            the in-plane pose check (``pose_refinement``: its matching under the given P
                is what the matching stage then reuses, hence matching near 0)
worker          CPU time of the view worker process (two views: the second view's mask, frame check and
                2D side, :mod:`pipeline.workers`); its stage wall times are in the stages above
other           the rest (visibility of the frame, projections, passing the work to the worker)
==============  =========================================================================

The stages are the pipeline's own route from raw frames (:func:`pipeline.frame.prepare_views`,
then :func:`pipeline.frame.register_prepared`; both views of the two-view variant are
registered jointly), timed by its stage timer; the benchmark adds the CPU time beside the
wall time of each. The two-view variant runs with the view worker and, alternating with
it, without ("two views (serial)") and with the follower passes of the deformation as they
were before issue 10's cheaper passes ("two views (cold passes)": the solver's own stall
window on the refinement, no preconditioner kept between solves; ``over_cold_passes_cpu``
holds the ratios). "AP (run: prior kept)" is the AP view as a frame of a run: its
:class:`quality.FluoroPrior` kept from frame to frame, as ``track`` keeps its run's (the prior's
band on the frame grid is rasterised once per run, not per frame).
Each run starts with an empty preconditioner cache: repeats of one frame must not find what
a new frame would not. Wall time
(``time.perf_counter``) and CPU time of this process (``time.process_time``) are both
recorded: the machine is shared with other work, so wall times are noisy and the CPU time
is the better guide (one BLAS thread, no worker threads: CPU time <= wall time); with the
view worker, the CPU time of the calling process (``this_process``) is the critical path's
when the worker keeps up. The goals: 33 ms for one view, 66 ms for two.

The frame check (:func:`quality.check_frame_mask`, run on every frame beside the registration) is
timed on its own on the two raw views and the two bench frames below (``frame_check``: the
whole check, the pixel noise, the contrast to noise, the one-tree check, the polarity reading;
its verdict and the contrast to noise's margin over ``MIN_CONTRAST_TO_NOISE``);
``--frame-check-only`` times only it.

The mask stage is also timed on the AP anatomy rendered as a bench frame with every distractor
(:mod:`phantom.distractors`: spine, pelvis, box, rail, table, collimator, devices, ruler, text,
exposure), unsubtracted and subtracted (``mask_by_frame_kind``, with its Dice; issue 11).

    OMP_NUM_THREADS=1 .venv/bin/python Testing/benchmarks/bench_frame.py --out OUT [--repeats 30] [--frame-check-only]

Writes ``bench_frame.json`` and ``bench_frame.png`` into ``--out``.
"""

from __future__ import annotations

from common import argument_parser, pyplot, save_figure, single_threaded_blas, write_report

single_threaded_blas()      # before NumPy

import functools  # noqa: E402
import inspect  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from FevarPlannerLib import phantom, pipeline, quality, segmentation  # noqa: E402
from FevarPlannerLib.deformation import solve  # noqa: E402
from FevarPlannerLib.pipeline import frame as frame_module, multiview, workers  # noqa: E402
from FevarPlannerLib.quality import FluoroPrior  # noqa: E402

STAGES = ("mask", "frame_check", "skeleton2d", "graph2d", "matching", "deformation", "plausibility", "pose", "worker",
          "other")
#: The pipeline's stage timer names of the stages that it times itself (the rest: as named).
TIMER_NAMES = {"pose": "pose_refinement"}
GOALS_MS = {"one_view": 33.0, "two_views": 66.0}
FRAME_SIZE = 1024


def _clock():
    return time.perf_counter(), time.process_time()


def _since(start) -> tuple[float, float]:
    wall, cpu = _clock()
    return wall - start[0], cpu - start[1]


def frame_cases(seed: int, second_angle: float):
    """(pre-operative model, [(view name, raw frame, true mask, P), ...]) of one phantom anatomy."""
    params = replace(phantom.random_params(np.random.default_rng(seed)), detector_rows=FRAME_SIZE,
                     detector_cols=FRAME_SIZE, primary_angle_deg=0.0, secondary_angle_deg=0.0)
    views = []
    preop = None
    for name, angle in (("AP", 0.0), (f"LAO{second_angle:g}", second_angle)):
        case = phantom.generate_case(replace(params, primary_angle_deg=angle), name=f"frame_{name}")
        if preop is None:
            preop = pipeline.preop_from_lumen(phantom.rasterize_lumen(case.preop, case.grid))
        frame, truth = phantom.render_fluoro(case.intraop, case.P_true, case.carm, case.params,
                                             np.random.default_rng(params.seed))
        views.append((name, frame, truth, case.P_true))
    return preop, views


@functools.cache
def _timer_users() -> tuple:
    """The modules of the pipeline package that use its stage timer (found once: a scan of
    ``sys.modules`` costs about a millisecond, which would land in "other")."""
    return tuple(module for name, module in sorted(sys.modules.items())
                 if (name == pipeline.__name__ or name.startswith(pipeline.__name__ + ".")) and hasattr(module, "_timed"))


@contextmanager
def _cpu_stage_timer(cpu: dict):
    """Make the pipeline's stage timer record this process's CPU time into ``cpu`` as well.

    The stage timer is patched in every module of the pipeline package that uses it.
    """
    users = _timer_users()
    wall_timer = pipeline._timed

    @contextmanager
    def both(timings, name):
        start = time.process_time()
        try:
            with wall_timer(timings, name):
                yield
        finally:
            cpu[name] = cpu.get(name, 0.0) + time.process_time() - start

    for module in users:
        module._timed = both
    try:
        yield
    finally:
        for module in users:
            module._timed = wall_timer


def _worker_cpu_seconds() -> float | None:
    """CPU seconds the running view worker has used (its scheduler's record, in ns: Linux), or None."""
    worker = workers._state["worker"]
    if worker is None:
        return None
    try:
        with open(f"/proc/{worker._process.pid}/schedstat") as record:
            return int(record.read().split()[0]) * 1e-9
    except (OSError, ValueError, IndexError):
        return None


def _remote_check_cpu(outcomes, worker_before: float | None) -> float:
    """CPU seconds of the frame checks that ran as jobs of their own in the view worker (one
    view: the check beside the registration): the worker's CPU since ``worker_before`` less the
    views it prepared (:attr:`ViewOutcome.cpu_seconds`); collects the checks (``plan`` does, before
    using the outcomes)."""
    remote = any(o.check_job is not None for o in outcomes)
    frame_module.finish_checks(outcomes)
    worker_after = _worker_cpu_seconds()
    if not remote or worker_before is None or worker_after is None:
        return 0.0
    return worker_after - worker_before - sum(o.cpu_seconds for o in outcomes if o.in_worker)


def time_views(preop, views, worker: bool = True, priors=None) -> tuple[dict, dict, dict]:
    """One pass of the per-frame path over ``views`` (registered jointly): ({stage: wall s}, {stage: CPU s}, facts).

    The pipeline's own route from raw frames (:func:`pipeline.frame.prepare_views`, then
    :func:`pipeline.frame.register_prepared`): with two views and ``worker``, the second
    view's 2D side runs in the view worker process. Stage wall times are the work done
    (summed over the views, whichever process did it); stage CPU times are this process's,
    the worker's CPU time is the stage "worker"; ``total`` wall is the elapsed time. ``priors``
    (one :class:`FluoroPrior` per view, kept from run to run as ``track`` keeps its run's): the
    prior's band is then rasterised once, not per frame. Each view is checked as ``plan`` checks
    it (stage ``frame_check``); a check that failed is in the facts (``frame_check_errors``).
    """
    workers.set_enabled(worker)
    solve._preconditioner_cache.clear()     # a new frame's solves share nothing with the last frame's
    wall, cpu = {"mask": 0.0}, {}
    worker_before = _worker_cpu_seconds()
    start = _clock()
    with _cpu_stage_timer(cpu):
        prior_start = _clock()
        priors = priors or [FluoroPrior.from_centerline(preop.centerline, P) for _, _, _, P in views]
        sources = [frame_module.ViewSource(name, P, image, prior=prior, check=True)
                   for (name, image, _, P), prior in zip(views, priors)]
        prior_wall, prior_cpu = _since(prior_start)
        outcomes = frame_module.prepare_views(preop, sources)
        result = frame_module.register_prepared(preop, outcomes)
        remote_check_cpu = _remote_check_cpu(outcomes, worker_before)
    total_wall, total_cpu = _since(start)
    wall["mask"] = prior_wall + sum(o.timings.get("segmentation2d", 0.0) for o in outcomes)
    cpu["mask"] = prior_cpu + cpu.pop("segmentation2d", 0.0)
    wall["frame_check"] = sum(o.timings.get("frame_check", 0.0) for o in outcomes)
    cpu["frame_check"] = cpu.get("frame_check", 0.0)        # this process's checks; a worker's job's below
    for stage in STAGES[2:-2]:
        wall[stage] = result.timings.get(TIMER_NAMES.get(stage, stage), 0.0)
        cpu[stage] = cpu.get(TIMER_NAMES.get(stage, stage), 0.0)
    wall["worker"] = 0.0
    cpu["worker"] = sum(o.cpu_seconds for o in outcomes if o.in_worker)
    local = [s for s in STAGES[:-2]]
    wall["other"] = max(0.0, total_wall - sum(wall[s] for s in local))
    cpu["other"] = total_cpu - sum(cpu[s] for s in local)
    cpu["frame_check"] += remote_check_cpu
    wall["total"], cpu["total"] = total_wall, total_cpu + cpu["worker"] + remote_check_cpu
    cpu["this_process"] = total_cpu
    facts = {"mask_pixels": [int(o.mask.sum()) for o in outcomes], "nodes_2d": len(result.skeleton2d),
             "frame_check_errors": [None if o.check_error is None else str(o.check_error) for o in outcomes],
             "correspondence": result.correspondence, "energy": result.energy,
             "in_worker": [o.in_worker for o in outcomes], "result_sum": float(np.sum(result.deformed.points))}
    return wall, cpu, facts


def mask_breakdown(preop, frame: np.ndarray, P: np.ndarray, repeats: int) -> dict:
    """Where the mask's time goes: the prior, and segment_fluoro at other work sizes and scales."""
    prior_times = []
    for _ in range(repeats):
        start = _clock()
        FluoroPrior.from_centerline(preop.centerline, P)
        prior_times.append(_since(start)[1])
    variants = {"default": {}, "work_size_192": {"work_size": 192}, "work_size_128": {"work_size": 128}}
    out = {"prior_construction_cpu_ms": 1e3 * float(np.median(prior_times))}
    for name, kwargs in variants.items():
        times = []
        for _ in range(repeats):
            prior = FluoroPrior.from_centerline(preop.centerline, P)
            start = _clock()
            segmentation.segment_fluoro(frame, prior, **kwargs)
            times.append(_since(start)[1])
        out[f"segment_fluoro_{name}_cpu_ms"] = 1e3 * float(np.median(times))
    return out


def bench_frames(seed: int):
    """(pre-operative model, P, {kind: BenchFrame}) of the 1024 x 1024 AP frame of ``seed`` rendered
    as a bench frame (:mod:`phantom.distractors`, every distractor): unsubtracted, and subtracted
    (DSA), vessels dark (issue 11)."""
    from FevarPlannerLib.phantom.distractors import render_bench_frame

    params = replace(phantom.random_params(np.random.default_rng(seed)), detector_rows=FRAME_SIZE,
                     detector_cols=FRAME_SIZE, primary_angle_deg=0.0, secondary_angle_deg=0.0)
    case = phantom.generate_case(params, name="frame_AP")
    preop = pipeline.preop_from_lumen(phantom.rasterize_lumen(case.preop, case.grid))
    return preop, case.P_true, {kind: render_bench_frame(case, np.random.default_rng(seed), subtracted=subtracted)
                                for kind, subtracted in (("unsubtracted", False), ("subtracted", True))}


def mask_by_frame_kind(preop, P: np.ndarray, benches: dict, repeats: int) -> dict:
    """CPU ms (median) of the mask stage (prior + segment_fluoro, as :func:`time_views`) and its Dice
    on each of :func:`bench_frames`."""
    out = {}
    for kind, bench in benches.items():
        times = []
        for _ in range(repeats + 1):
            start = _clock()
            mask = segmentation.segment_fluoro(bench.frame, FluoroPrior.from_centerline(preop.centerline, P))
            times.append(_since(start)[1])
        out[kind] = {"mask_cpu_ms": 1e3 * float(np.median(times[1:])),
                     "dice": float(segmentation.dice(mask, bench.mask))}
    return out


def _median_cpu_ms(work, repeats: int) -> float:
    """Median CPU ms of ``work()`` over ``repeats`` calls after one warm-up call."""
    times = []
    for _ in range(repeats + 1):
        start = _clock()
        work()
        times.append(_since(start)[1])
    return 1e3 * float(np.median(times[1:]))


def frame_check_cost(frames: dict, repeats: int) -> dict:
    """The frame check (:func:`quality.check_frame_mask`, as ``pipeline.frame._frame_check`` runs
    it on every frame) on each of ``frames`` ({name: (frame, prior, mask)}): median CPU ms of the
    whole check and of its parts (the pixel noise, the contrast to noise with it, the one-tree
    check, the polarity reading :func:`quality.dense_side`), and of the check as ``track`` runs it
    once its run's polarity is known (``check_run_side_known_cpu_ms``, where the frame shows it);
    its verdict and the contrast to noise and its margin over ``MIN_CONTRAST_TO_NOISE``."""
    out = {}
    for name, (frame, prior, mask) in frames.items():
        grey = np.asarray(frame, dtype=np.float32)
        cnr = quality.vessel_contrast_to_noise(frame, mask)
        out[name] = {
            "check_cpu_ms": _median_cpu_ms(lambda: _frame_check_verdict(mask, prior, frame), repeats),
            "noise_cpu_ms": _median_cpu_ms(lambda: quality._pixel_noise(grey), repeats),
            "contrast_to_noise_cpu_ms": _median_cpu_ms(lambda: quality.vessel_contrast_to_noise(frame, mask), repeats),
            "one_tree_cpu_ms": _median_cpu_ms(lambda: quality._check_one_tree(mask, prior, None), repeats),
            "polarity_cpu_ms": _median_cpu_ms(lambda: quality.dense_side(grey, mask), repeats),
            "verdict": _frame_check_verdict(mask, prior, frame), "contrast_to_noise": cnr,
            "margin_over_min_contrast_to_noise": cnr - quality.MIN_CONTRAST_TO_NOISE}
        side = quality.dense_side(grey, mask)
        if side and "run_dense_side" in inspect.signature(quality.check_frame_mask).parameters:
            out[name]["check_run_side_known_cpu_ms"] = _median_cpu_ms(
                lambda: quality.check_frame_mask(mask, prior, None, frame=frame, run_dense_side=side), repeats)
    return out


def _frame_check_verdict(mask, prior, frame) -> str:
    """"pass", or "refused: " and the frame check's message."""
    try:
        quality.check_frame_mask(mask, prior, None, frame=frame)
    except quality.QualityError as error:
        return f"refused: {error}"
    return "pass"


def profile_mask(preop, frame: np.ndarray, P: np.ndarray, repeats: int, top: int = 12) -> list[str]:
    """The functions segment_fluoro spends its (cumulative) time in, most first."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    for _ in range(repeats):
        prior = FluoroPrior.from_centerline(preop.centerline, P)
        profiler.runcall(segmentation.segment_fluoro, frame, prior)
    stats = pstats.Stats(profiler).sort_stats("tottime")
    rows = []
    for (filename, line, name), (_, calls, tottime, cumtime, _) in list(stats.stats.items()):
        rows.append((tottime, f"{Path(filename).name}:{line} {name}: {1e3 * tottime / repeats:.2f} ms own, "
                              f"{1e3 * cumtime / repeats:.2f} ms cumulative per frame, {calls // repeats} call(s)"))
    return [text for _, text in sorted(rows, reverse=True)[:top]]


def summarise(runs: list[tuple[dict, dict, dict]]) -> dict:
    """Medians over the runs of every stage and of the totals (wall: elapsed; CPU: both processes,
    and ``this_process``: the critical path's CPU time when the worker keeps up)."""
    keys = STAGES + ("total",)
    return {"wall_ms": {s: 1e3 * float(np.median([r[0][s] for r in runs])) for s in keys},
            "cpu_ms": {s: 1e3 * float(np.median([r[1][s] for r in runs])) for s in keys + ("this_process",)},
            "facts": runs[0][2]}


def over_cold_passes(now: dict, cold: dict) -> dict:
    """Ratios of the median CPU ms of the two-view run as the pipeline runs it over the one with
    the earlier follower passes (:data:`COLD_PASSES`): the deformation stage and the calling process."""
    return {stage: now["cpu_ms"][stage] / cold["cpu_ms"][stage] for stage in ("deformation", "this_process")}


def plot_frame_check(ax, checked: dict) -> None:
    """Bars: the frame check's median CPU ms per frame, whole and by part (:func:`frame_check_cost`)."""
    parts = ("check", "noise", "contrast_to_noise", "one_tree", "polarity")
    x = np.arange(len(checked))
    width = 0.8 / len(parts)
    for i, part in enumerate(parts):
        ax.bar(x + (i - (len(parts) - 1) / 2) * width, [row[f"{part}_cpu_ms"] for row in checked.values()], width,
               label="whole check" if part == "check" else part.replace("_", " "))
    ax.set_xticks(x, [f"{name}\nCNR {row['contrast_to_noise']:.1f}" for name, row in checked.items()], fontsize=8)
    ax.set(ylabel="median CPU time per frame (ms)", title="frame check, 1024 x 1024")
    ax.legend(fontsize=8)


def plot(path: Path, per_view: dict | None, two_views: dict | None, serial: dict | None, checked: dict) -> None:
    plt = pyplot()
    if per_view is None:
        fig, ax = plt.subplots(1, 1, figsize=(6.5, 4.5))
        plot_frame_check(ax, checked)
        save_figure(fig, path)
        return
    fig, axes = plt.subplots(1, 3, figsize=(19, 4.5))
    plot_frame_check(axes[2], checked)
    bars = per_view | {"two views (joint, worker)": two_views}
    names = list(bars)
    x = np.arange(len(STAGES))
    width = 0.8 / len(names)
    for i, name in enumerate(names):
        axes[0].bar(x + (i - (len(names) - 1) / 2) * width, [bars[name]["cpu_ms"][s] for s in STAGES], width,
                    label=f"{name}: total {bars[name]['cpu_ms']['total']:.1f} ms CPU "
                          f"({bars[name]['wall_ms']['total']:.1f} wall)")
    axes[0].set_xticks(x, STAGES, rotation=20)
    axes[0].set(ylabel="median CPU time per frame (ms)", title="per-frame stages, 1024 x 1024 raw frame")
    axes[0].legend(fontsize=8)
    labels = ["one view", "two views", "two views\n(worker off)"]
    runs = [per_view[names[0]], two_views, serial]
    xs = np.arange(len(runs))
    axes[1].bar(xs - 0.2, [r["cpu_ms"]["this_process"] for r in runs], 0.4, label="CPU of the calling process")
    axes[1].bar(xs + 0.2, [r["wall_ms"]["total"] for r in runs], 0.4, label="wall (shared machine: noisy)",
                color="tab:gray")
    for xi, goal in zip(xs, (GOALS_MS["one_view"], GOALS_MS["two_views"], GOALS_MS["two_views"])):
        axes[1].hlines(goal, xi - 0.45, xi + 0.45, colors="k", linestyles="--")
    axes[1].set_xticks(xs, labels)
    axes[1].set(ylabel="median per-frame time (ms)", title="total against the goal (dashed)")
    axes[1].legend(fontsize=8)
    save_figure(fig, path)


#: The follower passes' settings before issue 10's cheaper passes (multiview / solve constants),
#: for the "two views (cold passes)" variant: the solver's own stall window on the refinement,
#: no preconditioner kept between solves.
COLD_PASSES = ((multiview, "WARM_START_WINDOW", None), (solve, "_PRECONDITIONER_CACHE_SIZE", 0))


@contextmanager
def _settings(changes):
    """Set module constants ``changes`` ((module, name, value), ...) for the block."""
    saved = [(module, name, getattr(module, name)) for module, name, _ in changes]
    for module, name, value in changes:
        setattr(module, name, value)
    try:
        yield
    finally:
        for module, name, value in saved:
            setattr(module, name, value)


def pipeline_runs(preop, views, repeats: int) -> dict:
    """{variant: :func:`summarise` of its runs}: each view alone, the first as a frame of a run
    (its prior kept from frame to frame, as ``track`` keeps it), both jointly with the view worker
    and without it, and both with the earlier follower passes (:data:`COLD_PASSES`),
    alternating over ``repeats`` (the shared machine's load hits them alike)."""
    runs = {}
    kept = [FluoroPrior.from_centerline(preop.centerline, views[0][3])]
    variants = [(view[0], [view], True, (), None) for view in views] + [
        (f"{views[0][0]} (run: prior kept)", [views[0]], True, (), kept),
        ("two views", views, True, (), None), ("two views (serial)", views, False, (), None),
        ("two views (cold passes)", views, True, COLD_PASSES, None)]
    for _, chosen, worker, changes, priors in variants:
        with _settings(changes):
            time_views(preop, chosen, worker, priors)     # warm-up: imports, caches, the worker's copy of the model
    found = {name: [] for name, _, _, _, _ in variants}
    for _ in range(repeats):
        for name, chosen, worker, changes, priors in variants:
            with _settings(changes):
                found[name].append(time_views(preop, chosen, worker, priors))
    for name, _, _, _, _ in variants:
        runs[name] = summarise(found[name])
        print(name, {k: round(v, 2) for k, v in runs[name]["cpu_ms"].items()}, "CPU ms;",
              f"wall total {runs[name]['wall_ms']['total']:.1f} ms", flush=True)
    workers.set_enabled(None)
    return runs


def checked_frames(preop, views, bench_preop, bench_P, benches) -> dict:
    """{name: (frame, prior, mask)} of the raw views and the bench frames, as the frame check gets them."""
    checked = {}
    for name, image, P, model in [(name, image, P, preop) for name, image, _, P in views] + \
            [(f"bench {kind}", bench.frame, bench_P, bench_preop) for kind, bench in benches.items()]:
        prior = FluoroPrior.from_centerline(model.centerline, P)
        checked[name] = (image, prior, segmentation.segment_fluoro(image, prior))
    return checked


def main() -> None:
    parser = argument_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--second-angle", type=float, default=30.0, help="primary angle of the second view (deg)")
    parser.add_argument("--no-breakdown", action="store_true", help="skip the segment_fluoro breakdown")
    parser.add_argument("--frame-check-only", action="store_true", help="time only the frame check (no pipeline runs)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    preop, views = frame_cases(args.seed, args.second_angle)
    payload = {"frame_shape": [FRAME_SIZE, FRAME_SIZE], "repeats": args.repeats, "seed": args.seed,
               "goals_ms": GOALS_MS, "nodes_3d": len(preop.centerline),
               "note": "medians over repeats; CPU time = time.process_time of this process (one BLAS thread); "
                       "wall times are noisy on the shared 2-core machine"}
    runs = {}
    if not args.frame_check_only:
        payload["worker_ready"] = workers.wait_until_ready(120.0)
        runs = pipeline_runs(preop, views, args.repeats)
        payload |= {"views": {k: v for k, v in runs.items() if not k.startswith("two views")},
                    "two_views": runs["two views"], "two_views_serial": runs["two views (serial)"],
                    "two_views_cold_passes": runs["two views (cold passes)"],
                    "over_cold_passes_cpu": over_cold_passes(runs["two views"], runs["two views (cold passes)"]),
                    "two_views_how": "pipeline.frame.prepare_views + register_prepared on both frames (one joint "
                                     "deformation): the second view's mask and 2D side in the view worker process; "
                                     "two_views_serial: the same with the worker off, alternating with it"}
    breakdown = not args.no_breakdown and not args.frame_check_only
    if breakdown:
        _, frame, _, P = views[0]
        payload["mask_breakdown"] = mask_breakdown(preop, frame, P, max(5, args.repeats // 3))
        payload["mask_profile"] = profile_mask(preop, frame, P, max(5, args.repeats // 3))
        print(payload["mask_breakdown"], *payload["mask_profile"], sep="\n")
    bench_preop, bench_P, benches = bench_frames(args.seed)
    if breakdown:
        payload["mask_by_frame_kind"] = mask_by_frame_kind(bench_preop, bench_P, benches, max(5, args.repeats // 3))
        print("bench frames (every distractor):", payload["mask_by_frame_kind"])
    payload["frame_check"] = frame_check_cost(checked_frames(preop, views, bench_preop, bench_P, benches), args.repeats)
    for name, row in payload["frame_check"].items():
        print("frame check", name, {k: round(v, 2) if isinstance(v, float) else v[:60] for k, v in row.items()})
    write_report(args.out, "bench_frame", payload)
    plot(args.out / "bench_frame.png", payload.get("views"), payload.get("two_views"), payload.get("two_views_serial"),
         payload["frame_check"])


if __name__ == "__main__":
    main()

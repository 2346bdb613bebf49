"""Benchmark the whole per-frame path from a raw 1024 x 1024 frame, stage by stage (issue 10).

A phantom case (random anatomy, seed ``--seed``) is rendered as a raw DSA-like 1024 x 1024
frame (:func:`phantom.render_fluoro`) in the AP view and, for the two-view variant, in a
second view of the same anatomy (LAO ``--second-angle``). The pre-operative model is built
once (thinned lumen, Algorithm 1, centred: :func:`pipeline.preop_from_lumen`). Then, per
frame and over ``--repeats`` repeats, each stage of the per-frame path is timed as the
pipeline runs it:

=============  ==========================================================================
mask           the pre-operative prior projected through P (:class:`quality.FluoroPrior`)
               and :func:`segmentation.segment_fluoro` with it (as ``pipeline._vessel_mask``)
skeleton2d     :func:`skeleton.skeletonize_2d`
graph2d        :meth:`graph.SkeletonGraph.from_image` (with the mask's radii), Algorithm 1,
               anatomical labels and smoothing (``pipeline._classify_2d`` + smoothing)
matching       :func:`matching.candidate_correspondences`
deformation    soft assignment, deformation (eq. 6, L-BFGS) and TPS fill, per candidate
=============  ==========================================================================

Two views are timed as two single views (the pipeline has no joint multi-view
registration yet); their sum is the two-view time. Wall time (``time.perf_counter``) and
CPU time of this process (``time.process_time``) are both recorded: the machine is shared,
so wall times are noisy and the CPU time is the better guide (with one BLAS thread and no
worker threads, CPU time <= wall time). The goals: 33 ms for one view, 66 ms for two.

    OMP_NUM_THREADS=1 .venv/bin/python Testing/benchmarks/bench_frame.py --out OUT [--repeats 30]

Writes ``bench_frame.json`` and ``bench_frame.png`` into ``--out``.
"""

from __future__ import annotations

from common import argument_parser, pyplot, save_figure, single_threaded_blas, write_report

single_threaded_blas()      # before NumPy

import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from FevarPlannerLib import graph, matching, phantom, pipeline, segmentation, skeleton  # noqa: E402
from FevarPlannerLib.projection import pixels_per_mm  # noqa: E402
from FevarPlannerLib.quality import FluoroPrior  # noqa: E402

STAGES = ("mask", "skeleton2d", "graph2d", "matching", "deformation")
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


def time_frame(preop, frame: np.ndarray, P: np.ndarray) -> tuple[dict, dict, dict]:
    """One pass of the per-frame path: ({stage: wall s}, {stage: CPU s}, facts)."""
    wall, cpu = {}, {}

    def record(stage, start):
        wall[stage], cpu[stage] = _since(start)

    with pipeline._threadpools().limit(limits=1, user_api="blas"):
        start = _clock()
        prior = FluoroPrior.from_centerline(preop.centerline, P)
        mask = segmentation.segment_fluoro(frame, prior)
        record("mask", start)
        start = _clock()
        thin = skeleton.skeletonize_2d(mask)
        record("skeleton2d", start)
        start = _clock()
        g2 = graph.SkeletonGraph.from_image(thin, pixel_size=1.0 / pixels_per_mm(P, preop.centre), mask=mask)
        c2 = pipeline._classify_2d(g2, P, preop.centre)
        g2 = graph.smooth_positions(c2.graph, pipeline.SMOOTHING_ITERATIONS)
        record("graph2d", start)
        start = _clock()
        candidates = matching.candidate_correspondences(preop.graph, preop.classification, g2, c2, P)
        record("matching", start)
        start = _clock()
        trials = [pipeline._deform_with(preop, g2, c2, P, c, 500.0, 10.0) for c in candidates]
        best = min(trials, key=lambda t: t[2])
        record("deformation", start)
    facts = {"mask_pixels": int(mask.sum()), "skeleton_pixels": int(thin.sum()), "nodes_2d": len(g2),
             "candidates": len(candidates), "energy": best[1], "result_sum": float(np.sum(best[0]))}
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
    walls = {s: [r[0][s] for r in runs] for s in STAGES}
    cpus = {s: [r[1][s] for r in runs] for s in STAGES}
    return {"wall_ms": {s: 1e3 * float(np.median(v)) for s, v in walls.items()}
            | {"total": 1e3 * float(np.median(np.sum([walls[s] for s in STAGES], axis=0)))},
            "cpu_ms": {s: 1e3 * float(np.median(v)) for s, v in cpus.items()}
            | {"total": 1e3 * float(np.median(np.sum([cpus[s] for s in STAGES], axis=0)))},
            "facts": runs[0][2]}


def plot(path: Path, per_view: dict, two_views: dict) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5))
    names = list(per_view)
    x = np.arange(len(STAGES))
    width = 0.8 / len(names)
    for i, name in enumerate(names):
        axes[0].bar(x + (i - (len(names) - 1) / 2) * width, [per_view[name]["cpu_ms"][s] for s in STAGES], width,
                    label=f"{name}: total {per_view[name]['cpu_ms']['total']:.1f} ms CPU "
                          f"({per_view[name]['wall_ms']['total']:.1f} wall)")
    axes[0].set_xticks(x, STAGES)
    axes[0].set(ylabel="median CPU time per frame (ms)", title="per-frame stages, 1024 x 1024 raw frame")
    axes[0].legend(fontsize=8)
    labels = ["one view", "two views"]
    totals = [per_view[names[0]]["cpu_ms"]["total"], two_views["cpu_ms"]]
    walls = [per_view[names[0]]["wall_ms"]["total"], two_views["wall_ms"]]
    xs = np.arange(2)
    axes[1].bar(xs - 0.2, totals, 0.4, label="CPU")
    axes[1].bar(xs + 0.2, walls, 0.4, label="wall (shared machine: noisy)", color="tab:gray")
    for xi, goal in zip(xs, (GOALS_MS["one_view"], GOALS_MS["two_views"])):
        axes[1].hlines(goal, xi - 0.45, xi + 0.45, colors="k", linestyles="--")
    axes[1].set_xticks(xs, labels)
    axes[1].set(ylabel="median per-frame time (ms)", title="total against the goal (dashed)")
    axes[1].legend(fontsize=8)
    save_figure(fig, path)


def main() -> None:
    parser = argument_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--second-angle", type=float, default=30.0, help="primary angle of the second view (deg)")
    parser.add_argument("--no-breakdown", action="store_true", help="skip the segment_fluoro breakdown")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    preop, views = frame_cases(args.seed, args.second_angle)
    per_view = {}
    for name, frame, _, P in views:
        time_frame(preop, frame, P)     # warm-up: imports, caches
        runs = [time_frame(preop, frame, P) for _ in range(args.repeats)]
        per_view[name] = summarise(runs)
        print(name, {k: round(v, 2) for k, v in per_view[name]["cpu_ms"].items()}, "CPU ms;",
              f"wall total {per_view[name]['wall_ms']['total']:.1f} ms", flush=True)
    two = {"cpu_ms": sum(v["cpu_ms"]["total"] for v in per_view.values()),
           "wall_ms": sum(v["wall_ms"]["total"] for v in per_view.values()),
           "how": "two single-view registrations (no joint multi-view registration in the pipeline yet)"}
    payload = {"frame_shape": [FRAME_SIZE, FRAME_SIZE], "repeats": args.repeats, "seed": args.seed,
               "goals_ms": GOALS_MS, "nodes_3d": len(preop.centerline), "views": per_view, "two_views": two,
               "note": "medians over repeats; CPU time = time.process_time of this process (one BLAS thread); "
                       "wall times are noisy on the shared 2-core machine"}
    if not args.no_breakdown:
        _, frame, _, P = views[0]
        payload["mask_breakdown"] = mask_breakdown(preop, frame, P, max(5, args.repeats // 3))
        payload["mask_profile"] = profile_mask(preop, frame, P, max(5, args.repeats // 3))
        print(payload["mask_breakdown"], *payload["mask_profile"], sep="\n")
    print("two views", two, flush=True)
    write_report(args.out, "bench_frame", payload)
    plot(args.out / "bench_frame.png", per_view, two)


if __name__ == "__main__":
    main()

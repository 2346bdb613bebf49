"""Benchmark: ``fevar-planner track`` on a 30-frame fluoroscopic run (issue 12).

A phantom case (seed 4, the same anatomy in every frame, a new noise draw per frame) is
written with a 30-frame ``fluoro.dcm`` (NumberOfFrames = 30) and its lumen mask; the route
runs twice against a fresh pre-operative cache: the first run builds the pre-operative
model, the second finds it in the cache. Every frame is segmented (vesselness), registered
(the proposed method) and its path planned.

Then the warm-cache run is repeated ``--repeats`` times with the frame checks in the view
worker process (``tracking.WORKER_MIN_FRAMES`` lowered to the run's length, the worker started
beforehand, as in the workstation where it already runs) and in this process, alternately
(``worker_on`` / ``worker_off``: wall and CPU seconds of this process per run, per-frame medians
by step, and whether every frame's fit is the same).

Writes ``bench_tracking.json`` (both runs' :meth:`TrackResult.summary`, per-frame times in
ms) and ``bench_tracking.png`` (per-frame time by stage; the worker comparison) to ``--out``. Run:
``.venv/bin/python Testing/benchmarks/bench_tracking.py --out bench_out [--repeats 3]``.
"""

import os
import sys
import tempfile
from pathlib import Path

from common import argument_parser, single_threaded_blas, timed, write_report

single_threaded_blas()

import numpy as np  # noqa: E402

from FevarPlannerLib import io, phantom, tracking  # noqa: E402
from FevarPlannerLib.pipeline import workers  # noqa: E402
from FevarPlannerLib.tracking import TIMED_STEPS, track_case, write_track_outputs  # noqa: E402

N_FRAMES = 30
SEED = 4


def write_run(folder: Path) -> Path:
    """The phantom case with a N_FRAMES-frame run and no 2D mask (every frame is segmented)."""
    params = phantom.random_params(np.random.default_rng(SEED), misalign_shift_px=(0.0, 0.0), misalign_rotation_deg=0.0)
    generated = phantom.generate_case(params, name="run")
    case = phantom.write_case(generated, folder, mask_only=True)
    frames = [phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                    np.random.default_rng([SEED, k]))[0] for k in range(N_FRAMES)]
    io.write_fluoro_dicom(case / "fluoro.dcm", np.stack(frames), generated.carm)
    (case / "fluoro_mask.png").unlink()
    return case


def worker_comparison(case: Path, repeats: int) -> dict:
    """The warm-cache run with the frame checks in the view worker and here, alternating ``repeats`` times."""
    found = {"worker_on": [], "worker_off": []}
    fits = {}
    saved = tracking.WORKER_MIN_FRAMES
    try:
        tracking.WORKER_MIN_FRAMES = 1
        for _ in range(repeats):
            for name, on in (("worker_on", True), ("worker_off", False)):
                workers.set_enabled(on)
                if on:
                    workers.wait_until_ready(120.0)
                result, wall, cpu = timed(track_case, case)
                fits[name] = [r.fit_2d_px for r in result.records]
                steps = {step: float(np.median([1000.0 * r.times.get(step, 0.0) for r in result.records]))
                         for step in TIMED_STEPS + ("total",)}
                found[name].append({"wall_s": wall, "cpu_s": cpu, "per_frame_median_ms": steps})
    finally:
        tracking.WORKER_MIN_FRAMES = saved
        workers.set_enabled(None)
    out = {name: {"runs": runs, "median_wall_s": float(np.median([r["wall_s"] for r in runs])),
                  "median_cpu_s": float(np.median([r["cpu_s"] for r in runs])),
                  "median_per_frame_total_ms": float(np.median([r["per_frame_median_ms"]["total"] for r in runs]))}
           for name, runs in found.items()}
    out["same_fits"] = fits["worker_on"] == fits["worker_off"]
    return out


def plot(path: Path, result, comparison: dict) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11, 3.5), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 2, 1)
    frames = [r.frame for r in result.records]
    bottom = np.zeros(len(frames))
    for stage, color in zip(TIMED_STEPS, ("0.6", "tab:blue", "tab:red", "tab:orange", "tab:purple", "tab:green")):
        values = np.array([1000.0 * r.times.get(stage, 0.0) for r in result.records])
        axes.bar(frames, values, bottom=bottom, color=color, label=stage)
        bottom += values
    axes.set_xlabel("frame")
    axes.set_ylabel("time (ms)")
    axes.set_title(f"track: {len(frames)} frames, pre-operative model from the cache "
                   f"({result.preop_seconds:.2f} s)", fontsize=9)
    axes.legend(fontsize=8)
    right = figure.add_subplot(1, 2, 2)
    names = ("worker_on", "worker_off")
    x = np.arange(len(TIMED_STEPS) + 1)
    for k, name in enumerate(names):
        runs = comparison[name]["runs"]
        right.bar(x + (k - 0.5) * 0.4, [np.median([r["per_frame_median_ms"][s] for r in runs])
                                         for s in TIMED_STEPS + ("total",)], 0.4,
                  label=f"{name.replace('_', ' ')}: run wall {comparison[name]['median_wall_s']:.2f} s, "
                        f"CPU {comparison[name]['median_cpu_s']:.2f} s")
    right.set_xticks(x, list(TIMED_STEPS) + ["total"], rotation=20, fontsize=8)
    right.set(ylabel="per-frame median (ms)", title="frame check in the view worker or here (warm cache)")
    right.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)


def main(argv=None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=3, help="worker on / off pairs of the warm-cache run")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        os.environ["FEVAR_PLANNER_CACHE"] = str(Path(work) / "cache")
        case = write_run(Path(work) / "case")
        runs = {}
        for name in ("cold_cache", "warm_cache"):
            result, wall, cpu = timed(track_case, case)
            runs[name] = dict(result.summary(), wall_s=wall, cpu_s=cpu)
        write_track_outputs(result, args.out / "track_out")
        comparison = worker_comparison(case, args.repeats)
    plot(args.out / "bench_tracking.png", result, comparison)
    write_report(args.out, "bench_tracking", {"n_frames": N_FRAMES, "seed": SEED, "runs": runs,
                                              "frame_check_in_worker": comparison})
    for name, run in runs.items():
        total = run["per_frame_total_ms"]
        print(f"{name}: pre-operative {run['preop_s']:.2f} s (cache {run['preop_from_cache']}), per frame median "
              f"{total['median']:.1f} ms, p95 {total['p95']:.1f} ms, fit {run['fit_2d_px']['median']:.2f} px, "
              f"wall {run['wall_s']:.1f} s")
    for name in ("worker_on", "worker_off"):
        row = comparison[name]
        print(f"{name}: run wall {row['median_wall_s']:.2f} s, CPU {row['median_cpu_s']:.2f} s, per-frame total "
              f"{row['median_per_frame_total_ms']:.1f} ms (median of {len(row['runs'])})")
    print("same fits:", comparison["same_fits"])
    return 0


if __name__ == "__main__":
    sys.exit(main())

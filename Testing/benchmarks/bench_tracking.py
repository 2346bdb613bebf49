"""Benchmark: ``fevar-planner track`` on a 30-frame fluoroscopic run (issue 12).

A phantom case (seed 4, the same anatomy in every frame, a new noise draw per frame) is
written with a 30-frame ``fluoro.dcm`` (NumberOfFrames = 30) and its lumen mask; the route
runs twice against a fresh pre-operative cache: the first run builds the pre-operative
model, the second finds it in the cache. Every frame is segmented (vesselness), registered
(the proposed method) and its path planned.

Writes ``bench_tracking.json`` (both runs' :meth:`TrackResult.summary`, per-frame times in
ms) and ``bench_tracking.png`` (per-frame time by stage) to ``--out``. Run:
``.venv/bin/python Testing/benchmarks/bench_tracking.py --out bench_out``.
"""

import os
import sys
import tempfile
from pathlib import Path

from common import argument_parser, single_threaded_blas, timed, write_report

single_threaded_blas()

import numpy as np  # noqa: E402

from FevarPlannerLib import io, phantom  # noqa: E402
from FevarPlannerLib.tracking import track_case, write_track_outputs  # noqa: E402

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


def plot(path: Path, result) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7, 3.5), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    frames = [r.frame for r in result.records]
    bottom = np.zeros(len(frames))
    for stage, color in (("read", "0.6"), ("segmentation", "tab:blue"), ("registration", "tab:orange"),
                         ("planning", "tab:green")):
        values = np.array([1000.0 * r.times.get(stage, 0.0) for r in result.records])
        axes.bar(frames, values, bottom=bottom, color=color, label=stage)
        bottom += values
    axes.set_xlabel("frame")
    axes.set_ylabel("time (ms)")
    axes.set_title(f"track: {len(frames)} frames, pre-operative model from the cache "
                   f"({result.preop_seconds:.2f} s)", fontsize=9)
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)


def main(argv=None) -> int:
    args = argument_parser(__doc__).parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        os.environ["FEVAR_PLANNER_CACHE"] = str(Path(work) / "cache")
        case = write_run(Path(work) / "case")
        runs = {}
        for name in ("cold_cache", "warm_cache"):
            result, wall, cpu = timed(track_case, case)
            runs[name] = dict(result.summary(), wall_s=wall, cpu_s=cpu)
        write_track_outputs(result, args.out / "track_out")
    plot(args.out / "bench_tracking.png", result)
    write_report(args.out, "bench_tracking", {"n_frames": N_FRAMES, "seed": SEED, "runs": runs})
    for name, run in runs.items():
        total = run["per_frame_total_ms"]
        print(f"{name}: pre-operative {run['preop_s']:.2f} s (cache {run['preop_from_cache']}), per frame median "
              f"{total['median']:.1f} ms, p95 {total['p95']:.1f} ms, fit {run['fit_2d_px']['median']:.2f} px, "
              f"wall {run['wall_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Registration benchmark: accuracy and per-frame time of the proposed method.

Runs the paper's simulation protocol (20 cases, see FevarPlannerLib.benchmark) and

* sweeps the energy weights (alpha, beta) of eq. (6) to choose the defaults,
* times the intra-operative part (2D skeleton + graph, matching, assignment, deformation,
  TPS) per stage, as medians over repeats,

and writes ``bench_registration.json`` and ``bench_registration.png`` into ``--out``.

    .venv/bin/python Testing/benchmarks/bench_registration.py --out OUT [--cases 20] [--repeats 5]
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from common import argument_parser, write_report
from FevarPlannerLib import benchmark, evaluation
from FevarPlannerLib.pipeline import register_frame

WEIGHTS = [(50.0, 1.0), (100.0, 1.0), (100.0, 10.0), (500.0, 1.0), (500.0, 3.0), (500.0, 10.0), (2000.0, 10.0)]
#: A finer CT grid for the paper's node counts (700-1000 3D nodes).
FINE_SPACING_MM = 0.6
STAGES = ("skeleton2d", "graph2d", "matching", "deformation", "intraop")


def sweep(cases, weights=WEIGHTS) -> list[dict]:
    rows = []
    for alpha, beta in weights:
        e2, e3, times = [], [], []
        for _, preop, mask, P, gt, _ in cases:
            frame = register_frame(preop, mask, P, method="proposed", refine_pose=False, alpha=alpha, beta=beta)
            errors = evaluation.evaluate(frame.deformed, gt, frame.P, frame.skeleton2d.positions,
                                         frame.skeleton2d.edges())
            e2.append(errors["2d_px"]["mean"])
            e3.append(errors["3d_mm"]["mean"])
            times.append(frame.timings["intraop"])
        rows.append({"alpha": alpha, "beta": beta, "2d_px_mean": float(np.mean(e2)), "3d_mm_mean": float(np.mean(e3)),
                     "3d_mm_max": float(np.max(e3)), "intraop_s_median": float(np.median(times))})
        print(f"alpha {alpha:7.1f} beta {beta:5.1f}: 2D {rows[-1]['2d_px_mean']:.3f} px, "
              f"3D {rows[-1]['3d_mm_mean']:.3f} mm (max {rows[-1]['3d_mm_max']:.2f}), "
              f"{rows[-1]['intraop_s_median'] * 1000:.1f} ms", flush=True)
    return rows


def stage_times(cases, repeats: int) -> dict:
    per_stage = {stage: [] for stage in STAGES}
    nodes = []
    for _, preop, mask, P, _, _ in cases:
        runs = [register_frame(preop, mask, P, method="proposed", refine_pose=False) for _ in range(repeats)]
        for stage in STAGES:
            per_stage[stage].append(float(np.median([r.timings.get(stage, 0.0) for r in runs])))
        nodes.append((len(preop.centerline), len(runs[0].skeleton2d.positions)))
    return {"median_s": {stage: float(np.median(v)) for stage, v in per_stage.items()},
            "per_case_s": per_stage, "nodes_3d_2d": nodes}


def plot(path: Path, rows: list[dict], times: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    labels = [f"a={r['alpha']:g}\nb={r['beta']:g}" for r in rows]
    x = np.arange(len(rows))
    axes[0].bar(x, [r["2d_px_mean"] for r in rows])
    axes[0].set_ylabel("mean 2D distance (px)")
    axes[1].bar(x, [r["3d_mm_mean"] for r in rows], color="tab:orange")
    axes[1].set_ylabel("mean 3D distance (mm)")
    for ax in axes[:2]:
        ax.set_xticks(x, labels, fontsize=8)
    stages = [s for s in STAGES if s != "intraop"]
    width = 0.4
    x_stages = np.arange(len(stages))
    axes[2].bar(x_stages - width / 2, [times["median_s"][s] * 1000 for s in stages], width, color="tab:green",
                label=f"{times['nodes_3d_2d'][0][0]} 3D nodes")
    axes[2].bar(x_stages + width / 2, [times["fine_grid"]["median_s"][s] * 1000 for s in stages], width,
                color="tab:olive", label=f"{times['fine_grid']['nodes_3d_2d'][0][0]} 3D nodes "
                                         f"({FINE_SPACING_MM} mm CT)")
    axes[2].set_xticks(x_stages, stages)
    axes[2].axhline(times["median_s"]["intraop"] * 1000, color="k", ls="--",
                    label=f"intra-operative total {times['median_s']['intraop'] * 1000:.1f} ms")
    axes[2].axhline(times["fine_grid"]["median_s"]["intraop"] * 1000, color="tab:olive", ls="--",
                    label=f"total, fine grid {times['fine_grid']['median_s']['intraop'] * 1000:.1f} ms")
    axes[2].axhline(50, color="tab:red", ls=":", label="goal 50 ms")
    axes[2].set_ylabel("median time per frame (ms)")
    axes[2].legend(fontsize=8)
    fig.suptitle("Proposed method on the simulation protocol: energy weights and per-stage time")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    cases = list(benchmark.simulation_cases(args.seed, args.cases))
    rows = sweep(cases)
    times = stage_times(cases, args.repeats)
    print("median per-stage ms:", {k: round(v * 1000, 1) for k, v in times["median_s"].items()})
    fine = stage_times(list(benchmark.simulation_cases(args.seed, args.cases, ct_spacing_mm=FINE_SPACING_MM)),
                       args.repeats)
    times["fine_grid"] = {"ct_spacing_mm": FINE_SPACING_MM, **fine}
    print(f"on a {FINE_SPACING_MM} mm CT grid:", {k: round(v * 1000, 1) for k, v in fine["median_s"].items()},
          "nodes (3D, 2D):", fine["nodes_3d_2d"][0])
    write_report(args.out, "bench_registration", {"cases": args.cases, "seed": args.seed, "weights": rows,
                                                  "timing": times, "wall_s": time.perf_counter() - started})
    plot(args.out / "bench_registration.png", rows, times)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

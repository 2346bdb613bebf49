"""Benchmark of the ICP-TPS baseline: run time and 2D/3D error on synthetic AAA-like trees.

Each case (``fixtures.synthetic_case``) is a vessel tree (aorta, two renal and two iliac
arteries, curving in depth) sampled with ``n`` 3D nodes, deformed smoothly in the image plane (the ground truth) and
projected with an antero-posterior C-arm ``P`` into a 2D centreline of 1500 points
(about one per 1.3 px). The table reports shape variation (SV, the rigid input) and ICP-TPS.

    .venv/bin/python Testing/benchmarks/bench_baselines.py --out Testing/benchmarks/results

writes ``bench_baselines.json`` and ``bench_baselines.png`` to ``--out``.
"""

from __future__ import annotations

from pathlib import Path

from common import argument_parser, write_report
from fixtures import synthetic_case
from FevarPlannerLib.baselines import icp_tps, rigid
from FevarPlannerLib.evaluation import evaluate

def _summary(case: dict, result_points: np.ndarray) -> dict:
    metrics = evaluate(case["preop"].with_points(result_points), case["truth"], case["P"],
                       case["skeleton_points"], case["skeleton_edges"])
    return {key: metrics[key] for key in ("2d_px", "2d_reverse_px", "3d_mm", "3d_reverse_mm")}


def run(sizes: list[int], seed: int) -> list[dict]:
    rows = []
    for n_nodes in sizes:
        case = synthetic_case(n_nodes, seed)
        sv = rigid(case["preop"].points)
        icp = icp_tps(case["preop"].points, case["preop"].edges, case["skeleton_points"], case["P"])
        rows.append({
            "n_nodes_3d": len(case["preop"]), "n_nodes_2d": len(case["skeleton_points"]),
            "n_controls": len(icp.info["controls"]), "temperatures": icp.n_iter,
            "icp_tps_seconds": icp.timings,
            "sv": _summary(case, sv.points), "icp_tps": _summary(case, icp.points),
        })
        print(f"n3={rows[-1]['n_nodes_3d']:5d} n2={rows[-1]['n_nodes_2d']:5d} "
              f"time={icp.timings['total']:.2f}s  2D px SV {rows[-1]['sv']['2d_px']['mean']:.3f} "
              f"ICP-TPS {rows[-1]['icp_tps']['2d_px']['mean']:.3f}  3D mm SV {rows[-1]['sv']['3d_mm']['mean']:.3f} "
              f"ICP-TPS {rows[-1]['icp_tps']['3d_mm']['mean']:.3f}", flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [row["n_nodes_3d"] for row in rows]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    axes[0].plot(sizes, [row["icp_tps_seconds"]["total"] for row in rows], "o-", label="total")
    axes[0].plot(sizes, [row["icp_tps_seconds"]["correspondence"] for row in rows], "s--", label="soft-assign")
    axes[0].plot(sizes, [row["icp_tps_seconds"]["deformation"] for row in rows], "^--", label="TPS update")
    axes[0].set(title="ICP-TPS run time", xlabel="3D nodes", ylabel="seconds")
    axes[0].legend()
    for ax, key, unit in ((axes[1], "2d_px", "px"), (axes[2], "3d_mm", "mm")):
        for method, marker in (("sv", "o"), ("icp_tps", "s")):
            ax.errorbar(sizes, [row[method][key]["mean"] for row in rows],
                        yerr=[row[method][key]["std"] for row in rows], marker=marker, capsize=3,
                        label="SV" if method == "sv" else "ICP-TPS")
        ax.set(title=f"{key[:2].upper()} error (mean ± std)", xlabel="3D nodes", ylabel=unit)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argument_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[300, 700, 1000])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run(args.sizes, args.seed)
    write_report(args.out, "bench_baselines", {"seed": args.seed, "cases": rows})
    plot(rows, args.out / "bench_baselines.png")


if __name__ == "__main__":
    main()

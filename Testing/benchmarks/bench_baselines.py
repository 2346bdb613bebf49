"""Benchmark of the ICP-TPS baseline: run time and 2D/3D error on synthetic AAA-like trees.

Each case is a vessel tree (aorta, two renal and two iliac arteries, curving in depth)
sampled with ``n`` 3D nodes, deformed smoothly in the image plane (the ground truth) and
projected with an antero-posterior C-arm ``P`` into a 2D centreline of 1500 points
(about one per 1.3 px). The table reports shape variation (SV, the rigid input) and ICP-TPS.

    .venv/bin/python Testing/benchmarks/bench_baselines.py --out Testing/benchmarks/results

writes ``bench_baselines.json`` and ``bench_baselines.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np

from FevarPlannerLib.baselines import icp_tps, rigid
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.evaluation import evaluate
from FevarPlannerLib.projection import CArmGeometry, carm_axes, project, projection_matrix_from_carm

#: Antero-posterior C-arm of the synthetic cases (about 3.7 px per mm at the isocentre).
AP_VIEW = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(0.4, 0.4), primary_angle=0.0,
                       secondary_angle=0.0, rows=1024, cols=1024)

#: Vessel polylines (LPS mm): label -> vertices. Branches start on an aorta vertex.
_VESSELS = {
    "aorta": [[0, 0, 150], [2, 6, 110], [-3, 12, 60], [0, 8, 20], [0, 0, 0]],
    "renal_left": [[2, 6, 110], [25, 0, 114], [50, -10, 112]],
    "renal_right": [[2, 6, 110], [-22, -2, 108], [-46, -12, 111]],
    "iliac_left": [[0, 0, 0], [25, 6, -40], [40, 12, -80], [45, 0, -120]],
    "iliac_right": [[0, 0, 0], [-22, 8, -42], [-38, 14, -82], [-44, 2, -118]],
}


def _polyline_length(vertices: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(vertices, axis=0), axis=1).sum())


def _resample(vertices: np.ndarray, count: int) -> np.ndarray:
    """``count`` points equally spaced along a polyline, both ends included."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(vertices, axis=0), axis=1))])
    where = np.linspace(0.0, arc[-1], count)
    return np.stack([np.interp(where, arc, vertices[:, d]) for d in range(vertices.shape[1])], axis=1)


def vessel_tree(n_nodes: int) -> Centerline:
    """An AAA-like centreline tree with about ``n_nodes`` nodes, labelled by vessel."""
    polylines = {label: np.asarray(vertices, dtype=float) for label, vertices in _VESSELS.items()}
    total = sum(_polyline_length(v) for v in polylines.values())
    points, edges, labels = [], [], []
    for label, vertices in polylines.items():
        samples = _resample(vertices, max(3, int(round(n_nodes * _polyline_length(vertices) / total))))
        offset = len(points)
        if label != "aorta":
            root = int(np.argmin(np.linalg.norm(np.asarray(points) - samples[0], axis=1)))
            samples = samples[1:]
            edges.append([root, offset])
        points.extend(samples.tolist())
        labels.extend([label] * len(samples))
        edges.extend([[offset + i, offset + i + 1] for i in range(len(samples) - 1)])
    return Centerline(np.asarray(points), np.asarray(edges), labels)


def in_plane_deformation(points: np.ndarray, P_view: CArmGeometry, seed: int, amplitude_mm: float = 8.0,
                         width_mm: float = 60.0, bumps: int = 4) -> np.ndarray:
    """A smooth displacement field parallel to the detector: a sum of Gaussian bumps."""
    rng = np.random.default_rng(seed)
    _, u_axis, v_axis = carm_axes(P_view.primary_angle, P_view.secondary_angle)
    centres = points[rng.choice(len(points), size=bumps, replace=False)]
    directions = rng.normal(size=(bumps, 2))
    directions *= amplitude_mm / np.linalg.norm(directions, axis=1, keepdims=True)
    vectors = directions[:, :1] * u_axis + directions[:, 1:] * v_axis
    weights = np.exp(-((points[:, None, :] - centres[None]) ** 2).sum(axis=2) / (2 * width_mm ** 2))
    return points + weights @ vectors


def dense_projection(P: np.ndarray, centreline: Centerline, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The projected centreline as a 2D graph of about ``n_points`` points.

    Every vessel (the nodes of one label, in order, from the node it branches off) is
    projected and resampled evenly along its length, so the 2D points do not coincide
    with projected 3D nodes.
    """
    projected = project(P, centreline.points)
    labels = np.asarray(centreline.labels)
    chains = []
    for label in dict.fromkeys(centreline.labels):
        members = np.flatnonzero(labels == label)
        roots = [a for a, b in centreline.edges if b == members[0] and labels[a] != label]
        chains.append(projected[roots[:1] + members.tolist()])
    total = sum(_polyline_length(chain) for chain in chains)
    points, edges = [], []
    for chain in chains:
        samples = _resample(chain, max(2, int(round(n_points * _polyline_length(chain) / total))))
        offset = sum(len(p) for p in points)
        if offset:
            previous = np.vstack(points)
            edges.append([int(np.argmin(np.linalg.norm(previous - samples[0], axis=1))), offset])
            samples = samples[1:]
        points.append(samples)
        edges.extend([[offset + i, offset + i + 1] for i in range(len(samples) - 1)])
    return np.vstack(points), np.asarray(edges, dtype=np.int64)


def synthetic_case(n_nodes: int, seed: int = 0, skeleton_points: int = 1500) -> dict:
    """A registration case with ground truth: pre-op tree, deformed tree, P and 2D skeleton.

    The 2D skeleton's density does not depend on the 3D sampling, as with a real frame:
    1500 points put one about every 1.3 px along the projected tree.
    """
    preop = vessel_tree(n_nodes)
    isocentre = 0.5 * (preop.points.min(axis=0) + preop.points.max(axis=0))
    P = projection_matrix_from_carm(AP_VIEW, isocentre)
    truth = preop.with_points(in_plane_deformation(preop.points, AP_VIEW, seed))
    skeleton_points, skeleton_edges = dense_projection(P, truth, skeleton_points)
    return {"preop": preop, "truth": truth, "P": P, "skeleton_points": skeleton_points,
            "skeleton_edges": skeleton_edges}


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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the JSON and PNG")
    parser.add_argument("--sizes", type=int, nargs="+", default=[300, 700, 1000])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run(args.sizes, args.seed)
    report = {"benchmark": "baselines", "machine": platform.platform(), "cpus": os.cpu_count(),
              "python": platform.python_version(), "seed": args.seed, "cases": rows}
    (args.out / "bench_baselines.json").write_text(json.dumps(report, indent=2))
    plot(rows, args.out / "bench_baselines.png")


if __name__ == "__main__":
    main()

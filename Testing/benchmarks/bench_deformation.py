"""Benchmark the deformation stage: deform_assigned (eq. 6, L-BFGS) + fill_unassigned (TPS).

Builds a synthetic AAA-like skeleton (aorta, two renal and two iliac branches) with a given
number of assigned nodes, deforms it without stretching (bent aorta, swung branches), projects the deformed assigned
nodes through an AP C-arm (plus 0.3 px noise) as the 2D targets, and times the two calls.
A second view (LAO 60, the same anatomy) is timed too: ``deform_assigned(..., extra_views=...)``.

    .venv/bin/python Testing/benchmarks/bench_deformation.py --out Testing/benchmarks/results

Writes ``bench_deformation.json`` and ``bench_deformation.png`` into ``--out``. Times are
medians over ``--repeats`` runs, both wall-clock and CPU time of this process (the latter is
the better guide on a shared machine). The preconditioned L-BFGS variant is timed beside the
default one for comparison.
"""

from __future__ import annotations

from common import argument_parser, single_threaded_blas, timed, write_report

single_threaded_blas()      # before NumPy: set the variables yourself to compare

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from FevarPlannerLib.deformation import deform_assigned, fill_unassigned  # noqa: E402
from FevarPlannerLib.projection import CArmGeometry, project, projection_matrix_from_carm  # noqa: E402

GEOMETRY = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(0.5, 0.5), primary_angle=0.0,
                        secondary_angle=0.0, rows=1024, cols=1024)
#: The second view of the two-view variant.
SECOND_VIEW = CArmGeometry(**{**GEOMETRY.__dict__, "primary_angle": 60.0})
#: Variants timed per size: name -> (precondition, two views).
VARIANTS = {"default": (False, False), "preconditioned": (True, False), "two_views": (False, True),
            "two_views_preconditioned": (True, True)}

# (parent segment index or None, attach at fraction of parent, end-point offsets in mm,
#  fraction of the segment, from its far end, left unassigned)
SEGMENTS = (
    ("aorta", None, 0.0, lambda s: np.column_stack([4 * np.sin(2 * s), 6 * s - 3, 120 - 170 * s]), 0.08),
    ("renal_left", 0, 0.3, lambda s: np.column_stack([50 * s, 8 * s ** 2, -6 * s]), 0.35),
    ("renal_right", 0, 0.32, lambda s: np.column_stack([-48 * s, 10 * s ** 2, -4 * s]), 0.35),
    ("iliac_left", 0, 1.0, lambda s: np.column_stack([40 * s, 12 * s, -95 * s + 5 * np.sin(3 * s)]), 0.0),
    ("iliac_right", 0, 1.0, lambda s: np.column_stack([-38 * s, 10 * s, -100 * s]), 0.05),
)


def make_skeleton(n_assigned: int):
    """Points, edges, assigned mask, per-segment node groups and each segment's anchor node."""
    unassigned_share = 0.12
    n_total = int(round(n_assigned / (1 - unassigned_share)))
    lengths = []
    for _, _, _, curve, _ in SEGMENTS:
        pts = curve(np.linspace(0, 1, 200))
        lengths.append(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    counts = np.maximum(3, np.round(np.array(lengths) / sum(lengths) * n_total).astype(int))
    points, edges, groups, unassigned, anchors = [], [], [], [], []
    start = 0
    for (name, parent, at, curve, tail), count in zip(SEGMENTS, counts):
        if parent is None:
            base, first_edge_from, anchor = np.zeros(3), None, None
            s = np.linspace(0, 1, count)
        else:
            parent_nodes = groups[parent]
            anchor = parent_nodes[min(int(round(at * (len(parent_nodes) - 1))), len(parent_nodes) - 1)]
            base, first_edge_from = points[anchor], anchor
            s = np.linspace(0, 1, count + 1)[1:]
        seg = base + curve(s) - (curve(np.zeros(1))[0] if parent is not None else 0)
        idx = np.arange(start, start + count)
        points.extend(seg)
        chain = np.column_stack([idx[:-1], idx[1:]])
        edges.extend(chain.tolist())
        if first_edge_from is not None:
            edges.append([int(first_edge_from), int(idx[0])])
        n_tail = int(round(tail * count))
        if n_tail:
            unassigned.extend(idx[-n_tail:] if name != "aorta" else idx[:n_tail])
        groups.append(idx)
        anchors.append(anchor)
        start += count
    points = np.asarray(points)
    assigned = np.ones(len(points), dtype=bool)
    assigned[np.asarray(unassigned, dtype=int)] = False
    gap = groups[3][len(groups[3]) // 2: len(groups[3]) // 2 + max(2, len(groups[3]) // 15)]
    assigned[gap] = False
    return points, np.asarray(edges), assigned, groups, anchors


def _rotation(rotvec) -> np.ndarray:
    return Rotation.from_rotvec(rotvec).as_matrix()


def length_preserving_deformation(points, groups, anchors, rng) -> np.ndarray:
    """Bend the aorta smoothly and swing each branch about its anchor; every edge keeps its length.

    Vessels hardly stretch, which is what the length term of eq. 6 assumes: the aorta's
    edge vectors turn progressively (up to ~7 degrees at its end), each branch follows the
    local frame of its anchor and turns by another ~8 degrees, then all moves rigidly.
    """
    moved = points.copy()
    frame = np.repeat(np.eye(3)[None], len(points), axis=0)
    trunk = groups[0]
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    for k in range(1, len(trunk)):
        frame[trunk[k]] = _rotation(axis * 0.12 * k / len(trunk))
        moved[trunk[k]] = moved[trunk[k - 1]] + frame[trunk[k]] @ (points[trunk[k]] - points[trunk[k - 1]])
    for nodes, anchor in zip(groups[1:], anchors[1:]):
        swing = frame[anchor] @ _rotation(np.deg2rad(8.0) * rng.normal(size=3) / np.sqrt(3))
        moved[nodes] = moved[anchor] + (points[nodes] - points[anchor]) @ swing.T
    center = points.mean(axis=0)
    return (moved - center) @ _rotation(np.deg2rad([1.0, 2.0, 3.0])).T + center + [2.0, -1.0, 3.0]


def make_case(n_assigned: int, seed: int = 0):
    """Everything deform_assigned + fill_unassigned need, plus the ground truth."""
    rng = np.random.default_rng(seed)
    points, edges, assigned, groups, anchors = make_skeleton(n_assigned)
    truth = length_preserving_deformation(points, groups, anchors, rng)
    P = projection_matrix_from_carm(GEOMETRY, points.mean(axis=0))
    index = np.full(len(points), -1)
    index[assigned] = np.arange(np.count_nonzero(assigned))
    keep = assigned[edges[:, 0]] & assigned[edges[:, 1]]
    assigned_edges = index[edges[keep]]
    targets = project(P, truth[assigned]) + rng.normal(0, 0.3, (np.count_nonzero(assigned), 2))
    adjacency = scipy.sparse.csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                                        shape=(len(points), len(points)))
    P2 = projection_matrix_from_carm(SECOND_VIEW, points.mean(axis=0))
    targets2 = project(P2, truth[assigned]) + rng.normal(0, 0.3, (np.count_nonzero(assigned), 2))
    return dict(points=points, truth=truth, assigned=assigned, assigned_edges=assigned_edges,
                targets=targets, P=P, adjacency=adjacency, groups=groups, second_view=(P2, targets2, None))


def run_once(case, precondition=False, two_views=False):
    """Time one deform + fill; returns (timings dict, result, filled points)."""
    assigned = case["assigned"]
    extra_views = [case["second_view"]] if two_views else []
    result, deform_wall, deform_cpu = timed(deform_assigned, case["points"][assigned], case["targets"],
                                            case["assigned_edges"], case["P"], precondition=precondition,
                                            extra_views=extra_views)
    moved = case["points"].copy()
    moved[assigned] = result.points
    filled, fill_wall, fill_cpu = timed(fill_unassigned, case["points"], moved, assigned, case["adjacency"])
    timings = {"deform_s": deform_wall, "fill_s": fill_wall, "total_s": deform_wall + fill_wall,
               "deform_cpu_s": deform_cpu, "fill_cpu_s": fill_cpu, "total_cpu_s": deform_cpu + fill_cpu}
    return timings, result, filled


def _quality(case, result, filled) -> dict:
    assigned = case["assigned"]
    residual = np.linalg.norm(project(case["P"], result.points) - case["targets"], axis=1)
    initial_residual = np.linalg.norm(project(case["P"], case["points"][assigned]) - case["targets"], axis=1)
    error3d = np.linalg.norm(filled - case["truth"], axis=1)
    initial3d = np.linalg.norm(case["points"] - case["truth"], axis=1)
    return {
        "n_iter": result.n_iter,
        "n_evaluations": result.n_evaluations,
        "converged": result.converged,
        "energy_initial": result.energy_initial,
        "energy_final": result.energy_final,
        "terms": result.terms,
        "residual_2d_px_mean": {"initial": float(initial_residual.mean()), "final": float(residual.mean())},
        "error_3d_mm_mean": {"initial": float(initial3d.mean()), "final": float(error3d.mean()),
                             "unassigned_final": float(error3d[~assigned].mean())},
    }


def measure(n_assigned: int, repeats: int) -> dict:
    case = make_case(n_assigned)
    row = {"n_assigned": int(np.count_nonzero(case["assigned"])), "n_nodes": int(len(case["assigned"])),
           "repeats": repeats}
    for name, (precondition, two_views) in VARIANTS.items():
        runs = [run_once(case, precondition, two_views) for _ in range(repeats)]
        timings = {key: float(np.median([r[0][key] for r in runs])) for key in runs[0][0]}
        row[name] = {"median_s": timings, **_quality(case, *runs[0][1:])}
    return row


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["n_assigned"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for key, label in (("deform_cpu_s", "deform_assigned (L-BFGS), CPU"), ("fill_cpu_s", "fill_unassigned (TPS), CPU"),
                       ("total_cpu_s", "total, CPU"), ("total_s", "total, wall")):
        ax.plot(n, [1e3 * r["default"]["median_s"][key] for r in rows], "o-", label=label)
    ax.plot(n, [1e3 * r["preconditioned"]["median_s"]["total_cpu_s"] for r in rows], "s--",
            label="total with preconditioned L-BFGS, CPU")
    ax.plot(n, [1e3 * r["two_views"]["median_s"]["total_cpu_s"] for r in rows], "^--",
            label="total with two views (AP + LAO 60), CPU")
    ax.axhline(25, color="grey", ls="--", label="stage goal 25 ms")
    ax.set_xlabel("assigned nodes")
    ax.set_ylabel("median time (ms)")
    ax.set_title("Deformation stage")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    parser = argument_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[300, 700, 1000, 2000])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for size in args.sizes:
        row = measure(size, args.repeats)
        rows.append(row)
        for name in VARIANTS:
            r, t = row[name], row[name]["median_s"]
            print(f"n_a={row['n_assigned']:5d} {name:14s} deform {1e3 * t['deform_cpu_s']:6.1f} ms CPU "
                  f"({1e3 * t['deform_s']:6.1f} wall)  fill {1e3 * t['fill_cpu_s']:5.1f} ms CPU "
                  f"({1e3 * t['fill_s']:5.1f} wall)  iters {r['n_iter']:4d}  "
                  f"2D {r['residual_2d_px_mean']['initial']:.2f}->{r['residual_2d_px_mean']['final']:.2f} px  "
                  f"3D {r['error_3d_mm_mean']['initial']:.2f}->{r['error_3d_mm_mean']['final']:.2f} mm")
    write_report(args.out, "bench_deformation", {"results": rows})
    plot(rows, args.out / "bench_deformation.png")


if __name__ == "__main__":
    main()

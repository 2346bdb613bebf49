"""The paper's experiments on our phantoms: SV (rigid) / ICP-TPS / proposed.

``fevar-planner benchmark --out DIR [--quick]`` runs

1. the simulation protocol (paper Sec. III-A, Fig. 4): one phantom in five states bent in
   the frontal plane (as the paper's phantom, bent by a string on a table), cross-paired
   into 20 pre-op / intra-op cases; the 2D skeleton is the projection of the
   intra-operative 3D skeleton (drawn into the frame and thinned); then the same protocol
   with the sac also bent out of the image plane by up to +-1 degree (``OUT_OF_PLANE_DEG``),
   which one view cannot see: the sensitivity of both methods to it;
2. robustness (Fig. 5): in-plane translations and rotations of the frame of one simulation
   case, the methods given the unmoved ``P``; 3D errors against the moved anatomy (the
   patient moved) and against the unmoved one (``P`` is off instead), see ``_robustness``;
3. phantom-like cases (Fig. 6): masks as real data gives them (3D skeleton thinned from the
   pre-op lumen, 2D skeleton thinned from the projected intra-op lumen), and hard variants
   (strong deformation, extra branches, C-arm angulation);

and writes ``benchmark.json``, ``table.md`` (shaped like Table II) and figures
``fig4_simulation.png``, ``fig4b_simulation_out_of_plane.png``, ``fig5_robustness.png``,
``fig6_phantom.png``. ``acceptance`` in benchmark.json holds the 3D error ratio (ICP-TPS /
proposed) and the speed-up on the simulation set; ``comparisons`` the same for both
simulation sets.
Errors are the paper's: mean 2D point-to-curve distance of the projected result to the 2D
skeleton (px), mean 3D point-to-curve distance to the ground-truth centreline (mm), plus the
reverse 3D distance (ground truth to result). Time is the intra-operative part (2D skeleton
and graph, matching, assignment, deformation, TPS; for ICP-TPS its whole loop).

``fevar-planner benchmark --sets independent`` (or ``all``) runs the independent sets of
issue 10 beside them (:func:`run_independent_benchmark`): case folders of the
:mod:`scenarios` family, which shares no geometry or deformation code with :mod:`phantom`,
run through the case-folder route (:func:`pipeline.plan_case`, what a user gets), scored
with the depth floor and the in-plane / along-ray split per vessel
(:func:`evaluation.depth_analysis`); files ``independent.json``, ``independent_table.md``,
``independent_sets.png`` and ``independent_vessels.png``.
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage
from skimage.draw import line as draw_line

from . import evaluation, phantom, scenarios
from .centerline import Centerline
from .files import InputError, write_text_atomic
from .pipeline import plan_case, preop_from_lumen, register_frame
from .projection import patient_motion, project

__all__ = ["METHODS", "run_benchmark", "simulation_cases", "phantom_cases", "INDEPENDENT_SETS",
           "run_independent_benchmark"]

#: Method name in tables -> (pipeline method, pose refinement).
METHODS = {"SV": ("rigid", False), "ICP-TPS": ("icp-tps", False), "Proposed": ("proposed", False)}
TRANSLATIONS_PX = (0, 10, 20, 30, 40, 60)
ROTATIONS_DEG = (0, 5, 10, 15, 20, 30)
#: The sensitivity set: the simulation protocol with the sac also bent out of the image
#: plane by up to this much (degrees), a bend that one AP view cannot see.
OUT_OF_PLANE_DEG = 1.0
SIMULATION = "Simulation"
OUT_OF_PLANE = f"Simulation, ±{OUT_OF_PLANE_DEG:g}° out of plane"


def draw_skeleton_mask(points_uv: np.ndarray, edges: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Rasterise a projected skeleton graph as a three-pixel-wide line mask (simulation protocol).

    Three pixels so that the 2D stage's smoothing before thinning keeps it; thinning
    brings it back to the one-pixel skeleton.
    """
    mask = np.zeros(shape, dtype=bool)
    rc = np.round(points_uv[:, ::-1]).astype(int)
    for a, b in edges:
        rr, cc = draw_line(rc[a, 0], rc[a, 1], rc[b, 0], rc[b, 1])
        keep = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        mask[rr[keep], cc[keep]] = True
    return ndimage.binary_dilation(mask, structure=np.ones((3, 3), dtype=bool))


def _thinned(anatomy, grid):
    """The classified 3D skeleton graph of an anatomy's lumen, thinned on the CT grid and centred."""
    return preop_from_lumen(phantom.rasterize_lumen(anatomy, grid))


def simulation_cases(seed: int = 0, n: int = 20, ct_spacing_mm: float | None = None,
                     out_of_plane_deg: float = phantom.PAPER_OUT_OF_PLANE_DEG):
    """Yield ``(name, preop, mask2d, P, gt, intra_skeleton)`` for the paper's simulation protocol.

    ``intra_skeleton`` is the thinned intra-operative 3D skeleton whose projection drew
    ``mask2d``; ``gt`` the dense intra-operative centreline. ``ct_spacing_mm`` overrides the
    phantoms' CT grid (finer grids give longer skeletons: 0.6 mm gives about 700 nodes);
    ``out_of_plane_deg`` is :func:`phantom.paper_protocol`'s.
    """
    pairs = phantom.paper_protocol(seed, out_of_plane_deg)[:n]
    states = {id(state): state for pair in pairs for state in pair}
    if ct_spacing_mm is not None:
        states = {key: replace(state, ct_spacing_mm=ct_spacing_mm) for key, state in states.items()}
    thinned = {}
    for index, (pre, intra) in enumerate(pairs):
        case = phantom.generate_case(states[id(pre)], states[id(intra)], name=f"sim{index:02d}")
        for key, anatomy in ((id(pre), case.preop), (id(intra), case.intraop)):
            if key not in thinned:
                thinned[key] = _thinned(anatomy, case.grid)
        intra_skeleton = thinned[id(intra)].centerline
        shape = (case.carm.rows, case.carm.cols)
        mask = draw_skeleton_mask(project(case.P_true, intra_skeleton.points), intra_skeleton.edges, shape)
        yield case.name, thinned[id(pre)], mask, case.P_true, case.intraop.to_centerline(), intra_skeleton


HARD_VARIANTS = (("strong_deformation", {"deformation_scale": 1.6}),
                 ("extra_branches", {"sma": True, "coeliac": True, "internal_iliacs": True}),
                 ("angulated_lao30_cra15", {"primary_angle_deg": 30.0, "secondary_angle_deg": 15.0}),
                 ("angulated_rao25_cau10", {"primary_angle_deg": -25.0, "secondary_angle_deg": -10.0}))


def phantom_cases(seed: int = 0, n: int = 6, n_hard: int = len(HARD_VARIANTS)):
    """Yield ``(name, preop, mask2d, P_given, gt)`` for mask-level phantom cases.

    ``n`` random cases, then the first ``n_hard`` of :data:`HARD_VARIANTS`.
    """
    rng = np.random.default_rng(seed)
    plans = [(f"phantom{i:02d}", {}) for i in range(n)] + list(HARD_VARIANTS[:n_hard])
    for name, overrides in plans:
        params = phantom.random_params(rng, **overrides)
        case = phantom.generate_case(params, name=name)
        preop = _thinned(case.preop, case.grid)
        _, mask = phantom.render_fluoro(case.intraop, case.P_true, case.carm, case.params,
                                        np.random.default_rng(params.seed))
        yield name, preop, mask, case.P_given, case.intraop.to_centerline()


def _run_methods(preop, mask, P, gt, methods=METHODS, other_truths=None) -> dict:
    """Each method on one frame: errors against ``gt`` and, as ``3d_mm_<name>``, against
    every centreline of ``other_truths`` (another reading of what the frame shows)."""
    results = {}
    for label, (method, refine) in methods.items():
        t0 = time.perf_counter()
        try:
            frame = register_frame(preop, mask, P, method=method, refine_pose=refine)
        except ValueError as exc:
            results[label] = {"failed": str(exc)}
            continue
        wall = time.perf_counter() - t0
        skeleton2d = (frame.skeleton2d.positions, frame.skeleton2d.edges())
        errors = evaluation.evaluate(frame.deformed, gt, frame.P, *skeleton2d)
        results[label] = {"2d_px": errors["2d_px"], "3d_mm": errors["3d_mm"],
                          "3d_reverse_mm": errors["3d_reverse_mm"], "time_s": frame.timings["intraop"],
                          "wall_s": wall, "nodes3d": len(preop.centerline), "nodes2d": len(frame.skeleton2d.positions),
                          "correspondence": frame.correspondence}
        for name, truth in (other_truths or {}).items():
            results[label][f"3d_mm_{name}"] = evaluation.evaluate(frame.deformed, truth, frame.P, *skeleton2d)["3d_mm"]
    return results


def _summarise(cases: list[dict]) -> dict:
    summary = {}
    for label in METHODS:
        rows = [c["results"][label] for c in cases if "failed" not in c["results"].get(label, {"failed": 1})]
        if not rows:
            continue
        summary[label] = {
            "cases": len(rows), "failed": len(cases) - len(rows),
            "2d_px_mean": float(np.mean([r["2d_px"]["mean"] for r in rows])),
            "2d_px_std": float(np.mean([r["2d_px"]["std"] for r in rows])),
            "3d_mm_mean": float(np.mean([r["3d_mm"]["mean"] for r in rows])),
            "3d_mm_std": float(np.mean([r["3d_mm"]["std"] for r in rows])),
            "3d_reverse_mm_mean": float(np.mean([r["3d_reverse_mm"]["mean"] for r in rows])),
            "time_s_median": float(np.median([r["time_s"] for r in rows])),
        }
    return summary


def _moved(centerline, motion: np.ndarray):
    return centerline.with_points(centerline.points @ motion[:3, :3].T + motion[:3, 3])


def _robustness(name, preop, intra_skeleton, P, gt, shape, translations, rotations, progress_step):
    """Errors against in-plane translation (px) and rotation (deg) of the frame (paper Fig. 5).

    The intra-operative anatomy is moved rigidly so that its image moves in-plane
    (projection.patient_motion: a rotation about the principal axis, a shift parallel to the
    detector) and the methods get the unmoved ``P``. The same frame is read two ways: the
    patient moved and ``P`` is right (``3d_mm``: against the moved truth, what the paper's
    robustness experiment asks of a method that follows the frame), or the patient did not
    move and ``P`` is off (``3d_mm_if_P_off``: against the unmoved truth, what pose
    refinement is for).
    """
    curves = {"translation_px": [], "rotation_deg": []}
    at = intra_skeleton.points.mean(axis=0)
    methods = dict(METHODS, **{"Proposed + pose refinement": ("proposed", True)})
    for kind, values in (("translation_px", translations), ("rotation_deg", rotations)):
        for value in values:
            motion = patient_motion(P, at, translation_px=(value, 0.0) if kind == "translation_px" else (0.0, 0.0),
                                    rotation_deg=value if kind == "rotation_deg" else 0.0)
            moved = _moved(intra_skeleton, motion)
            mask = draw_skeleton_mask(project(P, moved.points), moved.edges, shape)
            results = _run_methods(preop, mask, P, _moved(gt, motion), methods, {"if_P_off": gt})
            curves[kind].append({"offset": value, "results": results})
            progress_step(f"robustness {kind} {value}")
    return {"case": name, **curves}


def _comparison(summary: dict) -> dict:
    """The issue's two acceptance numbers for one set: 3D error ratio and speed-up over ICP-TPS."""
    icp, proposed = summary["ICP-TPS"], summary["Proposed"]
    return {"error_ratio": icp["3d_mm_mean"] / proposed["3d_mm_mean"],
            "speedup": icp["time_s_median"] / proposed["time_s_median"]}


def _table_markdown(summaries: dict, comparisons: dict) -> str:
    lines = ["| Dataset | Method | 2D dist. (px) | 3D dist. (mm) | 3D reverse (mm) | time (s, median) |",
             "|---|---|---|---|---|---|"]
    for dataset, summary in summaries.items():
        for label, s in summary.items():
            lines.append(f"| {dataset} | {label} | {s['2d_px_mean']:.3f} ± {s['2d_px_std']:.3f} | "
                         f"{s['3d_mm_mean']:.3f} ± {s['3d_mm_std']:.3f} | {s['3d_reverse_mm_mean']:.3f} | "
                         f"{s['time_s_median']:.3f} |")
    lines.append("")
    for dataset, c in comparisons.items():
        lines.append(f"Proposed vs ICP-TPS, {dataset}: 3D error ratio (ICP-TPS / proposed) {c['error_ratio']:.2f}, "
                     f"speed-up (median ICP-TPS time / median proposed time) {c['speedup']:.1f}x.")
    return "\n".join(lines) + "\n"


def _bar_figure(path: Path, cases: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    x = np.arange(len(cases))
    width = 0.8 / len(METHODS)
    for k, label in enumerate(METHODS):
        for ax, key in zip(axes, ("2d_px", "3d_mm")):
            rows = [c["results"].get(label, {}) for c in cases]
            means = [r[key]["mean"] if key in r else np.nan for r in rows]
            stds = [r[key]["std"] if key in r else 0.0 for r in rows]
            ax.bar(x + (k - 1) * width, means, width, yerr=stds, label=label, capsize=2)
    for ax, ylabel in zip(axes, ("2D distance (px)", "3D distance (mm)")):
        ax.set_xticks(x, [c["name"] for c in cases], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(ylabel)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _robustness_figure(path: Path, robustness: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("2d_px", "2D distance (px)"), ("3d_mm", "3D distance (mm), patient moved"),
              ("3d_mm_if_P_off", "3D distance (mm), P off instead"))
    fig, axes = plt.subplots(2, 3, figsize=(16, 7.5))
    for row, kind in enumerate(("translation_px", "rotation_deg")):
        points = robustness[kind]
        offsets = [p["offset"] for p in points]
        for label in points[0]["results"]:
            for col, (key, ylabel) in enumerate(panels):
                values = [p["results"][label].get(key, {}).get("mean", np.nan) for p in points]
                stds = [p["results"][label].get(key, {}).get("std", 0.0) for p in points]
                axes[row, col].errorbar(offsets, values, yerr=stds, marker="o", capsize=3, label=label)
                axes[row, col].set_xlabel("in-plane translation (px)" if row == 0 else "in-plane rotation (deg)")
                axes[row, col].set_ylabel(ylabel)
                axes[row, col].set_yscale("log")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"Robustness to an in-plane offset of the frame ({robustness['case']}); the methods keep P")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_benchmark(out_dir, *, quick: bool = False, seed: int = 0, progress=None) -> dict:
    """Run the experiments and write benchmark.json, table.md and the figures into ``out_dir``.

    Parameters
    ----------
    out_dir : path
    quick : bool
        A small subset (4 simulation cases, 3 offsets per robustness curve, 1 + 2 phantom
        cases) that runs in about two minutes.
    seed : int
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    dict
        The summary (also in benchmark.json).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n_sim = 4 if quick else 20
    translations = TRANSLATIONS_PX[::2] if quick else TRANSLATIONS_PX
    rotations = ROTATIONS_DEG[::2] if quick else ROTATIONS_DEG
    n_phantom, n_hard = (1, 2) if quick else (6, len(HARD_VARIANTS))
    total_steps = 2 * n_sim + len(translations) + len(rotations) + n_phantom + n_hard
    done = [0]

    def step(message):
        done[0] += 1
        if progress is not None:
            progress(done[0] / total_steps, message)

    started = time.perf_counter()
    simulation, robustness = [], None
    for name, preop, mask, P, gt, intra_skeleton in simulation_cases(seed, n_sim):
        simulation.append({"name": name, "results": _run_methods(preop, mask, P, gt)})
        step(f"simulation {name}")
        if robustness is None:
            robustness = _robustness(name, preop, intra_skeleton, P, gt, mask.shape, translations, rotations, step)
    out_of_plane = []
    for name, preop, mask, P, gt, _ in simulation_cases(seed, n_sim, out_of_plane_deg=OUT_OF_PLANE_DEG):
        out_of_plane.append({"name": name, "results": _run_methods(preop, mask, P, gt)})
        step(f"simulation +-{OUT_OF_PLANE_DEG:g} deg out of plane {name}")
    phantoms = []
    for name, preop, mask, P, gt in phantom_cases(seed, n_phantom, n_hard):
        phantoms.append({"name": name, "results": _run_methods(preop, mask, P, gt)})
        step(f"phantom {name}")
    summaries = {SIMULATION: _summarise(simulation), OUT_OF_PLANE: _summarise(out_of_plane),
                 "Phantom": _summarise(phantoms)}
    comparisons = {dataset: _comparison(summaries[dataset]) for dataset in (SIMULATION, OUT_OF_PLANE)}
    report = {
        "version": 2, "quick": quick, "seed": seed, "wall_s": time.perf_counter() - started,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "out_of_plane_deg": OUT_OF_PLANE_DEG, "summary": summaries, "acceptance": comparisons[SIMULATION],
        "comparisons": comparisons, "simulation": simulation, "simulation_out_of_plane": out_of_plane,
        "robustness": robustness, "phantom": phantoms,
    }
    write_text_atomic(out_dir / "benchmark.json", json.dumps(report, indent=1))
    write_text_atomic(out_dir / "table.md", _table_markdown(summaries, comparisons))
    _bar_figure(out_dir / "fig4_simulation.png", simulation, f"Simulation protocol ({len(simulation)} cases): mean ± std")
    _bar_figure(out_dir / "fig4b_simulation_out_of_plane.png", out_of_plane,
                f"Simulation protocol with ±{OUT_OF_PLANE_DEG:g}° out-of-plane bend: mean ± std")
    _robustness_figure(out_dir / "fig5_robustness.png", robustness)
    _bar_figure(out_dir / "fig6_phantom.png", phantoms, "Phantom-like and hard cases: mean ± std")
    return {"summary": summaries, "acceptance": comparisons[SIMULATION], "comparisons": comparisons,
            "wall_s": report["wall_s"]}


# --------------------------------------------------------------------------- independent sets (issue 10)

#: Scenario kind -> set name of the independent sets.
INDEPENDENT_SETS = {
    "out_of_plane": "Independent: out-of-plane", "straightening": "Independent: straightening",
    "clipped": "Independent: clipped", "distal_forks": "Independent: distal forks",
    "wide_sac": "Independent: wide sac", "extra_branches": "Independent: extra branches",
    "misaligned": "Independent: misaligned", "angulated": "Independent: angulated",
    "two_views": "Independent: two views",
    "image_only": "Independent: image-only (CT + DSA frame)",
    "image_only_masks": "Independent: image-only cases given as masks",
}
#: The kinds run by default: all but the image-only pair, whose CT segmentation (UNet) takes
#: about 30-60 s a case per method; run them with ``kinds=("image_only",)``.
DEFAULT_INDEPENDENT_KINDS = tuple(k for k in scenarios.KINDS if k != "image_only")
#: Cases per independent set (the quick mode runs the last of them only).
INDEPENDENT_CASES = 4
#: "Reaches the floor": a 3D error at most this much above the case's depth floor (issue 10).
FLOOR_TOLERANCE_MM = 0.3


def _read_truth(folder: Path) -> tuple[Centerline, Centerline, np.ndarray, dict]:
    """The ground truth of a scenario folder: pre- and intra-op centrelines, main true P, views."""
    gt = json.loads((folder / "gt.json").read_text())
    return (Centerline.from_dict(gt["preop_centerline"]), Centerline.from_dict(gt["intraop_centerline"]),
            np.asarray(gt["projection_matrix_true"], dtype=float), gt.get("views", {}))


def _views_used(result) -> int:
    """How many views the pipeline registered on (1 unless its result lists several)."""
    views = getattr(result, "views", None)
    if views is None:
        views = result.to_dict().get("views")
    return max(1, len(views)) if views else 1


def _score_case_route(folder: Path, method: str, truth) -> dict:
    """Run ``plan_case`` on a folder with one method and score it (2D, 3D, depth split)."""
    gt_pre, gt_intra, P_true, _ = truth
    t0 = time.perf_counter()
    try:
        result = plan_case(folder, method=method)
    except (InputError, ValueError) as exc:
        return {"failed": str(exc)}
    wall = time.perf_counter() - t0
    depth = evaluation.depth_analysis(result.deformed, result.preop, gt_pre, gt_intra, P_true)
    errors = evaluation.evaluate(result.deformed, gt_intra, result.P, result.skeleton2d_points,
                                 result.skeleton2d_edges, labels=depth["labels"])
    return {"2d_px": errors["2d_px"]["mean"], "3d_mm": depth["3d_mm"]["mean"], "3d_max_mm": depth["3d_mm"]["max"],
            "3d_reverse_mm": errors["3d_reverse_mm"]["mean"], "in_plane_mm": depth["in_plane_mm"]["mean"],
            "along_ray_mm": depth["along_ray_mm"]["mean"], "rms_mm": depth["rms_mm"],
            "out_of_plane_recovered": depth["out_of_plane_recovered"], "per_vessel": depth["per_vessel"],
            "views_used": _views_used(result), "registration_s": result.timings.get("registration"),
            "wall_s": wall, "correspondence": result.inputs.get("correspondence"),
            "warnings": [str(w) for w in getattr(result, "warnings", [])]}


def _judge_against_sv_and_floor(results: dict, floor_mm: float) -> None:
    """Mark each method's result worse than SV and / or within the floor tolerance (in place)."""
    sv = results.get("SV", {}).get("3d_mm")
    for row in results.values():
        if "failed" in row:
            continue
        row["worse_than_sv"] = bool(sv is not None and row["3d_mm"] > sv)
        row["within_floor"] = bool(row["3d_mm"] <= floor_mm + FLOOR_TOLERANCE_MM)
        row["floor_gap_mm"] = row["3d_mm"] - floor_mm


def _independent_case(kind: str, folder: Path) -> dict:
    truth = _read_truth(folder)
    gt_pre, gt_intra, P_true, views = truth
    floor = evaluation.depth_floor(gt_pre, gt_intra, P_true)
    results = {label: _score_case_route(folder, method, truth) for label, (method, _) in METHODS.items()}
    _judge_against_sv_and_floor(results, floor["mean"])
    scenario = json.loads((folder / "scenario.json").read_text())
    return {"name": folder.name, "kind": kind, "folder": str(folder), "views": sorted(views),
            "depth_floor_mm": floor["mean"], "depth_floor_note": "main view" if len(views) > 1 else "the view",
            "depth_floor_per_vessel_mm": {k: v["mean"] for k, v in floor["per_vessel"].items()},
            "scenario": {k: scenario[k] for k in ("kind", "seed", "deformation", "views") if k in scenario}
            | {k: scenario[k] for k in ("severity_deg", "second_view_deg") if k in scenario},
            "results": results}


def _mean_or_none(values):
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def _vessel_summary(rows: list[dict]) -> dict:
    """Per vessel: the means over cases of each per-vessel number."""
    keys = ("3d_mm", "in_plane_mm", "along_ray_mm", "true_along_ray_mm", "depth_floor_mm", "out_of_plane_recovered")
    vessels = [label for label in evaluation.MAIN_VESSELS if any(label in r["per_vessel"] for r in rows)]
    return {label: {key: _mean_or_none([r["per_vessel"][label][key] for r in rows if label in r["per_vessel"]])
                    for key in keys} for label in vessels}


def _independent_summary(cases: list[dict]) -> dict:
    """Per method over a set's cases: means, counts worse than SV and within the floor, per vessel.

    A case a method failed on (``plan_case`` refused it) is counted in ``failed`` and left
    out of that method's means and counts; ``depth_floor_mm`` is the mean over all cases.
    """
    summary = {"cases": len(cases), "depth_floor_mm": float(np.mean([c["depth_floor_mm"] for c in cases])),
               "views_per_case": max(len(c["views"]) for c in cases), "methods": {}}
    for label in METHODS:
        rows = [c["results"][label] for c in cases if "failed" not in c["results"][label]]
        entry = {"cases": len(rows), "failed": len(cases) - len(rows)}
        if rows:
            entry.update({key: float(np.mean([r[key] for r in rows])) for key in
                          ("2d_px", "3d_mm", "in_plane_mm", "along_ray_mm", "floor_gap_mm")})
            entry.update({"worse_than_sv": int(sum(r["worse_than_sv"] for r in rows)),
                          "within_floor": int(sum(r["within_floor"] for r in rows)),
                          "views_used": max(r["views_used"] for r in rows),
                          "out_of_plane_recovered": _mean_or_none([r["out_of_plane_recovered"] for r in rows]),
                          "registration_s_median": float(np.median([r["registration_s"] or 0.0 for r in rows])),
                          "per_vessel": _vessel_summary(rows)})
        summary["methods"][label] = entry
    return summary


def _views_note(summary: dict) -> str:
    """What a multi-view set's row must say: the floor is the main view's; whether views were used."""
    if summary["views_per_case"] < 2:
        return ""
    used = max((m.get("views_used", 1) for m in summary["methods"].values()), default=1)
    if used < 2:
        return " (run single-view on the main frame: the pipeline read one view; floor of the main view)"
    return " (floor of the main view)"


def _method_note(summary: dict, method: dict) -> str:
    return f" [{method['views_used']} view(s) read]" if summary["views_per_case"] > 1 else ""


def _independent_table(summaries: dict) -> str:
    lines = ["| Set | Method | failed | 2D (px) | 3D (mm) | in-plane (mm) | along-ray (mm) | depth floor (mm) | "
             "worse than SV | within 0.3 mm of floor | depth recovered |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in summaries.items():
        for label, m in s["methods"].items():
            if not m["cases"]:
                lines.append(f"| {name} | {label} | {m['failed']}/{s['cases']} | | | | | | | | |")
                continue
            recovered = "" if m["out_of_plane_recovered"] is None else f"{m['out_of_plane_recovered']:.2f}"
            lines.append(f"| {name}{_views_note(s)} | {label}{_method_note(s, m)} | {m['failed']}/{s['cases']} | "
                         f"{m['2d_px']:.2f} | "
                         f"{m['3d_mm']:.2f} | {m['in_plane_mm']:.2f} | {m['along_ray_mm']:.2f} | "
                         f"{s['depth_floor_mm']:.2f} | {m['worse_than_sv']}/{m['cases']} | "
                         f"{m['within_floor']}/{m['cases']} | {recovered} |")
    lines += ["", "Per vessel (mean over the set's cases): 3D / in-plane / along-ray (mm), depth floor (mm), "
              "out-of-plane motion recovered.", "",
              "| Set | Method | " + " | ".join(evaluation.MAIN_VESSELS) + " |",
              "|---|---|" + "---|" * len(evaluation.MAIN_VESSELS)]
    for name, s in summaries.items():
        for label, m in s["methods"].items():
            cells = []
            for vessel in evaluation.MAIN_VESSELS:
                v = m.get("per_vessel", {}).get(vessel)
                if v is None:
                    cells.append("")
                    continue
                recovered = "" if v["out_of_plane_recovered"] is None else f", rec {v['out_of_plane_recovered']:.2f}"
                cells.append(f"{v['3d_mm']:.2f} / {v['in_plane_mm']:.2f} / {v['along_ray_mm']:.2f}, "
                             f"floor {v['depth_floor_mm']:.2f}{recovered}")
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _independent_sets_figure(path: Path, summaries: dict) -> None:
    """Per set: 3D, in-plane and along-ray error of each method (means), the depth floor drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summaries)
    x = np.arange(len(names))
    width = 0.8 / len(METHODS)
    panels = (("3d_mm", "3D error (mm)", True), ("in_plane_mm", "in-plane part (mm)", False),
              ("along_ray_mm", "along-ray part (mm)", True))
    fig, axes = plt.subplots(1, 3, figsize=(19, 5.2), sharey=True)
    floors = [summaries[n]["depth_floor_mm"] for n in names]
    for ax, (key, title, with_floor) in zip(axes, panels):
        for k, label in enumerate(METHODS):
            offset = (k - (len(METHODS) - 1) / 2) * width
            ax.bar(x + offset, [summaries[n]["methods"][label].get(key, np.nan) for n in names], width, label=label)
        if with_floor:
            ax.hlines(floors, x - 0.45, x + 0.45, colors="k", linewidth=2, label="depth floor")
        ax.set_xticks(x, [n.replace("Independent: ", "") for n in names], rotation=35, ha="right")
        ax.set_title(title)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("mean over the set's cases (mm)")
    fig.suptitle("Independent sets (scenarios family, case-folder route) and the single-view depth floor")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _independent_vessels_figure(path: Path, cases: list[dict]) -> None:
    """Per vessel over all independent cases: along-ray error per method against the floor, and
    the fraction of the true along-ray motion recovered."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vessels = evaluation.MAIN_VESSELS
    x = np.arange(len(vessels))
    width = 0.8 / len(METHODS)
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.8))
    pooled = {}
    for label in METHODS:
        rows = [c["results"][label] for c in cases if "failed" not in c["results"][label]]
        pooled[label] = _vessel_summary(rows) if rows else {}
    for k, label in enumerate(METHODS):
        offset = (k - (len(METHODS) - 1) / 2) * width
        along = [pooled[label].get(v, {}).get("along_ray_mm") for v in vessels]
        recovered = [pooled[label].get(v, {}).get("out_of_plane_recovered") for v in vessels]
        axes[0].bar(x + offset, [np.nan if a is None else a for a in along], width, label=label)
        axes[1].bar(x + offset, [np.nan if r is None else r for r in recovered], width, label=label)
    reference = pooled.get("SV", {})
    floors = [reference.get(v, {}).get("depth_floor_mm") for v in vessels]
    true_along = [reference.get(v, {}).get("true_along_ray_mm") for v in vessels]
    axes[0].hlines([np.nan if f is None else f for f in floors], x - 0.45, x + 0.45, colors="k", label="depth floor")
    axes[0].plot(x, [np.nan if t is None else t for t in true_along], "kx", label="true along-ray motion")
    axes[0].set_ylabel("along-ray error, mean (mm)")
    axes[1].axhline(0.0, color="k", linewidth=0.8)
    axes[1].set_ylim(-1.05, 1.05)
    axes[1].set_ylabel("out-of-plane motion recovered (1 = all; clipped at -1)")
    for ax in axes:
        ax.set_xticks(x, vessels)
        ax.legend(fontsize=8)
    fig.suptitle(f"Per vessel, all independent cases ({len(cases)})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def independent_case_folders(out_dir, *, quick: bool = False, seed: int = 0, kinds=None) -> list:
    """Write (or reuse) the independent sets' case folders under ``out_dir``; ``[(kind, folder)]``.

    Every kind is planned with :data:`INDEPENDENT_CASES` cases; the quick mode keeps the last
    (so its cases are a subset of the full run's). A folder already holding ``gt.json`` is
    reused (the same seed writes the same files).
    """
    out_dir = Path(out_dir)
    chosen = []
    for kind in kinds or DEFAULT_INDEPENDENT_KINDS:
        planned = scenarios.plan_scenarios(kind, INDEPENDENT_CASES, seed)
        for scenario in planned[-1:] if quick else planned:
            # an image-only case runs twice: from its images, and from the same anatomy's masks
            twins = [(kind, scenario.name, None)] + ([("image_only_masks", f"{scenario.name}_masks", False)]
                                                      if kind == "image_only" else [])
            for set_kind, name, images in twins:
                folder = out_dir / name
                if not (folder / "gt.json").is_file():
                    scenarios.write_scenario(scenario, folder, images=images)
                chosen.append((set_kind, folder))
    return chosen


def run_independent_benchmark(out_dir, *, quick: bool = False, seed: int = 0, progress=None, kinds=None) -> dict:
    """Run the independent sets (issue 10) and write independent.json, the table and figures.

    Parameters
    ----------
    out_dir : path
        Results go here, the case folders under ``out_dir/cases``.
    quick : bool
        One case per set (the hardest of each: 20 degrees out of plane, the 90 degree second
        view), about 1.5 minutes on 2 cores.
    seed : int
    progress : callable, optional
        ``progress(fraction, message)``.
    kinds : iterable of str, optional
        Scenario kinds (:data:`scenarios.KINDS`); default :data:`DEFAULT_INDEPENDENT_KINDS`.

    Returns
    -------
    dict
        ``summary`` (set name -> per-method means and counts, per vessel) and ``wall_s``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    folders = independent_case_folders(out_dir / "cases", quick=quick, seed=seed, kinds=kinds)
    cases = []
    for index, (kind, folder) in enumerate(folders):
        cases.append(_independent_case(kind, folder))
        if progress is not None:
            progress((index + 1) / len(folders), f"independent {folder.name}")
    summaries = {INDEPENDENT_SETS[kind]: _independent_summary([c for c in cases if c["kind"] == kind])
                 for kind in dict.fromkeys(c["kind"] for c in cases)}
    report = {"version": 1, "quick": quick, "seed": seed, "wall_s": time.perf_counter() - started,
              "floor_tolerance_mm": FLOOR_TOLERANCE_MM,
              "machine": {"platform": platform.platform(), "python": platform.python_version()},
              "metric": "3D: every result node (main vessels) to the nearest true segment, mean mm; in-plane / "
                        "along-ray: the same error split along the true ray of the main view; depth floor: the "
                        "oracle on the true rays at pre-operative depth (main view for two-view cases)",
              "summary": summaries, "cases": cases}
    write_text_atomic(out_dir / "independent.json", json.dumps(report, indent=1))
    write_text_atomic(out_dir / "independent_table.md", _independent_table(summaries))
    _independent_sets_figure(out_dir / "independent_sets.png", summaries)
    _independent_vessels_figure(out_dir / "independent_vessels.png", cases)
    return {"summary": summaries, "wall_s": report["wall_s"]}

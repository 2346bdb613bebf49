"""The paper's protocol on our phantoms (Sec. III, Figs. 4-6, Table II): the simulation set and
its out-of-plane sensitivity set, robustness to in-plane offsets of the frame, phantom-like
and hard cases; ``benchmark.json``, ``table.md`` and the four figures (package docstring).
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

from .. import evaluation, phantom
from ..files import write_text_atomic
from ..pipeline import preop_from_lumen, register_frame
from ..projection import patient_motion, project
from . import figures

__all__ = ["METHODS", "run_benchmark", "simulation_cases", "phantom_cases", "draw_skeleton_mask"]

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
    figures.bar_figure(out_dir / "fig4_simulation.png", simulation,
                       f"Simulation protocol ({len(simulation)} cases): mean ± std", METHODS)
    figures.bar_figure(out_dir / "fig4b_simulation_out_of_plane.png", out_of_plane,
                       f"Simulation protocol with ±{OUT_OF_PLANE_DEG:g}° out-of-plane bend: mean ± std", METHODS)
    figures.robustness_figure(out_dir / "fig5_robustness.png", robustness)
    figures.bar_figure(out_dir / "fig6_phantom.png", phantoms, "Phantom-like and hard cases: mean ± std", METHODS)
    return {"summary": summaries, "acceptance": comparisons[SIMULATION], "comparisons": comparisons,
            "wall_s": report["wall_s"]}

"""The independent sets of issue 10 (:func:`run_independent_benchmark`): case folders of the
:mod:`scenarios` family, planned through the case-folder route and scored against the
single-view depth floor; ``independent.json``, ``independent_table.md`` and two figures.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import numpy as np

from .. import evaluation, scenarios
from ..centerline import Centerline
from ..files import InputError, write_text_atomic
from ..pipeline import plan_case
from . import figures
from .paper import METHODS

__all__ = ["INDEPENDENT_SETS", "DEFAULT_INDEPENDENT_KINDS", "INDEPENDENT_CASES", "FLOOR_TOLERANCE_MM",
           "independent_case_folders", "run_independent_benchmark"]

#: Scenario kind -> set name of the independent sets.
INDEPENDENT_SETS = {
    "out_of_plane": "Independent: out-of-plane", "straightening": "Independent: straightening",
    "clipped": "Independent: clipped", "distal_forks": "Independent: distal forks",
    "wide_sac": "Independent: wide sac", "extra_branches": "Independent: extra branches",
    "misaligned": "Independent: misaligned", "angulated": "Independent: angulated",
    "two_views": "Independent: two views",
    "image_only": "Independent: image-only (CT + DSA frame)",
    "image_only_masks": "Independent: image-only cases given as masks",
    "patient_like": "Independent: patient-like anatomy",
    "bench_pinhole": "Independent: bench phantom (short pinhole)",
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
            "depth_floor_mm": floor["mean"],
            "depth_floor_axial_mm": evaluation.depth_floor(gt_pre, gt_intra, P_true, depth="axial")["mean"], "depth_floor_note": "main view" if len(views) > 1 else "the view",
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
               "depth_floor_axial_mm": _mean_or_none([c.get("depth_floor_axial_mm") for c in cases]),
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


def _pooled_vessels(cases: list[dict]) -> dict:
    """Method label -> the per-vessel summary over every independent case it did not fail."""
    pooled = {}
    for label in METHODS:
        rows = [c["results"][label] for c in cases if "failed" not in c["results"][label]]
        pooled[label] = _vessel_summary(rows) if rows else {}
    return pooled


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
    figures.independent_sets_figure(out_dir / "independent_sets.png", summaries, METHODS)
    figures.independent_vessels_figure(out_dir / "independent_vessels.png", _pooled_vessels(cases), len(cases),
                                       evaluation.MAIN_VESSELS)
    return {"summary": summaries, "wall_s": report["wall_s"]}

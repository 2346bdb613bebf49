"""Pose residual per case (issue 10): where the misaligned and angulated sets lose their 0.3 mm to the floor.

Writes the scenario case folders of ``--kinds`` (``bench_scenarios.py``'s, same seed, same
files), plans each with the proposed method and records, per case: the depth floor, the 3D
error and its in-plane / along-ray split, whether the pose check corrected ``P``, and the
pose residual of the used ``P`` against the true one on the true upper aorta
(``alignment.pose_residual``: px along and across it, degrees of turn), for the given ``P``
and for the one used. ``--oracle`` plans each case again from the true ``P`` (pose check
off): the error a perfect pose would leave. Outputs ``pose_residual.json`` and
``pose_residual.md`` in ``--out``.

    .venv/bin/python Testing/benchmarks/bench_pose_residual.py --out OUT [--seed 0] [--kinds misaligned angulated] [--oracle]
"""

from __future__ import annotations

import json
import tempfile
import warnings
from pathlib import Path

from common import argument_parser, single_threaded_blas, write_report

single_threaded_blas()

import numpy as np  # noqa: E402  (after the BLAS threads are set)

from FevarPlannerLib import evaluation  # noqa: E402
from FevarPlannerLib.alignment import pose_residual  # noqa: E402
from FevarPlannerLib.benchmark.independent import independent_case_folders  # noqa: E402
from FevarPlannerLib.centerline import Centerline  # noqa: E402
from FevarPlannerLib.pipeline import plan_case  # noqa: E402
from FevarPlannerLib.files import InputError  # noqa: E402
from FevarPlannerLib.quality import QualityError  # noqa: E402
from FevarPlannerLib.scenarios import EXTRA_KINDS, KINDS  # noqa: E402

#: Upper-aorta points this far (mm) above the higher renal ostium count (the ostia themselves may move).
ABOVE_OSTIA_MM = 3.0


def upper_aorta(centerline: Centerline) -> np.ndarray:
    """The aorta's points above its higher renal ostium, from the top down (LPS: z superior)."""
    points, labels = np.asarray(centerline.points), np.asarray(centerline.labels)
    aorta = points[labels == "aorta"]
    ostia = []
    for renal in ("renal_left", "renal_right"):
        branch = points[labels == renal]
        nearest = np.linalg.norm(branch[:, None] - aorta[None], axis=2).min(axis=1)
        ostia.append(branch[np.argmin(nearest), 2])
    above = aorta[aorta[:, 2] > max(ostia) + ABOVE_OSTIA_MM]
    return above[np.argsort(-above[:, 2])]


def _scored(result, truth) -> dict:
    gt_pre, gt_intra, P_true = truth
    depth = evaluation.depth_analysis(result.deformed, result.preop, gt_pre, gt_intra, P_true)
    return {"3d_mm": depth["3d_mm"]["mean"], "in_plane_mm": depth["in_plane_mm"]["mean"],
            "along_ray_mm": depth["along_ray_mm"]["mean"],
            "per_vessel": {k: {m: v[m] for m in ("3d_mm", "in_plane_mm", "along_ray_mm", "depth_floor_mm")}
                           for k, v in depth["per_vessel"].items()}}


def _with_true_pose(folder: Path, P_true: np.ndarray, scratch: Path) -> Path:
    """A geometry.json holding the case's true ``P`` (the oracle's input)."""
    geometry = json.loads((folder / "geometry.json").read_text())
    geometry["projection_matrix"] = np.asarray(P_true).tolist()
    path = scratch / f"{folder.name}_geometry.json"
    path.write_text(json.dumps(geometry))
    return path


def case_row(kind: str, folder: Path, oracle: bool, scratch: Path) -> dict:
    gt = json.loads((folder / "gt.json").read_text())
    gt_pre, gt_intra = Centerline.from_dict(gt["preop_centerline"]), Centerline.from_dict(gt["intraop_centerline"])
    P_true, P_given = np.asarray(gt["projection_matrix_true"]), np.asarray(gt["projection_matrix_given"])
    truth = (gt_pre, gt_intra, P_true)
    floor = evaluation.depth_floor(gt_pre, gt_intra, P_true)["mean"]
    upper = upper_aorta(gt_intra)
    result = plan_case(folder, method="proposed")
    row = {"name": folder.name, "kind": kind, "depth_floor_mm": floor, "proposed": _scored(result, truth),
           "pose_applied": not np.allclose(result.P, P_given), "pose_check": result.views[0].get("pose_correction"),
           "given_residual": pose_residual(P_given, P_true, upper), "used_residual": pose_residual(result.P, P_true, upper)}
    row["floor_gap_mm"] = row["proposed"]["3d_mm"] - floor
    if oracle:
        true_pose = plan_case(folder, method="proposed", geometry=_with_true_pose(folder, P_true, scratch),
                              refine_pose="off")
        row["true_pose"] = _scored(true_pose, truth)
        row["true_pose_gap_mm"] = row["true_pose"]["3d_mm"] - floor
    return row


def table(rows: list[dict]) -> str:
    lines = ["| Case | floor (mm) | proposed (mm) | gap (mm) | true-P gap (mm) | pose corrected | along (px) | "
             "across (px) | turn (deg) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        used = r["used_residual"]
        oracle = f"{r['true_pose_gap_mm']:+.2f}" if "true_pose_gap_mm" in r else "-"
        lines.append(f"| {r['name']} | {r['depth_floor_mm']:.2f} | {r['proposed']['3d_mm']:.2f} | "
                     f"{r['floor_gap_mm']:+.2f} | {oracle} | {'yes' if r['pose_applied'] else 'no'} | "
                     f"{used['along_px']:+.2f} | {used['across_px']:+.2f} | {used['rotation_deg']:+.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", nargs="+", choices=KINDS + EXTRA_KINDS, default=["misaligned", "angulated"])
    parser.add_argument("--oracle", action="store_true", help="also plan each case from its true P")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, refusals = [], []
    with tempfile.TemporaryDirectory() as scratch, warnings.catch_warnings():
        warnings.simplefilter("ignore")          # the plans' own notes; the residuals are the point here
        for kind, folder in independent_case_folders(args.out / "cases", seed=args.seed, kinds=args.kinds):
            try:
                rows.append(case_row(kind, folder, args.oracle, Path(scratch)))
            except (QualityError, InputError) as refused:       # the plan refused the case: recorded, not scored
                refusals.append({"name": folder.name, "kind": kind, "refused": str(refused)})
                print(f"| {folder.name} | refused: {refused}", flush=True)
                continue
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    write_report(args.out, "pose_residual", {"seed": args.seed, "kinds": args.kinds, "cases": rows,
                                             "refused": refusals})
    (args.out / "pose_residual.md").write_text(table(rows) + "".join(f"\n{r['name']}: refused ({r['refused']})"
                                                                      for r in refusals))
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

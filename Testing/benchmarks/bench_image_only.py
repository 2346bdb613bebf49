"""Image-only cases against the same cases given as masks, and which segmentation makes the difference.

Each random phantom case (``phantom.write_phantom_set``, preset "random") is planned four
ways, by copying the folder with a subset of its inputs:

- ``masks``: the given CT lumen (``aorta_mask``) and frame mask (``fluoro_mask``);
- ``image_only``: the CT series and the raw DSA frame only (both segmented);
- ``ct_segmented``: the CT segmented, the frame mask given (swaps the 3D side only);
- ``frame_segmented``: the CT lumen given, the frame segmented (swaps the 2D side only).

The 3D error is ``pipeline.plan_case``'s mean distance of the result to the true
intra-operative centreline (``errors['3d_mm']['mean']``). Issue 10/11 ask for image-only within
0.5 mm of masks. Develop on other seeds than the ones you report.

    .venv/bin/python Testing/benchmarks/bench_image_only.py --out Testing/benchmarks/results --seed 300 --n 4

Writes ``bench_image_only.json`` and ``bench_image_only.png`` into ``--out``.
"""

from __future__ import annotations

import common

common.single_threaded_blas()

import shutil  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from FevarPlannerLib import io  # noqa: E402
from FevarPlannerLib import phantom as ph  # noqa: E402
from FevarPlannerLib import pipeline  # noqa: E402
from FevarPlannerLib import segmentation as seg  # noqa: E402

#: Inputs each route keeps from the full case folder (besides case.json, geometry.json, gt.json).
ROUTES = {"masks": ("aorta_mask.nrrd", "fluoro_mask.png", "fluoro.dcm"),
          "image_only": ("ct", "fluoro.dcm"),
          "ct_segmented": ("ct", "fluoro_mask.png", "fluoro.dcm"),
          "frame_segmented": ("aorta_mask.nrrd", "fluoro.dcm")}
SHARED = ("case.json", "geometry.json", "gt.json")


def route_folder(case: Path, route: str, work: Path) -> Path:
    """A copy of ``case`` holding only what ``route`` uses."""
    folder = work / route / case.name
    folder.mkdir(parents=True, exist_ok=True)
    for name in SHARED + ROUTES[route]:
        source = case / name
        if source.is_dir():
            shutil.copytree(source, folder / name)
        elif source.exists():
            shutil.copy2(source, folder / name)
    return folder


def evaluate_case(case: Path, work: Path) -> dict:
    """3D error of every route on one case, and the segmentations' Dice against the given masks."""
    row = {"case": case.name}
    results = {}
    for route in ROUTES:
        result, seconds, _ = common.timed(pipeline.plan_case, route_folder(case, route, work))
        results[route] = result
        row[route] = {"3d_mm": float(result.errors["3d_mm"]["mean"]), "2d_px": float(result.errors["2d_px"]["mean"]),
                      "time_s": seconds}
    given = io.load_case(case)
    row["ct_lumen_dice"] = seg.dice(results["image_only"].qc.lumen, given.aorta_mask)
    row["frame_mask_dice"] = seg.dice(results["image_only"].qc.mask2d, given.fluoro_mask)
    row["difference_mm"] = row["image_only"]["3d_mm"] - row["masks"]["3d_mm"]
    return row


def plot(rows: list, path: Path) -> None:
    plt = common.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    x = np.arange(len(rows))
    for k, route in enumerate(ROUTES):
        axes[0].bar(x + (k - 1.5) * 0.2, [r[route]["3d_mm"] for r in rows], 0.2, label=route)
    axes[0].set(title="3D error, mean mm", xticks=x, xticklabels=[r["case"] for r in rows])
    axes[0].legend(fontsize=8)
    axes[1].bar(x, [r["difference_mm"] for r in rows], 0.5, color="tab:red")
    axes[1].axhline(0.5, color="k", ls="--", lw=1)
    axes[1].axhline(-0.5, color="k", ls="--", lw=1)
    axes[1].set(title="image-only minus masks, mm (goal within 0.5)", xticks=x,
                xticklabels=[r["case"] for r in rows])
    common.save_figure(fig, path)


def main() -> None:
    parser = common.argument_parser(__doc__)
    parser.add_argument("--seed", type=int, default=300)
    parser.add_argument("--n", type=int, default=4)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        cases = ph.write_phantom_set(Path(tmp) / "cases", n=args.n, seed=args.seed, preset="random")
        rows = [evaluate_case(case, Path(tmp) / "routes") for case in cases]
    summary = {route: float(np.mean([r[route]["3d_mm"] for r in rows])) for route in ROUTES}
    differences = [r["difference_mm"] for r in rows]
    payload = {"seed": args.seed, "n": args.n, "cases": rows, "mean_3d_mm": summary,
               "difference_mm": differences, "max_abs_difference_mm": float(np.max(np.abs(differences))),
               "within_0_5_mm": int(np.sum(np.abs(differences) <= 0.5))}
    common.write_report(args.out, "bench_image_only", payload)
    plot(rows, args.out / "bench_image_only.png")
    for r in rows:
        print(r["case"], {route: round(r[route]["3d_mm"], 3) for route in ROUTES},
              f"diff {r['difference_mm']:+.2f} mm, CT Dice {r['ct_lumen_dice']:.3f}, frame Dice {r['frame_mask_dice']:.3f}")
    print({k: round(v, 3) for k, v in summary.items()})


if __name__ == "__main__":
    main()

"""`plan` on raw bench-phantom frames of an independent family (``realbench_frames.py``).

For each seed, ``realbench_frames.write_seed`` writes the image-only case (DICOM CT + an 8-bit
``fluoro.png`` or a ``fluoro.dcm``, ``geometry.json``, ``gt.json``, no masks), the same case with
the true vessel mask (the reference route) and three non-angiograms of the same bench (the
phantom without contrast, the box alone, another phantom's frame). Each folder goes through
``pipeline.plan_case`` as ``fevar-planner plan`` runs it; the row records

- the exit code the CLI gives (0 answered, 2 refused: ``io.InputError``, 1 anything else) and
  the refusal's one line;
- the 3D error as ``bench_image_only.py`` measures it (``errors['3d_mm']['mean']``: every result
  point to the nearest true intra-operative segment) and its difference to the reference's;
- the frame Dice of the vessel mask ``plan`` used against the true mask (also on refusal, from
  the QC data), with precision and recall;
- whether a non-angiogram was refused (it must be).

Development seeds 480-485; held-out seeds 486-491 (run once, at the end); for the display
polarity read from the metal (``quality.dense_side``: an air-filled phantom in a water bath is a
negative angiogram, refused) held-out seeds 510-515.

    python Testing/benchmarks/bench_realbench.py --out OUT --seeds 480 481 482 483 484 485 [--keep DIR]

Writes ``bench_realbench.json`` and ``bench_realbench.png`` into ``--out``; with ``--keep`` the
case folders and each run's outputs (``segmentation_qc.png``, ``overlay.png``) stay in DIR.
"""

from __future__ import annotations

import common

common.single_threaded_blas()

import shutil  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import realbench_frames as rb  # noqa: E402
from FevarPlannerLib import io, pipeline, quality  # noqa: E402

ROUTES = ("angio", "angio_truemask", "no_contrast", "box_only", "other_phantom")
MUST_REFUSE = ("no_contrast", "box_only", "other_phantom")


def mask_scores(mask: np.ndarray | None, truth: np.ndarray) -> dict:
    """Dice, precision and recall of ``mask`` against ``truth`` (None when there is no mask)."""
    if mask is None or mask.shape != truth.shape:
        return {}
    mask, truth = mask.astype(bool), truth.astype(bool)
    overlap = float(np.sum(mask & truth))
    return {"dice": 2.0 * overlap / max(mask.sum() + truth.sum(), 1), "precision": overlap / max(mask.sum(), 1),
            "recall": overlap / max(truth.sum(), 1), "mask_px": int(mask.sum()), "true_px": int(truth.sum())}


def run_route(folder: Path, out: Path, truth: np.ndarray) -> dict:
    """One ``plan`` run: exit code, refusal line, 3D error, mask scores, warnings (``out``, this
    benchmark's own folder, is emptied first)."""
    shutil.rmtree(out, ignore_errors=True)
    for stale in (out.parent / f"{out.name}.segmentation_qc.png", out.parent / f"{out.name}.plan_mask.png"):
        stale.unlink(missing_ok=True)
    try:
        result, seconds, _ = common.timed(pipeline.plan_case, folder, out)
    except quality.QualityError as refusal:
        qc = refusal.qc
        _keep_mask(out, None if qc is None else qc.mask2d)
        return {"exit": 2, "refused": str(refusal), **mask_scores(None if qc is None else qc.mask2d, truth)}
    except io.InputError as refusal:
        return {"exit": 2, "refused": str(refusal)}
    except Exception as failure:          # noqa: BLE001 - the CLI's exit code 1, recorded
        return {"exit": 1, "error": f"{type(failure).__name__}: {failure}"}
    _keep_mask(out, result.qc.mask2d if result.qc else None)
    row = {"exit": 0, "3d_mm": float(result.errors["3d_mm"]["mean"]), "time_s": seconds,
           "warnings": list(result.warnings), **mask_scores(result.qc.mask2d if result.qc else None, truth)}
    return row


def _keep_mask(out: Path, mask) -> None:
    """The vessel mask ``plan`` used, beside (not inside) its output folder."""
    if mask is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        io.write_mask_png(out.parent / f"{out.name}.plan_mask.png", mask)


def mask_picture(frame: np.ndarray, mask: np.ndarray, truth: np.ndarray, path: Path) -> None:
    """The frame with the mask's agreement: green both, red mask only (false), blue truth only (missed)."""
    grey = frame.astype(float)
    grey = (grey - grey.min()) / max(np.ptp(grey), 1e-9)
    rgb = np.repeat(grey[..., None], 3, axis=-1) * 0.75
    for pixels, colour in ((mask & truth, (0.1, 0.9, 0.1)), (mask & ~truth, (1.0, 0.1, 0.1)), (~mask & truth, (0.2, 0.4, 1.0))):
        rgb[pixels] = 0.45 * rgb[pixels] + 0.55 * np.asarray(colour)
    from PIL import Image

    Image.fromarray(np.round(255 * rgb).astype(np.uint8)).save(path)


def evaluate_seed(root: Path, outputs: Path) -> dict:
    truth = io.read_mask_2d(root / "eval" / "true_mask.png") > 0
    row = {"seed": root.name}
    for route in ROUTES:
        row[route] = run_route(root / route, outputs / root.name / route, truth)
    if "3d_mm" in row["angio"] and "3d_mm" in row["angio_truemask"]:
        row["difference_mm"] = row["angio"]["3d_mm"] - row["angio_truemask"]["3d_mm"]
    mask_file = outputs / root.name / "angio.plan_mask.png"
    if mask_file.exists():
        frame = io.read_fluoro(next((root / "angio").glob("fluoro.*"))).image
        mask_picture(frame, io.read_mask_2d(mask_file) > 0, truth, outputs / root.name / "angio_mask_vs_truth.png")
    row["non_angiograms_answered"] = [r for r in MUST_REFUSE if row[r]["exit"] == 0]
    return row


def plot(rows: list, path: Path) -> None:
    plt = common.pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    x = np.arange(len(rows))
    names = [r["seed"].removeprefix("seed_") for r in rows]
    for k, route in enumerate(("angio", "angio_truemask")):
        values = [r[route].get("3d_mm", np.nan) for r in rows]
        axes[0].bar(x + (k - 0.5) * 0.35, values, 0.35, label=route)
        for xi, r in zip(x, rows):
            if r[route]["exit"] != 0:
                axes[0].text(xi + (k - 0.5) * 0.35, 0.2, f"exit {r[route]['exit']}", rotation=90, ha="center", fontsize=7)
    axes[0].set(title="3D error (mean mm), image-only vs true mask", xticks=x, xticklabels=names)
    axes[0].legend(fontsize=8)
    axes[1].bar(x, [r["angio"].get("dice", np.nan) for r in rows], 0.5, color="tab:green")
    axes[1].set(title="frame Dice of plan's vessel mask", xticks=x, xticklabels=names, ylim=(0, 1))
    for k, route in enumerate(MUST_REFUSE):
        axes[2].bar(x + (k - 1) * 0.25, [1.0 if r[route]["exit"] == 2 else 0.0 for r in rows], 0.25, label=route)
    axes[2].set(title="non-angiograms refused (1 = exit 2)", xticks=x, xticklabels=names, ylim=(0, 1.2))
    axes[2].legend(fontsize=8)
    common.save_figure(fig, path)


def main() -> None:
    parser = common.argument_parser(__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[480, 481, 482, 483, 484, 485])
    parser.add_argument("--keep", type=Path, default=None, help="keep the case folders and the runs' outputs here")
    parser.add_argument("--reuse", action="store_true", help="reuse case folders already in --keep")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) if args.keep is None else args.keep
        rows = []
        for seed in args.seeds:
            root = work / "cases" / f"seed_{seed}"
            if not (args.reuse and (root / "eval" / "scene.json").exists()):
                root = rb.write_seed(work / "cases", seed)
            rows.append(evaluate_seed(root, work / "outputs"))
            print(_line(rows[-1]), flush=True)
    differences = [r["difference_mm"] for r in rows if "difference_mm" in r]
    payload = {"seeds": args.seeds, "cases": rows,
               "angio_answered": sum(r["angio"]["exit"] == 0 for r in rows),
               "angio_within_0_5_mm_of_true_mask": int(np.sum(np.abs(differences) <= 0.5)),
               "mean_dice": float(np.nanmean([r["angio"].get("dice", np.nan) for r in rows])),
               "non_angiograms_answered": {route: [r["seed"] for r in rows if r[route]["exit"] == 0] for route in MUST_REFUSE}}
    common.write_report(args.out, "bench_realbench", payload)
    plot(rows, args.out / "bench_realbench.png")
    print({k: v for k, v in payload.items() if k != "cases"})


def _line(row: dict) -> str:
    def brief(r):
        if r["exit"] == 0:
            return f"{r['3d_mm']:.2f} mm" + (f" Dice {r['dice']:.3f}" if "dice" in r else "")
        return f"exit {r['exit']}: {r.get('refused', r.get('error', ''))[-110:]}"
    return f"{row['seed']}: " + " | ".join(f"{route}: {brief(row[route])}" for route in ROUTES)


if __name__ == "__main__":
    main()

"""Frame masks on bench frames: Dice per distractor kind, polarity and seed, and end to end (issue 11).

Each seed's phantom case (:func:`phantom.distractors.bench_case`) is rendered as bench frames
(:func:`phantom.distractors.render_bench_frame`, random choices from ``default_rng(seed)``):

- ``every``: every distractor, unsubtracted; ``every_dsa``: every distractor, subtracted;
- one frame per distractor alone (``spine``, ``pelvis``, ... ``exposure``), unsubtracted;
- ``spine_under`` / ``every_spine_under``: the spine alone / every distractor, unsubtracted, the
  vertebral column centred under the aorta and 3 times as dense as its iodine (as the aorta
  over the spine of a patient's oblique view; ``Testing/test_spine_frame.py``);

each with the vessels dark and bright. The frame is segmented as the pipeline does it
(:func:`segmentation.segment_fluoro` with the pre-operative tree projected through the given
P, ``P_given``) and scored by Dice against the projected lumen. With ``--reference REV`` the
``segmentation/fluoro.py`` of git revision REV is loaded beside the working tree's and run on
the same frames, interleaved, so that Dice and CPU times compare within one run.

With ``--end-to-end`` each seed's case is also written as a case folder whose frame is the
``every`` bench frame (unsubtracted, vessels dark) and planned by the routes of
``bench_image_only.py`` (masks given, image only, frame segmented, CT segmented): the 3D
error of an image-only plan against the same case given as masks (issue 11: within 0.5 mm);
``end_to_end_summary`` gives per seed image-only and frame-segmented minus masks (or
"refused"), how many image-only plans are within 0.5 mm and how many were refused.

Develop on seeds 211-216; report on 201-203 and 221-223. End to end (issue 11, unsubtracted
clean-up in ``segmentation/off_tree.py``): development seeds 231-250, held-out 274-279 (run
once before and once after a change); for the bands between edges over a vertebral body
(``fluoro._bands_between_edges``) held-out 460-465. ``--keep DIR`` keeps the case folders and every route's
outputs (``overlay.png``, ``segmentation_qc.png`` of a refusal) under ``DIR/outputs/<route>``.

    OMP_NUM_THREADS=1 .venv/bin/python Testing/benchmarks/bench_frame_masks.py --out OUT \\
        --seeds 221 222 223 [--reference main] [--end-to-end [--keep DIR]] [--pngs] [--cache DIR] [--time-1024 15]

Writes ``bench_frame_masks.json`` and ``bench_frame_masks.png`` into ``--out`` (with ``--pngs``
also one overlay per frame: true positives white, false negatives red, false positives blue).
"""

from __future__ import annotations

import common

common.single_threaded_blas()

import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from FevarPlannerLib import quality  # noqa: E402
from FevarPlannerLib import segmentation as seg  # noqa: E402
from FevarPlannerLib.phantom import distractors  # noqa: E402

#: (kind, render keyword arguments) of the frames rendered per seed and polarity.
KINDS = (("every", {}), ("every_dsa", {"subtracted": True})) + tuple(
    (name, {"distractors": (name,)}) for name in distractors.DISTRACTORS) + (
    ("spine_under", {"distractors": ("spine",), "spine_offset_mm": 0.0, "spine_gain": 3.0}),
    ("every_spine_under", {"spine_offset_mm": 0.0, "spine_gain": 3.0}))
POLARITIES = ("dark", "bright")
REPO = Path(__file__).resolve().parents[2]
FLUORO_PATH = "FevarPlanner/FevarPlannerLib/segmentation/fluoro.py"
OFF_TREE_PATH = "FevarPlanner/FevarPlannerLib/segmentation/off_tree.py"


def reference_segmenter(revision: str):
    """``segment_fluoro`` of ``segmentation/fluoro.py`` at git ``revision``, loaded as a sibling module
    of the working tree's (its relative imports resolve in the same package), with the
    revision's own ``segmentation/off_tree.py`` beside it (the two change together)."""
    off_tree = _load_revision_module(revision, OFF_TREE_PATH, "_off_tree_reference")
    fluoro = _load_revision_module(revision, FLUORO_PATH, "_fluoro_reference",
                                   (("from .off_tree import", "from ._off_tree_reference import"),)
                                   if off_tree is not None else ())
    return fluoro.segment_fluoro


def _load_revision_module(revision: str, path: str, name: str, replacements=()):
    """The module at ``path`` of git ``revision`` as ``FevarPlannerLib.segmentation.<name>`` (None
    when the revision has no such file), its source edited by ``replacements`` ((old, new), ...)."""
    shown = subprocess.run(["git", "-C", str(REPO), "show", f"{revision}:{path}"], capture_output=True, text=True)
    if shown.returncode != 0:
        return None
    source = shown.stdout
    for old, new in replacements:
        source = source.replace(old, new)
    file = Path(tempfile.mkdtemp()) / f"{name}.py"
    file.write_text(source)
    qualified = f"FevarPlannerLib.segmentation.{name}"
    spec = importlib.util.spec_from_file_location(qualified, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[qualified] = module
    spec.loader.exec_module(module)
    return module


def bench_frames(seed: int, kinds, cache: Path | None):
    """(case, prior, [(kind, polarity, BenchFrame), ...]) of one seed; frames read from / written to ``cache``."""
    case = distractors.bench_case(seed)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    frames = []
    for kind, kwargs in KINDS:
        if kind not in kinds:
            continue
        for polarity in POLARITIES:
            stored = None if cache is None else cache / f"{seed}_{kind}_{polarity}.npz"
            if stored is not None and stored.exists():
                data = np.load(stored)
                frame = distractors.BenchFrame(data["frame"], data["mask"], {})
            else:
                frame = distractors.render_bench_frame(case, np.random.default_rng(seed), polarity=polarity, **kwargs)
                if stored is not None:
                    np.savez_compressed(stored, frame=frame.frame, mask=frame.mask)
            frames.append((kind, polarity, frame))
    return case, prior, frames


def _cpu_ms(function, *args) -> tuple:
    start = time.process_time()
    value = function(*args)
    return value, 1e3 * (time.process_time() - start)


def overlay(mask: np.ndarray, truth: np.ndarray, frame: np.ndarray, path: Path) -> None:
    """The frame (dimmed) with true positives white, false negatives red, false positives blue."""
    from PIL import Image

    grey = frame.astype(np.float32)
    grey = 0.5 * (grey - grey.min()) / max(float(np.ptp(grey)), 1.0)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    rgb[mask & truth] = 1.0
    rgb[truth & ~mask] = (1.0, 0.0, 0.0)
    rgb[mask & ~truth] = (0.0, 0.4, 1.0)
    Image.fromarray((255 * rgb).astype(np.uint8)).save(path)


def frame_check(mask: np.ndarray, prior, frame: np.ndarray) -> str:
    """``quality.check_frame_mask``'s verdict on this tree's mask (with the frame, as the pipeline
    runs it): "accepted", or the refusal's message."""
    try:
        quality.check_frame_mask(mask, prior, frame=frame)
    except quality.QualityError as error:
        return f"refused: {error}"
    return "accepted"


def score_seed(seed: int, kinds, cache, reference, pngs: Path | None) -> list[dict]:
    """One row per bench frame of ``seed``: Dice, false-negative and false-positive shares, CPU ms."""
    case, prior, frames = bench_frames(seed, kinds, cache)
    # the reference keeps its own prior: the maps a segmenter derives from it are cached on it
    # (FluoroPrior.derived), and the two revisions may derive them differently
    reference_prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    rows = []
    for kind, polarity, frame in frames:
        seg.segment_fluoro(frame.frame, prior)          # warm the prior's derived maps
        mask, ms = _cpu_ms(seg.segment_fluoro, frame.frame, prior)
        truth = frame.mask
        row = {"seed": seed, "kind": kind, "polarity": polarity, "dice": seg.dice(mask, truth),
               "missed": float((truth & ~mask).sum() / max(truth.sum(), 1)),
               "extra": float((mask & ~truth).sum() / max(truth.sum(), 1)), "cpu_ms": ms,
               "check": frame_check(mask, prior, frame.frame)}
        if reference is not None:
            reference(frame.frame, reference_prior)
            old, old_ms = _cpu_ms(reference, frame.frame, reference_prior)
            row |= {"reference_dice": seg.dice(old, truth), "reference_cpu_ms": old_ms}
        if pngs is not None:
            overlay(mask, truth, frame.frame, pngs / f"{seed}_{kind}_{polarity}.png")
        print({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
        rows.append(row)
    return rows


def write_end_to_end_case(seed: int, work: Path) -> Path:
    """The seed's case folder ``work/cases/bench_<seed>`` whose frame (``fluoro.dcm``) is its ``every``
    bench frame (unsubtracted, dark), with that frame's true mask (``fluoro_mask.png``) beside it."""
    from FevarPlannerLib import io
    from FevarPlannerLib.phantom import write_case

    case = distractors.bench_case(seed)
    folder = write_case(case, work / "cases" / f"bench_{seed}")
    frame = distractors.render_bench_frame(case, np.random.default_rng(seed))
    io.write_fluoro_dicom(folder / "fluoro.dcm", frame.frame, case.carm, patient_name=f"Phantom^{case.name}",
                          patient_id=case.name)
    io.write_mask_png(folder / "fluoro_mask.png", frame.mask)
    return folder


def end_to_end(seed: int, work: Path, outputs: Path | None = None) -> dict:
    """The seed's case (:func:`write_end_to_end_case`) planned by every route of ``bench_image_only.py``
    (with ``outputs``, each route's outputs in ``outputs/<route>/bench_<seed>``)."""
    from bench_image_only import evaluate_case

    folder = write_end_to_end_case(seed, work)
    row = evaluate_case(folder, work / "routes", outputs)
    print(row, flush=True)
    return row


def end_to_end_summary(rows: list[dict]) -> dict:
    """Per seed, image-only and frame-segmented minus masks (mm), or the refusal; and how many
    image-only plans are within 0.5 mm of masks (issue 11) and how many were refused."""
    def difference(row, route):
        if "3d_mm" not in row.get(route, {}) or "3d_mm" not in row.get("masks", {}):
            return "refused" if "refused" in row.get(route, {}) else None
        return round(row[route]["3d_mm"] - row["masks"]["3d_mm"], 3)

    per_case = {row["case"]: {route: difference(row, route) for route in ("image_only", "frame_segmented")}
                for row in rows}
    image_only = [d["image_only"] for d in per_case.values()]
    return {"per_case": per_case, "refused": sum(d == "refused" for d in image_only),
            "within_0_5_mm": sum(isinstance(d, float) and abs(d) <= 0.5 for d in image_only)}


def mask_stage_times(reference, repeats: int, seed: int) -> dict:
    """Median CPU ms of the mask stage (the prior projected, then ``segment_fluoro``, as
    ``bench_frame.py`` times it) on the 1024 x 1024 frames of ``bench_frame.py`` (its plain
    rendered view, and its bench frames unsubtracted and subtracted), this tree's and the
    reference's calls interleaved so that both see the same load."""
    from bench_frame import bench_frames as frames_1024
    from bench_frame import frame_cases

    preop, views = frame_cases(seed, 30.0)
    _, frame, truth, P = views[0]
    bench_preop, bench_P, benches = frames_1024(seed)
    frames = {"rendered": (preop, P, frame, truth)} | {
        kind: (bench_preop, bench_P, bench.frame, bench.mask) for kind, bench in benches.items()}
    segmenters = {"dice": seg.segment_fluoro} | ({} if reference is None else {"reference_dice": reference})
    out = {}
    for kind, (model, P, image, truth) in frames.items():
        times = {name: [] for name in segmenters}
        for _ in range(repeats + 1):
            for name, segmenter in segmenters.items():
                start = time.process_time()
                mask = segmenter(image, quality.FluoroPrior.from_centerline(model.centerline, P))
                times[name].append(time.process_time() - start)
                out.setdefault(kind, {})[name] = seg.dice(mask, truth)
        for name, values in times.items():
            out[kind][name.replace("dice", "mask_cpu_ms")] = 1e3 * float(np.median(values[1:]))
        print(kind, out[kind], flush=True)
    return out


def summarise(rows: list[dict]) -> dict:
    """Mean Dice (and reference Dice, CPU ms) per kind and polarity, over the seeds."""
    out = {}
    for kind in dict.fromkeys(r["kind"] for r in rows):
        for polarity in POLARITIES:
            chosen = [r for r in rows if r["kind"] == kind and r["polarity"] == polarity]
            if chosen:
                out[f"{kind}/{polarity}"] = {key: float(np.mean([r[key] for r in chosen]))
                                             for key in ("dice", "reference_dice", "cpu_ms", "reference_cpu_ms")
                                             if key in chosen[0]}
    return out


def plot(summary: dict, path: Path) -> None:
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(14, 4.5))
    names = list(summary)
    x = np.arange(len(names))
    has_reference = "reference_dice" in summary[names[0]]
    if has_reference:
        ax.bar(x - 0.2, [summary[n]["reference_dice"] for n in names], 0.4, label="reference", color="tab:gray")
    ax.bar(x + (0.2 if has_reference else 0.0), [summary[n]["dice"] for n in names], 0.4, label="this tree")
    ax.axhline(0.9, color="k", ls="--", lw=1)
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set(ylim=(0.5, 1.0), ylabel="mean Dice over seeds", title="frame mask on bench frames (dashed: 0.90)")
    ax.legend(fontsize=8)
    common.save_figure(fig, path)


def main() -> None:
    parser = common.argument_parser(__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[211, 212, 213, 214, 215, 216])
    parser.add_argument("--kinds", nargs="+", default=[k for k, _ in KINDS], choices=[k for k, _ in KINDS])
    parser.add_argument("--reference", default=None, help="git revision whose segment_fluoro runs beside")
    parser.add_argument("--cache", type=Path, default=None, help="folder of rendered frames (npz), reused")
    parser.add_argument("--pngs", action="store_true", help="an overlay PNG per frame")
    parser.add_argument("--end-to-end", action="store_true", help="plan each seed's 'every' frame by every route")
    parser.add_argument("--no-masks", action="store_true", help="skip the per-frame Dice (with --end-to-end)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="with --end-to-end: keep the case folders and every route's outputs here")
    parser.add_argument("--time-1024", type=int, default=0, metavar="REPEATS",
                        help="also time the mask stage on bench_frame.py's 1024 x 1024 frames (its default seed, 3)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    pngs = args.out / "overlays" if args.pngs else None
    if pngs is not None:
        pngs.mkdir(exist_ok=True)
    reference = None if args.reference is None else reference_segmenter(args.reference)
    rows = [] if args.no_masks else [r for s in args.seeds for r in score_seed(s, args.kinds, args.cache, reference, pngs)]
    payload = {"seeds": args.seeds, "reference": args.reference, "frames": rows}
    if rows:
        payload["by_kind"] = summarise(rows)
        unsubtracted = [r for r in rows if r["kind"] != "every_dsa"]
        payload["mean_dice_unsubtracted"] = float(np.mean([r["dice"] for r in unsubtracted]))
        payload["mean_cpu_ms"] = float(np.mean([r["cpu_ms"] for r in rows]))
        payload["refused"] = {kind: sum(r["check"] != "accepted" for r in rows if r["kind"] == kind)
                              for kind in dict.fromkeys(r["kind"] for r in rows)}
        if reference is not None:
            payload["mean_reference_dice_unsubtracted"] = float(np.mean([r["reference_dice"] for r in unsubtracted]))
            payload["mean_reference_cpu_ms"] = float(np.mean([r["reference_cpu_ms"] for r in rows]))
    if args.time_1024:
        payload["mask_stage_1024"] = mask_stage_times(reference, args.time_1024, 3)
    if args.end_to_end:
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp) if args.keep is None else args.keep
            outputs = None if args.keep is None else args.keep / "outputs"
            payload["end_to_end"] = [end_to_end(s, work, outputs) for s in args.seeds]
        payload["end_to_end_summary"] = end_to_end_summary(payload["end_to_end"])
        print(payload["end_to_end_summary"], flush=True)
    common.write_report(args.out, "bench_frame_masks", payload)
    if rows:
        plot(payload["by_kind"], args.out / "bench_frame_masks.png")


if __name__ == "__main__":
    main()

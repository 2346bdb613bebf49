"""Benchmark the segmentation stage on held-out phantom cases.

CT side: Dice of the UNet, the threshold and the classical segmenter against the phantom lumen, mean
distance of the 3D skeleton of each predicted mask to the true centreline, and the time
of each; CPU inference time of the UNet on a 512 x 512 x 300 CT (a phantom CT embedded in
a body-sized field) and of the classical route on the same. Fluoroscopy side: Dice and time of
``segment_fluoro`` without and with the pre-operative prior on the cases' DSA frames and on a
1024 x 1024 phantom frame, and on phantom frames with distractors (wire, catheter,
collimator, table edge, burned-in text, spine; both polarities, subtracted or not).

    .venv/bin/python Testing/benchmarks/bench_segmentation.py --out Testing/benchmarks/results

Timings use ``--threads`` torch threads (default 1: on a 2-core machine shared with other
work, two threads contend and run slower than one).

Held-out cases are generated (``--n-cases``, ``--seed``; the shipped UNet was trained on
seed 100, so keep a different seed) unless ``--cases`` names existing case folders.
Writes ``bench_segmentation.json`` and ``bench_segmentation.png`` into ``--out``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "2")

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image
import torch
from scipy.spatial import cKDTree

from FevarPlannerLib import io
from FevarPlannerLib import phantom as ph
from FevarPlannerLib import segmentation as seg
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.conventions import BRANCH_LABELS
from FevarPlannerLib.quality import FluoroPrior
from FevarPlannerLib.pipeline import preop_from_skeleton
from FevarPlannerLib.skeleton import skeletonize_3d


def timed(function, *args, repeat: int = 1, **kwargs):
    """(result, best wall time in s) of ``function`` over ``repeat`` calls."""
    best, result = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        result = function(*args, **kwargs)
        best = min(best, time.perf_counter() - start)
    return result, best


def cpu_median(function, *args, repeat: int = 11, **kwargs) -> float:
    """Median CPU seconds (this process, all threads) of ``function`` over ``repeat`` calls:
    steadier than wall time on a shared machine."""
    seconds = []
    for _ in range(repeat):
        start = time.process_time()
        function(*args, **kwargs)
        seconds.append(time.process_time() - start)
    return float(np.median(seconds))


def frame_results(seed: int) -> dict:
    """Dice and time of ``segment_fluoro`` on a 1024 x 1024 phantom frame, with and without the prior."""
    frame, truth, case = phantom_frame_1024(seed)
    prior = FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    mask, seconds = timed(seg.segment_fluoro, frame, vessels="auto", repeat=5)
    prior_mask, prior_seconds = timed(seg.segment_fluoro, frame, prior, repeat=5)
    return {"frame": frame, "truth": truth, "mask": mask,
            "fluoro_1024_with_prior_dice": seg.dice(prior_mask, truth),
            "fluoro_1024_with_prior_time_s": prior_seconds,
            "fluoro_1024_with_prior_cpu_median_s": cpu_median(seg.segment_fluoro, frame, prior),
            "fluoro_1024_dice": seg.dice(mask, truth), "fluoro_1024_time_s": seconds}


def skeleton_distance_mm(mask: io.Volume, centreline: Centerline) -> dict:
    """Mean / 95th percentile distance of the mask's 3D skeleton voxels to the true centreline,
    of the centreline nodes to the skeleton (coverage), and of the pipeline's pre-operative
    centreline (thinned, smoothed and centred in the mask) to the true one."""
    skeleton = skeletonize_3d(mask)
    points = skeleton.index_to_lps(np.argwhere(skeleton.array > 0))
    truth = cKDTree(_densify(centreline))
    to_truth, _ = truth.query(points)
    to_skeleton, _ = cKDTree(points).query(centreline.points)
    try:
        pipeline_to_truth, _ = truth.query(preop_from_skeleton(skeleton, lumen=mask).centerline.points)
        centreline_mm = float(pipeline_to_truth.mean())
    except ValueError:              # the mask's tree lacks a branch: the pipeline would refuse it
        centreline_mm = float("nan")
    return {"skeleton_to_truth_mean_mm": float(to_truth.mean()),
            "skeleton_to_truth_p95_mm": float(np.percentile(to_truth, 95)),
            "truth_to_skeleton_mean_mm": float(to_skeleton.mean()),
            "centreline_to_truth_mean_mm": centreline_mm}


def _densify(centreline: Centerline, step_mm: float = 0.1) -> np.ndarray:
    """Points every ``step_mm`` along each edge (so nearest-point distances are to the curve)."""
    a, b = centreline.points[centreline.edges[:, 0]], centreline.points[centreline.edges[:, 1]]
    pieces = [centreline.points]
    for p, q in zip(a, b):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / step_mm)))
        pieces.append(p + np.linspace(0.0, 1.0, n + 1)[:, None] * (q - p))
    return np.vstack(pieces)


def branch_recall(mask: io.Volume, centreline: Centerline) -> dict:
    """Per branch of the true centreline (aorta, renals, iliacs): the fraction of its nodes that
    fall inside the mask (a branch the segmenter missed scores 0, one it lost half way 0.5)."""
    index = np.round(mask.lps_to_index(centreline.points)).astype(int)
    inside_grid = np.all((index >= 0) & (index < np.asarray(mask.shape)), axis=1)
    hit = np.zeros(len(index), dtype=bool)
    hit[inside_grid] = np.asarray(mask.array)[tuple(index[inside_grid].T)] > 0
    labels = np.asarray(centreline.labels)
    return {f"recall_{name}": float(hit[labels == name].mean()) for name in BRANCH_LABELS if (labels == name).any()}


CT_SEGMENTERS = ("unet", "threshold", "classical")


def evaluate_ct_case(folder: Path, model, segmenters=CT_SEGMENTERS) -> dict:
    ct, truth = seg.read_case(folder)
    centreline = Centerline.from_dict(json.loads((folder / "gt.json").read_text())["preop_centerline"])
    result = {"case": folder.name, "shape_kji": list(ct.shape)}
    functions = {"unet": lambda: seg.segment_ct_unet(ct, model), "threshold": lambda: seg.segment_ct_threshold(ct),
                 "classical": lambda: seg.segment_ct_classical(ct)}
    for name in segmenters:
        mask, seconds = timed(functions[name])
        result[name] = {"dice": seg.dice(mask, truth), "time_s": seconds, **skeleton_distance_mm(mask, centreline),
                        **branch_recall(mask, centreline)}
    return result


def evaluate_fluoro_case(folder: Path) -> dict:
    fluoro = io.read_fluoro(folder / "fluoro.dcm")
    truth = np.array(Image.open(folder / "fluoro_mask.png")) > 0
    mask, seconds = timed(seg.segment_fluoro, fluoro.image, vessels="auto", repeat=3)
    prior = case_prior(folder)
    prior_mask, prior_seconds = timed(seg.segment_fluoro, fluoro.image, prior, repeat=3)
    return {"case": folder.name, "shape": list(fluoro.shape), "dice": seg.dice(mask, truth), "time_s": seconds,
            "with_prior": {"dice": seg.dice(prior_mask, truth), "time_s": prior_seconds}}


def case_prior(folder: Path) -> FluoroPrior:
    """The pre-operative tree (gt.json's preop centreline) projected through the given P."""
    case = io.load_case(folder)
    centreline = Centerline.from_dict(json.loads((folder / "gt.json").read_text())["preop_centerline"])
    return FluoroPrior.from_centerline(centreline, case.P)


def distractor_frames(seeds=(1, 2, 3)) -> list:
    """Dice and distractors kept on the phantom frames with wire, catheter, collimator, table,
    text (and, unsubtracted, a spine) of Testing/test_segmentation.py, with the prior."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from test_segmentation import _distractors_taken, distractor_frame

    rows = []
    for seed in seeds:
        for subtracted in (True, False):
            for polarity in ("dark", "bright"):
                frame, truth, prior, parts = distractor_frame(seed, subtracted=subtracted, polarity=polarity)
                mask, seconds = timed(seg.segment_fluoro, frame, prior)
                rows.append({"seed": seed, "subtracted": subtracted, "polarity": polarity, "shape": list(frame.shape),
                             "dice_with_prior": seg.dice(mask, truth),
                             "dice_without_prior": seg.dice(seg.segment_fluoro(frame), truth),
                             "distractor_fraction_kept": _distractors_taken(mask, truth, parts), "time_s": seconds})
    return rows


def large_ct(ct: io.Volume, shape=(300, 512, 512), spacing=(0.8, 0.8, 1.0)) -> io.Volume:
    """A phantom CT embedded in a body-sized 512 x 512 field (soft tissue ellipse, air outside)."""
    nk, nj, ni = shape
    jj, ii = np.mgrid[0:nj, 0:ni]
    body = ((ii - ni / 2) / (0.45 * ni)) ** 2 + ((jj - nj / 2) / (0.36 * nj)) ** 2 <= 1.0
    axial = np.where(body, 40, -1000).astype(np.int16)
    array = np.broadcast_to(axial, shape).copy()
    k = np.arange(nk) % ct.shape[0]
    j0, i0 = (nj - ct.shape[1]) // 2, (ni - ct.shape[2]) // 2
    array[:, j0:j0 + ct.shape[1], i0:i0 + ct.shape[2]] = ct.array[k]
    return io.Volume(array, spacing, (-ni * spacing[0] / 2, -nj * spacing[1] / 2, 0.0), np.eye(3))


def phantom_frame_1024(seed: int):
    params = replace(ph.random_params(np.random.default_rng(seed)), detector_rows=1024, detector_cols=1024)
    case = ph.generate_case(params, name="frame1024")
    return (*ph.render_fluoro(case.intraop, case.P_true, case.carm, case.params, np.random.default_rng(seed)), case)


def held_out_cases(args, work: Path) -> list[Path]:
    if args.cases:
        return [Path(c) for c in args.cases]
    return ph.write_phantom_set(work / "held_out", n=args.n_cases, seed=args.seed, preset="random")


def plot(results: dict, example: dict, path: Path) -> None:
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.5))
    cases = results["ct_cases"]
    x = np.arange(len(cases))
    for offset, name in ((-0.27, "unet"), (0.0, "threshold"), (0.27, "classical")):
        axes[0].bar(x + offset, [c[name]["dice"] for c in cases], 0.27, label=name)
    axes[0].axhline(0.9, color="k", ls="--", lw=1)
    axes[0].set(title="CT lumen Dice (goal 0.90)", xticks=x, xticklabels=[c["case"] for c in cases], ylim=(0.5, 1))
    axes[0].legend()
    bars = [(name, key, what) for name in ("unet", "threshold")
            for key, what in (("skeleton_to_truth_mean_mm", "skeleton voxels"),
                              ("centreline_to_truth_mean_mm", "centred centreline"))]
    for k, (name, key, what) in enumerate(bars):
        axes[1].bar(x + (k - 1.5) * 0.2, [c[name][key] for c in cases], 0.2, label=f"{name}, {what}")
    axes[1].axhline(1.0, color="k", ls="--", lw=1)
    axes[1].set(title="3D centreline to the true one, mean mm (goal 1)", xticks=x,
                xticklabels=[c["case"] for c in cases])
    axes[1].legend(fontsize=7)
    axes[2].imshow(example["frame"], cmap="gray")
    axes[2].contour(example["truth"], levels=[0.5], colors="lime", linewidths=0.6)
    axes[2].contour(example["mask"], levels=[0.5], colors="red", linewidths=0.6)
    axes[2].set(title=f"1024^2 frame: truth (green), vesselness (red), Dice {example['dice']:.3f}")
    axes[2].axis("off")
    axes[3].imshow(example["ct_slice"], cmap="gray", vmin=-200, vmax=600)
    axes[3].contour(example["ct_truth"], levels=[0.5], colors="lime", linewidths=0.8)
    axes[3].contour(example["ct_unet"], levels=[0.5], colors="red", linewidths=0.8)
    axes[3].set(title="CT slice: truth (green), UNet (red)")
    axes[3].axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cases", nargs="*", help="existing held-out case folders (ct/ + aorta_mask + gt.json)")
    parser.add_argument("--n-cases", type=int, default=3)
    parser.add_argument("--seed", type=int, default=200)
    parser.add_argument("--model", help="UNet checkpoint (default: the shipped weights)")
    parser.add_argument("--frames-only", action="store_true",
                        help="only the fluoroscopy frames (1024^2 phantom, the cases' DSA, distractors)")
    parser.add_argument("--ct-only", action="store_true",
                        help="only the CT cases (Dice, skeleton distances, branch recall) of --segmenters")
    parser.add_argument("--segmenters", nargs="*", default=list(CT_SEGMENTERS), help="with --ct-only")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1 is fastest on a busy 2-core machine)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    if args.frames_only:
        frames_only(args)
        return
    if args.ct_only:
        ct_only(args)
        return
    model = seg.load_unet(args.model)
    with tempfile.TemporaryDirectory() as tmp:
        folders = held_out_cases(args, Path(tmp))
        ct_cases = [evaluate_ct_case(f, model) for f in folders]
        fluoro_cases = [evaluate_fluoro_case(f) for f in folders]
        ct, truth = seg.read_case(folders[0])
    big = large_ct(ct)
    _, unet_big_s = timed(seg.segment_ct_unet, big, model)
    _, unet_big_raw_s = timed(seg.segment_ct_unet, big, model, postprocess=False)
    frame = frame_results(args.seed)
    _, classical_big_s = timed(seg.segment_ct_classical, big)
    distractors = distractor_frames()
    results = {
        "ct_cases": ct_cases,
        "ct_mean": {name: {key: float(np.mean([c[name][key] for c in ct_cases])) for key in ct_cases[0][name]}
                    for name in ("unet", "threshold", "classical")},
        "ct_512x512x300_unet_s": unet_big_s,
        "ct_512x512x300_classical_s": classical_big_s,
        "fluoro_distractor_frames": distractors,
        "ct_512x512x300_unet_without_postprocess_s": unet_big_raw_s,
        "fluoro_cases": fluoro_cases,
        "fluoro_mean_dice": float(np.mean([c["dice"] for c in fluoro_cases])),
        **{key: value for key, value in frame.items() if key.startswith("fluoro_")},
        "model": str(args.model or seg.default_model_path()),
        "torch_threads": torch.get_num_threads(),
    }
    (args.out / "bench_segmentation.json").write_text(json.dumps(results, indent=2))
    k = int(np.argmax(truth.array.sum(axis=(1, 2))))
    example = {"frame": frame["frame"], "truth": frame["truth"], "mask": frame["mask"], "dice": results["fluoro_1024_dice"],
               "ct_slice": ct.array[k], "ct_truth": truth.array[k],
               "ct_unet": seg.segment_ct_unet(ct, model).array[k]}
    plot(results, example, args.out / "bench_segmentation.png")
    print(json.dumps({key: value for key, value in results.items() if key not in ("ct_cases", "fluoro_cases")},
                     indent=2))


def frames_only(args) -> None:
    """The frame part alone (``--frames-only``): writes ``bench_segmentation_frames.json``."""
    with tempfile.TemporaryDirectory() as tmp:
        folders = held_out_cases(args, Path(tmp))
        fluoro_cases = [evaluate_fluoro_case(f) for f in folders]
    frame = frame_results(args.seed)
    distractors = distractor_frames()
    results = {key: value for key, value in frame.items() if key.startswith("fluoro_")}
    results.update({
        "fluoro_cases": fluoro_cases,
        "fluoro_cases_with_prior_mean_dice": float(np.mean([c["with_prior"]["dice"] for c in fluoro_cases])),
        "fluoro_distractor_frames": distractors,
        "fluoro_distractor_mean_dice_with_prior": float(np.mean([r["dice_with_prior"] for r in distractors])),
    })
    (args.out / "bench_segmentation_frames.json").write_text(json.dumps(results, indent=2))
    print(json.dumps({key: value for key, value in results.items()
                      if key not in ("fluoro_cases", "fluoro_distractor_frames")}, indent=2))


def ct_only(args) -> None:
    """The CT part alone (``--ct-only``): writes ``bench_segmentation_ct.json``."""
    model = seg.load_unet(args.model) if "unet" in args.segmenters else None
    with tempfile.TemporaryDirectory() as tmp:
        ct_cases = [evaluate_ct_case(f, model, args.segmenters) for f in held_out_cases(args, Path(tmp))]
    results = {"ct_cases": ct_cases,
               "ct_mean": {name: {key: float(np.mean([c[name][key] for c in ct_cases if key in c[name]]))
                                  for key in ct_cases[0][name]} for name in args.segmenters}}
    (args.out / "bench_segmentation_ct.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results["ct_mean"], indent=2))


if __name__ == "__main__":
    main()

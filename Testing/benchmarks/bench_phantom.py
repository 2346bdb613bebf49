"""Benchmark the phantom generator and draw one case.

Times ``write_phantom_set(n, mask_only=True)`` (paper preset) and one full case (CT DICOM
series + XA frame), reports the per-case shape statistics (2D skeleton pixels, centreline
nodes, shape variation), and draws one case: the DSA frame with the projected ground
truth, the 3D pre- vs intra-operative centrelines and two CT views.

    .venv/bin/python Testing/benchmarks/bench_phantom.py --out Testing/benchmarks/results

Writes ``bench_phantom.json`` and ``bench_phantom.png`` into ``--out``.
"""

from __future__ import annotations

from common import argument_parser, blas_threads, pyplot, save_figure, timed, write_report

blas_threads(2)             # before NumPy: set the variables yourself to compare

import json  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402
from skimage.morphology import skeletonize  # noqa: E402

from FevarPlannerLib import io  # noqa: E402
from FevarPlannerLib import phantom as ph  # noqa: E402
from FevarPlannerLib.centerline import Centerline  # noqa: E402
from FevarPlannerLib.projection import project  # noqa: E402

COLOURS = {"aorta": "tab:red", "renal_left": "tab:cyan", "renal_right": "tab:pink", "iliac_left": "gold",
           "iliac_right": "tab:green", "other": "tab:blue"}


def case_statistics(folder: Path) -> dict:
    """2D skeleton size, centreline nodes and shape variation (3D, mm) of a written case."""
    gt = json.loads((folder / "gt.json").read_text())
    pre, intra = Centerline.from_dict(gt["preop_centerline"]), Centerline.from_dict(gt["intraop_centerline"])
    mask = np.array(Image.open(folder / "fluoro_mask.png")) > 0
    return {"skeleton2d_pixels": int(skeletonize(mask).sum()), "centerline_nodes": len(pre),
            "frame_pixels": int(mask.size),
            "shape_variation_mm": float(np.linalg.norm(pre.points - intra.points, axis=1).mean())}


def time_mask_only_set(n: int, seed: int, work: Path) -> tuple[float, list]:
    folders, seconds, _ = timed(ph.write_phantom_set, work / "set", n=n, seed=seed, preset="paper", mask_only=True)
    return seconds, folders


def time_full_case(seed: int, work: Path) -> tuple[float, Path]:
    params = ph.random_params(np.random.default_rng(seed), sma=True, coeliac=True, internal_iliacs=True)
    folder, seconds, _ = timed(lambda: ph.write_case(ph.generate_case(params, name="full"), work / "full"))
    return seconds, folder


def draw_case(folder: Path, path: Path) -> None:
    """Frame with projected ground truth, mask, 3D centrelines, axial and coronal CT."""
    gt = json.loads((folder / "gt.json").read_text())
    pre, intra = Centerline.from_dict(gt["preop_centerline"]), Centerline.from_dict(gt["intraop_centerline"])
    labels = np.array(intra.labels)
    P_true = np.array(gt["projection_matrix_true"])
    P_given = np.array(gt["projection_matrix_given"])
    frame = io.read_fluoro(folder / "fluoro.dcm").image
    ct = io.read_ct(folder / "ct")
    mask3d = io.read_volume(folder / "aorta_mask.nrrd").array > 0

    fig = pyplot().figure(figsize=(18, 9))
    ax = fig.add_subplot(1, 4, 1)
    ax.imshow(frame, cmap="gray")
    for label, colour in COLOURS.items():
        chosen = labels == label
        uv = project(P_true, intra.points[chosen])
        ax.plot(uv[:, 0], uv[:, 1], ".", color=colour, ms=1.5)
        uv_pre = project(P_given, pre.points[chosen])
        ax.plot(uv_pre[:, 0], uv_pre[:, 1], ".", color=colour, ms=0.8, alpha=0.35)
    ax.set_title("fluoro.dcm + intra-op GT (bold), pre-op via P_given (faint)", fontsize=9)
    ax = fig.add_subplot(1, 4, 2)
    ax.imshow(np.array(Image.open(folder / "fluoro_mask.png")), cmap="gray")
    ax.set_title("fluoro_mask.png", fontsize=9)
    ax = fig.add_subplot(1, 4, 3, projection="3d")
    for label, colour in COLOURS.items():
        chosen = labels == label
        ax.scatter(*pre.points[chosen].T, color="grey", s=1)
        ax.scatter(*intra.points[chosen].T, color=colour, s=1)
    ax.set_xlabel("x (L)")
    ax.set_ylabel("y (P)")
    ax.set_zlabel("z (S)")
    ax.view_init(elev=10, azim=-75)
    ax.set_title("pre-op (grey) vs intra-op centrelines, LPS mm", fontsize=9)
    sac_k = int(np.argmax(mask3d.sum(axis=(1, 2))))
    ax = fig.add_subplot(2, 4, 4)
    ax.imshow(ct.array[sac_k], cmap="gray", vmin=-200, vmax=500)
    ax.contour(mask3d[sac_k], [0.5], colors="r", linewidths=0.6)
    ax.set_title(f"CT axial slice {sac_k} (widest lumen), aorta_mask in red", fontsize=9)
    ax = fig.add_subplot(2, 4, 8)
    j = int(np.argmax(mask3d.sum(axis=(0, 2))))
    ax.imshow(ct.array[::-1, j], cmap="gray", vmin=-200, vmax=500)
    ax.set_title("CT coronal (superior up)", fontsize=9)
    save_figure(fig, path, dpi=90)


def main(argv=None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        set_seconds, folders = time_mask_only_set(args.n, args.seed, work)
        full_seconds, full = time_full_case(args.seed, work)
        stats = [case_statistics(f) for f in folders]
        draw_case(full, args.out / "bench_phantom.png")
        full_stats = case_statistics(full)
    summary = {
        "mask_only_set": {"n": args.n, "seconds": set_seconds, "seconds_per_case": set_seconds / args.n},
        "full_case": {"seconds": full_seconds, **full_stats},
        "skeleton2d_pixels": {"min": min(s["skeleton2d_pixels"] for s in stats),
                              "max": max(s["skeleton2d_pixels"] for s in stats)},
        "shape_variation_mm": {"mean": float(np.mean([s["shape_variation_mm"] for s in stats])),
                               "max": float(np.max([s["shape_variation_mm"] for s in stats]))},
        "cases": stats,
    }
    write_report(args.out, "bench_phantom", summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "cases"}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``fevar-planner``: the command line (plan, phantoms, demo, benchmark, train-unet, segment)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

__all__ = ["main", "ProgressBar"]


class ProgressBar:
    """A one-line text progress bar on stderr, callable as ``progress(fraction, message)``."""

    def __init__(self, stream=sys.stderr, width: int = 30, enabled: bool = True):
        self.stream, self.width, self.enabled = stream, width, enabled
        self.start = time.perf_counter()

    def __call__(self, fraction: float, message: str = "") -> None:
        if not self.enabled:
            return
        fraction = min(max(float(fraction), 0.0), 1.0)
        filled = int(round(fraction * self.width))
        elapsed = time.perf_counter() - self.start
        line = f"\r[{'#' * filled}{'.' * (self.width - filled)}] {fraction * 100:5.1f}% {elapsed:6.1f}s {message[:60]:<60}"
        self.stream.write(line)
        if fraction >= 1.0:
            self.stream.write("\n")
        self.stream.flush()

    def count(self, i: int, n: int, message: str = "") -> None:
        """Adapter for ``(i, n, name)`` style callbacks."""
        self(i / max(n, 1), message)


def _add_case_overrides(parser: argparse.ArgumentParser) -> None:
    for flag, what in (("ct", "CT (DICOM folder or NRRD/NIfTI/MHA)"), ("aorta-mask", "binary lumen label"),
                       ("skeleton3d", "binary 3D skeleton volume"), ("fluoro", "fluoroscopic frame"),
                       ("fluoro-mask", "binary 2D vessel mask PNG"), ("geometry", "geometry.json")):
        parser.add_argument(f"--{flag}", type=Path, default=None, help=f"override the case folder's {what}")
    parser.add_argument("--frame", type=int, default=0, help="frame index in a multi-frame DICOM (default 0)")


def _cmd_plan(args) -> int:
    from .pipeline import plan_case

    progress = ProgressBar(enabled=not args.quiet)
    result = plan_case(args.case, args.out, method=args.method, progress=progress,
                       ct=args.ct, aorta_mask=args.aorta_mask, skeleton3d=args.skeleton3d, fluoro=args.fluoro,
                       fluoro_mask=args.fluoro_mask, geometry=args.geometry, frame=args.frame,
                       start=args.start, target=args.target, refine_pose=args.refine_pose, segmenter=args.segmenter)
    _print_summary(result, args.out)
    return 0


def _print_summary(result, out_dir) -> None:
    t = result.timings
    print(f"method {result.method}: {len(result.deformed)} nodes, path {result.path.start_label} -> "
          f"{result.path.target_label} {result.path.length_mm:.1f} mm")
    print(f"time: total {t['total']:.2f} s, intra-operative registration {t['registration'] * 1000:.1f} ms")
    errors = result.errors or {}
    for key, unit in (("2d_px", "px"), ("3d_mm", "mm"), ("3d_reverse_mm", "mm")):
        if errors.get(key):
            print(f"error {key}: mean {errors[key]['mean']:.3f} {unit}, std {errors[key]['std']:.3f} {unit}")
    if out_dir is not None:
        print(f"outputs in {out_dir}")


def _cmd_phantoms(args) -> int:
    from .phantom import write_phantom_set

    bar = ProgressBar(enabled=not args.quiet)
    folders = write_phantom_set(args.out, n=args.n, seed=args.seed, preset=args.preset, mask_only=args.mask_only,
                                progress=bar.count)
    bar(1.0, f"{len(folders)} cases")
    print(f"wrote {len(folders)} phantom cases to {args.out}")
    return 0


def _cmd_demo(args) -> int:
    import numpy as np

    from . import export, phantom
    from .centerline import Centerline
    from .conventions import PALETTE
    from .pipeline import plan_case

    out = Path(args.out)
    bar = ProgressBar(enabled=not args.quiet)
    bar(0.0, "generating a phantom case (CT series, XA frame, masks)")
    # by default the job starts from the raw images: ct/ + fluoro.dcm + geometry.json
    params = phantom.random_params(np.random.default_rng(args.seed), misalign_shift_px=(0.0, 0.0),
                                   misalign_rotation_deg=0.0)
    case_dir = phantom.write_case(phantom.generate_case(params, name="demo"), out / "case")
    if not args.masks:
        case_dir = _raw_copy(case_dir, out / "case_raw")
    results = {method: plan_case(case_dir, out / method, method=method, progress=bar)
               for method in ("rigid", "icp-tps", "proposed")}
    for method, result in results.items():
        print(f"\n== {method} ({out / method})")
        _print_summary(result, None)
    gt = Centerline.from_dict(json.loads((case_dir / "gt.json").read_text())["intraop_centerline"])
    proposed = results["proposed"]
    export.render_centerlines_3d(out / "scene.png", [
        (proposed.preop, PALETTE["preop"], "pre-operative"), (gt, PALETTE["truth"], "intra-operative truth"),
        (proposed.deformed, PALETTE["recovered"], "recovered (proposed)"),
        (proposed.path.points, PALETTE["path"], "catheter path")])
    print(f"\npictures: {out / 'proposed' / 'overlay.png'} and {out / 'scene.png'}")
    return 0


def _raw_copy(case_dir: Path, raw_dir: Path) -> Path:
    """The raw images of a phantom case only (CT series, XA frame, geometry, ground truth)."""
    import shutil

    if raw_dir.exists():
        shutil.rmtree(raw_dir)
    shutil.copytree(case_dir / "ct", raw_dir / "ct")
    for name in ("fluoro.dcm", "geometry.json", "gt.json"):
        shutil.copy2(case_dir / name, raw_dir / name)
    return raw_dir


def _cmd_benchmark(args) -> int:
    from .benchmark import run_benchmark, run_independent_benchmark

    if args.sets in ("paper", "all"):
        summary = run_benchmark(args.out, quick=args.quick, seed=args.seed, progress=ProgressBar(enabled=not args.quiet))
        print(json.dumps(summary, indent=2))
    if args.sets in ("independent", "all"):
        summary = run_independent_benchmark(args.out, quick=args.quick, seed=args.seed,
                                            progress=ProgressBar(enabled=not args.quiet))
        print((args.out / "independent_table.md").read_text())
        print(f"independent sets: {summary['wall_s']:.0f} s; details in {args.out / 'independent.json'}")
    return 0


def _cmd_train_unet(args) -> int:
    from .segmentation import train_unet

    bar = ProgressBar(enabled=not args.quiet)
    path = train_unet(args.cases, args.out, iterations=args.iterations, seed=args.seed, lr=args.lr, crop=args.crop,
                      base=args.base, max_channels=args.max_channels, pixel_mm=args.pixel_mm, resume=args.resume,
                      progress=bar.count)
    print(f"weights written to {path}")
    return 0


def _cmd_segment(args) -> int:
    import numpy as np

    from .io import read_ct, write_volume
    from .segmentation import load_unet, mask_surface, segment_ct, write_surface_vtp

    ct = read_ct(args.ct)
    kwargs = {"model": load_unet(args.model)} if args.segmenter == "unet" else {}
    mask = segment_ct(ct, args.segmenter, **kwargs)
    write_volume(args.out, mask.with_array(mask.array.astype(np.uint8)))
    if args.surface is not None:
        write_surface_vtp(args.surface, mask_surface(mask))
    print(f"lumen mask ({int(mask.array.sum())} voxels) written to {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fevar-planner", description=__doc__)
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    sub = parser.add_subparsers(dest="command", required=True)

    plan = sub.add_parser("plan", help="register a case and plan the catheter path")
    plan.add_argument("case", type=Path, help="case folder (docs/DESIGN.md section 4)")
    plan.add_argument("--out", type=Path, required=True, help="output folder")
    plan.add_argument("--method", choices=("proposed", "icp-tps", "rigid"), default="proposed")
    plan.add_argument("--start", default="iliac_right", help="access vessel (default iliac_right)")
    plan.add_argument("--target", default="renal_left", help="target vessel ostium (default renal_left)")
    plan.add_argument("--segmenter", choices=("unet", "threshold"), default="unet",
                      help="CT segmentation when the case holds no mask (default unet)")
    plan.add_argument("--refine-pose", action="store_true",
                      help="correct the frame's in-plane pose first (for a frame known to be misaligned)")
    _add_case_overrides(plan)
    plan.set_defaults(func=_cmd_plan)

    phantoms = sub.add_parser("phantoms", help="write synthetic AAA cases with ground truth")
    phantoms.add_argument("--out", type=Path, required=True)
    phantoms.add_argument("--n", type=int, default=20)
    phantoms.add_argument("--seed", type=int, default=0)
    phantoms.add_argument("--preset", choices=("paper", "random"), default="paper")
    phantoms.add_argument("--mask-only", action="store_true", help="skip the CT series and the XA frame")
    phantoms.set_defaults(func=_cmd_phantoms)

    demo = sub.add_parser("demo", help="run the whole job on a built-in phantom case")
    demo.add_argument("--out", type=Path, default=Path("demo_out"))
    demo.add_argument("--seed", type=int, default=7)
    demo.add_argument("--masks", action="store_true",
                      help="use the phantom's masks instead of segmenting the CT and the frame")
    demo.set_defaults(func=_cmd_demo)

    bench = sub.add_parser("benchmark", help="the paper's experiments: SV / ICP-TPS / proposed")
    bench.add_argument("--out", type=Path, required=True)
    bench.add_argument("--quick", action="store_true", help="a small subset (about 2 minutes)")
    bench.add_argument("--seed", type=int, default=0)
    bench.add_argument("--sets", choices=("paper", "independent", "all"), default="paper",
                       help="the paper's protocol (default), the independent scenario sets of issue 10, or both")
    bench.set_defaults(func=_cmd_benchmark)

    train = sub.add_parser("train-unet", help="train the CT aorta UNet on phantom (or other) case folders")
    train.add_argument("cases", type=Path, nargs="+", help="case folders holding ct/ and aorta_mask.nrrd")
    train.add_argument("--out", type=Path, required=True, help="checkpoint / weights path (.pt)")
    train.add_argument("--iterations", type=int, default=8000)
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--resume", type=Path, default=None, help="checkpoint to continue from")
    train.add_argument("--lr", type=float, default=1e-3, help="SGD learning rate (paper: 1e-3)")
    train.add_argument("--crop", type=int, default=128, help="training window, pixels")
    train.add_argument("--base", type=int, default=8, help="channels of the first UNet block")
    train.add_argument("--max-channels", type=int, default=64)
    train.add_argument("--pixel-mm", type=float, default=1.0, help="in-plane resampling of the slices")
    train.set_defaults(func=_cmd_train_unet)

    segment = sub.add_parser("segment", help="segment the aorta lumen in a CT (UNet or threshold)")
    segment.add_argument("ct", type=Path, help="DICOM series folder or NRRD / NIfTI / MHA")
    segment.add_argument("--out", type=Path, required=True, help="mask file (.nrrd / .nii.gz / .mha)")
    segment.add_argument("--segmenter", choices=("unet", "threshold"), default="unet")
    segment.add_argument("--model", type=Path, default=None, help="UNet weights (default: the shipped ones)")
    segment.add_argument("--surface", type=Path, default=None, help="also write the lumen surface (.vtp)")
    segment.set_defaults(func=_cmd_segment)
    return parser


def main(argv=None) -> int:
    """Entry point of the ``fevar-planner`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"fevar-planner: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

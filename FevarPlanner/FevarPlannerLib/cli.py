"""``fevar-planner``: the command line (plan, track, geometry, phantoms, demo, benchmark, train-unet, segment)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
import warnings
from pathlib import Path

from . import RESEARCH_USE_STATEMENT, __version__

__all__ = ["main", "ProgressBar", "build_parser"]

METHOD_CHOICES = ("proposed", "icp-tps", "rigid")
DESCRIPTION = ("3D catheter path planning for fenestrated endovascular aortic repair (FEVAR) from a pre-operative CT "
               "and one intra-operative fluoroscopic frame (Zheng et al., ICRA 2019).")
EPILOG = (f"{RESEARCH_USE_STATEMENT} World coordinates are DICOM LPS millimetres; the case folder, "
          "result.json and the projection conventions are described in docs/DESIGN.md.")


class ProgressBar:
    """Progress on stderr, callable as ``progress(fraction, message)``.

    On a terminal: one bar redrawn in place. Elsewhere (a log file, a pipe): plain lines,
    one when the step changes, another tenth of the work is done or :attr:`HEARTBEAT_S`
    seconds have passed within a long step; never a carriage return, so a log reads step
    by step.
    """

    HEARTBEAT_S = 10.0
    #: The bar that last drew a terminal line it did not end (so an error starts on a new line).
    open_line = None

    def __init__(self, stream=None, width: int = 30, enabled: bool = True, tty: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.width, self.enabled = width, enabled
        self.tty = self.stream.isatty() if tty is None and hasattr(self.stream, "isatty") else bool(tty)
        self.start = time.perf_counter()
        self._last = (None, -1)
        self._last_time = 0.0

    def __call__(self, fraction: float, message: str = "") -> None:
        if not self.enabled:
            return
        fraction = min(max(float(fraction), 0.0), 1.0)
        elapsed = time.perf_counter() - self.start
        if not self.tty:
            self._line(fraction, message, elapsed)
            return
        filled = int(round(fraction * self.width))
        line = f"\r[{'#' * filled}{'.' * (self.width - filled)}] {fraction * 100:5.1f}% {elapsed:6.1f}s {message[:60]:<60}"
        self.stream.write(line)
        if fraction >= 1.0:
            self.stream.write("\n")
        ProgressBar.open_line = self if fraction < 1.0 else None
        self.stream.flush()

    @classmethod
    def end_open_line(cls) -> None:
        """End a progress line left open, so that what follows starts on a line of its own."""
        if cls.open_line is not None:
            cls.open_line.stream.write("\n")
            cls.open_line.stream.flush()
            cls.open_line = None

    def _line(self, fraction: float, message: str, elapsed: float) -> None:
        decile = int(fraction * 10)
        step = message.split(":")[0]  # "segmenting the aorta: slice 3/40" is one step
        if step == self._last[0] and decile <= self._last[1] and elapsed - self._last_time < self.HEARTBEAT_S:
            return
        self._last, self._last_time = (step, decile), elapsed
        self.stream.write(f"[{fraction * 100:3.0f}%] {elapsed:6.1f}s {message}\n")
        self.stream.flush()

    def count(self, i: int, n: int, message: str = "") -> None:
        """Adapter for ``(i, n, name)`` style callbacks."""
        self(i / max(n, 1), message)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Our warnings as one line on stderr: ``fevar-planner: note: ...`` (no source location).

    Warnings of other libraries (numpy, pydicom, torch, ...) are not shown: stderr holds one
    line per thing the user should act on.
    """
    if not category.__module__.startswith(__package__ or "FevarPlannerLib"):
        return
    ProgressBar.end_open_line()
    print(f"fevar-planner: note: {_one_line(str(message) or category.__name__)}", file=sys.stderr if file is None else file)


def _one_line(message: str) -> str:
    """The first line of ``message``, printable whatever bytes a file name held."""
    first = message.strip().splitlines()[0] if message.strip() else "unknown error"
    return first.encode("utf-8", "backslashreplace").decode("utf-8")


def _add_case_overrides(parser: argparse.ArgumentParser) -> None:
    for flag, what in (("ct", "CT (DICOM folder or NRRD/NIfTI/MHA)"), ("aorta-mask", "binary lumen label"),
                       ("skeleton3d", "binary 3D skeleton volume"), ("fluoro", "fluoroscopic frame"),
                       ("fluoro-mask", "binary 2D vessel mask PNG"), ("geometry", "geometry.json")):
        parser.add_argument(f"--{flag}", type=Path, default=None, metavar="PATH",
                            help=f"override the case folder's {what}")


def _add_planning_options(parser: argparse.ArgumentParser) -> None:
    from .planning import VESSEL_LABELS

    parser.add_argument("--method", choices=METHOD_CHOICES, default="proposed",
                        help="registration: the paper's method, the ICP-TPS baseline or rigid only (default proposed)")
    parser.add_argument("--start", choices=VESSEL_LABELS, default="iliac_right",
                        help="access vessel; the path starts at its distal end (default iliac_right)")
    parser.add_argument("--target", choices=VESSEL_LABELS, default="renal_left",
                        help="target vessel; the path ends at its ostium (default renal_left)")
    parser.add_argument("--segmenter", choices=("classical", "unet", "threshold"), default="classical",
                        help="CT segmentation when the case holds no mask (default classical: no training, "
                             "validated on a real CT; unet: trained on phantoms only)")
    parser.add_argument("--no-cache", dest="cache", action="store_false",
                        help="recompute the pre-operative model instead of reusing it from the cache "
                             "($FEVAR_PLANNER_CACHE, else ~/.cache/fevar-planner)")


def _cmd_plan(args) -> int:
    from .pipeline import plan_case, workers

    progress = ProgressBar(enabled=not args.quiet)
    # one case: the view worker could take no job before its imports are done, so starting
    # it would only cost (on the demo case 0.5 s of wall time, 1.5 s of CPU and 550 MB)
    previous = workers.set_enabled(False)
    try:
        result = plan_case(args.case, args.out, method=args.method, progress=progress,
                           ct=args.ct, aorta_mask=args.aorta_mask, skeleton3d=args.skeleton3d, fluoro=args.fluoro,
                           fluoro_mask=args.fluoro_mask, geometry=args.geometry, frame=args.frame,
                           start=args.start, target=args.target, refine_pose=args.pose, segmenter=args.segmenter,
                           cache=args.cache, drr=args.drr)
    finally:
        workers.set_enabled(previous)
    ProgressBar.end_open_line()
    _print_summary(result, args.out)
    return 0


def _print_summary(result, out_dir) -> None:
    t = result.timings
    print(f"method {result.method}: {len(result.deformed)} nodes, path {result.path.start_label} -> "
          f"{result.path.target_label} {result.path.length_mm:.1f} mm")
    print(f"time: total {t['total']:.2f} s, intra-operative registration {t['registration'] * 1000:.1f} ms")
    errors = result.errors or {}
    truth = errors.get("3d_mm") is not None
    names = {"2d_px": "error 2d_px" if truth else "fit to the frame's own skeleton (2D, not an error)",
             "3d_mm": "error 3d_mm", "3d_reverse_mm": "error 3d_reverse_mm"}
    for key, unit in (("2d_px", "px"), ("3d_mm", "mm"), ("3d_reverse_mm", "mm")):
        if errors.get(key):
            print(f"{names[key]}: mean {errors[key]['mean']:.3f} {unit}, std {errors[key]['std']:.3f} {unit}")
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

    from . import cache, export, phantom
    from .centerline import Centerline
    from .conventions import PALETTE
    from .io import load_case
    from .pipeline import run_case, write_outputs

    out = Path(args.out)
    bar = ProgressBar(enabled=not args.quiet)
    steps = 2 + 3 + 1
    bar(0.0, f"step 1/{steps}: generating a phantom case (CT series, XA frame, masks)")
    # by default the job starts from the raw images: ct/ + fluoro.dcm + geometry.json
    params = phantom.random_params(np.random.default_rng(args.seed), misalign_shift_px=(0.0, 0.0),
                                   misalign_rotation_deg=0.0)
    case_dir = phantom.write_case(phantom.generate_case(params, name="demo"), out / "case")
    if not args.masks:
        case_dir = _raw_copy(case_dir, out / "case_raw")
    case = load_case(case_dir)
    # the CT is segmented once; the three methods share the pre-operative model
    bar(1 / steps, f"step 2/{steps}: the pre-operative model (CT segmentation, 3D skeleton graph)")
    model = cache.preop_model(case, progress=_sub_progress(bar, 1 / steps, 2 / steps), use_cache=args.cache)
    results = {}
    for k, method in enumerate(("rigid", "icp-tps", "proposed")):
        bar((2 + k) / steps, f"step {3 + k}/{steps}: {method}")
        results[method] = run_case(case, method=method, preop=model, drr=(method == "proposed"))
        write_outputs(results[method], out / method)
    bar((steps - 1) / steps, f"step {steps}/{steps}: 3D picture")
    for method, result in results.items():
        print(f"\n== {method} ({out / method})")
        _print_summary(result, None)
    gt = Centerline.from_dict(json.loads((case_dir / "gt.json").read_text())["intraop_centerline"])
    proposed = results["proposed"]
    export.render_centerlines_3d(out / "scene.png", [
        (proposed.preop, PALETTE["preop"], "pre-operative"), (gt, PALETTE["truth"], "intra-operative truth"),
        (proposed.deformed, PALETTE["recovered"], "recovered (proposed)"),
        (proposed.path.points, PALETTE["path"], "catheter path")])
    bar(1.0, "done")
    print(f"\npre-operative model: {'from the cache' if model.from_cache else 'computed once'} "
          f"({sum(v for k, v in model.timings.items() if k != 'preop_cache_load'):.1f} s)")
    print(f"pictures: {out / 'proposed' / 'overlay.png'}, {out / 'proposed' / 'drr_check.png'} and {out / 'scene.png'}")
    return 0


def _sub_progress(bar, low: float, high: float):
    """``progress(fraction, message)`` mapped into ``[low, high]`` of ``bar``."""
    return lambda fraction, message="": bar(low + (high - low) * float(fraction), message)


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

    _check_not_an_input(args.out, list(args.cases))
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

    _check_not_an_input(args.out, [args.ct] + ([args.model] if args.model is not None else []))
    if args.model is not None and args.segmenter != "unet":
        from .files import InputError

        raise InputError(f"{args.model}: --model is used by --segmenter unet only (the {args.segmenter} "
                         f"segmenter would ignore it)")
    bar = ProgressBar(enabled=not args.quiet)
    bar(0.0, f"reading {args.ct}")
    ct = read_ct(args.ct)
    kwargs = {}
    if args.segmenter != "threshold":
        kwargs["progress"] = lambda done, total: bar(0.05 + 0.9 * done / max(total, 1), f"segmenting: slice {done}/{total}")
    if args.segmenter == "unet":
        kwargs["model"] = load_unet(args.model)
    mask = segment_ct(ct, args.segmenter, **kwargs)
    write_volume(args.out, mask.with_array(mask.array.astype(np.uint8)))
    if args.surface is not None:
        bar(0.97, "lumen surface")
        write_surface_vtp(args.surface, mask_surface(mask))
    bar(1.0, "done")
    print(f"lumen mask ({int(mask.array.sum())} voxels) written to {args.out}")
    return 0


def _cmd_geometry(args) -> int:
    from .io import find_case_file, load_case
    from .projection import update_in_plane_correction

    path = update_in_plane_correction(args.case, shift=args.shift, rotate=args.rotate, reset=args.reset)
    if find_case_file(args.case, "fluoro", (".dcm", ".png", ".jpg", ".tif")) is None and not path.is_file():
        print(f"{args.case}: no frame and no geometry.json")
        return 0
    case = load_case(args.case)
    print(case.geometry.describe())
    if args.drr is not None:
        from . import drr

        volume = case.ct if case.ct is not None else case.aorta_mask
        if volume is None:
            raise ValueError(f"{args.case}: no CT or aorta mask to render a DRR from")
        drr.write_drr_check(args.drr, case.fluoro.image, drr.check_drr(volume, case.P, case.fluoro.shape),
                            title=f"geometry check: {case.geometry.kind}", notes=case.geometry.assumptions)
        print(f"DRR check written to {args.drr}")
    return 0


def _cmd_track(args) -> int:
    from .tracking import track_case, write_track_outputs

    bar = ProgressBar(enabled=not args.quiet)
    result = track_case(args.case, method=args.method, start=args.start, target=args.target, first=args.first,
                        count=args.count, segmenter=args.segmenter, cache=args.cache, progress=bar,
                        ct=args.ct, aorta_mask=args.aorta_mask, skeleton3d=args.skeleton3d, fluoro=args.fluoro,
                        geometry=args.geometry)
    write_track_outputs(result, args.out)
    summary = result.summary()
    per_frame = summary["per_frame_total_ms"] or {}
    print(f"{summary['n_frames']} frames ({len(summary['failed_frames'])} failed), per frame median "
          f"{per_frame.get('median', float('nan')):.1f} ms, p95 {per_frame.get('p95', float('nan')):.1f} ms; "
          f"pre-operative model {'from the cache' if result.preop_from_cache else 'computed'} "
          f"in {result.preop_seconds:.2f} s")
    print(f"outputs in {args.out}: track.csv, track.json, result.json of the last frame")
    return 0


def _output_path(text: str) -> Path:
    """An ``--out`` value: any path but the empty one (which would mean the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return Path(text)


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors on one line (exit code 2), like every other bad input."""

    def error(self, message):
        ProgressBar.end_open_line()
        self.exit(2, f"fevar-planner: error: {self.prog}: {_one_line(message)}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="fevar-planner", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"fevar-planner {__version__}. {RESEARCH_USE_STATEMENT}",
                        help="print the version and the research-use statement, then exit")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    plan = sub.add_parser("plan", help="register a case and plan the catheter path", epilog=EPILOG)
    plan.add_argument("case", type=Path, help="case folder: ct/ or ct.nrrd, fluoro.dcm or fluoro.png, "
                                              "optional masks and geometry.json (docs/DESIGN.md section 4)")
    plan.add_argument("--out", type=_output_path, required=True, help="output folder (result.json, .vtp, .mrk.json, PNGs)")
    _add_planning_options(plan)
    plan.add_argument("--pose", choices=("auto", "off", "on"), default="auto",
                      help="in-plane pose check of the frame against P: auto (default) corrects P when the upper "
                           "aorta and renal ostia agree on one rigid offset; off keeps P; on always corrects")
    plan.add_argument("--refine-pose", dest="pose", action="store_const", const="on",
                      help="the same as --pose on (kept for old scripts)")
    plan.add_argument("--drr", dest="drr", action="store_const", const=True, default="auto",
                      help="always write drr_check.png (default: when P comes from the C-arm tags)")
    plan.add_argument("--no-drr", dest="drr", action="store_const", const=False, help="never render the DRR check")
    _add_case_overrides(plan)
    plan.add_argument("--frame", type=int, default=0, help="frame index in a multi-frame DICOM (default 0)")
    plan.set_defaults(func=_cmd_plan)

    track = sub.add_parser("track", help="register every frame of a multi-frame run against one pre-operative model",
                           epilog=EPILOG)
    track.add_argument("case", type=Path, help="case folder whose fluoro.dcm holds several frames")
    track.add_argument("--out", type=Path, required=True, help="output folder (track.csv, track.json, last frame)")
    _add_planning_options(track)
    track.add_argument("--first", type=int, default=0, help="first frame to register (default 0)")
    track.add_argument("--count", type=int, default=None, help="number of frames (default: to the end of the run)")
    _add_case_overrides(track)
    track.set_defaults(func=_cmd_track)

    geometry = sub.add_parser("geometry", help="show, check (DRR) and correct a case's projection geometry",
                              epilog=EPILOG)
    geometry.add_argument("case", type=Path, help="case folder")
    geometry.add_argument("--shift", type=float, nargs=2, metavar=("DU", "DV"), default=None,
                          help="in-plane correction: move the projection by DU columns and DV rows (pixels)")
    geometry.add_argument("--rotate", type=float, metavar="DEG", default=None,
                          help="in-plane correction: turn the projection about the image centre (degrees)")
    geometry.add_argument("--reset", action="store_true", help="remove the stored in-plane correction")
    geometry.add_argument("--drr", type=Path, default=None, metavar="PNG",
                          help="write the DRR check picture (frame beside the CT rendered through P)")
    geometry.set_defaults(func=_cmd_geometry)

    phantoms = sub.add_parser("phantoms", help="write synthetic AAA cases with ground truth", epilog=EPILOG)
    phantoms.add_argument("--out", type=Path, required=True, help="folder to write the case folders into")
    phantoms.add_argument("--n", type=int, default=20, help="number of cases (default 20)")
    phantoms.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    phantoms.add_argument("--preset", choices=("paper", "random"), default="paper",
                          help="the paper's simulation protocol or random anatomy (default paper)")
    phantoms.add_argument("--mask-only", action="store_true", help="skip the CT series and the XA frame")
    phantoms.set_defaults(func=_cmd_phantoms)

    demo = sub.add_parser("demo", help="run the whole job on a built-in phantom case", epilog=EPILOG)
    demo.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    demo.add_argument("--seed", type=int, default=7, help="phantom seed (default 7)")
    demo.add_argument("--masks", action="store_true",
                      help="use the phantom's masks instead of segmenting the CT and the frame")
    demo.add_argument("--no-cache", dest="cache", action="store_false",
                      help="do not read or write the pre-operative cache")
    demo.set_defaults(func=_cmd_demo)

    bench = sub.add_parser("benchmark", help="the paper's experiments: SV / ICP-TPS / proposed", epilog=EPILOG)
    bench.add_argument("--out", type=Path, required=True, help="output folder (table.md, benchmark.json, figures)")
    bench.add_argument("--quick", action="store_true", help="a small subset (about 2 minutes)")
    bench.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    bench.add_argument("--sets", choices=("paper", "independent", "all"), default="paper",
                       help="the paper's protocol (default), the independent scenario sets of issue 10, or both")
    bench.set_defaults(func=_cmd_benchmark)

    train = sub.add_parser("train-unet", help="train the CT aorta UNet on phantom (or other) case folders",
                           epilog=EPILOG)
    train.add_argument("cases", type=Path, nargs="+", help="case folders holding ct/ and aorta_mask.nrrd")
    train.add_argument("--out", type=Path, required=True, help="checkpoint / weights path (.pt)")
    train.add_argument("--iterations", type=int, default=8000, help="SGD iterations (default 8000)")
    train.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    train.add_argument("--resume", type=Path, default=None, help="checkpoint to continue from")
    train.add_argument("--lr", type=float, default=1e-3, help="SGD learning rate (paper: 1e-3)")
    train.add_argument("--crop", type=int, default=128, help="training window, pixels (default 128)")
    train.add_argument("--base", type=int, default=8, help="channels of the first UNet block (default 8)")
    train.add_argument("--max-channels", type=int, default=64, help="cap on the channels of any block (default 64)")
    train.add_argument("--pixel-mm", type=float, default=1.0, help="in-plane resampling of the slices, mm (default 1)")
    train.set_defaults(func=_cmd_train_unet)

    segment = sub.add_parser("segment", help="segment the aorta lumen in a CT (classical, UNet or threshold)", epilog=EPILOG)
    segment.add_argument("ct", type=Path, help="DICOM series folder or NRRD / NIfTI / MHA")
    segment.add_argument("--out", type=Path, required=True, help="mask file (.nrrd / .nii.gz / .mha)")
    segment.add_argument("--segmenter", choices=("classical", "unet", "threshold"), default="classical",
                         help="classical (aorta traced slice by slice, branches by vesselness; no training), "
                              "the UNet trained on phantoms, or HU thresholding (default classical)")
    segment.add_argument("--model", type=Path, default=None, help="UNet weights (default: the shipped ones)")
    segment.add_argument("--surface", type=Path, default=None, help="also write the lumen surface (.vtp)")
    segment.set_defaults(func=_cmd_segment)
    return parser


def _check_not_an_input(out: Path, inputs) -> None:
    """Refuse an output file that is an input, lies inside an input folder, or is not a plain file."""
    from .files import InputError, display_path

    target = Path(os.path.realpath(out))
    for given in inputs:
        source = Path(os.path.realpath(given))
        if target == source or (source.is_dir() and source in target.parents):
            raise InputError(f"{display_path(out)}: --out would overwrite or write inside the input "
                             f"{display_path(given)}")
    if os.path.lexists(out) and not Path(out).is_file():
        raise InputError(f"{display_path(out)}: --out exists and is not a regular file")


@contextlib.contextmanager
def _itk_warnings_off():
    """ITK prints its warnings straight to stderr, several lines each: keep them off the command
    line's stderr, which holds one line per problem (the readers check inputs themselves).
    VTK's are left on: its readers' errors are detected through them."""
    import SimpleITK as sitk

    previous = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(previous)


def _error_message(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        from .files import display_path

        return f"{display_path(exc.filename)}: {exc.strerror}"
    return str(exc) or type(exc).__name__


def main(argv=None) -> int:
    """Entry point of the ``fevar-planner`` console script.

    Bad input ends with exit code 2 and one line on stderr (after ending any progress line).
    Our own warnings (input notes, geometry assumptions) are printed as one-line notes;
    other libraries' warnings are not shown.
    """
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings(), _itk_warnings_off():
        warnings.simplefilter("always")
        warnings.showwarning = _show_warning
        try:
            return args.func(args)
        except (ValueError, OSError, MemoryError, RecursionError) as exc:
            ProgressBar.end_open_line()
            print(f"fevar-planner: error: {_one_line(_error_message(exc))}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            ProgressBar.end_open_line()
            print("fevar-planner: error: interrupted; the outputs were left as they were", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())

"""Wrong-frame benchmark (issue 11): does ``plan`` refuse a frame that is not this case's, and
only such frames?

Right case folders: the scenario family's quick sets (one case per kind, every kind but
image_only, ``--scenario-seeds``; two_views and bench_pinhole included), random paper-phantom
cases (``--phantom-seed``, ``--phantoms``) and paper-protocol cases (``--paper-seed``,
``--papers``: states of one phantom, right frames only), and right frames of random phantoms
deformed ``--large-scale`` times the usual (``--large``). Image-only right cases (the frame an
image to be segmented, no mask) when asked for: the scenario kind ``image_only``
(``--scenario-kinds image_only``: ``ct.nrrd`` + 16-bit ``fluoro.png``; its ``_masks`` twin is
left out) and ``bench_frame_masks.py``'s unsubtracted end-to-end cases (``--bench-frames
SEEDS``: DICOM CT + ``fluoro.dcm``). The paper benchmark
(``fevar-planner benchmark``) calls the registration directly and never meets these gates;
here its cases go through ``plan`` like any case folder. From each right case it writes wrong ones beside it:

* ``swap``: the frame (every view's frame files: ``fluoro_mask.png``, or the image
  ``fluoro.png`` / ``fluoro.dcm`` of an image-only case) of another case with frame files of
  the same names, filed in this folder, with this case's geometry;
* ``swap_geometry``: another case's frame with that case's own geometry (a whole frame of
  another patient);
* ``mirror``: this case's frame flipped left-right (the wrong side convention; a DICOM frame
  rewritten with its pixel data flipped and every tag kept);
* ``mirror_first_view`` / ``mirror_other_view`` (not built unless asked for; cases with
  several views only): the first view's frame / the last view's alone flipped left-right;
* ``angle``: this case's frame with the geometry of a view 40 degrees away (LAO 40 labelled as
  the given view: the projection rotated about the patient's long axis through the tree);
* ``late``: this case's frame taken after the bolus, the renal arteries gone (their pixels,
  those nearest to the true projection of the renal nodes, erased); mask cases only (an
  image's renals would have to be painted over with background, not built).

Each folder runs through ``pipeline.plan_case`` (the CLI's route, proposed method). A refusal
is a :class:`files.InputError` (exit code 2 in the CLI). Reported per kind: the refusal rate,
how many answers carry a registration warning (and which answers carry none: case, 3D error), and for the answers given the 3D error against the truth of the CT's own deformation
(``gt.json`` of the case whose CT it is). Right frames refused are false refusals.

Outputs in ``--out``: ``wrong_frames.json`` (every run with its message and the gate's
numbers), ``wrong_frames.png`` (refusal rate per kind) and the case folders under ``cases/``.

    .venv/bin/python Testing/benchmarks/bench_wrong_frames.py --out OUT [--scenario-seeds 0 1] [--phantom-seed 7]
        [--phantoms 4] [--paper-seed 3] [--papers 4]
    # one view of several mirrored, every two-view case of the seeds:
    .venv/bin/python Testing/benchmarks/bench_wrong_frames.py --out OUT --scenario-seeds 125 126 \
        --scenario-kinds two_views --all-cases --phantoms 0 --papers 0 \
        --wrong-kinds mirror_first_view mirror_other_view
    # image-only right cases (scenario kind image_only, bench frames 241-249):
    .venv/bin/python Testing/benchmarks/bench_wrong_frames.py --out OUT --scenario-seeds 300 0 \
        --scenario-kinds image_only --phantoms 0 --papers 0 --bench-frames 241 242 243
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

from common import argument_parser, single_threaded_blas

single_threaded_blas()

import numpy as np  # noqa: E402  (after the BLAS threads are set)

WRONG_KINDS = ("swap", "swap_geometry", "mirror", "angle", "late")
#: Wrong kinds built only when asked for (``--wrong-kinds``), from cases with several views.
VIEW_KINDS = ("mirror_first_view", "mirror_other_view")
#: The angle kind: the given geometry is that of a view this far (degrees) about the patient's long axis.
ANGLE_DEG = 40.0
RENALS = ("renal_left", "renal_right")
#: The case inputs (``io.CASE_INPUTS``) that are frame files.
FRAME_INPUTS = ("fluoro", "fluoro_mask")
#: Kinds of right case that get no wrong frames built from them.
RIGHT_ONLY = ("paper", "large")


def right_case_folders(root: Path, scenario_seeds, phantom_seed: int | None, n_phantoms: int,
                       paper_seed: int | None = None, n_papers: int = 0, scenario_kinds=None,
                       all_cases: bool = False) -> list:
    """Write (or reuse) the right cases; ``[(family, kind, folder)]``. Paper-protocol phantoms
    (kind ``paper``: several intra-operative states of one phantom) are right frames only.
    Scenario cases: one per kind of ``scenario_kinds`` (default: the quick sets' kinds), or
    every case of each kind with ``all_cases``."""
    from FevarPlannerLib.benchmark.independent import independent_case_folders
    from FevarPlannerLib.phantom import write_phantom_set

    cases = []
    for seed in scenario_seeds:
        for kind, folder in independent_case_folders(root / f"scenarios_seed{seed}", quick=not all_cases, seed=seed,
                                                     kinds=scenario_kinds):
            if kind != "image_only_masks":      # the image_only kind's mask twin: its images are the point
                cases.append((f"scenarios_seed{seed}", kind, Path(folder)))
    if phantom_seed is not None and n_phantoms > 0:
        where = root / f"phantom_seed{phantom_seed}"
        folders = sorted(where.glob("*/gt.json"))
        if len(folders) < n_phantoms:
            write_phantom_set(where, n=n_phantoms, seed=phantom_seed, preset="random", mask_only=True)
        for folder in sorted(p for p in where.iterdir() if (p / "gt.json").is_file())[:n_phantoms]:
            cases.append((f"phantom_seed{phantom_seed}", "phantom", folder))
    if paper_seed is not None and n_papers > 0:
        where = root / f"paper_seed{paper_seed}"
        if len(list(where.glob("*/gt.json"))) < n_papers:
            write_phantom_set(where, n=n_papers, seed=paper_seed, preset="paper", mask_only=True)
        for folder in sorted(p for p in where.iterdir() if (p / "gt.json").is_file())[:n_papers]:
            cases.append((f"paper_seed{paper_seed}", "paper", folder))
    return cases


def bench_frame_folders(root: Path, seeds) -> list:
    """Image-only right cases of ``bench_frame_masks.py --end-to-end``: each seed's bench phantom
    with its unsubtracted ``every`` frame as ``fluoro.dcm`` and its CT, no mask (the case written
    by ``bench_frame_masks.write_end_to_end_case``, cut to ``bench_image_only``'s ``image_only``
    route); ``[("bench_frames", "bench_unsubtracted", folder)]``."""
    from bench_frame_masks import write_end_to_end_case
    from bench_image_only import route_folder

    cases = []
    for seed in seeds:
        folder = root / "bench_frames" / "image_only" / f"bench_{seed}"
        if not (folder / "gt.json").is_file():
            full = write_end_to_end_case(seed, root / "bench_frames")
            folder = route_folder(full, "image_only", root / "bench_frames")
        cases.append(("bench_frames", "bench_unsubtracted", folder))
    return cases


def large_deformation_folders(root: Path, first_seed: int, n: int, scale: float) -> list:
    """Right frames of random phantoms whose deformation is ``scale`` times the usual (the
    authors' real phantom pair moves about 9 mm, twice our sets); ``[(family, "large", folder)]``."""
    from dataclasses import replace

    from FevarPlannerLib import phantom

    family = f"large_x{scale:g}_seed{first_seed}"
    cases = []
    for seed in range(first_seed, first_seed + n):
        folder = root / family / f"case_{seed}"
        if not (folder / "gt.json").is_file():
            params = replace(phantom.random_params(np.random.default_rng(seed)), deformation_scale=scale)
            phantom.write_case(phantom.generate_case(params, name=folder.name), folder, mask_only=True)
        cases.append((family, "large", folder))
    return cases


def _frame_files(where: Path) -> list:
    """The frame files of one view's folder, as the case reader finds them: the image
    (``fluoro.dcm``, ``fluoro.png`` ...) and / or the mask (``fluoro_mask.png``)."""
    from FevarPlannerLib.io import CASE_INPUTS, find_case_file

    found = (find_case_file(where, *CASE_INPUTS[name]) for name in FRAME_INPUTS)
    return [path for path in found if path is not None]


def _frame_folders(case: Path) -> dict:
    """View name -> the folder holding that view's frame files (``main``: the case folder)."""
    found = {"main": case}
    views = case / "views"
    if views.is_dir():
        found.update({p.name: p for p in sorted(views.iterdir()) if p.is_dir() and _frame_files(p)})
    return found


def image_only(case: Path) -> bool:
    """True when the case's frame is an image to be segmented (no ``fluoro_mask`` given)."""
    names = [path.name for path in _frame_files(case)]
    return bool(names) and not any(name.startswith("fluoro_mask") for name in names)


def _frame_signature(case: Path) -> tuple:
    """The names of the case's frame files: frames are swapped only between cases alike."""
    return tuple(path.name for path in _frame_files(case))


def _truth(case: Path) -> dict:
    return json.loads((case / "gt.json").read_text())


def _true_P(truth: dict, view: str) -> np.ndarray:
    if view != "main" and "views" in truth:
        return np.asarray(truth["views"][view]["projection_matrix_true"], dtype=float)
    return np.asarray(truth["projection_matrix_true"], dtype=float)


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image).copy()


def _write_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(array).save(path)


def flip_dicom(path: Path) -> None:
    """Rewrite a DICOM frame file with every frame flipped left-right, every tag kept
    (uncompressed transfer syntaxes only)."""
    import pydicom

    dataset = pydicom.dcmread(path)
    if dataset.file_meta.TransferSyntaxUID.is_compressed:
        raise ValueError(f"{path}: compressed pixel data ({dataset.file_meta.TransferSyntaxUID.name}), not flipped")
    pixels = dataset.pixel_array
    dataset.PixelData = np.ascontiguousarray(pixels[..., ::-1]).tobytes()
    dataset.save_as(path)


def flip_frame_file(path: Path) -> None:
    """Flip a frame file left-right in place, in its own format: DICOM (tags kept) or a raster
    image (mode and bit depth kept; a JPEG is re-encoded)."""
    from PIL import Image

    from FevarPlannerLib.io import DICOM_SUFFIXES

    if path.suffix.lower() in DICOM_SUFFIXES:
        flip_dicom(path)
        return
    with Image.open(path) as image:
        flipped = image.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
    flipped.save(path)


def _copy_case(source: Path, target: Path) -> Path:
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(source, target)
    return target


def _swapped(case: Path, other: Path, target: Path, with_geometry: bool) -> Path:
    """``case`` with ``other``'s frames (and geometry when ``with_geometry``); a view ``other``
    lacks is dropped."""
    folder = _copy_case(case, target)
    theirs = _frame_folders(other)
    for name, where in _frame_folders(folder).items():
        if name not in theirs:
            shutil.rmtree(where)
            continue
        for mine in _frame_files(where):
            mine.unlink()
        for frame in _frame_files(theirs[name]):
            shutil.copy2(frame, where / frame.name)
        if with_geometry:
            shutil.copy2(theirs[name] / "geometry.json", where / "geometry.json")
    return folder


def _mirrored(case: Path, target: Path, views=None) -> Path:
    """``case`` with the frames of ``views`` (names; default every view) flipped left-right: every
    frame file of the view (mask and / or image, DICOM with its tags kept)."""
    folder = _copy_case(case, target)
    for name, where in _frame_folders(folder).items():
        if views is None or name in views:
            for frame in _frame_files(where):
                flip_frame_file(frame)
    return folder


def _rotation_about_long_axis(P: np.ndarray, centre: np.ndarray, degrees: float) -> np.ndarray:
    """``P`` of a C-arm turned by ``degrees`` about the LPS z axis through ``centre``."""
    a = np.radians(degrees)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    move = np.eye(4)
    move[:3, :3] = R
    move[:3, 3] = centre - R @ centre
    return np.asarray(P, dtype=float) @ move


def _angled(case: Path, target: Path, degrees: float = ANGLE_DEG) -> Path:
    folder = _copy_case(case, target)
    centre = np.asarray(_truth(case)["preop_centerline"]["points"], dtype=float).mean(axis=0)
    geometry_path = folder / "geometry.json"
    geometry = json.loads(geometry_path.read_text())
    geometry["projection_matrix"] = _rotation_about_long_axis(geometry["projection_matrix"], centre, degrees).tolist()
    geometry_path.write_text(json.dumps(geometry))
    return folder


def _late(case: Path, target: Path) -> Path:
    """The frame with every pixel nearest to a renal node of the true projected tree erased."""
    from scipy.spatial import cKDTree

    from FevarPlannerLib.projection import project

    folder = _copy_case(case, target)
    truth = _truth(case)
    intra = truth["intraop_centerline"]
    points, labels = np.asarray(intra["points"], dtype=float), np.asarray(intra["labels"])
    for name, where in _frame_folders(folder).items():
        mask = _read_png(where / "fluoro_mask.png")
        vessel = (mask if mask.ndim == 2 else mask[..., 0]) > 0
        rows, cols = np.nonzero(vessel)
        _, nearest = cKDTree(project(_true_P(truth, name), points)).query(np.c_[cols, rows])
        renal = np.isin(labels[nearest], RENALS)
        mask[rows[renal], cols[renal]] = 0
        _write_png(where / "fluoro_mask.png", mask)
    return folder


def wrong_case_folders(rights: list, root: Path, kinds=WRONG_KINDS) -> list:
    """Every wrong kind of every right case; ``[(family, wrong kind, folder, right folder)]``.

    The frame swapped in comes from the next right case of the list whose frame files have the
    same names (another anatomy: each scenario kind and each random phantom draws its own tree;
    a mask for a mask, a DICOM for a DICOM); paper-protocol cases (states of one phantom) and
    large-deformation phantoms take no part. Image-only cases get no ``late`` kind (the renals
    are erased from a mask; an image would need them painted over)."""
    made = []
    sources = [right for right in rights if right[1] not in RIGHT_ONLY]
    for n, (family, kind, case) in enumerate(sources):
        alike = [right for right in sources[n + 1:] + sources[:n + 1]
                 if _frame_signature(right[2]) == _frame_signature(case)]
        other = alike[0][2]        # the case itself when none is alike: no swap kinds then
        base = root / family / case.name
        views = list(_frame_folders(case))
        builders = {"swap": lambda t: _swapped(case, other, t, False),
                    "swap_geometry": lambda t: _swapped(case, other, t, True),
                    "mirror": lambda t: _mirrored(case, t), "angle": lambda t: _angled(case, t),
                    "late": lambda t: _late(case, t),
                    "mirror_first_view": lambda t: _mirrored(case, t, views[:1]),
                    "mirror_other_view": lambda t: _mirrored(case, t, views[-1:])}
        for wrong in kinds:
            if ((wrong in VIEW_KINDS and len(views) < 2) or (wrong == "late" and image_only(case))
                    or (wrong.startswith("swap") and other == case)):
                continue
            made.append((family, wrong, builders[wrong](base / wrong), case))
    return made


#: Which gate a refusal came from, by the words of its message.
GATES = (("registration check", "registration check (issue 11)"), ("frame check", "frame check"),
         ("no usable vessel tree", "vessel-tree check"),
         ("implausible registration", "length / node-shift check"))


def _gate_of(message: str) -> str:
    return next((name for words, name in GATES if words in message), "other")


def run_plan(folder: Path) -> dict:
    """``plan_case`` on a folder: refused (the message) or answered (3D error, the gate's numbers)."""
    from FevarPlannerLib import plausibility
    from FevarPlannerLib.files import InputError
    from FevarPlannerLib.pipeline import plan_case, workers

    previous = workers.set_enabled(False)
    t0 = time.perf_counter()
    try:
        result = plan_case(folder, None, method="proposed")
    except InputError as exc:
        message = str(exc).splitlines()[0]
        return {"refused": True, "message": message, "gate": _gate_of(message), "wall_s": time.perf_counter() - t0}
    finally:
        workers.set_enabled(previous)
    errors = result.errors or {}
    row = {"refused": False, "wall_s": time.perf_counter() - t0,
           "3d_mm": (errors.get("3d_mm") or {}).get("mean"), "2d_px": (errors.get("2d_px") or {}).get("mean"),
           "warnings": [note for note in result.warnings if note.startswith("registration check")]}
    signals = getattr(plausibility, "registration_signals", None)     # absent before issue 11: a baseline run
    if signals is not None:
        cpu = time.process_time()
        row["signals"] = signals(result.preop, result.deformed, result.P, result.skeleton2d_points,
                                 result.skeleton2d_edges, np.shape(result.fluoro_image))
        row["gate_cpu_ms"] = 1000.0 * (time.process_time() - cpu)      # the gate's numbers, once, warm
    return row


def _rate(rows: list) -> dict:
    refused = sum(r["refused"] for r in rows)
    answered = [r["3d_mm"] for r in rows if not r["refused"] and r.get("3d_mm") is not None]
    gates = {}
    for r in rows:
        if r["refused"]:
            gates[r["gate"]] = gates.get(r["gate"], 0) + 1
    warned = sum(bool(r.get("warnings")) for r in rows if not r["refused"])
    silent = [r for r in rows if not r["refused"] and not r.get("warnings")]
    return {"runs": len(rows), "refused": refused, "refusal_rate": refused / max(len(rows), 1), "by_gate": gates,
            "answered_with_registration_warning": warned,
            "answered_without_warning": [(r["case"], r.get("3d_mm")) for r in silent],
            "answered_3d_mm_median": float(np.median(answered)) if answered else None,
            "answered_3d_mm_max": float(np.max(answered)) if answered else None}


def summarise(runs: list) -> dict:
    """Refusal rate per wrong kind (all, per family, and of the cases whose right frame was
    answered) and per family of right frames (false refusals)."""
    summary = {"wrong": {}, "wrong_by_family": {}, "wrong_right_answered": {}, "right": {}}
    for kind in WRONG_KINDS + VIEW_KINDS:
        if any(r["kind"] == kind for r in runs):
            summary["wrong"][kind] = _rate([r for r in runs if r["kind"] == kind])
            summary["wrong_by_family"][kind] = {
                family: _rate([r for r in runs if r["kind"] == kind and r["family"] == family])
                for family in sorted({r["family"] for r in runs if r["kind"] == kind})}
    right = [r for r in runs if r["kind"] == "right"]
    # a wrong frame of a case whose right frame is refused too (its CT, say) says nothing of the gates
    refused_rights = {(r["family"], r["case"]) for r in right if r["refused"]}
    for kind in summary["wrong"]:
        summary["wrong_right_answered"][kind] = _rate([r for r in runs if r["kind"] == kind
                                                       and (r["family"], r["case"]) not in refused_rights])
    for family in sorted({r["family"] for r in right}):
        summary["right"][family] = _rate([r for r in right if r["family"] == family])
    summary["right"]["all"] = _rate(right)
    summary["right"]["refused"] = [(r["family"], r["case"], r["message"]) for r in right if r["refused"]]
    costs = [r["gate_cpu_ms"] for r in runs if "gate_cpu_ms" in r]
    summary["gate_cpu_ms_median"] = float(np.median(costs)) if costs else None
    return summary


def figure(path: Path, summary: dict) -> None:
    from common import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.6))
    names = list(summary["wrong"]) + ["right: " + f for f in summary["right"] if f not in ("all", "refused")]
    rates = [summary["wrong"][k]["refusal_rate"] for k in summary["wrong"]] + \
            [summary["right"][f]["refusal_rate"] for f in summary["right"] if f not in ("all", "refused")]
    colours = ["tab:green"] * len(summary["wrong"]) + ["tab:red"] * (len(names) - len(summary["wrong"]))
    ax.bar(range(len(names)), rates, color=colours)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("refused (exit 2)")
    ax.set_title("Wrong frames refused (green: higher is better); right frames refused (red: false refusals)",
                 fontsize=9)
    save_figure(fig, path)


def main(argv=None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--scenario-seeds", type=int, nargs="*", default=[0])
    parser.add_argument("--phantom-seed", type=int, default=7)
    parser.add_argument("--phantoms", type=int, default=4)
    parser.add_argument("--paper-seed", type=int, default=3, help="paper-protocol phantoms (right frames only)")
    parser.add_argument("--papers", type=int, default=4)
    parser.add_argument("--scenario-kinds", nargs="*", default=None,
                        help="scenario kinds of the right cases (default: every quick-set kind)")
    parser.add_argument("--all-cases", action="store_true", help="every scenario case of each kind, not one")
    parser.add_argument("--wrong-kinds", nargs="*", choices=WRONG_KINDS + VIEW_KINDS, default=list(WRONG_KINDS),
                        help="wrong kinds to build (none: right frames only)")
    parser.add_argument("--large", type=int, default=0,
                        help="right frames of this many random phantoms with a larger deformation")
    parser.add_argument("--large-seed", type=int, default=600)
    parser.add_argument("--large-scale", type=float, default=2.0, help="their deformation_scale")
    parser.add_argument("--bench-frames", type=int, nargs="*", default=[], metavar="SEED",
                        help="image-only right cases: bench_frame_masks.py's unsubtracted end-to-end cases of these seeds")
    parser.add_argument("--cases", type=Path, default=None, help="where the case folders go (default OUT/cases)")
    args = parser.parse_args(argv)
    cases = args.cases or args.out / "cases"
    started = time.perf_counter()
    rights = right_case_folders(cases / "right", args.scenario_seeds, args.phantom_seed, args.phantoms,
                                args.paper_seed, args.papers, args.scenario_kinds, args.all_cases)
    if args.bench_frames:
        rights += bench_frame_folders(cases / "right", args.bench_frames)
    if args.large:
        rights += large_deformation_folders(cases / "right", args.large_seed, args.large, args.large_scale)
    wrongs = wrong_case_folders(rights, cases / "wrong", args.wrong_kinds)
    runs = []
    jobs = [(family, "right", folder, folder) for family, _, folder in rights] + wrongs
    for n, (family, kind, folder, origin) in enumerate(jobs):
        row = {"family": family, "kind": kind, "case": origin.name, "folder": str(folder)} | run_plan(folder)
        runs.append(row)
        print(f"[{n + 1}/{len(jobs)}] {family} {origin.name} {kind}: "
              f"{'REFUSED ' + row['message'][:150] if row['refused'] else 'answered 3D %.1f mm' % (row['3d_mm'] or -1)}",
              file=sys.stderr, flush=True)
    summary = summarise(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"version": 1, "scenario_seeds": args.scenario_seeds, "phantom_seed": args.phantom_seed,
              "bench_frames": args.bench_frames,
              "wall_s": time.perf_counter() - started, "summary": summary, "runs": runs}
    (args.out / "wrong_frames.json").write_text(json.dumps(report, indent=1))
    figure(args.out / "wrong_frames.png", summary)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

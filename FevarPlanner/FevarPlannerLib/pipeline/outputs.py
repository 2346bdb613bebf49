"""The output set of a case (result.json, centreline .vtp, path markups, overlay and QC
pictures), written to a staging folder and swapped in whole (:func:`write_outputs`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from .. import export, quality
from ..conventions import PALETTE
from ..files import InputError, atomic_folder, display_path, output_mode, staging_folder, swap_folder
from ..projection import view_label
from .results import PlanResult


def picture_title(result: PlanResult) -> str:
    """The caption of the pictures: method, view angles, and the 2D number named for what it is.

    Without ground truth the 2D number is the fit to the frame's own skeleton, not an error.
    """
    tags = (result.geometry or {}).get("tags", {})
    if "PositionerPrimaryAngle" in tags:
        view = f"{view_label(tags['PositionerPrimaryAngle'], tags['PositionerSecondaryAngle'])} (tags)"
    else:
        view = f"{export.view_name(result.P, result.deformed.points.mean(axis=0))} (from P)"
    errors = result.errors or {}
    text = f"{result.method} | {view}"
    if errors.get("2d_px"):
        mean = errors["2d_px"]["mean"]
        if errors.get("3d_mm"):
            text += f" | 2D error {mean:.2f} px, 3D error {errors['3d_mm']['mean']:.2f} mm (vs. truth)"
        else:
            text += f" | fit to the frame's own skeleton {mean:.2f} px"
    return text


#: The files :func:`write_outputs` writes (``segmentation_qc.png`` when the segmentation QC
#: ran); a folder holding only these, or a ``result.json``, or nothing may be replaced.
OUTPUT_NAMES = ("deformed_centerline.vtp", "path.mrk.json", "overlay.png", "result.json")
QC_NAME = "segmentation_qc.png"
DRR_NAME = "drr_check.png"


def _write_failure_qc(out_dir: Path, failure) -> Path:
    """The QC picture of a failed segmentation gate, without touching a previous output set.

    A new or empty output folder gets it as its only file (swapped in whole); a folder that
    holds a previous set keeps it unchanged and the picture goes beside it, as
    ``<out>.segmentation_qc.png``. Returns the picture's path.
    """
    if os.path.isdir(out_dir) and os.listdir(out_dir):
        beside = out_dir.parent / f"{out_dir.name}.{QC_NAME}"
        quality.write_segmentation_qc(beside, failure.qc, str(failure))
        failure.args = (str(failure).replace(f"see {QC_NAME}", f"see {display_path(beside)}"),)
        return beside
    with atomic_folder(out_dir) as staging:
        quality.write_segmentation_qc(staging / QC_NAME, failure.qc, str(failure))
    return out_dir / QC_NAME


def refusal_picture(failure: Exception, out_dir=None) -> Path | None:
    """Write the QC picture of a refused plan, so that a front end can show why; its path.

    ``failure`` is what a gate raised: a :class:`quality.QualityError` carries the picture's
    data, anything else has none (``None`` is returned). With ``out_dir`` the picture goes
    where ``plan --out`` puts it (:func:`_write_failure_qc`); without, into a new temporary
    folder. The message's "see segmentation_qc.png" then names the written file in full.
    """
    if getattr(failure, "qc", None) is None:
        return None
    if out_dir is not None:
        path = _write_failure_qc(Path(out_dir), failure)
    else:
        path = Path(tempfile.mkdtemp(prefix="fevarplanner-refused-")) / QC_NAME
        quality.write_segmentation_qc(path, failure.qc, str(failure))
    failure.args = (str(failure).replace(f"see {QC_NAME}", f"see {display_path(path)}"),)
    return path


def check_output_folder(out_dir, folders=(), files=()) -> Path:
    """Refuse an output folder that would overwrite or mix with something else, before any work.

    Refused: ``out_dir`` equal to, inside or containing an input (the case folder or any
    input file's folder); an existing file or special file in its place; a folder that
    holds anything but a previous output set (a ``result.json``) or nothing.
    """
    out = Path(out_dir)
    shown = display_path(out)
    if str(out).strip() == "":
        raise InputError("--out: empty path")
    try:
        str(out).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{shown}: the output folder's name is not valid UTF-8 (the writers cannot take it); "
                         f"choose another name") from None
    target = Path(os.path.realpath(out))
    inputs = [(Path(f), Path(f)) for f in folders] + [(Path(f), Path(f) if Path(f).is_dir() else Path(f).parent)
                                                      for f in files]
    for given, folder in inputs:
        folder = Path(os.path.realpath(folder))
        if target == folder:
            relation = "is the folder of"
        elif folder in target.parents:
            relation = "lies inside the folder of"
        elif target in folder.parents:
            relation = "contains"
        else:
            continue
        raise InputError(f"{shown}: the output folder {relation} the input {display_path(given)}; choose a folder "
                         f"apart from the inputs")
    if os.path.lexists(out):
        if not out.is_dir():
            raise InputError(f"{shown}: exists and is not a folder")
        entries = sorted(os.listdir(out))
        foreign = [name for name in entries if not _looks_like_an_output(out / name)]
        if entries and "result.json" not in entries and not set(entries) <= set(OUTPUT_NAMES + (QC_NAME, DRR_NAME)):
            foreign = entries
        if foreign:
            raise InputError(f"{shown}: the folder holds files that are not a FevarPlanner output set "
                             f"({', '.join(display_path(n) for n in foreign[:3])}{', ...' if len(foreign) > 3 else ''})"
                             f", which replacing the set would delete; choose a new or empty folder")
    elif not out.parent.is_dir() and out.parent.exists():
        raise InputError(f"{shown}: its parent {display_path(out.parent)} is not a folder")
    return out


#: Suffixes of the files an output set is made of; anything else in an output folder (a
#: subfolder, notes) was put there by someone else and is not deleted by a new set.
OUTPUT_SUFFIXES = (".vtp", ".json", ".png", ".csv")


def _looks_like_an_output(path: Path) -> bool:
    return path.is_file() and not path.is_symlink() and path.suffix in OUTPUT_SUFFIXES


def _write_output_set(result: PlanResult, folder: Path) -> dict:
    paths = {name: folder / name for name in OUTPUT_NAMES}
    export.write_centerline_vtp(paths["deformed_centerline.vtp"], result.deformed)
    export.write_path_markups(paths["path.mrk.json"], result.path.points)
    colors, names = PALETTE, export.ROLE_NAMES
    layers = [
        export.centerline_layer(f"{names['preop']} (projected)", result.P, result.preop, colors["preop"]),
        export.centerline_layer(f"{names['recovered']} (projected)", result.P, result.deformed, colors["recovered"]),
        export.path_layer(names["path"], result.P, result.path.points, colors["path"]),
    ]
    export.render_overlay(paths["overlay.png"], result.fluoro_image, skeleton2d=result.skeleton2d_points,
                          layers=layers, title=picture_title(result), P=result.P,
                          anchor=result.deformed.points.mean(axis=0), warnings=result.warnings)
    if result.qc is not None:
        paths[QC_NAME] = folder / QC_NAME
        quality.write_segmentation_qc(paths[QC_NAME], result.qc)
    if result.drr is not None:
        from .. import drr

        paths[DRR_NAME] = folder / DRR_NAME
        notes = (result.geometry or {}).get("assumptions", [])
        drr.write_drr_check(paths[DRR_NAME], result.fluoro_image, result.drr,
                            title=f"geometry check, {picture_title(result)}", notes=notes)
    export.write_result_json(paths["result.json"], result.to_dict())
    return paths


def write_outputs(result: PlanResult, out_dir, extra=None) -> dict:
    """Write result.json, deformed_centerline.vtp, path.mrk.json and overlay.png into ``out_dir``.

    The whole set is written into a temporary folder beside ``out_dir`` and swapped in at
    the end (:func:`swap_folder`): until then a previous set stays as it was, and a
    failure (a full disk) or a killed process never leaves a half-written or mixed folder.
    Files and the folder get the modes the umask gives new ones. ``extra(folder)``, if
    given, writes further files of the same set into the staging folder and returns their
    paths. Returns the final paths.
    """
    out_dir = Path(out_dir)
    check_output_folder(out_dir)
    staging = staging_folder(out_dir, "writing")
    try:
        os.chmod(staging, output_mode(folder=True))
        written = _write_output_set(result, staging)
        if extra is not None:
            written.update(extra(staging))
        swap_folder(staging, out_dir)
    except OSError as exc:
        where = display_path(exc.filename) if exc.filename else display_path(out_dir)
        raise InputError(f"{where}: cannot write the outputs ({exc.strerror or exc}); {display_path(out_dir)} "
                         f"was left as it was") from None
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return {name: out_dir / path.name for name, path in written.items()}

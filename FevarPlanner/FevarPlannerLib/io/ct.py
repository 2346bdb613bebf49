"""Reading a CT (a DICOM series folder or a volume file) and 3D masks.

A DICOM folder is scanned header by header in Python (modality, units, foreign files,
several series, slice geometry) before any pixel is decoded.
"""

from __future__ import annotations

import os
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk

from ..files import InputError, InputWarning, check_inside, check_readable, display_path
from .dicom_header import _header_vector, _is_dicom_file, _tag_int, _tag_number, _tag_text
from .volume import Volume, _last_line, max_voxels, read_volume


def read_ct(path) -> Volume:
    """Read a CT from a DICOM series folder or an NRRD / NIfTI / MHA file.

    A folder holding several series gives the one with the most slices (with a warning
    naming the folder and the series UIDs). Missing slices, uneven slice spacing, sheared
    (gantry-tilted) stacks or mixed slice sizes raise :class:`InputError` naming the folder.
    """
    path = Path(path)
    check_readable(path)
    if path.is_dir():
        return _read_dicom_series(path)
    if _is_dicom_file(path):
        raise InputError(f"{path}: a single DICOM file; give the folder holding the CT series")
    volume = read_volume(path)
    if min(volume.shape) < 2:
        raise InputError(f"{path}: volume of shape {tuple(volume.shape)} is not 3D (a single slice?)")
    return volume


def _read_dicom_series(folder: Path) -> Volume:
    slices, series_uid, ignored = _pick_dicom_series(folder)
    _check_slice_geometry(folder, slices, series_uid, ignored)
    files = [item.file for item in slices]
    rows, cols = _tag_int(slices[0].header, "Rows", slices[0].file), _tag_int(slices[0].header, "Columns",
                                                                                slices[0].file)
    if rows * cols * len(files) > max_voxels():
        raise InputError(f"{display_path(folder)}: CT series of {cols} x {rows} x {len(files)} voxels exceeds the "
                         f"limit of {max_voxels()} voxels (set FEVAR_MAX_VOXELS to raise it)")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(f) for f in files])
    try:
        image = reader.Execute()
    except RuntimeError as exc:
        raise InputError(f"{display_path(folder)}: cannot read DICOM series {series_uid} ({_last_line(exc)})") from None
    volume = Volume.from_sitk(image)
    from ..plausibility import check_grid

    check_grid(folder, volume.spacing, volume.origin, volume.direction.ravel())
    return volume


@dataclass
class _Slice:
    file: Path
    header: pydicom.Dataset


#: Header fields read from every file of a CT folder (pixels are not read).
SLICE_TAGS = ["SOPClassUID", "SOPInstanceUID", "SeriesInstanceUID", "SeriesDescription", "Modality",
              "ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "Rows", "Columns",
              "BitsAllocated", "SamplesPerPixel", "RescaleSlope", "RescaleIntercept", "NumberOfFrames"]
#: Transfer syntaxes whose pixel data is stored uncompressed (its size is known from the header).
_NATIVE_SYNTAXES = {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.2"}


def _scan_entry(folder: Path, entry: os.DirEntry) -> tuple[_Slice | None, str | None]:
    """One entry of a CT folder: a slice, or None and why it is ignored. Corrupt DICOM raises."""
    path = folder / entry.name
    shown = display_path(entry.name)
    try:
        info = os.stat(path)
    except OSError:
        return None, f"{shown} (a broken link)"
    if stat.S_ISDIR(info.st_mode):
        return None, f"{shown}/ (a folder)"
    if not stat.S_ISREG(info.st_mode):
        return None, f"{shown} ({_special_kind(info.st_mode) or 'not a file'}, not opened)"
    check_inside(path, folder, "the CT folder")
    if info.st_size == 0:
        return None, f"{shown} (empty, 0 bytes)"
    with open(path, "rb") as handle:
        magic = handle.read(132)[128:132]
    if magic != b"DICM":
        return None, f"{shown} (not DICOM)"
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{display_path(path)}: a DICOM file whose name is not valid UTF-8 (the DICOM reader "
                         f"cannot open it); rename it") from None
    try:
        header = pydicom.dcmread(path, stop_before_pixels=True, specific_tags=SLICE_TAGS)
    except Exception as exc:  # any parser failure of a file that says it is DICOM: corrupt
        raise InputError(f"{display_path(path)}: corrupt DICOM file ({_last_line(exc)})") from None
    if "SOPClassUID" not in header and "Modality" not in header:
        raise InputError(f"{display_path(path)}: corrupt DICOM file (no SOP class or modality in its header)")
    if "Rows" not in header or "ImagePositionPatient" not in header:
        what = _tag_text(header, "Modality") or "no image"
        return None, f"{shown} (not an image slice: Modality {what})"
    _check_pixel_bytes(path, header, info.st_size)
    return _Slice(path, header), None


def _check_pixel_bytes(path: Path, header: pydicom.Dataset, size: int) -> None:
    """Refuse an uncompressed slice too short to hold its own pixels (a truncated file)."""
    syntax = str(getattr(header.file_meta, "TransferSyntaxUID", "")) if hasattr(header, "file_meta") else ""
    if syntax not in _NATIVE_SYNTAXES:
        return
    need = (_tag_int(header, "Rows", path) * _tag_int(header, "Columns", path)
            * _tag_int(header, "SamplesPerPixel", path, default=1) * _tag_int(header, "NumberOfFrames", path, default=1)
            * _tag_int(header, "BitsAllocated", path, default=16) // 8)
    if size < need:
        raise InputError(f"{display_path(path)}: truncated DICOM slice ({size} bytes, its pixel data alone "
                         f"needs {need})")


def _pick_dicom_series(folder: Path) -> tuple[list[_Slice], str, list[str]]:
    """The slices of the longest image series in ``folder``, the series UID and the ignored files.

    Only regular files are opened, and only their headers. Files that are not DICOM images
    (notes, ``.DS_Store``, structured reports) are ignored with an :class:`InputWarning`;
    so is a second series, naming the one chosen.
    """
    try:
        entries = sorted(os.scandir(folder), key=lambda e: os.fsencode(e.name))
    except OSError as exc:
        raise InputError(f"{display_path(folder)}: cannot list the folder ({exc.strerror})") from None
    series: dict[str, list[_Slice]] = {}
    ignored = []
    for entry in entries:
        item, reason = _scan_entry(folder, entry)
        if item is None:
            ignored.append(reason)
        else:
            series.setdefault(_tag_text(item.header, "SeriesInstanceUID"), []).append(item)
    if not series:
        raise InputError(f"{display_path(folder)}: no DICOM series found in the folder"
                         + (f" (it holds {_listing(ignored)})" if ignored else " (it is empty)"))
    chosen = max(sorted(series), key=lambda uid: len(series[uid]))
    if ignored:
        warnings.warn(f"{display_path(folder)}: ignored {len(ignored)} file(s) that are not CT slices: "
                      f"{_listing(ignored)}", InputWarning, stacklevel=3)
    if len(series) > 1:
        others = ", ".join(f"{uid} ({len(series[uid])} slices, {_describe(series[uid])})"
                           for uid in sorted(series) if uid != chosen)
        warnings.warn(f"{display_path(folder)}: {len(series)} DICOM series found; using {chosen} "
                      f"({len(series[chosen])} slices, {_describe(series[chosen])}), the one with most slices, "
                      f"and ignoring {others}; if the CT is another one, put it in a folder of its own "
                      f"and pass that with --ct", InputWarning, stacklevel=3)
    _check_modality_and_units(series[chosen])
    return series[chosen], chosen, ignored


def _listing(items, limit: int = 5) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f" and {len(items) - limit} more" if len(items) > limit else "")


def _describe(slices: list[_Slice]) -> str:
    header = slices[0].header
    return f"{_tag_text(header, 'Modality') or 'no modality'} '{_tag_text(header, 'SeriesDescription')}'"


def _check_modality_and_units(slices: list[_Slice]) -> None:
    """Every slice says CT and carries a finite, non-zero rescale (HU = slope * stored + intercept)."""
    for item in slices:
        modality = _tag_text(item.header, "Modality")
        if modality != "CT":
            raise InputError(f"{display_path(item.file)}: Modality (0008,0060) is {modality or 'empty'!r}; the CT "
                             f"series must be a CT (HU values)")
        slope = _tag_number(item.header, "RescaleSlope", item.file, default=1.0)
        _tag_number(item.header, "RescaleIntercept", item.file, default=0.0)
        if slope == 0:
            raise InputError(f"{display_path(item.file)}: DICOM tag RescaleSlope (0028,1053) is 0 (every HU value "
                             f"would be the intercept)")


def _check_slice_geometry(folder: Path, slices: list[_Slice], series_uid: str, ignored=()) -> None:
    """Refuse series whose slices do not form one regular grid; sort ``slices`` along the normal.

    Missing, uneven, duplicate and sheared slices are named; files the scan ignored (empty
    or not DICOM) are listed with a missing-slice error, as they may be the missing slices.
    """
    where = display_path(folder)
    if len(slices) < 2:
        raise InputError(f"{where}: DICOM series {series_uid} has only {len(slices)} slice; a CT needs at least 2")
    orientations = np.array([_header_vector(s.header, "ImageOrientationPatient", 6, s.file) for s in slices])
    in_plane = {(_tag_int(s.header, "Rows", s.file), _tag_int(s.header, "Columns", s.file),
                 tuple(np.round(_header_vector(s.header, "PixelSpacing", 2, s.file), 6))) for s in slices}
    for rows, cols, spacing in in_plane:
        if rows < 1 or cols < 1 or min(spacing) <= 0:
            raise InputError(f"{where}: slices of series {series_uid} have {rows}x{cols} pixels of "
                             f"PixelSpacing (0028,0030) {list(spacing)}; both must be positive")
    if np.abs(orientations - orientations[0]).max() > 1e-4:
        raise InputError(f"{where}: slices of series {series_uid} have different orientations")
    if len(in_plane) > 1:
        raise InputError(f"{where}: slices of series {series_uid} differ in size or pixel spacing")
    normal = np.cross(orientations[0, :3], orientations[0, 3:])
    if np.linalg.norm(normal) < 0.5:
        raise InputError(f"{display_path(slices[0].file)}: ImageOrientationPatient (0020,0037) is not two "
                         f"orthogonal unit vectors")
    positions = np.array([_header_vector(s.header, "ImagePositionPatient", 3, s.file) for s in slices])
    order = np.argsort(positions @ normal, kind="stable")
    slices[:] = [slices[i] for i in order]
    positions = positions[order]
    steps = np.diff(positions, axis=0)
    along = steps @ normal
    duplicate = np.flatnonzero(np.abs(along) < 1e-6)
    if len(duplicate):
        first, second = slices[duplicate[0]].file, slices[duplicate[0] + 1].file
        raise InputError(f"{where}: duplicate slices in series {series_uid}: {display_path(first.name)} and "
                         f"{display_path(second.name)} share ImagePositionPatient {positions[duplicate[0]].tolist()}")
    step = float(np.median(along))
    sideways = np.linalg.norm(steps - np.outer(along, normal), axis=1)
    if sideways.max() > max(0.01, 0.01 * step):
        raise InputError(f"{where}: slices of series {series_uid} are sheared (gantry tilt of "
                         f"{np.degrees(np.arctan2(sideways.max(), step)):.2f} deg); resample them first")
    worst = int(np.argmax(np.abs(along - step)))
    if abs(along[worst] - step) > max(0.01, 0.01 * step):
        gap = along[worst]
        problem = "missing slices" if gap > 1.5 * step else "inconsistent slice spacing"
        also = f"; the folder also holds {_listing(list(ignored))}" if ignored and problem == "missing slices" else ""
        raise InputError(f"{where}: {problem} in series {series_uid} ({gap:.4g} mm between slices "
                         f"{worst + 1} and {worst + 2} where the spacing is {step:.4g} mm){also}")


def read_mask(path) -> Volume:
    """Read a binary 3D mask or skeleton (non-zero = foreground) as a bool :class:`Volume`."""
    path = Path(path)
    volume = read_ct(path) if path.is_dir() else read_volume(path)
    mask = volume.array != 0
    if not mask.any():
        raise InputError(f"{path}: no foreground voxels (the mask is empty)")
    if mask.all():
        raise InputError(f"{path}: every voxel is foreground (an inverted or non-binary mask?)")
    return volume.with_array(mask)


def check_same_grid(volume: Volume, reference: Volume, path, reference_name: str = "the CT") -> None:
    """Raise :class:`InputError` unless ``volume`` lies on the grid of ``reference``."""
    same = (volume.shape == reference.shape
            and np.allclose(volume.spacing, reference.spacing, rtol=0, atol=1e-4)
            and np.allclose(volume.origin, reference.origin, rtol=0, atol=1e-3)
            and np.allclose(volume.direction, reference.direction, rtol=0, atol=1e-5))
    if not same:
        raise InputError(f"{path}: its grid (shape {tuple(volume.shape)}, spacing {np.round(volume.spacing, 4).tolist()}, "
                         f"origin {np.round(volume.origin, 3).tolist()}) differs from {reference_name}'s "
                         f"(shape {tuple(reference.shape)}, spacing {np.round(reference.spacing, 4).tolist()}, "
                         f"origin {np.round(reference.origin, 3).tolist()})")

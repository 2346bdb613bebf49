"""The case folder's file rules: which file stands for which input, and the projection
matrix of a frame found in it (docs/DESIGN.md section 4).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..files import InputError, InputWarning, check_input_file, check_inside, display_path
from ..projection import (GeometryAssumptionWarning, GeometrySource, apply_in_plane_correction, facing_the_scan,
                          projection_matrix_from_carm, read_geometry_file)
from .fluoro import CARM_TAGS, Fluoro
from .volume import DICOM_SUFFIXES, RASTER_SUFFIXES, VOLUME_SUFFIXES, Volume


#: Case-folder inputs (docs/DESIGN.md section 4): name -> (file stem, accepted suffixes in the
#: order they are tried; "/" means a folder, i.e. a DICOM series).
CASE_INPUTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "ct": ("ct", ("/",) + VOLUME_SUFFIXES),
    "aorta_mask": ("aorta_mask", VOLUME_SUFFIXES),
    "skeleton3d": ("skeleton3d", VOLUME_SUFFIXES),
    "fluoro": ("fluoro", DICOM_SUFFIXES + RASTER_SUFFIXES),
    "fluoro_mask": ("fluoro_mask", (".png", ".tif", ".tiff", ".bmp")),
    "geometry": ("geometry", (".json",)),
}


def find_case_file(case_dir, stem: str, suffixes) -> Path | None:
    """The first ``case_dir/stem + suffix`` that exists (``"/"`` = a folder), or None.

    When several exist, the first in ``suffixes`` order is used and a warning names the others.

    Every candidate that exists is checked from ``stat`` alone: a broken link, a folder
    named like a file, a pipe or device, an empty file, or a link leading out of the case
    folder raises :class:`InputError` instead of being skipped or read.
    """
    case_dir = Path(case_dir)
    found = []
    for suffix in suffixes:
        candidate = case_dir / stem if suffix == "/" else case_dir / f"{stem}{suffix}"
        if not os.path.lexists(candidate):
            continue
        if suffix == "/":
            if not candidate.is_dir():
                continue
        else:
            check_input_file(candidate)
        check_inside(candidate, case_dir, "the case folder")
        found.append(candidate)
    if len(found) > 1:
        warnings.warn(f"{display_path(case_dir)}: several {stem} inputs ({', '.join(p.name for p in found)}); "
                      f"using {found[0].name}", InputWarning, stacklevel=2)
    return found[0] if found else None


def _folder_listing(case_dir: Path | None, limit: int = 20) -> str:
    if case_dir is None:
        return "no case folder was given"
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in case_dir.iterdir())
    shown = ", ".join(names[:limit]) + (f", ... ({len(names)} entries)" if len(names) > limit else "")
    return f"the folder holds: {shown or 'nothing'}"


def _projection_for_case(case_dir: Path | None, available: dict[str, Path], fluoro: Fluoro,
                         reference: Volume) -> tuple[np.ndarray, Path, GeometrySource]:
    """P from geometry.json, else from the frame's C-arm tags with the isocentre at the volume centre.

    A geometry.json holding only an ``in_plane_correction`` corrects the P of the tags. When
    P comes from the tags, a :class:`GeometryAssumptionWarning` says what was assumed.
    """
    P, correction = None, None
    if "geometry" in available:
        try:
            P, correction = read_geometry_file(available["geometry"])
        except ValueError as exc:
            raise InputError(str(exc)) from None
    if P is not None:
        source = GeometrySource("geometry.json", str(available["geometry"]))
        path = available["geometry"]
        P, source.sign_flipped = facing_the_scan(P, reference.center_lps())
    elif fluoro.carm is None:
        where = case_dir if case_dir is not None else fluoro.path
        raise InputError(f"{where}: geometry.json is missing (or holds no projection_matrix) and {fluoro.path} "
                         f"has no C-arm tags (lacks {', '.join(fluoro.missing_tags)})")
    else:
        try:
            P = projection_matrix_from_carm(fluoro.carm, reference.center_lps())
        except ValueError as exc:
            raise InputError(f"{fluoro.path}: {exc}") from None
        source, path = GeometrySource.from_carm(fluoro.carm, fluoro.path, reference.center_lps()), fluoro.path
    if correction:
        source.in_plane_correction = dict(correction, file=str(available["geometry"]))
        P = apply_in_plane_correction(P, correction, fluoro.shape)
    if source.assumptions:
        warnings.warn(source.describe(), GeometryAssumptionWarning, stacklevel=3)
    return P, path, source


def projection_for_frame(fluoro: Fluoro, reference: Volume, geometry=None) -> tuple[np.ndarray, GeometrySource]:
    """``P`` of a frame for callers holding loaded data (the Slicer module): same rules as a case folder.

    ``geometry`` (a geometry.json path) gives the matrix and/or an in-plane correction;
    without it ``P`` comes from the frame's C-arm tags, the isocentre at ``reference``'s centre.
    """
    available = {"geometry": Path(geometry)} if geometry else {}
    P, _, source = _projection_for_case(None, available, fluoro, reference)
    return P, source


def frame_from_mask(mask: np.ndarray, path=None) -> Fluoro:
    """A stand-in frame for a case that holds only a vessel mask: dark vessels on grey.

    It carries no C-arm tags, so such a case needs ``geometry.json``; it exists so that the
    overlay and the viewers always have a picture to draw on.
    """
    image = np.where(mask, 0.25, 0.75).astype(np.float32)
    return Fluoro(image=image, pixel_spacing=None, carm=None, path=Path(path) if path is not None else None,
                  missing_tags=CARM_TAGS)

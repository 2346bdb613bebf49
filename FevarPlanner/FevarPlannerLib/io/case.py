"""Loading a case: the pre-operative 3D input, the frame(s) and their projection matrices.

Flags given explicitly override the files found in the case folder (:mod:`folder`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..files import InputError, check_readable, display_path
from ..projection import GeometrySource
from .ct import check_same_grid, read_ct, read_mask
from .fluoro import Fluoro, read_fluoro, read_mask_2d
from .folder import CASE_INPUTS, _folder_listing, _projection_for_case, find_case_file, frame_from_mask
from .views import MAIN_VIEW, VIEW_INPUTS, View, _view_folders, load_views
from .volume import Volume


#: 3D inputs, most processed first: the first one present is used.
PRECEDENCE_3D = ("skeleton3d", "aorta_mask", "ct")
_READERS_3D = {"skeleton3d": read_mask, "aorta_mask": read_mask, "ct": read_ct}


@dataclass
class Case:
    """The inputs of one planning case, as read by :func:`load_case`.

    Only the most processed 3D input is read (``skeleton3d`` > ``aorta_mask`` > ``ct``);
    the other 3D fields stay None. ``paths`` names the files used, ``available`` every
    input the folder and the flags offered. ``views`` holds every frame of the case as a
    :class:`View`: the top-level one as ``main`` (first), then ``views/<name>/`` by name;
    ``fluoro``, ``fluoro_mask`` and ``P`` are those of the first view.
    """

    case_dir: Path | None
    ct: Volume | None
    aorta_mask: Volume | None
    skeleton3d: Volume | None
    fluoro: Fluoro
    fluoro_mask: np.ndarray | None
    P: np.ndarray
    paths: dict[str, Path] = field(default_factory=dict)
    available: dict[str, Path] = field(default_factory=dict)
    geometry: GeometrySource | None = None
    views: list = field(default_factory=list)

    @property
    def stage_3d(self) -> str:
        """Which 3D input was loaded: ``"skeleton3d"``, ``"aorta_mask"`` or ``"ct"``."""
        return next(name for name in PRECEDENCE_3D if getattr(self, name) is not None)

    @property
    def reference_volume(self) -> Volume:
        """Whichever 3D volume was loaded (they all share the CT grid)."""
        return getattr(self, self.stage_3d)

    def load_input(self, name: str) -> Volume:
        """Read another available 3D input (e.g. the aorta mask for the surface) on the same grid.

        Raises :class:`InputError` if the case has no such input or its grid differs from
        :attr:`reference_volume`'s.
        """
        if name not in _READERS_3D:
            raise ValueError(f"unknown 3D input {name!r}; expected one of {PRECEDENCE_3D}")
        if getattr(self, name) is not None:
            return getattr(self, name)
        if name not in self.available:
            raise InputError(f"{self.case_dir}: the case has no {name} input")
        volume = _READERS_3D[name](self.available[name])
        check_same_grid(volume, self.reference_volume, self.available[name], f"the {self.stage_3d}")
        return volume


def _gather_inputs(case_dir: Path | None, flags: dict[str, Path | None]) -> dict[str, Path]:
    """Every input on offer, flags first.

    A flag for one side (3D: ct / aorta_mask / skeleton3d; 2D: fluoro / fluoro_mask) hides
    the folder's files of that side that it could contradict: any 3D flag hides all folder
    3D inputs, and a ``fluoro`` flag hides the folder's ``fluoro_mask`` (drawn on another frame).
    """
    chosen = {name: Path(path) for name, path in flags.items() if path is not None}
    hidden = set()
    if any(name in chosen for name in PRECEDENCE_3D):
        hidden.update(PRECEDENCE_3D)
    if "fluoro" in chosen:
        hidden.add("fluoro_mask")
    if case_dir is not None:
        for name, (stem, suffixes) in CASE_INPUTS.items():
            if name not in chosen and name not in hidden:
                found = find_case_file(case_dir, stem, suffixes)
                if found is not None:
                    chosen[name] = found
    for name, path in chosen.items():
        if not os.path.lexists(path):
            raise InputError(f"{display_path(path)}: no such file (given for {name})")
        check_readable(path, folder_ok=name == "ct")
    return chosen


def _require_inputs(case_dir: Path | None, available: dict[str, Path], has_views: bool = False) -> None:
    where = case_dir if case_dir is not None else "case"
    if not any(name in available for name in PRECEDENCE_3D):
        raise InputError(f"{where}: no 3D input (skeleton3d.*, aorta_mask.* or ct/ / ct.nrrd|.nii.gz|.mha); "
                         f"{_folder_listing(case_dir)}")
    if "fluoro" not in available and "fluoro_mask" not in available and not has_views:
        raise InputError(f"{where}: no fluoroscopy frame (fluoro.dcm or fluoro.png|.jpg|.tif) and no "
                         f"fluoro_mask.png; "
                         f"{_folder_listing(case_dir)}")


def load_case(case_dir=None, *, ct=None, aorta_mask=None, skeleton3d=None, fluoro=None, fluoro_mask=None,
              geometry=None, frame: int = 0) -> Case:
    """Read a case folder (docs/DESIGN.md section 4); keyword paths override the folder's files.

    On the 3D side only the most processed input present is read: ``skeleton3d`` >
    ``aorta_mask`` > ``ct`` (a 500 MB CT is not read when a skeleton is there; use
    :meth:`Case.load_input` for another one). Any 3D flag replaces all the folder's 3D
    inputs. On the 2D side the frame ``fluoro`` (frame number ``frame``) is always read and
    ``fluoro_mask``, if present, must match its pixel grid; a ``fluoro`` flag hides the
    folder's ``fluoro_mask``. A case with a mask and no frame (the mask-only phantoms) gets
    a stand-in frame drawn from the mask (:func:`frame_from_mask`).

    ``P`` comes from ``geometry.json`` when present. Otherwise it is built from the DICOM
    frame's C-arm tags with :func:`projection.projection_matrix_from_carm`, placing the
    C-arm isocentre at the centre of the loaded 3D volume (:meth:`Volume.center_lps`),
    since an XA file does not say where the isocentre lies in the CT.

    Raises
    ------
    InputError
        A missing input (the message lists what the folder holds), an unreadable or empty
        file, a mask off the frame's grid, or no geometry at all.
    """
    if case_dir is not None:
        case_dir = Path(case_dir)
        if not case_dir.is_dir():
            raise InputError(f"{display_path(case_dir)}: case folder does not exist")
        check_readable(case_dir)
    flags = {"ct": ct, "aorta_mask": aorta_mask, "skeleton3d": skeleton3d, "fluoro": fluoro,
             "fluoro_mask": fluoro_mask, "geometry": geometry}
    available = _gather_inputs(case_dir, flags)
    _require_inputs(case_dir, available, has_views=bool(_view_folders(case_dir)))
    stage = next(name for name in PRECEDENCE_3D if name in available)
    volumes = {name: None for name in PRECEDENCE_3D}
    volumes[stage] = _READERS_3D[stage](available[stage])
    if stage == "skeleton3d":
        from ..plausibility import check_skeleton_is_thin

        check_skeleton_is_thin(volumes[stage], available[stage])
    paths = {stage: available[stage]}
    mask_2d = frame_2d = P = None
    if "fluoro" in available:
        frame_2d = read_fluoro(available["fluoro"], frame=frame)
        paths["fluoro"] = available["fluoro"]
    if "fluoro_mask" in available:
        mask_2d = read_mask_2d(available["fluoro_mask"], shape=frame_2d.shape if "fluoro" in available else None)
        paths["fluoro_mask"] = available["fluoro_mask"]
        if "fluoro" not in available:
            frame_2d = frame_from_mask(mask_2d, available["fluoro_mask"])
    views = load_views(case_dir, volumes[stage])
    if frame_2d is not None:
        P, paths["geometry"], source = _projection_for_case(case_dir, available, frame_2d, volumes[stage])
        main_paths = {name: paths[name] for name in VIEW_INPUTS if name in paths}
        views.insert(0, View(MAIN_VIEW, frame_2d, mask_2d, P, main_paths, source))
    return Case(case_dir=case_dir, ct=volumes["ct"], aorta_mask=volumes["aorta_mask"],
                skeleton3d=volumes["skeleton3d"], fluoro=views[0].fluoro, fluoro_mask=views[0].fluoro_mask,
                P=views[0].P, paths=paths, available=available, geometry=views[0].geometry, views=views)

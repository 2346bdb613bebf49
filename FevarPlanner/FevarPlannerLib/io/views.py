"""Several views of one case: ``views/<name>/`` sub-folders, each with its own frame,
mask and geometry (the case folder's own frame is the view ``main``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..files import InputError
from ..projection import GeometrySource
from .fluoro import Fluoro, read_fluoro, read_mask_2d
from .folder import CASE_INPUTS, _folder_listing, _projection_for_case, find_case_file, frame_from_mask
from .volume import Volume


#: The folder of a case that holds its further views, one sub-folder per view.
VIEWS_FOLDER = "views"
#: The name of the view given by the case folder's own frame.
MAIN_VIEW = "main"
#: The inputs a view folder may hold (CASE_INPUTS' names, same stems and suffixes).
VIEW_INPUTS = ("fluoro", "fluoro_mask", "geometry")


@dataclass
class View:
    """One frame of the intra-operative anatomy, with its own pose (DESIGN.md section 4).

    Attributes
    ----------
    name : str
        ``main`` for the case folder's own frame, else the ``views/<name>/`` folder name.
    fluoro : Fluoro
        The frame (a stand-in drawn from the mask when the view holds only a mask).
    fluoro_mask : numpy.ndarray of bool or None
        The given vessel mask on the frame's grid.
    P : numpy.ndarray, shape (3, 4)
        Projection matrix from the view's ``geometry.json``, else from its DICOM C-arm tags.
    paths : dict
        The files read (``fluoro``, ``fluoro_mask``, ``geometry``).
    geometry : GeometrySource or None
        Where ``P`` came from and what was assumed (:func:`_projection_for_case`).
    """

    name: str
    fluoro: Fluoro
    fluoro_mask: np.ndarray | None
    P: np.ndarray
    paths: dict = field(default_factory=dict)
    geometry: GeometrySource | None = None

    @property
    def has_frame(self) -> bool:
        """True when the view holds a real frame (not a stand-in drawn from its mask)."""
        return "fluoro" in self.paths


def _view_folders(case_dir: Path | None) -> list[Path]:
    folder = Path(case_dir) / VIEWS_FOLDER if case_dir is not None else None
    if folder is None or not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_dir())


def _read_view(folder: Path, reference: Volume, frame: int) -> View:
    """One ``views/<name>/`` folder: frame and/or mask, and its geometry, as at the top level."""
    available = {}
    for name in VIEW_INPUTS:
        found = find_case_file(folder, *CASE_INPUTS[name])
        if found is not None:
            available[name] = found
    if "fluoro" not in available and "fluoro_mask" not in available:
        raise InputError(f"{folder}: view without a frame (fluoro.dcm or fluoro.png|.jpg|.tif) or a "
                         f"fluoro_mask.png; {_folder_listing(folder)}")
    paths, mask = {}, None
    image = read_fluoro(available["fluoro"], frame=frame) if "fluoro" in available else None
    if image is not None:
        paths["fluoro"] = available["fluoro"]
    if "fluoro_mask" in available:
        mask = read_mask_2d(available["fluoro_mask"], shape=image.shape if image is not None else None)
        paths["fluoro_mask"] = available["fluoro_mask"]
        if image is None:
            image = frame_from_mask(mask, available["fluoro_mask"])
    P, paths["geometry"], source = _projection_for_case(folder, available, image, reference)
    return View(folder.name, image, mask, P, paths, source)


def load_views(case_dir, reference: Volume, frame: int = 0) -> list[View]:
    """The further views of a case folder, ``views/<name>/`` in name order (none: ``[]``).

    Each folder holds ``fluoro.dcm`` or ``fluoro.png|.jpg|.tif`` and/or ``fluoro_mask.png``
    and optionally ``geometry.json``, with the top level's rules; without ``geometry.json``
    its P comes from the DICOM C-arm tags with the isocentre at the centre of ``reference``.
    ``frame`` picks the frame of multi-frame DICOM files (the top-level ``frame`` option
    applies to the case folder's own frame only).

    Raises
    ------
    InputError
        A view named ``main`` (the top-level frame's name), a view without a frame or a
        mask, or any of the top level's errors for its files.
    """
    views = []
    for folder in _view_folders(case_dir):
        if folder.name == MAIN_VIEW:
            raise InputError(f"{folder}: the view name {MAIN_VIEW!r} belongs to the case folder's own frame")
        views.append(_read_view(folder, reference, frame))
    return views

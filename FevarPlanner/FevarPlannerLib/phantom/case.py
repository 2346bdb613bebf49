"""A generated case (both shapes, C-arm, poses, CT grid) and its case folder."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import files, io
from ..projection import CArmGeometry, projection_matrix_from_carm, write_geometry_json
from .anatomy import Anatomy, build_preop_anatomy
from .ct import _ct_from_lumen_field
from .deform import deform_anatomy, state_anatomy
from .fluoro import _misaligned, fit_detector, render_fluoro
from .params import PhantomParams
from .raster import Grid, _lumen_field, ct_grid


@dataclass
class PhantomCase:
    """A generated case: both shapes, the C-arm, the poses and the CT grid.

    Attributes
    ----------
    name : str
    params : PhantomParams
        Intra-operative state (deformation, C-arm, fluoroscopy noise).
    preop_params : PhantomParams
        Pre-operative state (CT noise); for a random case the same object as ``params``,
        whose pre-operative shape is the rest anatomy.
    preop, intraop : Anatomy
    carm : CArmGeometry
        The true C-arm; its tags give ``P_true`` with the isocentre at the CT centre.
    P_true, P_given : numpy.ndarray, shape (3, 4)
        The projection that made the frame and the one written to geometry.json.
    grid : Grid
        The CT grid.
    info : dict
        Extra JSON-serialisable facts (protocol, pairing).
    """

    name: str
    params: PhantomParams
    preop_params: PhantomParams
    preop: Anatomy
    intraop: Anatomy
    carm: CArmGeometry
    P_true: np.ndarray
    P_given: np.ndarray
    grid: Grid
    info: dict = field(default_factory=dict)


def _same_phantom(pre: PhantomParams, intra: PhantomParams) -> None:
    if pre.shape_dict() != intra.shape_dict():
        differing = sorted(k for k, v in pre.shape_dict().items() if intra.shape_dict()[k] != v)
        raise ValueError(f"pre- and intra-operative states describe different phantoms (differ in {differing})")


def generate_case(params: PhantomParams, intraop_params: PhantomParams | None = None, *,
                  name: str = "phantom", info: dict | None = None) -> PhantomCase:
    """Build a case.

    Parameters
    ----------
    params : PhantomParams
        With ``intraop_params`` None: the pre-operative shape is the rest anatomy and the
        intra-operative one is it deformed by ``params``. Otherwise ``params`` is the
        pre-operative state (rest anatomy deformed by its own deformation parameters).
    intraop_params : PhantomParams, optional
        The intra-operative state of the same phantom (paper protocol); its C-arm,
        misalignment and fluoroscopy parameters are used.
    name : str
    info : dict, optional

    Returns
    -------
    PhantomCase
    """
    params.validate()
    if intraop_params is None:
        pre_params, intra_params = params, params
        preop = build_preop_anatomy(params)
        intraop = deform_anatomy(preop, params)
    else:
        intraop_params.validate()
        _same_phantom(params, intraop_params)
        pre_params, intra_params = params, intraop_params
        preop, intraop = state_anatomy(params), state_anatomy(intraop_params)
    grid = ct_grid(preop, pre_params.ct_spacing_mm, pre_params.ct_margin_mm)
    isocenter = grid.center_lps()
    carm = fit_detector(intraop, intra_params, isocenter)
    P_true = projection_matrix_from_carm(carm, isocenter)
    P_given = _misaligned(P_true, intra_params, isocenter, carm)
    return PhantomCase(name, intra_params, pre_params, preop, intraop, carm, P_true, P_given, grid, dict(info or {}))


def _ground_truth(case: PhantomCase) -> dict:
    pre, intra = case.preop.to_centerline(), case.intraop.to_centerline()
    return {
        "version": 1,
        "preop_centerline": pre.to_dict(),
        "intraop_centerline": intra.to_dict(),
        "correspondence": "node n of intraop_centerline is node n of preop_centerline",
        "projection_matrix_true": case.P_true.tolist(),
        "projection_matrix_given": case.P_given.tolist(),
        "vessel_lengths_mm": {"preop": case.preop.lengths(), "intraop": case.intraop.lengths()},
    }


def _case_json(case: PhantomCase) -> dict:
    return {
        "version": 1,
        "name": case.name,
        "seed": case.params.seed,
        "params": case.params.to_dict(),
        "preop_params": case.preop_params.to_dict(),
        "carm": {"sid": case.carm.sid, "sod": case.carm.sod, "pixel_spacing": list(case.carm.pixel_spacing),
                 "primary_angle": case.carm.primary_angle, "secondary_angle": case.carm.secondary_angle,
                 "rows": case.carm.rows, "cols": case.carm.cols},
        "ct_grid": {"shape_kji": list(case.grid.shape), "spacing_ijk": list(case.grid.spacing),
                    "origin": list(case.grid.origin)},
        **case.info,
    }


def write_case(case: PhantomCase, folder, *, mask_only: bool = False) -> Path:
    """Write a case folder (docs/DESIGN.md section 4) atomically and return its path.

    Files: ``ct/`` (DICOM series, skipped with ``mask_only``), ``aorta_mask.nrrd``,
    ``fluoro.dcm`` (skipped with ``mask_only``), ``fluoro_mask.png``, ``geometry.json``
    (``P_given``, and ``true_projection_matrix``), ``gt.json``, ``case.json``.
    """
    folder = Path(folder)
    pre_rng = np.random.default_rng([case.preop_params.seed, 1])
    intra_rng = np.random.default_rng([case.params.seed, 2])
    with files.atomic_folder(folder) as tmp:
        volume = case.grid.volume(dtype=np.uint8)
        lumen = _lumen_field(case.preop, volume)
        io.write_volume(tmp / "aorta_mask.nrrd", volume.with_array((lumen <= 0.0).astype(np.uint8)))
        frame, fluoro_mask = render_fluoro(case.intraop, case.P_true, case.carm, case.params, intra_rng)
        io.write_mask_png(tmp / "fluoro_mask.png", fluoro_mask)
        if not mask_only:
            ct = _ct_from_lumen_field(case.preop, case.preop_params, pre_rng, volume, lumen)
            io.write_ct_dicom_series(ct, tmp / "ct", series_description=f"FevarPlanner phantom CT {case.name}",
                                     patient_name=f"Phantom^{case.name}", patient_id=case.name)
            io.write_fluoro_dicom(tmp / "fluoro.dcm", frame, case.carm, patient_name=f"Phantom^{case.name}",
                                  patient_id=case.name)
        write_geometry_json(tmp / "geometry.json", case.P_given, true_projection_matrix=case.P_true.tolist(),
                            isocenter=case.grid.center_lps().tolist())
        files.write_text_atomic(tmp / "gt.json", json.dumps(_ground_truth(case)))
        files.write_text_atomic(tmp / "case.json", json.dumps(_case_json(case), indent=2))
    return folder


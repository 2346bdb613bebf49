"""Reading and writing images, volumes and case folders, all in DICOM LPS millimetres.

numpy volumes are indexed ``(k, j, i)`` (slice, row, column) as SimpleITK returns them;
``Volume.index_to_lps`` takes ``(k, j, i)`` indices and returns ``(x, y, z)`` LPS mm.
Every writer goes through a temporary file in the target folder and a rename
(:mod:`FevarPlannerLib.files`), so a failure never leaves a half-written output behind.

The package, one module per kind of input (every name is re-exported here):

    volume          the Volume type, size limits, 3D image files (NRRD / NIfTI / MHA)
    ct              a CT (DICOM series folder or volume file) and 3D masks
    dicom_header    DICOM tag helpers shared by the CT and fluoroscopy readers
    fluoro          fluoroscopic frames (DICOM or raster) and 2D masks
    dicom_writers   DICOM / PNG writers (the phantom's CT series, run and masks)
    folder          the case folder's file rules and a frame's projection matrix
    case            load_case: a case from its folder and flags
    views           several views (views/<name>/)
    truth           the ground-truth centreline (gt.json)

The ground floor's names (InputError, atomic writes, ...) live in :mod:`FevarPlannerLib.files`
and are re-exported here too, so ``io.InputError`` keeps working.
"""

from __future__ import annotations

from ..files import (MAX_JSON_BYTES, InputError, InputWarning, atomic_folder, atomic_path, check_input_file,
                     check_inside, check_readable, display_path, output_mode, read_json_file, swap_folder,
                     write_bytes_atomic, write_text_atomic)
from .case import Case, PRECEDENCE_3D, load_case
from .ct import SLICE_TAGS, check_same_grid, read_ct, read_mask
from .dicom_writers import write_ct_dicom_series, write_fluoro_dicom, write_mask_png, write_png
from .fluoro import CARM_TAGS, Fluoro, FluoroRun, read_fluoro, read_mask_2d
from .folder import CASE_INPUTS, find_case_file, frame_from_mask, projection_for_frame
from .truth import read_ground_truth
from .views import MAIN_VIEW, VIEWS_FOLDER, VIEW_INPUTS, View, load_views
from .volume import (DICOM_SUFFIXES, LUMA_WEIGHTS, MAX_FRAME_PIXELS, MAX_HEADER_BYTES, MAX_VOXELS, RASTER_SUFFIXES,
                     VOLUME_SUFFIXES, Volume, max_frame_pixels, max_voxels, read_volume, write_volume)

__all__ = [
    "InputError",
    "InputWarning",
    "check_readable",
    "check_input_file",
    "check_inside",
    "display_path",
    "max_voxels",
    "read_json_file",
    "read_ground_truth",
    "swap_folder",
    "output_mode",
    "Volume",
    "read_volume",
    "write_volume",
    "atomic_path",
    "write_text_atomic",
    "write_bytes_atomic",
    "atomic_folder",
    "write_ct_dicom_series",
    "write_fluoro_dicom",
    "write_png",
    "write_mask_png",
    "read_ct",
    "read_mask",
    "check_same_grid",
    "Fluoro",
    "read_fluoro",
    "FluoroRun",
    "read_mask_2d",
    "Case",
    "View",
    "CASE_INPUTS",
    "find_case_file",
    "load_case",
    "projection_for_frame",
    "load_views",
]


"""DICOM and PNG writers: what the phantom writes (a CT series, a fluoroscopic run, masks).

Every file goes through a temporary file in the target folder and a rename
(:mod:`files`). UIDs are derived from the content, so the same phantom writes the same files.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from PIL import Image
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.tag import Tag
from pydicom.uid import (CTImageStorage, ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID,
                         XRayAngiographicImageStorage, generate_uid)
from pydicom.valuerep import format_number_as_ds

from ..files import atomic_folder, atomic_path
from ..projection import CArmGeometry
from .volume import Volume


def _ds(value: float) -> str:
    """A float as a valid DICOM decimal string (at most 16 characters)."""
    return format_number_as_ds(float(value))


def _digest(*parts) -> str:
    """A stable hex digest of arrays, numbers and strings (for deterministic UIDs)."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(str((part.dtype.str, part.shape)).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(repr(part).encode())
    return h.hexdigest()


def _uid(*sources: str) -> str:
    return generate_uid(entropy_srcs=[str(s) for s in sources])


def _new_dataset(sop_class_uid: str, sop_instance_uid: str) -> FileDataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class_uid
    meta.MediaStorageSOPInstanceUID = sop_instance_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = sop_class_uid
    ds.SOPInstanceUID = sop_instance_uid
    ds.SpecificCharacterSet = "ISO_IR 100"
    return ds


def _set_patient_study_series(ds: FileDataset, *, patient_name: str, patient_id: str, study_uid: str,
                              series_uid: str, modality: str, series_description: str) -> None:
    """Patient, study and series modules; dates are left empty so output is reproducible."""
    ds.PatientName = patient_name
    ds.PatientID = patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.StudyInstanceUID = study_uid
    ds.StudyDate = ""
    ds.StudyTime = ""
    ds.StudyID = "1"
    ds.AccessionNumber = ""
    ds.ReferringPhysicianName = ""
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = 1
    ds.Modality = modality
    ds.SeriesDescription = series_description
    ds.Manufacturer = "FevarPlanner"


def _set_grey_pixels(ds: FileDataset, pixels: np.ndarray, *, signed: bool, photometric: str) -> None:
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 1 if signed else 0
    ds.PixelData = np.ascontiguousarray(pixels.astype("<i2" if signed else "<u2")).tobytes()


def _as_integer_pixels(array, dtype, what: str) -> np.ndarray:
    """``array`` rounded to ``dtype``; ``ValueError`` if not finite or out of its range."""
    a = np.asarray(array)
    if a.dtype == bool:
        return a.astype(dtype)
    if not np.issubdtype(a.dtype, np.number):
        raise ValueError(f"{what}: expected a numeric array, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: contains NaN or infinite values")
        a = np.rint(a)
    info = np.iinfo(dtype)
    if a.size and (a.min() < info.min or a.max() > info.max):
        raise ValueError(f"{what}: values [{a.min()}, {a.max()}] do not fit {np.dtype(dtype).name}")
    return a.astype(dtype)


def write_ct_dicom_series(volume: Volume, folder, *, series_description: str = "FevarPlanner phantom CT",
                          patient_name: str = "Phantom^AAA", patient_id: str = "PHANTOM",
                          study_uid: str | None = None, series_uid: str | None = None) -> None:
    """Write ``volume`` (HU) as a CT Image Storage series, one file per ``k`` slice.

    Parameters
    ----------
    volume : Volume
        Values in HU; rounded to int16 (``ValueError`` if they do not fit). Slice ``k`` is
        written with ImagePositionPatient = LPS of voxel ``(k, 0, 0)``, ImageOrientationPatient
        = the ``i`` and ``j`` direction columns, PixelSpacing = (``j``, ``i``) spacing,
        SliceThickness = ``k`` spacing, RescaleSlope 1, RescaleIntercept 0.
    folder : path
        Target folder, written atomically (an existing folder is replaced as a whole).
    study_uid, series_uid : str, optional
        Default: UIDs derived from a hash of the volume and the patient fields, so the same
        inputs give the same files.

    Notes
    -----
    ``read_ct(folder)`` returns the same array, spacing, origin and direction for any
    right-handed direction (``det > 0``). A DICOM series' slice axis is always the
    row x column normal, so a left-handed grid comes back with ``k`` reversed: the same
    voxels at the same LPS positions, described by a right-handed direction.
    """
    pixels = _as_integer_pixels(volume.array, np.int16, "CT volume")
    if pixels.ndim != 3:
        raise ValueError(f"CT volume: expected a 3D array, got shape {pixels.shape}")
    key = _digest(pixels, volume.spacing, volume.origin, volume.direction, patient_name, patient_id,
                  series_description)
    study_uid = study_uid or _uid(key, "study")
    series_uid = series_uid or _uid(key, "series", study_uid)
    frame_uid = _uid(key, "frame-of-reference", study_uid)
    orientation = [_ds(v) for v in np.concatenate([volume.direction[:, 0], volume.direction[:, 1]])]
    spacing_i, spacing_j, spacing_k = volume.spacing
    folder = Path(folder)
    with atomic_folder(folder) as tmp:
        for k in range(pixels.shape[0]):
            ds = _new_dataset(CTImageStorage, _uid(series_uid, "slice", k))
            _set_patient_study_series(ds, patient_name=patient_name, patient_id=patient_id, study_uid=study_uid,
                                      series_uid=series_uid, modality="CT", series_description=series_description)
            ds.FrameOfReferenceUID = frame_uid
            ds.PositionReferenceIndicator = ""
            ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
            ds.InstanceNumber = k + 1
            ds.AcquisitionNumber = 1
            ds.KVP = ""
            ds.ImagePositionPatient = [_ds(v) for v in volume.index_to_lps((k, 0, 0))]
            ds.ImageOrientationPatient = orientation
            ds.PixelSpacing = [_ds(spacing_j), _ds(spacing_i)]
            ds.SliceThickness = _ds(spacing_k)
            ds.Rows, ds.Columns = pixels.shape[1], pixels.shape[2]
            ds.RescaleIntercept = "0"
            ds.RescaleSlope = "1"
            ds.RescaleType = "HU"
            _set_grey_pixels(ds, pixels[k], signed=True, photometric="MONOCHROME2")
            ds.save_as(tmp / f"slice_{k + 1:05d}.dcm", enforce_file_format=True)


def write_fluoro_dicom(path, frames, carm: CArmGeometry, *, photometric: str = "MONOCHROME2",
                       patient_name: str = "Phantom^AAA", patient_id: str = "PHANTOM",
                       study_uid: str | None = None,
                       series_description: str = "FevarPlanner phantom fluoroscopy") -> None:
    """Write an X-Ray Angiographic Image Storage file with the C-arm tags of ``carm``.

    Parameters
    ----------
    path : path
        Target ``.dcm`` file, written atomically.
    frames : array_like, shape (rows, cols) or (n, rows, cols)
        Stored pixel values, 0..65535 (uint16). Three dimensions give a multi-frame file
        (NumberOfFrames = n, FrameTime 66.7 ms).
    carm : CArmGeometry
        Written as DistanceSourceToDetector, DistanceSourceToPatient, ImagerPixelSpacing,
        PositionerPrimaryAngle and PositionerSecondaryAngle; its rows/cols must match ``frames``.
    photometric : {"MONOCHROME2", "MONOCHROME1"}
        How a viewer shows the stored values: with MONOCHROME1 bigger is darker, so
        ``read_fluoro`` returns ``65535 - frames``.
    """
    if photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise ValueError(f"photometric must be MONOCHROME1 or MONOCHROME2, got {photometric!r}")
    pixels = _as_integer_pixels(frames, np.uint16, "fluoroscopy frames")
    if pixels.ndim not in (2, 3):
        raise ValueError(f"fluoroscopy frames: expected (rows, cols) or (n, rows, cols), got shape {pixels.shape}")
    rows, cols = pixels.shape[-2:]
    if (rows, cols) != (carm.rows, carm.cols):
        raise ValueError(f"fluoroscopy frames are {rows}x{cols} pixels but the C-arm geometry says "
                         f"{carm.rows}x{carm.cols}")
    key = _digest(pixels, carm, photometric, patient_name, patient_id, series_description)
    study_uid = study_uid or _uid(key, "study")
    series_uid = _uid(key, "series", study_uid)
    ds = _new_dataset(XRayAngiographicImageStorage, _uid(series_uid, "image"))
    _set_patient_study_series(ds, patient_name=patient_name, patient_id=patient_id, study_uid=study_uid,
                              series_uid=series_uid, modality="XA", series_description=series_description)
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.InstanceNumber = 1
    ds.PixelIntensityRelationship = "LIN"
    ds.KVP = ""
    ds.DistanceSourceToDetector = _ds(carm.sid)
    ds.DistanceSourceToPatient = _ds(carm.sod)
    ds.ImagerPixelSpacing = [_ds(carm.pixel_spacing[0]), _ds(carm.pixel_spacing[1])]
    ds.PositionerMotion = "STATIC"
    ds.PositionerPrimaryAngle = _ds(carm.primary_angle)
    ds.PositionerSecondaryAngle = _ds(carm.secondary_angle)
    ds.Rows, ds.Columns = rows, cols
    if pixels.ndim == 3:
        ds.NumberOfFrames = pixels.shape[0]
        ds.FrameTime = _ds(1000.0 / 15.0)
        ds.FrameIncrementPointer = Tag(0x0018, 0x1063)
    _set_grey_pixels(ds, pixels, signed=False, photometric=photometric)
    with atomic_path(path, suffix=".dcm") as tmp:
        ds.save_as(tmp, enforce_file_format=True)


def _check_2d(array: np.ndarray, what: str) -> np.ndarray:
    array = np.asarray(array)
    if array.ndim != 2 or 0 in array.shape:
        raise ValueError(f"{what}: expected a non-empty 2D array, got shape {array.shape}")
    return array


def write_png(path, array) -> None:
    """Write a 2D uint8 or uint16 grey image as PNG (16-bit for uint16), atomically."""
    array = _check_2d(array, f"{path}")
    if array.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: write_png takes uint8 or uint16 arrays, got {array.dtype}")
    image = Image.fromarray(np.ascontiguousarray(array))
    with atomic_path(path, suffix=".png") as tmp:
        image.save(tmp, format="PNG")


def write_mask_png(path, mask) -> None:
    """Write a 2D mask as an 8-bit PNG: non-zero -> 255, zero -> 0."""
    mask = _check_2d(mask, f"{path}")
    write_png(path, np.where(mask != 0, 255, 0).astype(np.uint8))

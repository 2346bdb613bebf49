"""Reading and writing images, volumes and files, all in DICOM LPS millimetres.

numpy volumes are indexed ``(k, j, i)`` (slice, row, column) as SimpleITK returns them;
``Volume.index_to_lps`` takes ``(k, j, i)`` indices and returns ``(x, y, z)`` LPS mm.
Every writer goes through a temporary file in the target folder and a rename, so a failure
never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk
from PIL import Image
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.tag import Tag
from pydicom.uid import (CTImageStorage, ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID,
                         XRayAngiographicImageStorage, generate_uid)
from pydicom.valuerep import format_number_as_ds

from .projection import CArmGeometry

__all__ = [
    "InputError",
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
]

VOLUME_SUFFIXES = (".nrrd", ".nii.gz", ".nii", ".mha", ".mhd")


class InputError(ValueError):
    """Bad input: the message names the file and the problem (one line)."""


@dataclass
class Volume:
    """A 3D image on a physical grid.

    Attributes
    ----------
    array : numpy.ndarray
        Voxel values indexed ``(k, j, i)``.
    spacing : numpy.ndarray, shape (3,)
        Voxel size along ``(i, j, k)`` in mm (SimpleITK order).
    origin : numpy.ndarray, shape (3,)
        LPS position of voxel ``(0, 0, 0)``.
    direction : numpy.ndarray, shape (3, 3)
        Columns are the LPS directions of the ``i``, ``j``, ``k`` axes.
    """

    array: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray

    def __post_init__(self):
        self.spacing = np.asarray(self.spacing, dtype=float).reshape(3)
        self.origin = np.asarray(self.origin, dtype=float).reshape(3)
        self.direction = np.asarray(self.direction, dtype=float).reshape(3, 3)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.array.shape

    @property
    def index_to_lps_matrix(self) -> np.ndarray:
        """4x4 matrix mapping homogeneous ``(i, j, k, 1)`` to ``(x, y, z, 1)`` LPS mm."""
        M = np.eye(4)
        M[:3, :3] = self.direction @ np.diag(self.spacing)
        M[:3, 3] = self.origin
        return M

    def index_to_lps(self, kji: np.ndarray) -> np.ndarray:
        """LPS mm of voxel indices given as ``(k, j, i)`` rows (float indices allowed)."""
        ijk = np.asarray(kji, dtype=float)[..., ::-1]
        return ijk @ (self.direction @ np.diag(self.spacing)).T + self.origin

    def lps_to_index(self, points: np.ndarray) -> np.ndarray:
        """Continuous ``(k, j, i)`` indices of LPS points."""
        A = self.direction @ np.diag(self.spacing)
        ijk = np.linalg.solve(A, (np.asarray(points, dtype=float) - self.origin).T).T
        return ijk[..., ::-1]

    def center_lps(self) -> np.ndarray:
        """LPS position of the centre of the grid."""
        return self.index_to_lps((np.array(self.shape) - 1) / 2.0)

    def with_array(self, array: np.ndarray) -> "Volume":
        """A volume on the same grid holding ``array``."""
        if array.shape != self.array.shape:
            raise ValueError(f"array shape {array.shape} does not match grid {self.array.shape}")
        return Volume(array, self.spacing.copy(), self.origin.copy(), self.direction.copy())

    def to_sitk(self) -> sitk.Image:
        image = sitk.GetImageFromArray(self.array)
        image.SetSpacing(self.spacing.tolist())
        image.SetOrigin(self.origin.tolist())
        image.SetDirection(self.direction.ravel().tolist())
        return image

    @classmethod
    def from_sitk(cls, image: sitk.Image) -> "Volume":
        if image.GetDimension() != 3:
            raise ValueError(f"expected a 3D image, got {image.GetDimension()}D")
        return cls(sitk.GetArrayFromImage(image), image.GetSpacing(), image.GetOrigin(), image.GetDirection())


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_file() and path.stat().st_size == 0:
        raise InputError(f"{path}: file is empty (0 bytes)")


def read_volume(path) -> Volume:
    """Read a 3D NRRD / NIfTI / MHA file into a :class:`Volume` (LPS, as SimpleITK reports)."""
    path = Path(path)
    _check_readable(path)
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unreadable"
        raise InputError(f"{path}: cannot read volume ({first})") from None
    if image.GetDimension() != 3:
        raise InputError(f"{path}: expected a 3D volume, got {image.GetDimension()}D")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"{path}: expected a scalar volume, got {image.GetNumberOfComponentsPerPixel()} components")
    volume = Volume.from_sitk(image)
    if np.issubdtype(volume.array.dtype, np.floating) and not np.all(np.isfinite(volume.array)):
        raise InputError(f"{path}: volume contains NaN or infinite values")
    return volume


def write_volume(path, volume: Volume, compress: bool = True) -> None:
    """Write ``volume`` to NRRD / NIfTI / MHA (by suffix), atomically."""
    path = Path(path)
    suffix = "".join(path.suffixes[-2:]) if path.name.endswith(".nii.gz") else path.suffix
    with atomic_path(path, suffix=suffix) as tmp:
        sitk.WriteImage(volume.to_sitk(), str(tmp), compress)


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file and a rename."""
    write_bytes_atomic(path, text.encode("utf-8"))


@contextlib.contextmanager
def atomic_folder(folder):
    """Yield a temporary folder beside ``folder``; it replaces ``folder`` if the block succeeds.

    An existing ``folder`` is moved aside first and deleted only once the new one is in
    place, so a failure leaves the old content untouched.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder")
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        yield tmp
        old = None
        if folder.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
            os.replace(folder, old)
        os.replace(tmp, folder)
        if old is not None:
            shutil.rmtree(old)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


# --------------------------------------------------------------------------- DICOM writers

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

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
import stat
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk
from PIL import Image
from pydicom.dataset import FileDataset, FileMetaDataset
from pydicom.pixels import pixel_array as decode_dicom_pixels
from pydicom.tag import Tag
from pydicom.uid import (CTImageStorage, ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID,
                         XRayAngiographicImageStorage, generate_uid)
from pydicom.valuerep import format_number_as_ds

from .files import (MAX_JSON_BYTES, InputError, InputWarning, atomic_folder, atomic_path, check_input_file,
                    check_inside, check_readable, display_path, output_mode, read_json_file, swap_folder,
                    write_bytes_atomic, write_text_atomic)
from .projection import (CArmGeometry, GeometryAssumptionWarning, GeometrySource, apply_in_plane_correction,
                         projection_matrix_from_carm, read_geometry_file)

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
    "read_mask_2d",
    "Case",
    "View",
    "CASE_INPUTS",
    "find_case_file",
    "load_case",
    "projection_for_frame",
    "load_views",
]

VOLUME_SUFFIXES = (".nrrd", ".nii.gz", ".nii", ".mha", ".mhd")
DICOM_SUFFIXES = (".dcm", ".dicom")
RASTER_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
#: Refuse 2D frames larger than this many pixels (a 10k x 10k frame), before decoding them;
#: the environment variable FEVAR_MAX_FRAME_PIXELS raises it.
MAX_FRAME_PIXELS = 100_000_000
#: Refuse 3D images of more voxels than this (a 1024 x 1024 x 400 CT), read from the header
#: before anything is allocated; the environment variable FEVAR_MAX_VOXELS raises it.
MAX_VOXELS = 400_000_000
#: A text image header (NRRD, MetaImage) larger than this is not a header.
MAX_HEADER_BYTES = 1_000_000
#: BT.601 luma weights, as used to turn RGB frames into grey.
LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114])


def _env_limit(name: str, default: int) -> int:
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = int(float(text))
    except ValueError:
        raise InputError(f"environment variable {name}={text!r}: not a number") from None
    if value <= 0:
        raise InputError(f"environment variable {name}={text!r}: must be positive")
    return value


def max_voxels() -> int:
    """The 3D size limit: :data:`MAX_VOXELS`, or the environment variable ``FEVAR_MAX_VOXELS``."""
    return _env_limit("FEVAR_MAX_VOXELS", MAX_VOXELS)


def max_frame_pixels() -> int:
    """The 2D size limit: :data:`MAX_FRAME_PIXELS`, or ``FEVAR_MAX_FRAME_PIXELS``."""
    return _env_limit("FEVAR_MAX_FRAME_PIXELS", MAX_FRAME_PIXELS)


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



def _read_head(path: Path, limit: int) -> bytes:
    with open(path, "rb") as handle:
        return handle.read(limit + 1)


def _nrrd_fields(path: Path) -> dict[str, str] | None:
    """The fields of an NRRD header (lower-case keys), or None if ``path`` is not NRRD."""
    head = _read_head(path, MAX_HEADER_BYTES)
    if not head.startswith(b"NRRD000"):
        return None
    end = head.find(b"\n\n")
    if end < 0:
        end = head.find(b"\r\n\r\n")
    if end < 0 and len(head) > MAX_HEADER_BYTES:
        raise InputError(f"{display_path(path)}: NRRD header larger than {MAX_HEADER_BYTES} bytes (no blank line "
                         f"ends it)")
    text = head[: end if end >= 0 else len(head)].decode("latin-1")
    fields = {}
    for line in text.splitlines()[1:]:
        if line.startswith("#") or ":" not in line:
            continue
        key, _, value = line.partition(":")
        fields[key.strip().lower()] = value.lstrip("=").strip()
    return fields


def _metaimage_fields(path: Path) -> dict[str, str] | None:
    """The fields of a MetaImage (.mha / .mhd) header (lower-case keys), or None if not one."""
    if path.suffix.lower() not in (".mha", ".mhd"):
        return None
    head = _read_head(path, MAX_HEADER_BYTES)
    fields = {}
    for raw in head.split(b"\n"):
        key, sep, value = raw.decode("latin-1").partition("=")
        if not sep:
            break
        fields[key.strip().lower()] = value.strip()
        if key.strip().lower() == "elementdatafile":
            return fields
    if len(head) > MAX_HEADER_BYTES:
        raise InputError(f"{display_path(path)}: MetaImage header larger than {MAX_HEADER_BYTES} bytes")
    return fields


def _check_detached_data(path: Path) -> None:
    """Refuse a detached header whose data file lies outside the header's folder or is not a file."""
    data_files = []
    nrrd = _nrrd_fields(path)
    if nrrd is not None:
        name = nrrd.get("data file", nrrd.get("datafile"))
        if name is not None:
            data_files.append(("data file", name))
    meta = _metaimage_fields(path)
    if meta is not None and meta.get("elementdatafile", "LOCAL").upper() != "LOCAL":
        data_files.append(("ElementDataFile", meta["elementdatafile"]))
    for key, name in data_files:
        if name.split()[0].upper() == "LIST" or len(name.split()) > 1 or "%" in name:
            raise InputError(f"{display_path(path)}: '{key}' names several data files ({name[:60]}); "
                             f"only one detached data file is supported")
        target = path.parent / name
        try:
            check_inside(target, path.parent, "the folder of its header")
            check_input_file(target)
        except InputError as exc:
            raise InputError(f"{display_path(path)}: its detached data file ('{key}: {name}') is refused: "
                             f"{exc}") from None


def _check_image_header(path: Path) -> None:
    """Read a 3D image's header only and refuse sizes over :func:`max_voxels` or a broken grid."""
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError as exc:
        raise InputError(f"{display_path(path)}: cannot read volume ({_last_line(exc)})") from None
    if reader.GetDimension() != 3:
        raise InputError(f"{display_path(path)}: expected a 3D volume, got {reader.GetDimension()}D")
    size = reader.GetSize()
    voxels = int(np.prod(np.array(size, dtype=object))) * reader.GetNumberOfComponents()
    if voxels > max_voxels():
        raise InputError(f"{display_path(path)}: image of {' x '.join(map(str, size))} voxels exceeds the limit of "
                         f"{max_voxels()} voxels (set FEVAR_MAX_VOXELS to raise it)")
    from .plausibility import check_grid

    check_grid(path, reader.GetSpacing(), reader.GetOrigin(), reader.GetDirection())


def read_volume(path) -> Volume:
    """Read a 3D NRRD / NIfTI / MHA file into a :class:`Volume` (LPS, as SimpleITK reports)."""
    path = Path(path)
    check_input_file(path)
    _check_detached_data(path)
    _check_image_header(path)
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise InputError(f"{path}: cannot read volume ({_last_line(exc)})") from None
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


# --------------------------------------------------------------------------- CT and masks

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
    from .plausibility import check_grid

    check_grid(folder, volume.spacing, volume.origin, volume.direction.ravel())
    return volume


def _last_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[-1] if text else type(exc).__name__


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


def _tag_text(ds: pydicom.Dataset, keyword: str) -> str:
    element = ds.get(keyword)
    return "" if element is None else str(element)


def _tag_number(ds: pydicom.Dataset, keyword: str, file, default=None, kind=float):
    """A numeric tag as ``kind``, refusing text, NaN and infinity with the file and tag named."""
    try:
        value = ds.get(keyword)
    except Exception as exc:  # pydicom converts lazily and raises many types on a malformed value
        raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) is malformed "
                         f"({_last_line(exc)})") from None
    if value is None or value == "":
        if default is None:
            raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) is missing")
        return default
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) is not a number "
                         f"({str(value)[:40]!r})") from None
    if not np.isfinite(number):
        raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) is {number}")
    if kind is int and number != int(number):
        raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) is not an integer "
                         f"({number})")
    return kind(number)


def _tag_int(ds: pydicom.Dataset, keyword: str, file, default=None) -> int:
    return _tag_number(ds, keyword, file, default, kind=int)


def _tag_id(keyword: str) -> str:
    tag = Tag(keyword)
    return f"{tag.group:04X},{tag.element:04X}"


def _header_vector(ds: pydicom.Dataset, keyword: str, size: int, file) -> np.ndarray:
    try:
        value = ds.get(keyword)
        numbers = None if value is None or len(value) != size else [float(v) for v in value]
    except (TypeError, ValueError):
        numbers = None
    if numbers is None:
        raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) is missing or malformed "
                         f"(expected {size} numbers)")
    if not np.all(np.isfinite(numbers)):
        raise InputError(f"{display_path(file)}: DICOM tag {keyword} ({_tag_id(keyword)}) holds NaN or infinity")
    return np.array(numbers)


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


# --------------------------------------------------------------------------- fluoroscopy

CARM_TAGS = ("DistanceSourceToDetector", "DistanceSourceToPatient", "ImagerPixelSpacing",
             "PositionerPrimaryAngle", "PositionerSecondaryAngle", "Rows", "Columns")


@dataclass
class Fluoro:
    """One fluoroscopic frame.

    Attributes
    ----------
    image : numpy.ndarray, float32, shape (rows, cols)
        Intensities in the MONOCHROME2 sense (bigger = brighter); ``u`` = column, ``v`` = row.
    pixel_spacing : tuple of float or None
        ``(row, col)`` mm: ImagerPixelSpacing, else PixelSpacing, else None.
    carm : CArmGeometry or None
        The C-arm geometry from the DICOM tags, None if any of :data:`CARM_TAGS` is missing.
    path : Path or None
        The file it was read from.
    frame, n_frames : int
        Which frame of how many in the file.
    missing_tags : tuple of str
        The C-arm tags the file lacks (empty when ``carm`` is set).
    """

    image: np.ndarray
    pixel_spacing: tuple[float, float] | None
    carm: CArmGeometry | None
    path: Path | None
    frame: int = 0
    n_frames: int = 1
    missing_tags: tuple[str, ...] = ()

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape


def _is_dicom_file(path: Path) -> bool:
    if path.suffix.lower() in DICOM_SUFFIXES:
        return True
    if path.suffix.lower() in RASTER_SUFFIXES:
        return False
    with open(path, "rb") as handle:
        return handle.read(132)[128:132] == b"DICM"


def read_fluoro(path, frame: int = 0) -> Fluoro:
    """Read one frame of a DICOM XA / RF file or a PNG / JPG / TIFF / BMP image.

    DICOM frames may be single- or multi-frame (``frame`` picks one); MONOCHROME1 is
    inverted so that bigger is always brighter; a Rescale Slope / Intercept is applied;
    colour images become grey (BT.601 luma). An out-of-range ``frame``, a corrupt or empty
    file, NaN pixels or a frame over :data:`MAX_FRAME_PIXELS` raise :class:`InputError`.
    """
    path = Path(path)
    check_readable(path)
    if path.is_dir():
        raise InputError(f"{display_path(path)}: is a folder; expected a fluoroscopy image file")
    if _is_dicom_file(path):
        fluoro = _read_fluoro_dicom(path, frame)
    elif path.suffix.lower() in RASTER_SUFFIXES:
        fluoro = _read_fluoro_raster(path, frame)
    else:
        raise InputError(f"{path}: unknown image format (expected DICOM, PNG, JPG, TIFF or BMP)")
    if not np.all(np.isfinite(fluoro.image)):
        raise InputError(f"{path}: image contains NaN or infinite values")
    return fluoro


def _check_frame_index(path: Path, frame: int, n_frames: int) -> int:
    if not isinstance(frame, (int, np.integer)) or not 0 <= frame < n_frames:
        raise InputError(f"{path}: frame {frame} out of range (the file has {n_frames} frame"
                         f"{'s' if n_frames != 1 else ''})")
    return int(frame)


def _check_frame_size(path: Path, rows: int, cols: int) -> None:
    if rows <= 0 or cols <= 0:
        raise InputError(f"{path}: image has no pixels ({rows}x{cols})")
    if rows * cols > max_frame_pixels():
        raise InputError(f"{display_path(path)}: image of {rows}x{cols} pixels is larger than the limit of "
                         f"{max_frame_pixels()} pixels (set FEVAR_MAX_FRAME_PIXELS to raise it)")


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return (rgb[..., :3].astype(np.float64) @ LUMA_WEIGHTS).astype(np.float32)


def _read_fluoro_dicom(path: Path, frame: int) -> Fluoro:
    try:
        ds = pydicom.dcmread(path)
    except Exception as exc:  # any parser failure of a foreign file is bad input
        raise InputError(f"{path}: not a readable DICOM file ({_last_line(exc)})") from None
    if "PixelData" not in ds:
        raise InputError(f"{path}: DICOM file holds no pixel data")
    rows, cols = _tag_int(ds, "Rows", path, default=0), _tag_int(ds, "Columns", path, default=0)
    _check_frame_size(path, rows, cols)
    n_frames = _tag_int(ds, "NumberOfFrames", path, default=1)
    frame = _check_frame_index(path, frame, n_frames)
    try:
        pixels = decode_dicom_pixels(ds, index=frame)
    except Exception as exc:  # decoder plugins raise many types; all mean "cannot decode"
        syntax = ds.file_meta.get("TransferSyntaxUID", "unknown")
        raise InputError(f"{path}: cannot decode pixel data (transfer syntax {syntax}: {_last_line(exc)})") from None
    image = _luminance(pixels) if pixels.ndim == 3 else pixels.astype(np.float32)
    if image.shape != (rows, cols):
        raise InputError(f"{path}: decoded frame is {image.shape}, expected {rows}x{cols}")
    if ds.get("PhotometricInterpretation") == "MONOCHROME1":
        image = _invert_stored_range(ds, image, path)
    slope = _tag_number(ds, "RescaleSlope", path, default=1.0)
    intercept = _tag_number(ds, "RescaleIntercept", path, default=0.0)
    image = (image * slope + intercept).astype(np.float32)
    carm, missing = _carm_from_dataset(ds, path)
    return Fluoro(image=image, pixel_spacing=_dicom_pixel_spacing(ds, path), carm=carm, path=path,
                  frame=frame, n_frames=n_frames, missing_tags=missing)


def _invert_stored_range(ds: pydicom.Dataset, image: np.ndarray, path: Path) -> np.ndarray:
    """MONOCHROME1 -> MONOCHROME2: mirror the stored values in their representable range."""
    bits = _tag_int(ds, "BitsStored", path, default=0) or _tag_int(ds, "BitsAllocated", path, default=16)
    if _tag_int(ds, "PixelRepresentation", path, default=0) == 1:
        low, high = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    else:
        low, high = 0, 2 ** bits - 1
    return (low + high - image).astype(np.float32)


def _dicom_pixel_spacing(ds: pydicom.Dataset, path: Path) -> tuple[float, float] | None:
    for keyword in ("ImagerPixelSpacing", "PixelSpacing"):
        if ds.get(keyword) not in (None, ""):
            spacing = _header_vector(ds, keyword, 2, path)
            if spacing.min() <= 0:
                raise InputError(f"{display_path(path)}: DICOM tag {keyword} ({_tag_id(keyword)}) must be positive, "
                                 f"got {spacing.tolist()}")
            return float(spacing[0]), float(spacing[1])
    return None


def _carm_from_dataset(ds: pydicom.Dataset, path: Path) -> tuple[CArmGeometry | None, tuple[str, ...]]:
    """The C-arm geometry of the tags, or ``(None, missing tag names)``."""
    missing = tuple(tag for tag in CARM_TAGS if ds.get(tag) in (None, ""))
    if missing:
        return None, missing
    spacing = _header_vector(ds, "ImagerPixelSpacing", 2, path)
    carm = CArmGeometry(sid=_tag_number(ds, "DistanceSourceToDetector", path),
                        sod=_tag_number(ds, "DistanceSourceToPatient", path),
                        pixel_spacing=(float(spacing[0]), float(spacing[1])),
                        primary_angle=_tag_number(ds, "PositionerPrimaryAngle", path),
                        secondary_angle=_tag_number(ds, "PositionerSecondaryAngle", path),
                        rows=_tag_int(ds, "Rows", path), cols=_tag_int(ds, "Columns", path))
    if not (0 < carm.sod < carm.sid) or min(carm.pixel_spacing) <= 0:
        raise InputError(f"{path}: inconsistent C-arm tags (need 0 < DistanceSourceToPatient={carm.sod} < "
                         f"DistanceSourceToDetector={carm.sid} and positive ImagerPixelSpacing)")
    return carm, ()


def _read_fluoro_raster(path: Path, frame: int) -> Fluoro:
    try:
        with _pillow_without_its_size_limit(), Image.open(path) as opened:
            _check_frame_size(path, opened.height, opened.width)
            n_frames = int(getattr(opened, "n_frames", 1))
            frame = _check_frame_index(path, frame, n_frames)
            opened.seek(frame)
            image = _raster_to_grey(opened)
    except InputError:
        raise
    except Exception as exc:  # Pillow raises many types for truncated or foreign files
        raise InputError(f"{path}: not a readable image ({_last_line(exc)})") from None
    return Fluoro(image=image, pixel_spacing=None, carm=None, path=path, frame=frame, n_frames=n_frames,
                  missing_tags=CARM_TAGS)


@contextlib.contextmanager
def _pillow_without_its_size_limit():
    """Let :func:`_check_frame_size` apply our limit (FEVAR_MAX_FRAME_PIXELS) instead of Pillow's."""
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None
    try:
        yield
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def _raster_to_grey(image: Image.Image) -> np.ndarray:
    """A Pillow image as float32 grey: grey modes as stored, colour through BT.601 luma."""
    if image.mode in ("1", "L", "I", "F") or image.mode.startswith("I;16"):
        return np.asarray(image).astype(np.float32)
    if image.mode in ("LA", "La"):
        return np.asarray(image)[..., 0].astype(np.float32)
    return _luminance(np.asarray(image.convert("RGB")))


def read_mask_2d(path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a 2D vessel mask (non-zero = vessel) as a bool array of the frame's shape.

    Lossy JPEG masks are thresholded at half their maximum instead, since compression
    turns the background's zeros into small values.
    """
    path = Path(path)
    grey = read_fluoro(path).image
    if path.suffix.lower() in (".jpg", ".jpeg"):
        mask = grey > 0.5 * grey.max()
    else:
        mask = grey != 0
    if shape is not None and mask.shape != tuple(shape):
        raise InputError(f"{path}: mask is {mask.shape[0]}x{mask.shape[1]} pixels but the frame is "
                         f"{shape[0]}x{shape[1]}")
    if not mask.any():
        raise InputError(f"{path}: no foreground pixels (the mask is empty)")
    if mask.all():
        raise InputError(f"{path}: every pixel is foreground (an inverted or non-binary mask?)")
    return mask


# --------------------------------------------------------------------------- case folder

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
#: 3D inputs, most processed first: the first one present is used.
PRECEDENCE_3D = ("skeleton3d", "aorta_mask", "ct")
_READERS_3D = {"skeleton3d": read_mask, "aorta_mask": read_mask, "ct": read_ct}


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


def _folder_listing(case_dir: Path | None, limit: int = 20) -> str:
    if case_dir is None:
        return "no case folder was given"
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in case_dir.iterdir())
    shown = ", ".join(names[:limit]) + (f", ... ({len(names)} entries)" if len(names) > limit else "")
    return f"the folder holds: {shown or 'nothing'}"


def _require_inputs(case_dir: Path | None, available: dict[str, Path], has_views: bool = False) -> None:
    where = case_dir if case_dir is not None else "case"
    if not any(name in available for name in PRECEDENCE_3D):
        raise InputError(f"{where}: no 3D input (skeleton3d.*, aorta_mask.* or ct/ / ct.nrrd|.nii.gz|.mha); "
                         f"{_folder_listing(case_dir)}")
    if "fluoro" not in available and "fluoro_mask" not in available and not has_views:
        raise InputError(f"{where}: no fluoroscopy frame (fluoro.dcm or fluoro.png|.jpg|.tif) and no "
                         f"fluoro_mask.png; "
                         f"{_folder_listing(case_dir)}")


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
        from .plausibility import check_skeleton_is_thin

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


# --------------------------------------------------------------------------- several views (views/<name>/)

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


# --------------------------------------------------------------------------- JSON inputs

def _json_points(value, path: Path, key: str) -> np.ndarray:
    """``value`` as an (n, 3) array of finite numbers, or :class:`InputError` naming ``key``."""
    if not isinstance(value, list) or not value:
        raise InputError(f"{display_path(path)}: key '{key}' must be a non-empty list of [x, y, z] points")
    for i, point in enumerate(value):
        if (not isinstance(point, list) or len(point) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in point)):
            raise InputError(f"{display_path(path)}: key '{key}[{i}]' must be 3 numbers, got {str(point)[:40]}")
    points = np.array(value, dtype=float)
    if not np.all(np.isfinite(points)):
        raise InputError(f"{display_path(path)}: key '{key}' holds NaN or infinite values")
    return points


def read_ground_truth(path, key: str = "intraop_centerline"):
    """The ground-truth centreline ``key`` of a phantom's ``gt.json``, validated."""
    from .centerline import Centerline

    path = Path(path)
    data = read_json_file(path, "ground-truth JSON")
    if not isinstance(data, dict) or not isinstance(data.get(key), dict):
        raise InputError(f"{display_path(path)}: key '{key}' missing or not an object")
    entry = data[key]
    points = _json_points(entry.get("points"), path, f"{key}.points")
    edges = entry.get("edges", [])
    if (not isinstance(edges, list) or not all(isinstance(e, list) and len(e) == 2 and
                                               all(isinstance(i, int) and 0 <= i < len(points) for i in e)
                                               for e in edges)):
        raise InputError(f"{display_path(path)}: key '{key}.edges' must be pairs of node indices below {len(points)}")
    labels = entry.get("labels", [])
    if not isinstance(labels, list) or not all(isinstance(v, str) for v in labels) or (
            labels and len(labels) != len(points)):
        raise InputError(f"{display_path(path)}: key '{key}.labels' must be one string per point")
    return Centerline(points, np.array(edges, dtype=np.int64).reshape(-1, 2), list(labels))

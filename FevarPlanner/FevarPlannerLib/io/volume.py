"""The volume type and 3D image files (NRRD / NIfTI / MetaImage), in DICOM LPS millimetres.

numpy volumes are indexed ``(k, j, i)`` (slice, row, column) as SimpleITK returns them;
``Volume.index_to_lps`` takes ``(k, j, i)`` indices and returns ``(x, y, z)`` LPS mm.
Headers are read and checked (size limits, detached data, grid) before any voxel is.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ..files import InputError, atomic_path, check_input_file, check_inside, display_path


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

    @property
    def superior_step(self) -> int:
        """+1 when increasing k goes superior (towards +z in LPS), else -1."""
        return 1 if (self.direction @ np.array([0.0, 0.0, 1.0]))[2] >= 0 else -1

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
    from ..plausibility import check_grid

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


def _last_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[-1] if text else type(exc).__name__

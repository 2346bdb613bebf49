"""Reading and writing images, volumes and files, all in DICOM LPS millimetres.

numpy volumes are indexed ``(k, j, i)`` (slice, row, column) as SimpleITK returns them;
``Volume.index_to_lps`` takes ``(k, j, i)`` indices and returns ``(x, y, z)`` LPS mm.
Every writer goes through a temporary file in the target folder and a rename, so a failure
never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

__all__ = [
    "InputError",
    "Volume",
    "read_volume",
    "write_volume",
    "atomic_path",
    "write_text_atomic",
    "write_bytes_atomic",
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

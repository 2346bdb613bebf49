"""Reading fluoroscopic frames (DICOM X-ray angiography or raster images) and 2D masks.

A frame's C-arm tags, when present, give its projection matrix (:mod:`projection`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
from PIL import Image
from pydicom.pixels import pixel_array as decode_dicom_pixels

from ..files import InputError, check_readable, display_path
from ..projection import CArmGeometry
from .dicom_header import _header_vector, _is_dicom_file, _tag_id, _tag_int, _tag_number
from .volume import LUMA_WEIGHTS, RASTER_SUFFIXES, _last_line, max_frame_pixels


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
        fluoro = _fluoro_of_dataset(_dicom_dataset(path), path, frame)
    elif path.suffix.lower() in RASTER_SUFFIXES:
        fluoro = _read_fluoro_raster(path, frame)
    else:
        raise InputError(f"{path}: unknown image format (expected DICOM, PNG, JPG, TIFF or BMP)")
    return _finite(fluoro, path)


def _finite(fluoro: Fluoro, path: Path) -> Fluoro:
    if not np.all(np.isfinite(fluoro.image)):
        raise InputError(f"{path}: image contains NaN or infinite values")
    return fluoro


class FluoroRun:
    """The frames of one fluoroscopy file, its DICOM parsed once (a run's frames one after another).

    ``frame(index)`` is ``read_fluoro(path, index)``: the same image and tags, the same errors;
    a DICOM file is read and parsed at the first call only (``read_fluoro`` parses the whole
    file, every frame's pixel data included, for each frame it reads).
    """

    def __init__(self, path):
        self.path = Path(path)
        self._dataset = None

    def frame(self, index: int) -> Fluoro:
        if self._dataset is None:
            check_readable(self.path)
            if self.path.is_dir() or not _is_dicom_file(self.path):
                return read_fluoro(self.path, index)
            self._dataset = _dicom_dataset(self.path)
        return _finite(_fluoro_of_dataset(self._dataset, self.path, index), self.path)


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


def _dicom_dataset(path: Path) -> pydicom.Dataset:
    """The parsed DICOM file, which must hold pixel data."""
    try:
        ds = pydicom.dcmread(path)
    except Exception as exc:  # any parser failure of a foreign file is bad input
        raise InputError(f"{path}: not a readable DICOM file ({_last_line(exc)})") from None
    if "PixelData" not in ds:
        raise InputError(f"{path}: DICOM file holds no pixel data")
    return ds


def _fluoro_of_dataset(ds: pydicom.Dataset, path: Path, frame: int) -> Fluoro:
    """Frame ``frame`` of the parsed DICOM file ``ds`` (read from ``path``)."""
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


#: A mask with more distinct values than this is grey content, not labels (:func:`read_mask_2d`).
MAX_LABEL_LEVELS = 8


def _is_grey(image: np.ndarray) -> bool:
    """More than :data:`MAX_LABEL_LEVELS` distinct values: lossy or smoothed content, not labels."""
    return len(np.unique(image)) > MAX_LABEL_LEVELS


def read_mask_2d(path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a 2D vessel mask (non-zero = vessel) as a bool array of the frame's shape.

    Lossy JPEG masks are thresholded at half their maximum instead, since compression
    turns the background's zeros into small values; so is a mask in any format that holds
    more than :data:`MAX_LABEL_LEVELS` grey levels (lossy content saved losslessly, e.g. a
    JPEG label re-saved as PNG: its halo and specks are not vessel).
    """
    path = Path(path)
    grey = read_fluoro(path).image
    if path.suffix.lower() in (".jpg", ".jpeg") or _is_grey(grey):
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

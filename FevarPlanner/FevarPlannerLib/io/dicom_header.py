"""DICOM header helpers shared by the CT series scan and the fluoroscopy reader.

Each tag is read with a one-line :class:`files.InputError` naming the file and the tag
when it is missing or malformed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
from pydicom.tag import Tag

from ..files import InputError, display_path
from .volume import DICOM_SUFFIXES, RASTER_SUFFIXES, _last_line


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


def _is_dicom_file(path: Path) -> bool:
    if path.suffix.lower() in DICOM_SUFFIXES:
        return True
    if path.suffix.lower() in RASTER_SUFFIXES:
        return False
    with open(path, "rb") as handle:
        return handle.read(132)[128:132] == b"DICM"

"""The bad-input corpus: one change each to a small, good phantom case, run through the CLI.

Each entry changes one thing (a file of the case folder, an option, the output folder) and
expects what every bad input must give: exit code 2, exactly one line on stderr that names
the file (and the DICOM tag or JSON key) and the problem, no traceback, and the output
folder byte for byte as it was before the run (it holds a previous output set).

The good case is built once per test session (a 2 mm phantom: mask case and DICOM CT case);
entries run in-process through ``cli.main``. Test ids are ``category-name``.
"""

from __future__ import annotations

import errno
import gzip
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pydicom
import pytest
import torch
from PIL import Image

from FevarPlannerLib import cli, export, io
from FevarPlannerLib.projection import source_position
from fixtures import coarse_phantom_folders

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- the good case

@pytest.fixture(scope="session")
def good(tmp_path_factory):
    """The good cases (mask case and CT case) and a previous output set, built once."""
    root = tmp_path_factory.mktemp("corpus")
    full, mask_case = coarse_phantom_folders(root, "mask_case", ("aorta_mask.nrrd", "fluoro.dcm", "fluoro_mask.png",
                                                                 "geometry.json", "gt.json"))
    ct_case = root / "ct_case"
    ct_case.mkdir()
    ct = io.read_ct(full / "ct")
    # twelve slices of the phantom's CT: a real series, small enough to edit slice by slice
    io.write_ct_dicom_series(io.Volume(ct.array[:12].copy(), ct.spacing, ct.origin, ct.direction), ct_case / "ct")
    for name in ("fluoro_mask.png", "geometry.json"):
        shutil.copy2(full / name, ct_case / name)
    previous = root / "previous_out"
    assert cli.main(["-q", "plan", str(mask_case), "--out", str(previous)]) == 0
    return {"mask": mask_case, "ct": ct_case, "previous": previous}


def snapshot(folder: Path) -> dict:
    """Every path under ``folder`` with its bytes (None for folders); {} if it does not exist."""
    if not os.path.lexists(folder):
        return {}
    if not folder.is_dir():
        return {"": folder.read_bytes() if folder.is_file() else "special"}
    return {str(p.relative_to(folder)): (None if p.is_dir() else p.read_bytes()) for p in sorted(folder.rglob("*"))}


@dataclass
class Run:
    """What an entry may change: the case folder, the arguments, the output folder, the environment."""

    case: Path
    out: Path
    tmp: Path
    args: list = field(default_factory=list)
    command: str = "plan"
    argv: list | None = None


@dataclass
class Bad:
    category: str
    name: str
    mutate: Callable[[Run], None]
    words: tuple
    base: str = "mask"
    env: dict = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.category}-{self.name}"


CORPUS: list[Bad] = []
#: A frame without the expected vessel tree may be caught by any of these gates (the 2D graph,
#: the segmentation QC, the vessel-tree gate, the result gates); "|" separates alternatives.
NOT_A_TREE = ("skeleton has only|not found in the frame|no usable vessel tree|implausible registration|"
              "usable angiogram|devices only")


def bad(category: str, name: str, *words: str, base: str = "mask", env=None):
    def register(mutate):
        CORPUS.append(Bad(category, name, mutate, words, base, dict(env or {})))
        return mutate
    return register


# --------------------------------------------------------------------------- helpers to break files

def _flags(r: Run) -> Path:
    """A folder apart from the case and the output for files given by flag."""
    folder = r.tmp / "flags"
    folder.mkdir(exist_ok=True)
    return folder


def _flag_file(r: Run, option: str, name: str) -> Path:
    """``name`` in the flags folder, given to the command as ``option`` (the caller makes it, or not)."""
    path = _flags(r) / name
    r.args += [option, str(path)]
    return path


def _write(path: Path, data: bytes) -> None:
    path.unlink(missing_ok=True) if not path.is_dir() else shutil.rmtree(path)
    path.write_bytes(data)


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _random_bytes(path: Path, n: int = 4096) -> None:
    _write(path, np.random.default_rng(7).integers(0, 256, n, dtype=np.uint8).tobytes())


def broken_file(name: str, category: str, *, keep: float, truncated: str, random: str) -> None:
    """Register the three file-level breaks of a case file: 0 bytes ("empty"), cut to ``keep`` of
    its length (message words ``truncated``) and 4 KiB of random bytes (words ``random``)."""
    bad(category, "zero_bytes", name, "empty")(lambda r: _write(r.case / name, b""))
    bad(category, "truncated", name, truncated)(lambda r: _truncate(r.case / name, keep))
    bad(category, "random_bytes", name, random)(lambda r: _random_bytes(r.case / name))


def _text_file(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _fifo(path: Path) -> None:
    path.unlink(missing_ok=True) if not path.is_dir() else shutil.rmtree(path)
    os.mkfifo(path)


def _link(path: Path, target) -> None:
    path.unlink(missing_ok=True) if not path.is_dir() else shutil.rmtree(path)
    os.symlink(target, path)


def _folder(path: Path) -> None:
    path.unlink(missing_ok=True)
    path.mkdir()


def not_a_plain_file(name: str, category: str, *kinds: str) -> None:
    """Register breaks that put something other than a plain file of the case at ``name``:
    ``"fifo"`` (a named pipe), ``"is_a_folder"``, ``"broken_link"`` and ``"link_out_of_case"``
    (a link to a good copy outside the case folder)."""
    suffix = Path(name).suffix

    def link_out_of_case(r):
        shutil.copy2(r.case / name, r.tmp / f"elsewhere{suffix}")
        _link(r.case / name, r.tmp / f"elsewhere{suffix}")

    breaks = {"fifo": ("named pipe", lambda r: _fifo(r.case / name)),
              "is_a_folder": ("is a folder", lambda r: _folder(r.case / name)),
              "broken_link": ("broken link", lambda r: _link(r.case / name, r.tmp / f"absent{suffix}")),
              "link_out_of_case": ("outside the case folder", link_out_of_case)}
    for kind in kinds:
        words, mutate = breaks[kind]
        bad(category, kind, name, words)(mutate)


def _nrrd(path: Path, header: dict, data: bytes = b"", encoding: str = "raw") -> None:
    """Write an NRRD by hand: ``header`` fields, then the data (attached unless 'data file' is set)."""
    fields = {"type": "uint8", "dimension": "3", "space": "left-posterior-superior",
              "space directions": "(2,0,0) (0,2,0) (0,0,2)", "space origin": "(0,0,0)", "encoding": encoding,
              **header}
    lines = ["NRRD0004"] + [f"{k}: {v}" for k, v in fields.items()]
    _write(path, ("\n".join(lines) + "\n\n").encode() + data)


def _edit_mask(case: Path, **changes) -> None:
    """Rewrite aorta_mask.nrrd with its array / spacing / origin changed."""
    volume = io.read_volume(case / "aorta_mask.nrrd")
    array = changes.pop("array", volume.array)
    edited = io.Volume(array, changes.get("spacing", volume.spacing), changes.get("origin", volume.origin),
                       changes.get("direction", volume.direction))
    io.write_volume(case / "aorta_mask.nrrd", edited)


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    data = edit(data)
    path.write_text(json.dumps(data))


def _set_P(case: Path, P) -> None:
    _edit_json(case / "geometry.json", lambda d: {**d, "projection_matrix": P})


def _P(case: Path) -> np.ndarray:
    return np.array(json.loads((case / "geometry.json").read_text())["projection_matrix"])


def _edit_dicom(path: Path, **tags) -> None:
    ds = pydicom.dcmread(path)
    for keyword, value in tags.items():
        setattr(ds, keyword, value)
    ds.save_as(path)


def _edit_raw_tag(path: Path, keyword: str, text: str) -> None:
    """Set a tag's raw bytes (even invalid text for its VR), bypassing pydicom's validation."""
    ds = pydicom.dcmread(path)
    element = ds[keyword]
    raw = text.encode("ascii")
    if len(raw) % 2:
        raw += b" "
    ds[keyword] = pydicom.dataelem.RawDataElement(element.tag, element.VR, len(raw), raw, 0, False, True)
    ds.save_as(path)


def _slices(case: Path) -> list[Path]:
    return sorted((case / "ct").glob("*.dcm"))


def _every_slice(case: Path, **tags) -> None:
    for path in _slices(case):
        _edit_dicom(path, **tags)


# --------------------------------------------------------------------------- aorta_mask (3D volume files)

M = "aorta_mask.nrrd"


broken_file(M, "aorta_mask", keep=0.6, truncated="cannot read", random="cannot read")


@bad("aorta_mask", "header_only", M, "cannot read")
def _(r): _nrrd(r.case / M, {"sizes": "10 10 10"})


@bad("aorta_mask", "nonsense_header", M, "cannot read")
def _(r): _write(r.case / M, b"NRRD0004\nnonsense: 1\n\n")


@bad("aorta_mask", "all_zero", M, "empty")
def _(r): _edit_mask(r.case, array=np.zeros((4, 5, 6), np.uint8))


@bad("aorta_mask", "all_one", M, "every voxel")
def _(r): _edit_mask(r.case, array=np.ones((4, 5, 6), np.uint8))


@bad("aorta_mask", "nan_values", M, "NaN")
def _(r): _edit_mask(r.case, array=np.full((4, 5, 6), np.nan, np.float32))


@bad("aorta_mask", "slice_spacing_1000mm", M, "spacing 1000 mm")
def _(r): _edit_mask(r.case, spacing=(2.0, 2.0, 1000.0))


@bad("aorta_mask", "spacing_0.001mm", M, "spacing 0.001 mm")
def _(r): _edit_mask(r.case, spacing=(0.001, 2.0, 2.0))


@bad("aorta_mask", "spacing_nan_in_nrrd_header", M, "cannot read")
def _(r): _nrrd(r.case / M, {"sizes": "4 4 4", "space directions": "(nan,0,0) (0,2,0) (0,0,2)"}, bytes(64))


@bad("aorta_mask", "spacing_nan_in_metaimage", "aorta_mask.mha", "spacing")
def _(r):
    (r.case / M).unlink()
    (r.case / "aorta_mask.mha").write_bytes(b"ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementSpacing = nan 2 2\n"
                                            b"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + bytes(64))


@bad("aorta_mask", "two_dimensional", M, "3D")
def _(r):
    _write(r.case / M, b"NRRD0004\ntype: uint8\ndimension: 2\nsizes: 4 4\nencoding: raw\n\n" + bytes(16))


@bad("aorta_mask", "vector_voxels", M, "components")
def _(r):
    _write(r.case / M, b"NRRD0004\ntype: uint8\ndimension: 4\nsizes: 3 4 4 4\nkinds: vector domain domain "
           b"domain\nencoding: raw\n\n" + bytes(192))


@bad("aorta_mask", "giant_header_sizes", M, "exceeds the limit", "FEVAR_MAX_VOXELS")
def _(r): _nrrd(r.case / M, {"sizes": "4000 4000 4000"}, gzip.compress(bytes(1000)), encoding="gzip")


@bad("aorta_mask", "decompression_bomb", M, "exceeds the limit", "FEVAR_MAX_VOXELS")
def _(r):
    # 64 kB of gzip that expands to 64 MB and whose header says 600 MB
    _nrrd(r.case / M, {"sizes": "1024 1024 600"}, _bomb(), encoding="gzip")


def _bomb(n_mb: int = 64) -> bytes:
    """A gzip stream of n_mb MB of zeros (a few tens of kB), made without holding it in memory twice."""
    import zlib

    compressor = zlib.compressobj(9, zlib.DEFLATED, 31)
    chunk = bytes(1024 * 1024)
    return b"".join(compressor.compress(chunk) for _ in range(n_mb)) + compressor.flush()


@bad("aorta_mask", "voxel_limit_env", M, "exceeds the limit", "FEVAR_MAX_VOXELS", env={"FEVAR_MAX_VOXELS": "1000"})
def _(r): pass


@bad("aorta_mask", "huge_text_header", M, "header larger than")
def _(r): _write(r.case / M, b"NRRD0004\n" + b"# padding comment line\n" * 60000)


@bad("aorta_mask", "detached_data_outside_case", M, "data file", "outside the folder of its header")
def _(r):
    (r.tmp / "outside.raw").write_bytes(bytes(64))
    _nrrd(r.case / M, {"sizes": "4 4 4", "data file": "../outside.raw"})


@bad("aorta_mask", "detached_data_dev_urandom", M, "data file", "outside the folder of its header")
def _(r): _nrrd(r.case / M, {"sizes": "4 4 4", "data file": "/dev/urandom"})


@bad("aorta_mask", "detached_data_fifo", M, "named pipe")
def _(r):
    _fifo(r.case / "data.raw")
    _nrrd(r.case / M, {"sizes": "4 4 4", "data file": "data.raw"})


@bad("aorta_mask", "detached_data_missing", M, "no such file")
def _(r): _nrrd(r.case / M, {"sizes": "4 4 4", "data file": "absent.raw"})


@bad("aorta_mask", "detached_data_list", M, "several data files")
def _(r): _nrrd(r.case / M, {"sizes": "4 4 4", "data file": "LIST"})


@bad("aorta_mask", "metaimage_data_outside", "aorta_mask.mha", "ElementDataFile", "outside")
def _(r):
    (r.case / M).unlink()
    (r.case / "aorta_mask.mha").write_text("ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\n"
                                           "ElementDataFile = /etc/hostname\n")


not_a_plain_file(M, "aorta_mask", "fifo", "is_a_folder", "broken_link", "link_out_of_case")


@bad("aorta_mask", "link_to_dev_zero", M, "character device")
def _(r): _link(r.case / M, "/dev/zero")


@bad("aorta_mask", "flag_missing_file", "nope.nrrd", "no such file")
def _(r): _flag_file(r, "--aorta-mask", "nope.nrrd")


@bad("aorta_mask", "flag_fifo", "pipe.nrrd", "named pipe")
def _(r): _fifo(_flag_file(r, "--aorta-mask", "pipe.nrrd"))


@bad("aorta_mask", "png_given_as_mask", "mask.png", "3D")
def _(r): shutil.copy2(r.case / "fluoro_mask.png", _flag_file(r, "--aorta-mask", "mask.png"))


# --------------------------------------------------------------------------- skeleton3d

S = "skeleton3d.nrrd"


@bad("skeleton3d", "thick_mask_as_skeleton", S, "not a one-voxel-thin skeleton")
def _(r): shutil.copy2(r.case / M, r.case / S)


@bad("skeleton3d", "straight_line", S, "end nodes")
def _(r):
    volume = io.read_volume(r.case / M)
    line = np.zeros(volume.shape, np.uint8)
    line[5:-5, volume.shape[1] // 2, volume.shape[2] // 2] = 1
    io.write_volume(r.case / S, volume.with_array(line))


@bad("skeleton3d", "zero_bytes", S, "empty")
def _(r): _write(r.case / S, b"")


@bad("skeleton3d", "all_zero", S, "empty")
def _(r):
    volume = io.read_volume(r.case / M)
    io.write_volume(r.case / S, volume.with_array(np.zeros(volume.shape, np.uint8)))


@bad("skeleton3d", "flag_thick_mask", "aorta_mask.nrrd", "not a one-voxel-thin skeleton")
def _(r): r.args += ["--skeleton3d", str(r.case / M)]


# --------------------------------------------------------------------------- fluoro.dcm (XA frame)

F = "fluoro.dcm"


broken_file(F, "fluoro", keep=0.5, truncated="fluoro.dcm", random="not a readable DICOM")


@bad("fluoro", "sid_nan", F, "DistanceSourceToDetector", "nan")
def _(r): _edit_raw_tag(r.case / F, "DistanceSourceToDetector", "NaN")


@bad("fluoro", "primary_angle_inf", F, "PositionerPrimaryAngle", "inf")
def _(r): _edit_raw_tag(r.case / F, "PositionerPrimaryAngle", "Infinity")


@bad("fluoro", "sod_text", F, "DistanceSourceToPatient")
def _(r): _edit_raw_tag(r.case / F, "DistanceSourceToPatient", "abcd")


@bad("fluoro", "frames_text", F, "NumberOfFrames")
def _(r):
    ds = pydicom.dcmread(r.case / F)
    ds.NumberOfFrames = 1
    ds.save_as(r.case / F)
    _edit_raw_tag(r.case / F, "NumberOfFrames", "abcd")


@bad("fluoro", "sod_beyond_sid", F, "DistanceSourceToPatient")
def _(r): _edit_dicom(r.case / F, DistanceSourceToPatient="5000")


@bad("fluoro", "imager_spacing_zero", F, "ImagerPixelSpacing")
def _(r): _edit_dicom(r.case / F, ImagerPixelSpacing=["0", "0"])


@bad("fluoro", "imager_spacing_text", F, "ImagerPixelSpacing")
def _(r): _edit_raw_tag(r.case / F, "ImagerPixelSpacing", "a\\b")


@bad("fluoro", "rescale_slope_nan", F, "RescaleSlope")
def _(r): _edit_dicom(r.case / F, RescaleSlope="NaN")


@bad("fluoro", "no_pixel_data", F, "no pixel data")
def _(r):
    ds = pydicom.dcmread(r.case / F)
    del ds.PixelData
    ds.save_as(r.case / F)


@bad("fluoro", "giant_rows", F, "larger than the limit", "FEVAR_MAX_FRAME_PIXELS")
def _(r): _edit_dicom(r.case / F, Rows=65535, Columns=65535)


@bad("fluoro", "grid_differs_from_mask", "fluoro_mask.png", "frame is")
def _(r):
    mask = np.asarray(Image.open(r.case / "fluoro_mask.png"))
    Image.fromarray(mask[:-8]).save(r.case / "fluoro_mask.png")


@bad("fluoro", "fifo", F, "named pipe")
def _(r): _fifo(r.case / F)


@bad("fluoro", "link_to_dev_urandom", F, "character device")
def _(r): _link(r.case / F, "/dev/urandom")


@bad("fluoro", "flag_fifo", "pipe.dcm", "named pipe")
def _(r): _fifo(_flag_file(r, "--fluoro", "pipe.dcm"))


@bad("fluoro", "flag_text_file", "notes.txt", "unknown image format")
def _(r): _flag_file(r, "--fluoro", "notes.txt").write_text("hello")


@bad("fluoro", "flag_folder", "frames", "is a folder")
def _(r): _flag_file(r, "--fluoro", "frames").mkdir()


@bad("fluoro", "flat_frame", "fluoro.png", "flat")
def _(r):
    (r.case / F).unlink()
    (r.case / "fluoro_mask.png").unlink()
    Image.fromarray(np.full((416, 416), 128, np.uint8)).save(r.case / "fluoro.png")


@bad("fluoro", "pure_noise_frame", "fluoro.png", NOT_A_TREE)
def _(r):
    (r.case / F).unlink()
    (r.case / "fluoro_mask.png").unlink()
    noise = np.random.default_rng(0).integers(0, 255, (416, 416)).astype(np.uint8)
    Image.fromarray(noise).save(r.case / "fluoro.png")


@bad("fluoro", "png_bomb_header", "fluoro.png", "larger than the limit")
def _(r):
    (r.case / F).unlink()
    (r.case / "fluoro_mask.png").unlink()
    _png_with_size(r.case / "fluoro.png", 100_000, 100_000)


def _png_with_size(path: Path, width: int, height: int) -> None:
    """A PNG whose header claims ``width x height`` (its data is a tiny stream)."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    _write(path, b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(1000)))
           + chunk(b"IEND", b""))


@bad("options", "frame_out_of_range", F, "frame 5 out of range")
def _(r): r.args += ["--frame", "5"]


@bad("options", "frame_negative", F, "out of range")
def _(r): r.args += ["--frame", "-1"]


# --------------------------------------------------------------------------- fluoro_mask.png

K = "fluoro_mask.png"


broken_file(K, "fluoro_mask", keep=0.4, truncated="not a readable image", random="not a readable image")


@bad("fluoro_mask", "all_black", K, "no foreground")
def _(r): Image.fromarray(np.zeros((416, 416), np.uint8)).save(r.case / K)


@bad("fluoro_mask", "all_white", K, "every pixel")
def _(r): Image.fromarray(np.full((416, 416), 255, np.uint8)).save(r.case / K)


@bad("fluoro_mask", "random_noise", K, NOT_A_TREE)
def _(r):
    noise = np.random.default_rng(1).random((416, 416)) < 0.3
    Image.fromarray((noise * 255).astype(np.uint8)).save(r.case / K)


@bad("fluoro_mask", "other_anatomy", K, NOT_A_TREE)
def _(r):
    mask = np.zeros((416, 416), np.uint8)
    mask[20:60, 20:400] = 255
    Image.fromarray(mask).save(r.case / K)


@bad("fluoro_mask", "png_bomb_header", K, "larger than the limit")
def _(r): _png_with_size(r.case / K, 200_000, 200_000)


not_a_plain_file(K, "fluoro_mask", "fifo", "is_a_folder", "link_out_of_case")


@bad("fluoro_mask", "nan_tiff", "fluoro_mask.tif", "NaN")
def _(r):
    (r.case / K).unlink()
    (r.case / F).unlink()
    Image.fromarray(np.full((416, 416), np.nan, np.float32)).save(r.case / "fluoro_mask.tif")


# --------------------------------------------------------------------------- geometry.json

G = "geometry.json"


@bad("geometry", "zero_bytes", G, "empty")
def _(r): _write(r.case / G, b"")


@bad("geometry", "not_json", G, "not valid geometry JSON")
def _(r): _write(r.case / G, b"{projection_matrix: oops")


@bad("geometry", "not_utf8", G, "not UTF-8")
def _(r): _write(r.case / G, b'{"projection_matrix": "\xff\xfe"}')


@bad("geometry", "nested_100000", G, "nested too deeply")
def _(r): _write(r.case / G, b"[" * 100_000 + b"]" * 100_000)


@bad("geometry", "top_level_list", G, "projection_matrix")
def _(r): _write(r.case / G, b"[1, 2, 3]")


@bad("geometry", "key_missing", G, "projection_matrix")
def _(r): _write(r.case / G, b'{"matrix": []}')


@bad("geometry", "entries_strings", G, "projection_matrix", "entry [0][0]", "str")
def _(r): _set_P(r.case, [[str(v) for v in row] for row in _P(r.case).tolist()])


@bad("geometry", "entry_bool", G, "projection_matrix", "entry [1][2]", "bool")
def _(r):
    P = _P(r.case).tolist()
    P[1][2] = True
    _set_P(r.case, P)


@bad("geometry", "entry_null", G, "projection_matrix", "entry [2][3]")
def _(r):
    P = _P(r.case).tolist()
    P[2][3] = None
    _set_P(r.case, P)


@bad("geometry", "two_rows", G, "projection_matrix", "3x4")
def _(r): _set_P(r.case, _P(r.case)[:2].tolist())


@bad("geometry", "matrix_is_string", G, "projection_matrix")
def _(r): _set_P(r.case, "identity")


@bad("geometry", "nan_literal", G, "projection_matrix", "NaN")
def _(r): _write(r.case / G, json.dumps({"projection_matrix": [[float("nan")] * 4] * 3}).encode())


@bad("geometry", "scaled_1e300", G, "projection_matrix", "badly scaled")
def _(r): _set_P(r.case, (_P(r.case) * 1e300).tolist())


@bad("geometry", "all_zero", G, "projection_matrix", "degenerate")
def _(r): _set_P(r.case, np.zeros((3, 4)).tolist())


@bad("geometry", "singular", G, "projection_matrix", "singular")
def _(r):
    P = _P(r.case)
    P[:, 2] = P[:, 0]
    _set_P(r.case, P.tolist())


@bad("geometry", "source_inside_the_anatomy", G, "behind the X-ray source")
def _(r):
    # the world moved so that the source sits at the scan's centre: anatomy on both sides of it,
    # wrong whatever P's sign (a P and its negative, the same projection, are both accepted)
    P = _P(r.case)
    centre = io.read_volume(r.case / "aorta_mask.nrrd").center_lps()
    move = np.eye(4)
    move[:3, 3] = source_position(P) - centre
    _set_P(r.case, (P @ move).tolist())


@bad("geometry", "projects_20000px_outside", G, "outside the")
def _(r):
    shift = np.eye(3)
    shift[0, 2] = 20000.0
    _set_P(r.case, (shift @ _P(r.case)).tolist())


not_a_plain_file(G, "geometry", "fifo", "is_a_folder", "broken_link", "link_out_of_case")


@bad("geometry", "flag_missing", "nope.json", "no such file")
def _(r): _flag_file(r, "--geometry", "nope.json")


# --------------------------------------------------------------------------- gt.json (ground truth)

T = "gt.json"


@bad("gt", "top_level_list", T, "intraop_centerline")
def _(r): _write(r.case / T, b"[]")


@bad("gt", "points_are_strings", T, "intraop_centerline.points[0]")
def _(r):
    _edit_json(r.case / T, lambda d: {**d, "intraop_centerline": {**d["intraop_centerline"],
                                                                   "points": ["a"] * 5}})


@bad("gt", "points_a_string", T, "intraop_centerline.points")
def _(r): _edit_json(r.case / T, lambda d: {**d, "intraop_centerline": {"points": "none"}})


@bad("gt", "key_missing", T, "intraop_centerline")
def _(r): _write(r.case / T, b'{"version": 1}')


@bad("gt", "edges_out_of_range", T, "intraop_centerline.edges")
def _(r):
    _edit_json(r.case / T, lambda d: {**d, "intraop_centerline": {**d["intraop_centerline"],
                                                                   "edges": [[0, 10 ** 6]]}})


@bad("gt", "not_json", T, "not valid")
def _(r): _write(r.case / T, b"{")


@bad("gt", "nested_100000", T, "nested too deeply")
def _(r): _write(r.case / T, b"{\"a\":" * 50_000 + b"1" + b"}" * 50_000)


@bad("gt", "fifo", T, "named pipe")
def _(r): _fifo(r.case / T)


# --------------------------------------------------------------------------- ct/ (DICOM series)

def _ct(name, *words, env=None):
    return bad("ct", name, *words, base="ct", env=env)


@_ct("empty_slice", "slice_00005.dcm", "empty")
def _(r): _write(_slices(r.case)[4], b"")


@_ct("truncated_slice", "slice_00005.dcm", "truncated")
def _(r): _truncate(_slices(r.case)[4], 0.6)


@_ct("corrupt_header", "slice_00005.dcm", "corrupt DICOM")
def _(r):
    path = _slices(r.case)[4]
    data = path.read_bytes()
    path.write_bytes(data[:132] + b"\xff" * 64)


@_ct("duplicate_slice", "duplicate slices", "slice_00005")
def _(r): shutil.copy2(_slices(r.case)[4], r.case / "ct" / "slice_copy.dcm")


@_ct("missing_slice", "ct", "missing slices")
def _(r): _slices(r.case)[4].unlink()


@_ct("modality_mr", "slice_00001.dcm", "Modality", "MR")
def _(r): _every_slice(r.case, Modality="MR")


@_ct("one_slice_mr", "slice_00003.dcm", "Modality", "MR")
def _(r): _edit_dicom(_slices(r.case)[2], Modality="MR")


@_ct("rescale_slope_nan", "slice_00001.dcm", "RescaleSlope", "nan")
def _(r): _every_slice(r.case, RescaleSlope="NaN")


@_ct("rescale_slope_zero", "slice_00001.dcm", "RescaleSlope", "0")
def _(r): _every_slice(r.case, RescaleSlope="0")


@_ct("rescale_intercept_text", "slice_00002.dcm", "RescaleIntercept")
def _(r): _edit_raw_tag(_slices(r.case)[1], "RescaleIntercept", "abcd")


@_ct("pixel_spacing_nan", "slice_00001.dcm", "PixelSpacing", "NaN")
def _(r): _edit_dicom(_slices(r.case)[0], PixelSpacing=["NaN", "NaN"])


@_ct("pixel_spacing_text", "slice_00001.dcm", "PixelSpacing")
def _(r): _edit_raw_tag(_slices(r.case)[0], "PixelSpacing", "abcd\\efgh")


@_ct("slice_spacing_1000mm", "ct", "spacing 1000 mm")
def _(r):
    for k, path in enumerate(_slices(r.case)):
        ds = pydicom.dcmread(path)
        ds.ImagePositionPatient = [ds.ImagePositionPatient[0], ds.ImagePositionPatient[1], str(1000.0 * k)]
        ds.save_as(path)


@_ct("position_text", "slice_00003.dcm", "ImagePositionPatient")
def _(r): _edit_raw_tag(_slices(r.case)[2], "ImagePositionPatient", "a\\b\\c")


@_ct("orientation_zero", "slice_00001.dcm", "ImageOrientationPatient")
def _(r): _every_slice(r.case, ImageOrientationPatient=["0"] * 6)


@_ct("sheared", "ct", "sheared")
def _(r):
    for k, path in enumerate(_slices(r.case)):
        ds = pydicom.dcmread(path)
        ds.ImagePositionPatient = [f"{float(ds.ImagePositionPatient[0]) + 0.5 * k:.6g}", ds.ImagePositionPatient[1],
                                   ds.ImagePositionPatient[2]]
        ds.save_as(path)


@_ct("different_sizes", "ct", "differ in size")
def _(r):
    path = _slices(r.case)[3]
    ds = pydicom.dcmread(path)
    pixels = ds.pixel_array[:-2]
    ds.Rows = pixels.shape[0]
    ds.PixelData = pixels.tobytes()
    ds.save_as(path)


@_ct("only_two_slices_left_one", "ct", "only 1 slice")
def _(r):
    for path in _slices(r.case)[1:]:
        path.unlink()


@_ct("only_junk", "ct", "no DICOM series", "README.txt")
def _(r):
    for path in _slices(r.case):
        path.unlink()
    (r.case / "ct" / "README.txt").write_text("the CT is on the PACS")
    (r.case / "ct" / ".DS_Store").write_bytes(b"\0\0\0\1Bud1" * 100)


@_ct("structured_report_only", "ct", "no DICOM series", "not an image slice")
def _(r):
    keep = _slices(r.case)[0]
    for path in _slices(r.case)[1:]:
        path.unlink()
    ds = pydicom.dcmread(keep)
    for keyword in ("PixelData", "Rows", "Columns", "ImagePositionPatient"):
        delattr(ds, keyword)
    ds.Modality = "SR"
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.88.22"
    ds.save_as(keep)


@_ct("empty_folder", "ct", "no DICOM series")
def _(r):
    for path in _slices(r.case):
        path.unlink()


@_ct("slice_link_out_of_case", "slice_00005.dcm", "outside the CT folder")
def _(r):
    path = _slices(r.case)[4]
    shutil.move(path, r.tmp / "moved.dcm")
    os.symlink(r.tmp / "moved.dcm", path)


@_ct("non_utf8_slice_name", "\\xff", "not valid UTF-8")
def _(r):
    path = _slices(r.case)[4]
    os.rename(path, os.fsencode(r.case / "ct") + b"/slice_\xff.dcm")


@_ct("voxel_limit", "ct", "exceeds the limit", "FEVAR_MAX_VOXELS", env={"FEVAR_MAX_VOXELS": "10000"})
def _(r): pass


@_ct("ct_folder_is_link_out", "ct", "outside the case folder")
def _(r):
    shutil.move(r.case / "ct", r.tmp / "ct_elsewhere")
    os.symlink(r.tmp / "ct_elsewhere", r.case / "ct")


@_ct("single_dicom_as_ct_flag", "slice_00001.dcm", "single DICOM file")
def _(r): r.args += ["--ct", str(_slices(r.case)[0])]


@_ct("ct_nrrd_fifo", "ct.nrrd", "named pipe")
def _(r):
    shutil.rmtree(r.case / "ct")
    _fifo(r.case / "ct.nrrd")


# --------------------------------------------------------------------------- case folder

@bad("case", "missing_folder", "nope", "does not exist")
def _(r):
    r.case = r.tmp / "nope"


@bad("case", "empty_folder", "case", "no 3D input")
def _(r):
    for path in list(r.case.iterdir()):
        path.unlink()


@bad("case", "no_frame", "case", "no fluoroscopy frame")
def _(r):
    (r.case / F).unlink()
    (r.case / K).unlink()


@bad("case", "no_geometry_no_tags", "geometry.json is missing")
def _(r):
    (r.case / G).unlink()
    (r.case / F).unlink()


@bad("case", "non_utf8_folder_name", "\\xff", "not valid UTF-8")
def _(r):
    target = os.fsencode(r.tmp) + b"/case_\xff"
    os.rename(r.case, target)
    r.case = Path(os.fsdecode(target))


# --------------------------------------------------------------------------- options

@bad("options", "start_equals_target", "--start and --target", "renal_left")
def _(r): r.args += ["--start", "renal_left", "--target", "renal_left"]


@bad("options", "start_is_aorta", "--start", "aorta")
def _(r): r.args += ["--start", "aorta"]


@bad("options", "unknown_target", "--target", "sma")
def _(r): r.args += ["--target", "sma"]


@bad("options", "unknown_method", "--method", "magic")
def _(r): r.args += ["--method", "magic"]


@bad("options", "frame_not_integer", "--frame", "two")
def _(r): r.args += ["--frame", "two"]


# --------------------------------------------------------------------------- output folder

@bad("out", "equal_to_case", "case", "is the folder of the input")
def _(r): r.out = r.case


@bad("out", "inside_case", "case", "lies inside the folder of the input")
def _(r): r.out = r.case / "results"


@bad("out", "contains_case", "contains the input")
def _(r): r.out = r.tmp


@bad("out", "folder_of_flag_input", "lies inside the folder of the input", "mask.nrrd")
def _(r):
    (r.tmp / "inputs").mkdir()
    shutil.copy2(r.case / M, r.tmp / "inputs" / "mask.nrrd")
    r.args += ["--aorta-mask", str(r.tmp / "inputs" / "mask.nrrd")]
    r.out = r.tmp / "inputs" / "out"


@bad("out", "is_a_file", "out.txt", "not a folder")
def _(r): r.out = _text_file(r.tmp / "out.txt", "keep me")


@bad("out", "holds_other_files", "thesis", "not a FevarPlanner output set")
def _(r):
    r.out = r.tmp / "thesis"
    r.out.mkdir()
    (r.out / "chapter1.tex").write_text("keep me")


@bad("out", "parent_is_a_file", "not a folder")
def _(r):
    (r.tmp / "plain").write_text("x")
    r.out = r.tmp / "plain" / "out"


@bad("out", "dev_null", "/dev/null", "not a folder")
def _(r): r.out = Path("/dev/null")


@bad("out", "empty_string", "--out", "empty")
def _(r): r.argv = ["-q", "plan", str(r.case), "--out", ""]


@bad("out", "name_too_long", "File name too long")
def _(r): r.out = r.tmp / ("x" * 300)


@bad("out", "full_disk", "No space left on device", "was left as it was")
def _(r):
    r.patch = ("FevarPlannerLib.export.write_result_json", errno.ENOSPC)


@bad("out", "failure_after_first_file", "Input/output error", "was left as it was")
def _(r):
    r.patch = ("FevarPlannerLib.export.render_overlay", errno.EIO)


# --------------------------------------------------------------------------- weights and checkpoints

class _Exploit:
    """Pickled, it asks the loader to call ``open(marker, 'w')``: code run by loading a file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _crafted_checkpoint(path: Path, marker: Path) -> None:
    with open(path, "wb") as handle:
        torch.save({"model_config": {}, "payload": _Exploit(marker)}, handle)


@bad("weights", "segment_model_crafted_pickle", "evil.pt", "refused to load")
def _(r):
    _crafted_checkpoint(r.tmp / "evil.pt", r.tmp / "pwned")
    r.argv = ["-q", "segment", str(r.case / M), "--out", str(r.out / "mask.nrrd"), "--model", str(r.tmp / "evil.pt"),
              "--segmenter", "unet"]


@bad("weights", "resume_crafted_pickle", "evil.pt", "refused to load")
def _(r):
    _crafted_checkpoint(r.tmp / "evil.pt", r.tmp / "pwned")
    r.argv = ["-q", "train-unet", str(r.case), "--out", str(r.out / "w.pt"), "--iterations", "1",
              "--resume", str(r.tmp / "evil.pt")]


@bad("weights", "segment_model_zero_bytes", "w.pt", "empty")
def _(r):
    (r.tmp / "w.pt").write_bytes(b"")
    r.argv = ["-q", "segment", str(r.case / M), "--out", str(r.out / "mask.nrrd"), "--model", str(r.tmp / "w.pt"),
              "--segmenter", "unet"]


@bad("weights", "segment_model_random_bytes", "w.pt", "not a readable PyTorch checkpoint")
def _(r):
    _random_bytes(r.tmp / "w.pt")
    r.argv = ["-q", "segment", str(r.case / M), "--out", str(r.out / "mask.nrrd"), "--model", str(r.tmp / "w.pt"),
              "--segmenter", "unet"]


@bad("weights", "segment_model_fifo", "w.pt", "named pipe")
def _(r):
    _fifo(r.tmp / "w.pt")
    r.argv = ["-q", "segment", str(r.case / M), "--out", str(r.out / "mask.nrrd"), "--model", str(r.tmp / "w.pt"),
              "--segmenter", "unet"]


@bad("weights", "segment_model_without_unet", "w.pt", "--segmenter unet only")
def _(r):
    (r.tmp / "w.pt").write_bytes(b"weights")
    r.argv = ["-q", "segment", str(r.case / M), "--out", str(r.out / "mask.nrrd"), "--model", str(r.tmp / "w.pt"),
              "--segmenter", "threshold"]


@bad("weights", "segment_out_is_the_input", M, "overwrite")
def _(r):
    r.argv = ["-q", "segment", str(r.case / M), "--out", str(r.case / M), "--segmenter", "threshold"]


@bad("weights", "segment_ct_fifo", "ct.nrrd", "named pipe")
def _(r):
    _fifo(r.tmp / "ct.nrrd")
    r.argv = ["-q", "segment", str(r.tmp / "ct.nrrd"), "--out", str(r.out / "mask.nrrd"), "--segmenter", "threshold"]


# --------------------------------------------------------------------------- found by probing further

@_ct("pixel_spacing_zero", "ct", "PixelSpacing", "positive")
def _(r): _every_slice(r.case, PixelSpacing=["0", "0"])


@_ct("rows_zero_everywhere", "ct", "0x78 pixels")
def _(r): _every_slice(r.case, Rows=0)


@bad("fluoro", "number_of_frames_zero", F, "frame 0 out of range")
def _(r): _edit_dicom(r.case / F, NumberOfFrames=0)


@bad("fluoro", "rows_zero", F, "no pixels")
def _(r): _edit_dicom(r.case / F, Rows=0)


@bad("geometry", "one_entry_1e308", G, "projection_matrix", "badly scaled")
def _(r):
    P = _P(r.case)
    P[0, 0] = 1e308
    _set_P(r.case, P.tolist())


@bad("geometry", "file_of_65MB", G, "exceeds the")
def _(r): _write(r.case / G, b" " * (65 * 1024 * 1024) + b"{}")


@bad("gt", "other_anatomy", T, "share no anatomy label")
def _(r): _edit_json(r.case / T, lambda d: {**d, "intraop_centerline": {"points": [[0, 0, 0]] * 3}})


@bad("aorta_mask", "size_zero", M, "size is zero")
def _(r): _nrrd(r.case / M, {"sizes": "0 4 4"})


@bad("aorta_mask", "direction_singular", M, "direction matrix is singular")
def _(r): _nrrd(r.case / M, {"sizes": "4 4 4", "space directions": "(2,0,0) (2,0,0) (0,0,2)"}, bytes(64))


@bad("aorta_mask", "nifti_decompression_bomb", "aorta_mask.nii.gz", "2000 x 2000 x 700", "FEVAR_MAX_VOXELS")
def _(r):
    import struct

    (r.case / M).unlink()
    header = bytearray(352)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, 3, 2000, 2000, 700, 1, 1, 1, 1)
    struct.pack_into("<hh", header, 70, 2, 8)                 # uint8
    struct.pack_into("<8f", header, 76, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<f", header, 108, 352)
    header[344:348] = b"n+1\0"
    (r.case / "aorta_mask.nii.gz").write_bytes(gzip.compress(bytes(header) + bytes(4096)))


@bad("case", "is_a_file", "case.txt", "does not exist")
def _(r): r.case = _text_file(r.tmp / "case.txt", "not a folder")


@bad("case", "is_a_fifo", "case_fifo", "does not exist")
def _(r):
    r.case = r.tmp / "case_fifo"
    os.mkfifo(r.case)


@bad("out", "link_to_the_case", "is the folder of the input")
def _(r):
    os.symlink(r.case, r.tmp / "link")
    r.out = r.tmp / "link"


@bad("out", "previous_set_plus_a_subfolder", "views", "would delete")
def _(r): (r.out / "views").mkdir()


@bad("out", "previous_set_plus_notes", "notes.txt", "would delete")
def _(r): (r.out / "notes.txt").write_text("keep me")


@bad("out", "non_utf8_name", "\\xff", "not valid UTF-8")
def _(r): r.out = Path(os.fsdecode(os.fsencode(r.tmp) + b"/out_\xff"))


# --------------------------------------------------------------------------- the runner

def _stage(r: Run, good) -> None:
    shutil.copytree(good["previous"], r.out)


@pytest.mark.parametrize("entry", CORPUS, ids=[entry.id for entry in CORPUS])
def test_bad_input_is_refused_cleanly(entry: Bad, good, tmp_path, capsys, monkeypatch):
    case = tmp_path / "case"
    shutil.copytree(good[entry.base], case)
    run = Run(case=case, out=tmp_path / "out", tmp=tmp_path)
    _stage(run, good)
    run.patch = None
    entry.mutate(run)
    for name, value in entry.env.items():
        monkeypatch.setenv(name, value)
    if run.patch is not None:
        target, code = run.patch

        def fail(*args, **kwargs):
            raise OSError(code, os.strerror(code), str(run.out))
        monkeypatch.setattr(target, fail)
    before = snapshot(run.out)
    argv = run.argv or ["-q", "plan", str(run.case), "--out", str(run.out), *run.args]
    capsys.readouterr()
    try:
        code = cli.main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("fevar-planner: error: "), err
    assert "Traceback" not in err
    for word in entry.words:
        assert any(w in lines[0] for w in word.split("|")), (word, lines[0])
    assert snapshot(run.out) == before
    assert not list(run.out.parent.glob(f".{run.out.name}.*")), "a staging folder was left behind"
    assert not (tmp_path / "pwned").exists(), "loading the file ran code"


def test_the_corpus_is_large_and_covers_every_input_kind():
    categories = {entry.category for entry in CORPUS}
    assert len(CORPUS) >= 100
    assert {"ct", "aorta_mask", "skeleton3d", "fluoro", "fluoro_mask", "geometry", "gt", "case", "options",
            "out", "weights"} <= categories
    assert len({entry.id for entry in CORPUS}) == len(CORPUS)


# --------------------------------------------------------------------------- killed and concurrent runs

def _cli_process(argv: list[str]) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO / "FevarPlanner"), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "FevarPlannerLib.cli", "-q", *argv], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _without_timings(snap: dict) -> dict:
    """A snapshot with result.json's timings blanked (the one part that differs run to run)."""
    out = dict(snap)
    if out.get("result.json"):
        data = json.loads(out["result.json"])
        data["timings_s"] = {}
        out["result.json"] = json.dumps(data, sort_keys=True).encode()
    return out


@pytest.fixture(scope="module")
def reference_sets(good, tmp_path_factory):
    """Complete output sets of the mask case by two methods, as the killed runs would write them."""
    root = tmp_path_factory.mktemp("reference")
    sets = {}
    for method in ("rigid", "proposed"):
        assert cli.main(["-q", "plan", str(good["mask"]), "--out", str(root / method), "--method", method]) == 0
        sets[method] = snapshot(root / method)
    return root, sets


def _kill_when(process: subprocess.Popen, ready, timeout_s: float = 60.0) -> bool:
    """SIGKILL ``process`` as soon as ``ready()`` holds; False if it ended first."""
    end = time.monotonic() + timeout_s
    while process.poll() is None and time.monotonic() < end:
        if ready():
            process.send_signal(signal.SIGKILL)
            process.wait()
            return True
        time.sleep(0.001)
    process.wait()
    return False


@pytest.mark.parametrize("moment", ["starting", "writing", "writing_plus_30ms"])
def test_a_killed_run_leaves_the_old_set_or_the_whole_new_one(good, reference_sets, tmp_path, moment):
    root, sets = reference_sets
    out = tmp_path / "out"
    shutil.copytree(root / "rigid", out)
    process = _cli_process(["plan", str(good["mask"]), "--out", str(out), "--method", "proposed"])
    started = time.monotonic()
    if moment == "starting":
        killed = _kill_when(process, lambda: time.monotonic() - started > 0.3)
    else:
        # the staging folder beside the output appears when the outputs start to be written
        wait_s = 0.03 if moment == "writing_plus_30ms" else 0.0
        seen = []

        def writing() -> bool:
            if not seen and any(tmp_path.glob(".out.writing.*")):
                seen.append(time.monotonic())
            return bool(seen) and time.monotonic() - seen[0] >= wait_s
        killed = _kill_when(process, writing)
    after = snapshot(out)
    assert after == sets["rigid"] or _without_timings(after) == _without_timings(sets["proposed"])
    if killed and moment == "starting":
        assert after == sets["rigid"]


def test_two_runs_into_one_folder_leave_one_whole_set(good, reference_sets, tmp_path):
    root, sets = reference_sets
    out = tmp_path / "out"
    runs = [_cli_process(["plan", str(good["mask"]), "--out", str(out), "--method", method])
            for method in ("rigid", "proposed")]
    codes = [run.wait() for run in runs]
    assert codes == [0, 0], [run.stderr.read().decode(errors="replace") for run in runs]
    after = _without_timings(snapshot(out))
    assert after in (_without_timings(sets["rigid"]), _without_timings(sets["proposed"]))
    assert not list(tmp_path.glob(".out.*"))


def test_a_flag_may_point_out_of_the_case_where_a_case_file_may_not(good, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(good["mask"], case)
    elsewhere = tmp_path / "shared"
    elsewhere.mkdir()
    shutil.move(case / "geometry.json", elsewhere / "geometry.json")
    os.symlink(elsewhere / "geometry.json", case / "geometry.json")
    assert cli.main(["-q", "plan", str(case), "--out", str(tmp_path / "out")]) == 2
    assert "outside the case folder" in capsys.readouterr().err
    assert cli.main(["-q", "plan", str(case), "--out", str(tmp_path / "out"),
                     "--geometry", str(case / "geometry.json")]) == 0


def test_the_shipped_weights_load_without_unpickling_code():
    from FevarPlannerLib.segmentation import default_model_path, load_unet

    if not default_model_path().is_file():
        pytest.skip("no shipped weights in this tree")
    model = load_unet()
    assert sum(p.numel() for p in model.parameters()) > 1000


def test_a_crafted_checkpoint_is_refused_and_runs_nothing(tmp_path):
    from FevarPlannerLib.segmentation import load_unet

    marker = tmp_path / "pwned"
    _crafted_checkpoint(tmp_path / "evil.pt", marker)
    with pytest.raises(io.InputError, match="refused to load.*open"):
        load_unet(tmp_path / "evil.pt")
    assert not marker.exists()
    # the same file loaded the unsafe way would have run it: the test's file is a real exploit
    torch.load(tmp_path / "evil.pt", weights_only=False)
    assert marker.exists()


# --------------------------------------------------------------------------- the gates on their own

def test_skeleton_thinness_separates_a_curve_from_a_solid():
    from FevarPlannerLib.plausibility import check_skeleton_is_thin

    curve = np.zeros((20, 20, 20), bool)
    curve[2:18, 10, 10] = True
    curve[10, 10:18, 10] = True                       # a junction: one voxel with three neighbours
    grid = dict(spacing=(1, 1, 1), origin=(0, 0, 0), direction=np.eye(3))
    check_skeleton_is_thin(io.Volume(curve, **grid), "curve.nrrd")
    solid = np.zeros((20, 20, 20), bool)
    solid[5:15, 5:15, 5:15] = True
    with pytest.raises(io.InputError, match=r"solid.nrrd: not a one-voxel-thin skeleton \(100% of its 1000 voxels"):
        check_skeleton_is_thin(io.Volume(solid, **grid), "solid.nrrd")


def test_result_gates_warn_then_refuse_as_nodes_move_further():
    from FevarPlannerLib.centerline import Centerline
    from FevarPlannerLib.plausibility import result_warnings

    points = np.column_stack([np.zeros(11), np.zeros(11), np.linspace(0, 100, 11)])
    edges = np.column_stack([np.arange(10), np.arange(1, 11)])
    preop = Centerline(points, edges, ["aorta"] * 11)
    assert result_warnings(preop, preop, "f.png") == []
    moved = points + [35.0, 0.0, 0.0]
    assert any("moved 35 mm" in w for w in result_warnings(preop, preop.with_points(moved), "f.png"))
    with pytest.raises(io.InputError, match="f.png: implausible registration: a node moved 50 mm"):
        result_warnings(preop, preop.with_points(points + [50.0, 0.0, 0.0]), "f.png")
    stretched = points * [1, 1, 1.45]
    with pytest.raises(io.InputError, match=r"aorta is 145 mm long after registration, 100 mm before \(\+45%\)"):
        result_warnings(preop, preop.with_points(stretched), "f.png", method="proposed")
    assert any("+45%" in w for w in result_warnings(preop, preop.with_points(stretched), "f.png", method="icp-tps"))


def test_a_planted_cache_entry_runs_nothing_and_is_recomputed(good, tmp_path, monkeypatch):
    from FevarPlannerLib import cache

    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(tmp_path / "cache"))
    case = io.load_case(good["mask"])
    first = cache.preop_model(case, segmenter="threshold")
    entry = cache._entry_path(tmp_path / "cache", first.key)
    assert entry.is_file() and not first.from_cache
    marker = tmp_path / "pwned"
    entry.write_bytes(pickle.dumps({"key": first.key, "payload": _Exploit(marker)}))
    again = cache.preop_model(case, segmenter="threshold")
    assert not marker.exists() and not again.from_cache
    assert cache.preop_model(case, segmenter="threshold").from_cache    # the planted file was replaced
    entry.unlink()
    os.mkfifo(entry)                                                    # a pipe is never opened
    assert not cache.preop_model(case, segmenter="threshold").from_cache

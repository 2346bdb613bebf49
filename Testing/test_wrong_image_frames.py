"""Issue 11, image-only wrong frames: the builders of Testing/benchmarks/bench_wrong_frames.py on
frames that are images (``fluoro.dcm``, 16-bit ``fluoro.png``), not masks.

A mirrored DICOM frame keeps every tag and has its pixels (every frame of a run) flipped
left-right; a mirrored 16-bit PNG stays 16-bit; frames are swapped only between cases whose
frame files have the same names, and an image-only case gets no ``late`` kind.
"""

import json
import sys
from pathlib import Path

import numpy as np
import pydicom
import pytest
from PIL import Image

from FevarPlannerLib import io
from FevarPlannerLib.projection import CArmGeometry

sys.path.insert(0, str(Path(__file__).resolve().parent / "benchmarks"))
bench = pytest.importorskip("bench_wrong_frames")

ROWS, COLS = 24, 32
PIXEL_DATA = 0x7FE00010


def ramp_frames(n: int) -> np.ndarray:
    """``n`` frames whose pixels all differ, so that any flip shows."""
    return (np.arange(n * ROWS * COLS, dtype=np.uint16).reshape(n, ROWS, COLS) * 7 + 100).astype(np.uint16)


def write_dicom(path: Path, frames: np.ndarray) -> Path:
    carm = CArmGeometry(sid=1200.0, sod=800.0, pixel_spacing=(0.3, 0.3), primary_angle=12.0, secondary_angle=-5.0,
                        rows=ROWS, cols=COLS)
    io.write_fluoro_dicom(path, frames, carm, patient_name="Test^Flip", patient_id="FLIP")
    return path


def tags_but_pixels(dataset) -> dict:
    return {element.tag: element.value for element in dataset if element.tag != PIXEL_DATA}


@pytest.mark.parametrize("n_frames", [1, 3])
def test_flipped_dicom_keeps_its_tags_and_mirrors_its_pixels(tmp_path, n_frames):
    frames = ramp_frames(n_frames)
    path = write_dicom(tmp_path / "fluoro.dcm", frames[0] if n_frames == 1 else frames)
    before = pydicom.dcmread(path)
    bench.flip_frame_file(path)
    after = pydicom.dcmread(path)
    assert tags_but_pixels(after) == tags_but_pixels(before)
    assert after.file_meta.TransferSyntaxUID == before.file_meta.TransferSyntaxUID
    np.testing.assert_array_equal(after.pixel_array, before.pixel_array[..., ::-1])
    read = io.read_fluoro(path, frame=n_frames - 1)
    np.testing.assert_array_equal(read.image, frames[-1][:, ::-1].astype(read.image.dtype))
    assert read.carm.primary_angle == pytest.approx(12.0)


def test_flipped_16_bit_png_stays_16_bit(tmp_path):
    image = ramp_frames(1)[0] * 9
    path = tmp_path / "fluoro.png"
    io.write_png(path, image)
    bench.flip_frame_file(path)
    with Image.open(path) as flipped:
        pixels = np.asarray(flipped)
    np.testing.assert_array_equal(pixels, image[:, ::-1])
    assert pixels.max() > 255


def image_case(folder: Path, frame_name: str, value: int) -> Path:
    folder.mkdir(parents=True)
    frame = np.full((ROWS, COLS), value, dtype=np.uint16)
    if frame_name == "fluoro.dcm":
        write_dicom(folder / frame_name, frame)
    elif frame_name == "fluoro_mask.png":
        io.write_mask_png(folder / frame_name, frame > 0)
    else:
        io.write_png(folder / frame_name, frame)
    (folder / "geometry.json").write_text(json.dumps({"projection_matrix": np.eye(3, 4).tolist()}))
    return folder


def test_frames_swapped_only_between_cases_alike(tmp_path):
    rights = [("f", "image_only", image_case(tmp_path / "a", "fluoro.dcm", 1000)),
              ("f", "image_only", image_case(tmp_path / "b", "fluoro.dcm", 2000)),
              ("f", "image_only", image_case(tmp_path / "c", "fluoro.png", 3000)),
              ("f", "phantom", image_case(tmp_path / "d", "fluoro_mask.png", 1))]
    made = bench.wrong_case_folders(rights, tmp_path / "wrong", kinds=("swap", "mirror"))
    kinds = {(right.name, kind) for _, kind, _, right in made}
    assert kinds == {("a", "swap"), ("a", "mirror"), ("b", "swap"), ("b", "mirror"), ("c", "mirror"), ("d", "mirror")}
    assert bench.wrong_case_folders(rights[:3], tmp_path / "late", kinds=("late",)) == []
    swapped = next(folder for _, kind, folder, right in made if kind == "swap" and right.name == "a")
    assert [p.name for p in bench._frame_files(swapped)] == ["fluoro.dcm"]
    assert int(io.read_fluoro(swapped / "fluoro.dcm").image.max()) == 2000
    assert bench.image_only(rights[0][2]) and not bench.image_only(rights[3][2])

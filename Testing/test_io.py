"""IO stage: CT series, masks, fluoroscopy frames, writers and the case folder (docs/DESIGN.md 3-5)."""

import json
import warnings

import numpy as np
import pydicom
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from FevarPlannerLib import io
from FevarPlannerLib.io import InputError, Volume
from FevarPlannerLib.projection import CArmGeometry, projection_matrix_from_carm, write_geometry_json

OBLIQUE = Rotation.from_euler("xyz", [12.0, -25.0, 40.0], degrees=True).as_matrix()
FLIPPED = np.diag([-1.0, -1.0, 1.0])
CARM = CArmGeometry(sid=1150.0, sod=780.0, pixel_spacing=(0.4, 0.38), primary_angle=17.5,
                    secondary_angle=-8.25, rows=24, cols=32)


def ct_volume(direction=np.eye(3), shape=(5, 6, 7), seed=0) -> Volume:
    rng = np.random.default_rng(seed)
    array = rng.integers(-1024, 2500, size=shape).astype(np.int16)
    return Volume(array, spacing=(0.7, 0.85, 2.5), origin=(-120.5, 33.25, -410.125), direction=direction)


def mask_volume(shape=(5, 6, 7), origin=(-120.5, 33.25, -410.125)) -> Volume:
    array = np.zeros(shape, dtype=np.uint8)
    array[1:4, 2:4, 3] = 1
    return Volume(array, spacing=(0.7, 0.85, 2.5), origin=origin, direction=np.eye(3))


def fluoro_frames(n=None, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (CARM.rows, CARM.cols) if n is None else (n, CARM.rows, CARM.cols)
    return rng.integers(0, 4096, size=shape).astype(np.uint16)


def assert_one_line_naming(excinfo, path, *words):
    message = str(excinfo.value)
    assert "\n" not in message
    assert str(path) in message
    for word in words:
        assert word in message


# --------------------------------------------------------------------------- CT

@pytest.mark.parametrize("direction", [np.eye(3), OBLIQUE, FLIPPED], ids=["axial", "oblique", "flipped"])
def test_ct_dicom_series_round_trip(tmp_path, direction):
    volume = ct_volume(direction)
    io.write_ct_dicom_series(volume, tmp_path / "ct")
    assert len(list((tmp_path / "ct").glob("*.dcm"))) == volume.shape[0]
    back = io.read_ct(tmp_path / "ct")
    assert back.array.dtype == np.int16
    np.testing.assert_array_equal(back.array, volume.array)
    np.testing.assert_allclose(back.spacing, volume.spacing, atol=1e-6)
    np.testing.assert_allclose(back.origin, volume.origin, atol=1e-6)
    np.testing.assert_allclose(back.direction, volume.direction, atol=1e-6)


def test_ct_dicom_header_fields(tmp_path):
    volume = ct_volume(OBLIQUE)
    io.write_ct_dicom_series(volume, tmp_path / "ct", patient_id="P7")
    ds = pydicom.dcmread(sorted((tmp_path / "ct").glob("*.dcm"))[2])
    assert ds.SOPClassUID == pydicom.uid.CTImageStorage
    assert ds.PatientID == "P7" and ds.Modality == "CT"
    assert float(ds.RescaleSlope) == 1.0 and float(ds.RescaleIntercept) == 0.0
    np.testing.assert_allclose([float(v) for v in ds.ImagePositionPatient], volume.index_to_lps((2, 0, 0)), atol=1e-9)
    np.testing.assert_allclose([float(v) for v in ds.PixelSpacing], [0.85, 0.7])
    assert float(ds.SliceThickness) == 2.5


def test_left_handed_grid_keeps_voxel_positions(tmp_path):
    volume = ct_volume(np.diag([1.0, 1.0, -1.0]))
    io.write_ct_dicom_series(volume, tmp_path / "ct")
    back = io.read_ct(tmp_path / "ct")
    np.testing.assert_array_equal(back.array, volume.array[::-1])
    np.testing.assert_allclose(back.index_to_lps((0, 2, 3)), volume.index_to_lps((4, 2, 3)), atol=1e-6)
    assert np.linalg.det(back.direction) > 0


def test_ct_writer_is_deterministic_and_replaces_folder_atomically(tmp_path):
    volume = ct_volume()
    io.write_ct_dicom_series(volume, tmp_path / "ct")
    uids = [pydicom.dcmread(p).SOPInstanceUID for p in sorted((tmp_path / "ct").glob("*.dcm"))]
    (tmp_path / "ct" / "stale.txt").write_text("old")
    io.write_ct_dicom_series(volume, tmp_path / "ct")
    assert not (tmp_path / "ct" / "stale.txt").exists()
    assert [pydicom.dcmread(p).SOPInstanceUID for p in sorted((tmp_path / "ct").glob("*.dcm"))] == uids
    assert len(set(uids)) == len(uids)
    too_bright = volume.with_array(volume.array.astype(np.int32) + 40000)
    with pytest.raises(ValueError, match="int16"):
        io.write_ct_dicom_series(too_bright, tmp_path / "ct")
    np.testing.assert_array_equal(io.read_ct(tmp_path / "ct").array, volume.array)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ct"]


def test_two_series_in_one_folder_picks_the_longer_with_warning(tmp_path):
    io.write_ct_dicom_series(ct_volume(shape=(3, 6, 7)), tmp_path / "short", series_uid="1.2.3.4.1")
    io.write_ct_dicom_series(ct_volume(shape=(5, 6, 7), seed=4), tmp_path / "long", series_uid="1.2.3.4.2")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for tag, folder in (("a", "short"), ("b", "long")):
        for path in (tmp_path / folder).iterdir():
            path.rename(mixed / f"{tag}_{path.name}")
    with pytest.warns(UserWarning) as record:
        back = io.read_ct(mixed)
    message = str(record[0].message)
    assert str(mixed) in message and "1.2.3.4.1" in message and "1.2.3.4.2" in message
    np.testing.assert_array_equal(back.array, ct_volume(shape=(5, 6, 7), seed=4).array)


def test_missing_slice_is_an_error(tmp_path):
    io.write_ct_dicom_series(ct_volume(shape=(6, 6, 7)), tmp_path / "ct")
    sorted((tmp_path / "ct").glob("*.dcm"))[3].unlink()
    with pytest.raises(InputError) as excinfo:
        io.read_ct(tmp_path / "ct")
    assert_one_line_naming(excinfo, tmp_path / "ct", "missing slices", "5 mm")


def test_uneven_slice_spacing_is_an_error(tmp_path):
    io.write_ct_dicom_series(ct_volume(shape=(6, 6, 7)), tmp_path / "ct")
    path = sorted((tmp_path / "ct").glob("*.dcm"))[3]
    ds = pydicom.dcmread(path)
    ds.ImagePositionPatient = [ds.ImagePositionPatient[0], ds.ImagePositionPatient[1],
                               float(ds.ImagePositionPatient[2]) + 0.5]
    ds.save_as(path)
    with pytest.raises(InputError) as excinfo:
        io.read_ct(tmp_path / "ct")
    assert_one_line_naming(excinfo, tmp_path / "ct", "inconsistent slice spacing")


def test_folder_without_dicom_is_an_error(tmp_path):
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "notes.txt").write_text("no images here")
    (tmp_path / "ct" / "empty.dcm").write_bytes(b"")
    with pytest.raises(InputError) as excinfo:
        io.read_ct(tmp_path / "ct")
    assert_one_line_naming(excinfo, tmp_path / "ct", "no DICOM series")


@pytest.mark.parametrize("suffix", [".nrrd", ".nii.gz", ".mha"])
def test_volume_file_round_trip(tmp_path, suffix):
    volume = ct_volume(FLIPPED if suffix == ".nii.gz" else OBLIQUE)
    io.write_volume(tmp_path / f"ct{suffix}", volume)
    back = io.read_ct(tmp_path / f"ct{suffix}")
    np.testing.assert_array_equal(back.array, volume.array)
    np.testing.assert_allclose(back.spacing, volume.spacing, atol=1e-5)
    np.testing.assert_allclose(back.origin, volume.origin, atol=1e-4)
    np.testing.assert_allclose(back.direction, volume.direction, atol=1e-5)


def test_read_mask_gives_bool_and_refuses_empty_or_full(tmp_path):
    io.write_volume(tmp_path / "mask.nrrd", mask_volume())
    mask = io.read_mask(tmp_path / "mask.nrrd")
    assert mask.array.dtype == bool and mask.array.sum() == 6
    empty = mask_volume().with_array(np.zeros((5, 6, 7), dtype=np.uint8))
    io.write_volume(tmp_path / "empty.nrrd", empty)
    with pytest.raises(InputError) as excinfo:
        io.read_mask(tmp_path / "empty.nrrd")
    assert_one_line_naming(excinfo, tmp_path / "empty.nrrd", "no foreground voxels")
    io.write_volume(tmp_path / "full.nrrd", empty.with_array(np.ones((5, 6, 7), dtype=np.uint8)))
    with pytest.raises(InputError, match="every voxel"):
        io.read_mask(tmp_path / "full.nrrd")


def test_check_same_grid(tmp_path):
    io.check_same_grid(mask_volume(), ct_volume(), "a.nrrd")
    with pytest.raises(InputError) as excinfo:
        io.check_same_grid(mask_volume(origin=(0.0, 0.0, 0.0)), ct_volume(), "a.nrrd")
    assert_one_line_naming(excinfo, "a.nrrd", "differs from the CT")


# --------------------------------------------------------------------------- fluoroscopy

def test_xa_single_frame_round_trip_and_projection_from_tags(tmp_path):
    frames = fluoro_frames()
    io.write_fluoro_dicom(tmp_path / "f.dcm", frames, CARM)
    fluoro = io.read_fluoro(tmp_path / "f.dcm")
    assert fluoro.image.dtype == np.float32 and fluoro.shape == (24, 32)
    np.testing.assert_array_equal(fluoro.image, frames.astype(np.float32))
    assert (fluoro.frame, fluoro.n_frames) == (0, 1)
    assert fluoro.carm == CARM
    assert fluoro.pixel_spacing == CARM.pixel_spacing
    isocentre = np.array([10.0, -20.0, 300.0])
    np.testing.assert_allclose(projection_matrix_from_carm(fluoro.carm, isocentre),
                               projection_matrix_from_carm(CARM, isocentre), rtol=1e-12)
    assert pydicom.dcmread(tmp_path / "f.dcm").SOPClassUID == pydicom.uid.XRayAngiographicImageStorage


def test_xa_multi_frame_selects_frames(tmp_path):
    frames = fluoro_frames(n=3)
    io.write_fluoro_dicom(tmp_path / "run.dcm", frames, CARM)
    assert int(pydicom.dcmread(tmp_path / "run.dcm").NumberOfFrames) == 3
    for index in range(3):
        fluoro = io.read_fluoro(tmp_path / "run.dcm", frame=index)
        np.testing.assert_array_equal(fluoro.image, frames[index])
        assert (fluoro.frame, fluoro.n_frames) == (index, 3)
    with pytest.raises(InputError) as excinfo:
        io.read_fluoro(tmp_path / "run.dcm", frame=3)
    assert_one_line_naming(excinfo, tmp_path / "run.dcm", "frame 3 out of range", "3 frames")


def test_monochrome1_is_inverted(tmp_path):
    frames = fluoro_frames()
    io.write_fluoro_dicom(tmp_path / "m1.dcm", frames, CARM, photometric="MONOCHROME1")
    fluoro = io.read_fluoro(tmp_path / "m1.dcm")
    np.testing.assert_array_equal(fluoro.image, 65535.0 - frames)


def test_dicom_without_carm_tags_and_with_pixel_spacing_fallback(tmp_path):
    io.write_fluoro_dicom(tmp_path / "f.dcm", fluoro_frames(), CARM)
    ds = pydicom.dcmread(tmp_path / "f.dcm")
    del ds.DistanceSourceToPatient, ds.ImagerPixelSpacing
    ds.PixelSpacing = [0.5, 0.25]
    ds.save_as(tmp_path / "g.dcm")
    fluoro = io.read_fluoro(tmp_path / "g.dcm")
    assert fluoro.carm is None and fluoro.pixel_spacing == (0.5, 0.25)
    assert set(fluoro.missing_tags) == {"DistanceSourceToPatient", "ImagerPixelSpacing"}


def test_fluoro_writer_checks_frame_size(tmp_path):
    with pytest.raises(ValueError, match="24x32"):
        io.write_fluoro_dicom(tmp_path / "f.dcm", np.zeros((10, 10), np.uint16), CARM)
    assert not any(tmp_path.iterdir())


def test_png_grey_8_and_16_bit_and_rgb(tmp_path):
    grey8 = (np.arange(20 * 30) % 256).astype(np.uint8).reshape(20, 30)
    grey16 = (np.arange(20 * 30) * 97).astype(np.uint16).reshape(20, 30)
    io.write_png(tmp_path / "g8.png", grey8)
    io.write_png(tmp_path / "g16.png", grey16)
    np.testing.assert_array_equal(io.read_fluoro(tmp_path / "g8.png").image, grey8)
    np.testing.assert_array_equal(io.read_fluoro(tmp_path / "g16.png").image, grey16)
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    Image.fromarray(np.dstack([rgb, np.full((4, 5), 128, np.uint8)])).save(tmp_path / "rgba.tif")
    expected = 0.299 * 200 + 0.587 * 100 + 0.114 * 50
    for name in ("rgb.png", "rgba.tif"):
        fluoro = io.read_fluoro(tmp_path / name)
        assert fluoro.carm is None and fluoro.pixel_spacing is None
        np.testing.assert_allclose(fluoro.image, expected, rtol=1e-6)


def test_read_mask_2d(tmp_path):
    mask = np.zeros((24, 32), bool)
    mask[5:9, 3:20] = True
    io.write_mask_png(tmp_path / "mask.png", mask)
    assert np.asarray(Image.open(tmp_path / "mask.png")).max() == 255
    np.testing.assert_array_equal(io.read_mask_2d(tmp_path / "mask.png", shape=(24, 32)), mask)
    with pytest.raises(InputError) as excinfo:
        io.read_mask_2d(tmp_path / "mask.png", shape=(30, 32))
    assert_one_line_naming(excinfo, tmp_path / "mask.png", "24x32", "30x32")
    io.write_mask_png(tmp_path / "empty.png", np.zeros((24, 32), bool))
    with pytest.raises(InputError) as excinfo:
        io.read_mask_2d(tmp_path / "empty.png")
    assert_one_line_naming(excinfo, tmp_path / "empty.png", "no foreground pixels")


def test_jpeg_mask_ignores_compression_noise(tmp_path):
    mask = np.zeros((32, 32), bool)
    mask[10:20, 4:28] = True
    Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(tmp_path / "mask.jpg", quality=60)
    assert (np.asarray(Image.open(tmp_path / "mask.jpg"))[~mask] > 0).any()
    assert (io.read_mask_2d(tmp_path / "mask.jpg") != mask).mean() < 0.02


# --------------------------------------------------------------------------- bad files

def _nan_volume(path):
    io.write_volume(path, Volume(np.full((2, 3, 4), np.nan, np.float32), (1, 1, 1), (0, 0, 0), np.eye(3)))


@pytest.mark.parametrize("name, make, reader, words", [
    ("empty.dcm", lambda p: p.write_bytes(b""), io.read_fluoro, ["0 bytes"]),
    ("junk.dcm", lambda p: p.write_bytes(b"this is not DICOM at all" * 20), io.read_fluoro, ["not a readable DICOM"]),
    ("junk.png", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 30), io.read_fluoro, ["not a readable image"]),
    ("absent.png", lambda p: None, io.read_fluoro, ["no such file"]),
    ("empty.nrrd", lambda p: p.write_bytes(b""), io.read_ct, ["0 bytes"]),
    ("junk.nrrd", lambda p: p.write_bytes(b"NRRD0004\nnonsense: 1\n\n"), io.read_ct, ["cannot read volume"]),
    ("nan.nrrd", _nan_volume, io.read_ct, ["NaN"]),
    ("flat.png", lambda p: io.write_png(p, np.zeros((4, 4), np.uint8)), io.read_ct, ["3D"]),
    ("nan.tif", lambda p: Image.fromarray(np.full((4, 4), np.nan, np.float32)).save(p), io.read_fluoro, ["NaN"]),
    ("notes.txt", lambda p: p.write_text("hello"), io.read_fluoro, ["unknown image format"]),
    ("xa.dcm", lambda p: io.write_fluoro_dicom(p, fluoro_frames(), CARM), io.read_ct, ["single DICOM file"]),
    ("slab.mha", lambda p: io.write_volume(p, ct_volume(shape=(1, 6, 7))), io.read_ct, ["not 3D"]),
    ("folder", lambda p: p.mkdir(), io.read_fluoro, ["is a folder"]),
])
def test_bad_files_give_one_line_errors_naming_the_file(tmp_path, name, make, reader, words):
    path = tmp_path / name
    make(path)
    with pytest.raises(InputError) as excinfo:
        reader(path)
    assert_one_line_naming(excinfo, path, *words)


def test_truncated_dicom_pixel_data_is_an_error(tmp_path):
    io.write_fluoro_dicom(tmp_path / "f.dcm", fluoro_frames(), CARM)
    data = (tmp_path / "f.dcm").read_bytes()
    (tmp_path / "cut.dcm").write_bytes(data[: len(data) - 600])
    with pytest.raises(InputError) as excinfo:
        io.read_fluoro(tmp_path / "cut.dcm")
    assert_one_line_naming(excinfo, tmp_path / "cut.dcm")


# --------------------------------------------------------------------------- case folder

@pytest.fixture
def case_dir(tmp_path):
    """A full case: a corrupt ct.nrrd (so reading it would fail), a mask, a skeleton, a DICOM frame."""
    case = tmp_path / "case"
    case.mkdir()
    (case / "ct.nrrd").write_bytes(b"NRRD0004\ncorrupt\n")
    io.write_volume(case / "aorta_mask.nrrd", mask_volume())
    skeleton = np.zeros((5, 6, 7), np.uint8)
    skeleton[1:4, 3, 3] = 1
    io.write_volume(case / "skeleton3d.nrrd", mask_volume().with_array(skeleton))
    io.write_fluoro_dicom(case / "fluoro.dcm", fluoro_frames(n=2), CARM)
    mask = np.zeros((24, 32), bool)
    mask[4:20, 15:17] = True
    io.write_mask_png(case / "fluoro_mask.png", mask)
    return case


def test_load_case_most_processed_input_wins(case_dir):
    P = projection_matrix_from_carm(CARM, (1.0, 2.0, 3.0)) * 2.0
    write_geometry_json(case_dir / "geometry.json", P)
    case = io.load_case(case_dir, frame=1)
    assert case.stage_3d == "skeleton3d" and case.ct is None and case.aorta_mask is None
    assert case.skeleton3d.array.dtype == bool and case.skeleton3d.array.sum() == 3
    assert case.reference_volume is case.skeleton3d
    assert case.fluoro.frame == 1 and case.fluoro_mask.sum() == 32
    np.testing.assert_allclose(case.P, P)
    assert case.paths == {"skeleton3d": case_dir / "skeleton3d.nrrd", "fluoro": case_dir / "fluoro.dcm",
                          "fluoro_mask": case_dir / "fluoro_mask.png", "geometry": case_dir / "geometry.json"}
    assert case.available["ct"] == case_dir / "ct.nrrd"
    np.testing.assert_array_equal(case.load_input("aorta_mask").array, io.read_mask(case_dir / "aorta_mask.nrrd").array)


def test_a_negated_projection_matrix_is_the_same_projection(case_dir):
    # P is homogeneous (eq. 1): a calibration may hand over -P (w < 0 in front of the source)
    P = projection_matrix_from_carm(CARM, mask_volume().center_lps())
    write_geometry_json(case_dir / "geometry.json", -3.0 * P)
    case = io.load_case(case_dir)
    np.testing.assert_allclose(case.P, 3.0 * P, rtol=1e-12)
    assert case.geometry.sign_flipped and case.geometry.to_dict()["sign_flipped"] is True
    write_geometry_json(case_dir / "geometry.json", 3.0 * P)
    assert not io.load_case(case_dir).geometry.sign_flipped


def test_load_case_geometry_from_carm_tags_at_volume_centre(case_dir):
    (case_dir / "skeleton3d.nrrd").unlink()
    case = io.load_case(case_dir)
    assert case.stage_3d == "aorta_mask"
    expected = projection_matrix_from_carm(CARM, mask_volume().center_lps())
    np.testing.assert_allclose(case.P, expected, rtol=1e-12, atol=1e-9)
    assert case.paths["geometry"] == case_dir / "fluoro.dcm"


def test_load_case_flags_override_the_folder(case_dir, tmp_path):
    other = tmp_path / "other_mask.nii.gz"
    io.write_volume(other, mask_volume(origin=(5.0, 6.0, 7.0)))
    case = io.load_case(case_dir, aorta_mask=other)
    assert case.stage_3d == "aorta_mask" and case.skeleton3d is None
    np.testing.assert_allclose(case.aorta_mask.origin, [5.0, 6.0, 7.0])
    assert "skeleton3d" not in case.available
    png = tmp_path / "frame.png"
    io.write_png(png, fluoro_frames())
    geometry = tmp_path / "g.json"
    write_geometry_json(geometry, projection_matrix_from_carm(CARM))
    case = io.load_case(case_dir, fluoro=png, geometry=geometry)
    assert case.fluoro.path == png and case.fluoro_mask is None
    np.testing.assert_allclose(case.P, projection_matrix_from_carm(CARM))


def test_load_case_reports_what_is_missing(case_dir, tmp_path):
    (case_dir / "fluoro.dcm").unlink()
    (case_dir / "fluoro_mask.png").unlink(missing_ok=True)
    with pytest.raises(InputError) as excinfo:
        io.load_case(case_dir)
    assert_one_line_naming(excinfo, case_dir, "no fluoroscopy frame", "aorta_mask.nrrd", "skeleton3d.nrrd")
    io.write_png(case_dir / "fluoro.png", fluoro_frames())
    with pytest.raises(InputError) as excinfo:
        io.load_case(case_dir)
    assert_one_line_naming(excinfo, case_dir, "geometry.json is missing", "no C-arm tags")
    empty = tmp_path / "empty_case"
    empty.mkdir()
    with pytest.raises(InputError) as excinfo:
        io.load_case(empty)
    assert_one_line_naming(excinfo, empty, "no 3D input", "holds: nothing")
    with pytest.raises(InputError, match="no such file"):
        io.load_case(case_dir, ct=tmp_path / "nope.nrrd")


def test_load_case_mask_off_the_frame_grid(case_dir):
    io.write_mask_png(case_dir / "fluoro_mask.png", np.eye(20, dtype=bool))
    with pytest.raises(InputError) as excinfo:
        io.load_case(case_dir)
    assert_one_line_naming(excinfo, case_dir / "fluoro_mask.png", "20x20", "24x32")


def test_load_input_checks_the_grid(case_dir):
    io.write_volume(case_dir / "aorta_mask.nrrd", mask_volume(origin=(0.0, 0.0, 0.0)))
    case = io.load_case(case_dir)
    with pytest.raises(InputError) as excinfo:
        case.load_input("aorta_mask")
    assert_one_line_naming(excinfo, case_dir / "aorta_mask.nrrd", "differs from the skeleton3d")


def test_load_case_with_dicom_ct_folder(tmp_path):
    case = tmp_path / "case"
    volume = ct_volume(OBLIQUE)
    io.write_ct_dicom_series(volume, case / "ct")
    io.write_fluoro_dicom(case / "fluoro.dcm", fluoro_frames(), CARM)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = io.load_case(case)
    # the one warning says what P from the tags assumed
    assert [w.category.__name__ for w in caught] == ["GeometryAssumptionWarning"]
    assert "isocentre lies at the centre of the CT volume" in str(caught[0].message)
    assert "table position" in str(caught[0].message)
    assert loaded.geometry.kind == "dicom-tags" and loaded.geometry.tags["PositionerPrimaryAngle"] == CARM.primary_angle
    assert loaded.stage_3d == "ct"
    np.testing.assert_array_equal(loaded.ct.array, volume.array)
    np.testing.assert_allclose(loaded.P, projection_matrix_from_carm(CARM, volume.center_lps()), atol=1e-8)
    assert json.loads(json.dumps({k: str(v) for k, v in loaded.paths.items()}))["ct"] == str(case / "ct")


def test_mask_only_case_gets_a_stand_in_frame(case_dir):
    mask = io.read_mask_2d(case_dir / "fluoro_mask.png")
    (case_dir / "fluoro.dcm").unlink()
    with pytest.raises(InputError, match="geometry.json is missing"):
        io.load_case(case_dir)
    from FevarPlannerLib.projection import write_geometry_json
    write_geometry_json(case_dir / "geometry.json", np.hstack([np.eye(3), np.ones((3, 1))]))
    case = io.load_case(case_dir)
    assert case.fluoro.shape == mask.shape
    assert np.array_equal(case.fluoro_mask, mask)
    assert case.fluoro.image[mask].max() < case.fluoro.image[~mask].min()


# --------------------------------------------------------------------------- refusing before reading

def test_special_files_are_refused_from_stat_without_opening(tmp_path):
    import os

    os.mkfifo(tmp_path / "pipe.nrrd")
    with pytest.raises(InputError, match="named pipe"):
        io.read_volume(tmp_path / "pipe.nrrd")          # would block for ever if opened
    (tmp_path / "dev.dcm").symlink_to("/dev/zero")
    with pytest.raises(InputError, match="character device"):
        io.read_fluoro(tmp_path / "dev.dcm")
    (tmp_path / "broken.png").symlink_to(tmp_path / "absent.png")
    with pytest.raises(InputError, match="broken link"):
        io.read_fluoro(tmp_path / "broken.png")


def test_header_limits_come_before_allocation(tmp_path, monkeypatch):
    io.write_volume(tmp_path / "m.nrrd", mask_volume())
    monkeypatch.setenv("FEVAR_MAX_VOXELS", str(5 * 6 * 7 - 1))
    with pytest.raises(InputError, match=r"7 x 6 x 5 voxels exceeds the limit of 209 voxels .*FEVAR_MAX_VOXELS"):
        io.read_mask(tmp_path / "m.nrrd")
    monkeypatch.setenv("FEVAR_MAX_VOXELS", str(5 * 6 * 7))
    assert io.read_mask(tmp_path / "m.nrrd").shape == (5, 6, 7)
    monkeypatch.setenv("FEVAR_MAX_VOXELS", "lots")
    with pytest.raises(InputError, match="FEVAR_MAX_VOXELS='lots': not a number"):
        io.read_mask(tmp_path / "m.nrrd")


def test_detached_data_must_lie_beside_its_header(tmp_path):
    (tmp_path / "case").mkdir()
    (tmp_path / "data.raw").write_bytes(bytes(8))
    header = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\ndata file: {}\n"
    (tmp_path / "case" / "m.nrrd").write_text(header.format("../data.raw"))
    with pytest.raises(InputError, match=r"m.nrrd: its detached data file .*outside the folder of its header"):
        io.read_volume(tmp_path / "case" / "m.nrrd")
    (tmp_path / "case" / "data.raw").write_bytes(bytes([0, 1, 0, 0, 0, 0, 0, 0]))
    (tmp_path / "case" / "m.nrrd").write_text(header.format("data.raw"))
    assert io.read_volume(tmp_path / "case" / "m.nrrd").array.sum() == 1


def test_swap_folder_replaces_a_set_whole_and_modes_follow_the_umask(tmp_path):
    import os

    old = tmp_path / "out"
    old.mkdir()
    (old / "a.txt").write_text("old")
    new = tmp_path / ".staging"
    new.mkdir()
    (new / "b.txt").write_text("new")
    io.swap_folder(new, old)
    assert sorted(p.name for p in old.iterdir()) == ["b.txt"] and not new.exists()
    previous = os.umask(0o077)
    try:
        io.write_text_atomic(tmp_path / "f.txt", "x")
        assert io.output_mode() == 0o600 and io.output_mode(folder=True) == 0o700
    finally:
        os.umask(previous)
    assert (tmp_path / "f.txt").stat().st_mode & 0o777 == 0o600
    io.write_text_atomic(tmp_path / "g.txt", "x")
    assert (tmp_path / "g.txt").stat().st_mode & 0o777 == 0o666 & ~previous


def test_dicom_tags_are_checked_as_numbers_naming_the_tag(tmp_path):
    io.write_fluoro_dicom(tmp_path / "f.dcm", fluoro_frames(), CARM)
    ds = pydicom.dcmread(tmp_path / "f.dcm")
    ds.DistanceSourceToDetector = "NaN"
    ds.save_as(tmp_path / "f.dcm")
    with pytest.raises(InputError) as excinfo:
        io.read_fluoro(tmp_path / "f.dcm")
    assert_one_line_naming(excinfo, tmp_path / "f.dcm", "DistanceSourceToDetector (0018,1110)", "nan")


def test_json_inputs_refuse_deep_nesting_and_points_that_are_not_numbers(tmp_path):
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError, match="nested too deeply"):
        io.read_json_file(tmp_path / "deep.json")
    (tmp_path / "gt.json").write_text(json.dumps({"intraop_centerline": {"points": [[0, 0, "1"]]}}))
    with pytest.raises(InputError, match=r"key 'intraop_centerline.points\[0\]' must be 3 numbers"):
        io.read_ground_truth(tmp_path / "gt.json")
    (tmp_path / "gt.json").write_text(json.dumps({"intraop_centerline": {"points": [[0, 0, 1], [0, 1, 1]],
                                                                         "edges": [[0, 1]]}}))
    assert io.read_ground_truth(tmp_path / "gt.json").points.shape == (2, 3)


def test_a_folder_that_appears_before_the_rename_is_exchanged_not_overwritten(tmp_path):
    from FevarPlannerLib import files

    new, folder = tmp_path / "new", tmp_path / "out"
    new.mkdir()
    (new / "result.json").write_text("new")
    folder.mkdir()
    (folder / "result.json").write_text("other run")
    assert files._moved_into_free_place(new, folder) is False
    assert (new / "result.json").read_text() == "new"
    assert (folder / "result.json").read_text() == "other run"
    files.swap_folder(new, folder)
    assert (folder / "result.json").read_text() == "new"
    assert not new.exists()


def _dead_pid() -> int:
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_staging_left_by_a_killed_run_is_removed_by_the_next_run_and_live_ones_are_kept(tmp_path):
    from FevarPlannerLib import files

    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "result.json").write_text("old set")
    owner = files._staging_owner()
    host = owner.rsplit("-", 1)[0]
    dead = tmp_path / f".out.writing.{host}-{_dead_pid()}.abc123"
    live = tmp_path / f".out.writing.{owner}.def456"
    elsewhere = tmp_path / f".out.writing.otherhost-{_dead_pid()}.ghi789"
    unrelated = tmp_path / ".output.writing.x"
    for leftover in (dead, live, elsewhere, unrelated):
        leftover.mkdir()
        (leftover / "overlay.png").write_bytes(b"half")
    with files.atomic_folder(folder) as staging:
        assert staging.name.startswith(f".out.staging.{owner}.")
        (staging / "result.json").write_text("new set")
    assert (folder / "result.json").read_text() == "new set"
    assert not dead.exists()
    assert live.exists() and elsewhere.exists() and unrelated.exists()
    assert sorted(p.name for p in tmp_path.glob(".out.*")) == sorted([live.name, elsewhere.name])


def test_stale_staging_is_kept_while_the_output_folder_is_missing(tmp_path):
    from FevarPlannerLib import files

    host = files._staging_owner().rsplit("-", 1)[0]
    only_copy = tmp_path / f".out.old.{host}-{_dead_pid()}.abc123"
    only_copy.mkdir()
    assert files.remove_stale_staging(tmp_path / "out") == []
    assert only_copy.exists()

"""Segmentation stage: UNet, training, CT threshold segmenter, post-processing, surface,
fluoroscopy vesselness. All data are small synthetic volumes and frames made here."""

import dataclasses
import functools

import numpy as np
import pytest
import torch
from scipy import ndimage as ndi
import vtk
from vtk.util import numpy_support

from FevarPlannerLib import phantom as ph
from FevarPlannerLib import quality
from FevarPlannerLib import segmentation as seg
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.projection import project
from FevarPlannerLib.io import InputError, Volume


# ----------------------------------------------------------------------------------------
# Synthetic data
# ----------------------------------------------------------------------------------------

def synthetic_ct(shape=(36, 72, 80), spacing=(1.5, 1.5, 2.0), radius_mm=9.0, seed=0):
    """A body ellipse (40 HU) with a bright aortic tube (350 HU) wandering along z, anterior
    to a spine (cortical ring 900 HU around a 250 HU body, in contact with nothing), plus noise.

    Returns the CT Volume, the true lumen Volume and the tube centre (LPS) per slice.
    """
    rng = np.random.default_rng(seed)
    nk, nj, ni = shape
    si, sj, sk = spacing
    origin = np.array([-ni * si / 2, -nj * sj / 2, -nk * sk])
    k, j, i = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
    x, y, z = origin[0] + i * si, origin[1] + j * sj, origin[2] + k * sk
    hu = np.full(shape, -1000.0)
    body = (x / 55.0) ** 2 + (y / 45.0) ** 2 <= 1.0
    hu[body] = 40.0
    spine_r = np.hypot(x - 0.0, y - 22.0)
    hu[spine_r <= 12.0] = 250.0
    hu[(spine_r > 9.0) & (spine_r <= 12.0)] = 900.0
    zc = origin[2] + np.arange(nk) * sk
    centre_x = 6.0 * np.sin(zc / 25.0)
    centre_y = -8.0 + 2.0 * np.cos(zc / 30.0)
    lumen = np.hypot(x - centre_x[:, None, None], y - centre_y[:, None, None]) <= radius_mm
    hu[lumen] = 350.0
    hu += rng.normal(0.0, 15.0, shape)
    ct = Volume(hu.astype(np.float32), spacing, origin, np.eye(3))
    centres = np.column_stack([centre_x, centre_y, zc])
    return ct, ct.with_array(lumen), centres


def _tube_path_length(u, v, p0, p1, radius):
    """Path length through a cylinder of ``radius`` along the 2D segment p0 -> p1 (projection)."""
    d = np.asarray(p1, float) - np.asarray(p0, float)
    t = np.clip(((u - p0[0]) * d[0] + (v - p0[1]) * d[1]) / (d @ d), 0.0, 1.0)
    dist = np.hypot(u - (p0[0] + t * d[0]), v - (p0[1] + t * d[1]))
    return 2.0 * np.sqrt(np.clip(radius ** 2 - dist ** 2, 0.0, None))


def synthetic_frame(size=512, vessels="dark", bone="bright", noise=0.02, seed=0):
    """A DSA-like frame: an aorta with renal and iliac branches (projected cylinders), a large
    bone blob and a spine band, Gaussian noise. Returns (frame in [0, 1], true vessel mask)."""
    rng = np.random.default_rng(seed)
    s = size / 512.0
    v, u = np.mgrid[0:size, 0:size].astype(float)
    segments = [((256, 40), (256, 330), 13), ((256, 150), (120, 130), 5), ((256, 160), (400, 175), 5),
                ((256, 330), (170, 480), 8), ((256, 330), (350, 490), 8)]
    length = np.zeros((size, size))
    for p0, p1, r in segments:
        length = np.maximum(length, _tube_path_length(u, v, np.multiply(p0, s), np.multiply(p1, s), r * s))
    truth = length > 0
    attenuation = 0.6 * length / (26.0 * s)
    bone_blob = np.exp(-(((u - 330 * s) / (70 * s)) ** 2 + ((v - 260 * s) / (50 * s)) ** 2) ** 2)
    spine = np.exp(-((u - 280 * s) / (40 * s)) ** 4)
    background = 0.55 + 0.1 * (u / size) + (0.25 if bone == "bright" else -0.25) * bone_blob + 0.1 * spine
    frame = background - attenuation if vessels == "dark" else background + attenuation
    frame = frame + rng.normal(0.0, noise, frame.shape)
    return frame, truth


# ----------------------------------------------------------------------------------------
# UNet and training
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("height,width", [(37, 50), (64, 64), (1, 3)])
def test_unet_output_keeps_odd_input_sizes(height, width):
    model = seg.UNet(1, 2, base=4, depth=6, max_channels=16).eval()
    with torch.no_grad():
        out = model(torch.zeros(2, 1, height, width))
    assert out.shape == (2, 2, height, width)


def test_unet_has_six_resolution_blocks_and_small_weights():
    """Data pass through six resolutions (each half the last), and the output is cropped back."""
    model = seg.UNet().eval()
    sizes = []
    hooks = [encoder.register_forward_hook(lambda _module, _input, output: sizes.append(tuple(output.shape[-2:])))
             for encoder in model.encoders]
    with torch.no_grad():
        logits = model(torch.zeros(1, 1, 50, 70))               # padded to 64 x 96 (multiples of 32)
    for hook in hooks:
        hook.remove()
    assert sizes == [(64 // 2 ** level, 96 // 2 ** level) for level in range(6)]
    assert tuple(logits.shape) == (1, 2, 50, 70)
    n_params = sum(p.numel() for p in model.parameters())
    assert 50_000 < n_params < 1_000_000     # a few MB of float32 at most


def _tiny_training_pairs():
    ct, lumen, _ = synthetic_ct(shape=(6, 48, 48), spacing=(2.0, 2.0, 4.0))
    return [(ct, lumen)]


def test_training_reduces_loss_and_resumes_exactly(tmp_path):
    pairs = _tiny_training_pairs()
    options = dict(lr=1e-2, seed=3, crop=64, base=4, max_channels=16, pixel_mm=2.0, checkpoint_every=10)
    full = seg.train_unet(pairs, tmp_path / "full.pt", iterations=40, **options)
    state = torch.load(full, weights_only=False)
    losses = state["losses"]
    assert len(losses) == 40 and state["iteration"] == 40
    assert np.mean(losses[-10:]) < 0.7 * np.mean(losses[:10])

    first = seg.train_unet(pairs, tmp_path / "part.pt", iterations=20, **options)
    assert torch.load(first, weights_only=False)["iteration"] == 20
    resumed = seg.train_unet(pairs, tmp_path / "resumed.pt", iterations=40, resume=first, **options)
    resumed_state = torch.load(resumed, weights_only=False)
    assert resumed_state["iteration"] == 40
    np.testing.assert_allclose(resumed_state["losses"], losses, rtol=1e-5, atol=1e-7)
    for name, tensor in state["model_state"].items():
        torch.testing.assert_close(resumed_state["model_state"][name], tensor, rtol=1e-5, atol=1e-6)


def test_progress_reports_every_iteration(tmp_path):
    calls = []
    seg.train_unet(_tiny_training_pairs(), tmp_path / "m.pt", iterations=3, crop=64, base=4, max_channels=8,
                   pixel_mm=2.0, progress=lambda done, total, msg: calls.append((done, total, msg)))
    assert [c[:2] for c in calls] == [(1, 3), (2, 3), (3, 3)]
    assert calls[-1][2].startswith("loss ")


def test_load_unet_roundtrip_and_segment_ct_runs(tmp_path):
    torch.manual_seed(0)
    path = seg.train_unet(_tiny_training_pairs(), tmp_path / "m.pt", iterations=2, crop=64, base=4,
                          max_channels=8, pixel_mm=2.0)
    state = torch.load(path, weights_only=False)
    model = seg.load_unet(path)
    assert not model.training and model.settings["pixel_mm"] == 2.0
    for name, tensor in model.state_dict().items():                 # every trained weight came back
        assert torch.equal(tensor, state["model_state"][name]), name
    # the mask follows the weights: a head that always says "lumen", then one that never does
    ct, _, _ = synthetic_ct(shape=(5, 40, 44), spacing=(1.5, 1.5, 2.0))
    body = ct.array > -500
    for lumen_logit in (5.0, -5.0):
        state["model_state"]["head.weight"].zero_()
        state["model_state"]["head.bias"].copy_(torch.tensor([0.0, lumen_logit]))
        torch.save(state, tmp_path / "fixed.pt")
        seen = []
        mask = seg.segment_ct_unet(ct, seg.load_unet(tmp_path / "fixed.pt"), postprocess=False, chunk=2,
                                   progress=lambda done, total: seen.append((done, total)))
        assert mask.shape == ct.shape and mask.array.dtype == bool
        assert seen[-1] == (5, 5)
        assert mask.array[body].all() if lumen_logit > 0 else not mask.array.any()


def test_load_unet_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="missing.pt"):
        seg.load_unet(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"something": 1}, bad)
    with pytest.raises(InputError, match="bad.pt"):
        seg.load_unet(bad)


def _mirrored_in_plane(volume):
    """The same physical volume stored with the i and j axes reversed (direction diag(-1, -1, 1))."""
    corner = volume.index_to_lps([0, volume.shape[1] - 1, volume.shape[2] - 1])
    return Volume(volume.array[:, ::-1, ::-1].copy(), volume.spacing, corner, np.diag([-1.0, -1.0, 1.0]))


def test_shipped_unet_segments_a_synthetic_ct_in_either_storage_order():
    ct, lumen, _ = synthetic_ct(shape=(24, 72, 80), spacing=(1.2, 1.2, 2.0))
    model = seg.load_unet()
    assert seg.dice(seg.segment_ct(ct, "unet", model=model), lumen) >= 0.9
    mirrored = seg.segment_ct_unet(_mirrored_in_plane(ct), model)
    assert seg.dice(mirrored, _mirrored_in_plane(lumen)) >= 0.9


def test_default_model_path_points_into_resources():
    path = seg.default_model_path()
    assert path.parts[-3:] == ("Resources", "Models", "aorta_unet.pt")
    assert (path.parent.parent.parent / "FevarPlanner" / "FevarPlannerLib").is_dir()


# ----------------------------------------------------------------------------------------
# Threshold segmenter, post-processing, surface
# ----------------------------------------------------------------------------------------

def test_threshold_segmentation_finds_the_aorta_not_the_spine():
    ct, lumen, centres = synthetic_ct()
    seed = seg.find_aorta_seed(ct)
    distances = np.linalg.norm(centres[:, :2] - seed[:2], axis=1)
    assert distances[np.argmin(np.abs(centres[:, 2] - seed[2]))] < 4.0
    mask = seg.segment_ct_threshold(ct)
    assert seg.dice(mask, lumen) >= 0.9


def test_threshold_segmentation_with_seed_and_bad_seed():
    ct, lumen, centres = synthetic_ct()
    mask = seg.segment_ct(ct, "threshold", seed_lps=centres[10])
    assert seg.dice(mask, lumen) >= 0.9
    with pytest.raises(InputError, match="outside"):
        seg.segment_ct_threshold(ct, seed_lps=[500.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="segmenter"):
        seg.segment_ct(ct, "magic")


def test_postprocess_removes_stray_blob_and_fills_hole():
    truth = np.zeros((20, 30, 30), bool)
    truth[2:18, 8:22, 8:22] = True
    noisy = truth.copy()
    noisy[8:11, 12:15, 12:15] = False          # an enclosed hole
    noisy[5, 2:4, 2:4] = True                  # a stray blob
    volume = Volume(noisy, (1.0, 1.0, 1.0), (0, 0, 0), np.eye(3))
    cleaned = seg.postprocess_mask(volume)
    assert isinstance(cleaned, Volume)
    np.testing.assert_array_equal(cleaned.array, truth)
    np.testing.assert_array_equal(seg.postprocess_mask(noisy), truth)


def test_postprocess_keeps_several_objects_when_asked():
    mask = np.zeros((10, 30, 30), bool)
    mask[2:8, 2:10, 2:10] = True
    mask[2:8, 15:25, 15:25] = True
    mask[5, 28, 28] = True
    cleaned = seg.postprocess_mask(mask, keep_largest=False, min_size_mm3=10)
    assert seg.dice(cleaned, mask) > 0.99 and not cleaned[5, 28, 28]


def test_surface_lies_on_the_tube_wall_in_lps(tmp_path):
    ct, lumen, centres = synthetic_ct(spacing=(1.5, 1.5, 2.0))
    direction = np.diag([-1.0, 1.0, 1.0])           # a mirrored grid must still land in LPS
    flipped = Volume(lumen.array[:, :, ::-1].copy(), lumen.spacing, lumen.index_to_lps([0, 0, lumen.shape[2] - 1]),
                     direction)
    for mask in (lumen, flipped):
        poly = seg.mask_surface(mask)
        points = numpy_support.vtk_to_numpy(poly.GetPoints().GetData())
        axis = np.column_stack([np.interp(points[:, 2], centres[:, 2], centres[:, n]) for n in range(2)])
        inner = (points[:, 2] > centres[1, 2]) & (points[:, 2] < centres[-2, 2])   # skip the end caps
        offset = points[inner, :2] - axis[inner]
        assert np.abs(np.hypot(*offset.T) - 9.0).max() <= 1.5      # within one in-plane voxel of the wall
        normals = numpy_support.vtk_to_numpy(poly.GetPointData().GetNormals())
        outward = np.einsum("ij,ij->i", normals[inner, :2], offset)
        assert np.mean(outward > 0) > 0.95
        faces = numpy_support.vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        a, b, c = (points[faces[:, n]] for n in range(3))
        face_normals = np.cross(b - a, c - a)
        assert np.einsum("ij,ij->i", face_normals, normals[faces].sum(axis=1)).mean() > 0
    path = tmp_path / "lumen.vtp"
    seg.write_surface_vtp(path, poly)
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    assert reader.GetOutput().GetNumberOfPoints() == poly.GetNumberOfPoints()
    assert not list(tmp_path.glob(".lumen.vtp*"))


def test_command_line_segments_a_ct_file_and_writes_the_surface(tmp_path):
    from FevarPlannerLib.io import read_volume, write_volume
    ct, lumen, _ = synthetic_ct()
    write_volume(tmp_path / "ct.nrrd", ct.with_array(ct.array.astype(np.int16)))
    from FevarPlannerLib.cli import main
    code = main(["-q", "segment", str(tmp_path / "ct.nrrd"), "--out", str(tmp_path / "mask.nrrd"),
                 "--segmenter", "threshold", "--surface", str(tmp_path / "lumen.vtp")])
    assert code == 0
    assert seg.dice(read_volume(tmp_path / "mask.nrrd"), lumen) >= 0.9
    assert (tmp_path / "lumen.vtp").stat().st_size > 1000


def test_surface_of_empty_mask_is_an_error():
    with pytest.raises(InputError, match="empty"):
        seg.mask_surface(Volume(np.zeros((3, 3, 3), bool), (1, 1, 1), (0, 0, 0), np.eye(3)))


# ----------------------------------------------------------------------------------------
# Fluoroscopy
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("vessels,bone", [("dark", "bright"), ("dark", "dark"), ("bright", "bright")])
def test_fluoro_vesselness_dice_both_polarities(vessels, bone):
    frame, truth = synthetic_frame(vessels=vessels, bone=bone)
    for polarity in ("auto", vessels):
        mask = seg.segment_fluoro(frame, vessels=polarity)
        assert mask.shape == truth.shape and mask.dtype == bool
        assert seg.dice(mask, truth) >= 0.85, polarity


def test_fluoro_monochrome1_and_integer_frames():
    frame, truth = synthetic_frame(vessels="dark")
    stored = np.round((1.0 - frame) * 4000).astype(np.uint16)     # MONOCHROME1: high = dark
    mask = seg.segment_fluoro(stored, vessels="dark", photometric="MONOCHROME1")
    assert seg.dice(mask, truth) >= 0.85


def test_fluoro_odd_size_and_errors():
    frame, truth = synthetic_frame(size=300, seed=2)
    mask = seg.segment_fluoro(frame[:297, :283], vessels="dark")
    assert mask.shape == (297, 283)
    assert seg.dice(mask, truth[:297, :283]) >= 0.85
    with pytest.raises(InputError, match="flat"):
        seg.segment_fluoro(np.ones((64, 64)))
    with pytest.raises(InputError, match="NaN"):
        seg.segment_fluoro(np.full((64, 64), np.nan))
    with pytest.raises(ValueError, match="vessels"):
        seg.segment_fluoro(frame, vessels="sideways")


def test_dice_values():
    a = np.zeros((4, 4), bool)
    b = a.copy()
    assert seg.dice(a, b) == 1.0
    a[:2] = True
    b[1:3] = True
    assert seg.dice(a, b) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        seg.dice(a, np.zeros((3, 3)))


# ----------------------------------------------------------------------------------------
# Classical CT route (no training)
# ----------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def _phantom_ct(seed=3, spacing_mm=1.5, noise_hu=12.0):
    params = ph.random_params(np.random.default_rng(seed), ct_spacing_mm=spacing_mm, ct_noise_hu=noise_hu)
    case = ph.generate_case(params)
    ct = ph.render_ct(case.preop, case.preop_params, np.random.default_rng(seed), case.grid)
    return ct, ph.rasterize_lumen(case.preop, ct), case


@pytest.mark.parametrize("spacing", [(1.5, 1.5, 2.0), (0.8, 0.8, 3.0)])
def test_classical_ct_traces_the_tube_at_any_spacing(spacing):
    shape = (int(72 / spacing[2]), int(108 / spacing[1]), int(120 / spacing[0]))
    ct, lumen, _ = synthetic_ct(shape=shape, spacing=spacing)
    calls = []
    mask = seg.segment_ct_classical(ct, progress=lambda done, total: calls.append((done, total)))
    assert seg.dice(mask, lumen) >= 0.9
    assert len(calls) >= shape[0] - 2 and calls[-1] == (shape[0], shape[0])     # progress moves per slice
    assert [done for done, _ in calls] == sorted(done for done, _ in calls)


def test_classical_ct_finds_the_phantom_tree_with_branches_not_kidneys_or_spine():
    ct, truth, case = _phantom_ct()
    mask, parts = seg.segment_ct_classical(ct, return_labels=True)
    assert seg.dice(mask, truth) >= 0.9
    truth_a = np.asarray(truth.array) > 0
    found = np.asarray(mask.array)
    assert (found & truth_a).sum() / found.sum() >= 0.97           # no kidney, spine or fat
    labels = np.asarray(parts.array)
    for name in ("renal_left", "renal_right", "iliac_left", "iliac_right"):
        tip = ct.lps_to_index(case.preop.vessels[name].points[-5]).round().astype(int)
        near = tuple(slice(max(t - 3, 0), t + 4) for t in tip)
        assert labels[near].any(), f"{name} not reached"


def test_classical_ct_refuses_a_ct_without_an_aorta():
    """The contrast lumen (350 HU) gone, the spine's cortex (900 HU) kept: a patient scan without
    an enhancing aorta. (With the cortex gone too the scan has no bone: a vessel phantom, where
    any round bright blob may be the lumen; the spine's 250 HU core would then be taken.)"""
    ct, _, _ = synthetic_ct()
    plain = ct.with_array(np.where((ct.array > 300) & (ct.array < 700), 40.0, ct.array).astype(np.float32))
    with pytest.raises(InputError, match="no aorta found"):
        seg.segment_ct_classical(plain)


def test_segment_ct_dispatches_the_classical_route():
    ct, lumen, _ = synthetic_ct()
    assert seg.dice(seg.segment_ct(ct, "classical"), lumen) >= 0.9


# ----------------------------------------------------------------------------------------
# Frame with the pre-operative prior, distractors
# ----------------------------------------------------------------------------------------

def _segment_mask(shape, p0, p1, width):
    """Anti-aliased coverage of a straight segment of ``width`` pixels (p = (u, v))."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    d = np.subtract(p1, p0).astype(float)
    d = d if d @ d > 1e-9 else np.array([1e-3, 0.0])
    t = np.clip(((u - p0[0]) * d[0] + (v - p0[1]) * d[1]) / (d @ d), 0, 1)
    return np.clip(width / 2 + 0.5 - np.hypot(u - (p0[0] + t * d[0]), v - (p0[1] + t * d[1])), 0, 1)


def distractor_frame(seed=1, *, subtracted=True, polarity="dark", contrast=True):
    """:func:`_distractor_frame` (cached), inverted for ``polarity='bright'``."""
    frame, truth, prior, parts = _distractor_frame(seed, subtracted, contrast)
    return (4095 - frame if polarity == "bright" else frame), truth, prior, parts


@functools.lru_cache(maxsize=None)
def _distractor_frame(seed, subtracted, contrast):
    """A phantom frame with a guide wire along the right iliac into the aorta, a straight catheter
    beside the aorta, a collimator border, a table edge, burned-in text and (unsubtracted) a spine.

    Returns (uint16 frame, true vessel mask, FluoroPrior of the pre-op tree through P_given,
    {distractor: mask})."""
    from PIL import Image, ImageDraw

    rng = np.random.default_rng(seed)
    case = ph.generate_case(ph.random_params(rng))
    params = case.params if contrast else dataclasses.replace(case.params, fluoro_attenuation_per_mm=0.0)
    frame, truth = ph.render_fluoro(case.intraop, case.P_true, case.carm, params, rng)
    truth = truth if contrast else np.zeros_like(truth)
    image = frame.astype(np.float64) / 4095.0
    rows, cols = image.shape
    px_mm = 1.0 / 0.6
    aorta = project(case.P_true, case.intraop.vessels["aorta"].points)
    iliac = project(case.P_true, case.intraop.vessels["iliac_right"].points)
    if not subtracted:      # vertebrae beside the aorta and soft tissue
        v, u = np.mgrid[0:rows, 0:cols].astype(float)
        order = np.argsort(aorta[:, 1])
        spine_u = np.interp(v, aorta[order, 1], aorta[order, 0]) + 15 * px_mm
        body = np.exp(-((u - spine_u) / (25 * px_mm)) ** 6) * (np.mod(v / px_mm, 35) > 6)
        image *= np.exp(-0.5 * ndi.gaussian_filter(body, 2)) * np.exp(-0.15 * np.exp(-((u - cols / 2) / (0.4 * cols)) ** 2))
    out = (iliac[-1] - iliac[-8]) / np.linalg.norm(iliac[-1] - iliac[-8])
    path = [iliac[-1] + 60 * px_mm * out] + list(iliac[::-1][::5]) + list(aorta[::-1][::10])
    wire = np.max([_segment_mask(image.shape, p, q, 1.6) for p, q in zip(path[:-1], path[1:])], axis=0)
    catheter = _segment_mask(image.shape, aorta[0] - [30 * px_mm, 0], aorta[-1] + [-30 * px_mm, 60 * px_mm], 3.0)
    image *= np.exp(-0.5 * np.maximum(wire, catheter))
    parts = {"wire": wire > 0.5, "catheter": catheter > 0.5}
    table_row, border = int(0.85 * rows), int(0.06 * cols)
    image[table_row:] *= 0.85
    image[:, :border] = 0.97
    parts["table"] = np.zeros_like(truth)
    parts["table"][table_row - 2:table_row + 2] = True
    parts["collimator"] = np.zeros_like(truth)
    parts["collimator"][:, border - 3:border + 3] = True
    text = Image.new("L", (cols, rows), 0)
    ImageDraw.Draw(text).text((cols - 160, 10), "L  12:34:56  30fps", fill=255)
    text = np.asarray(text) > 0
    image[text] = 1.0
    parts["text"] = ndi.binary_dilation(text, iterations=2)
    image = np.clip(image, 0, 1)
    prior = quality.FluoroPrior.from_centerline(case.preop.to_centerline(), case.P_given)
    return (image * 4095).astype(np.uint16), truth, prior, parts


def _distractors_taken(mask, truth, parts) -> dict:
    away = ~ndi.binary_dilation(truth, iterations=3)
    return {name: float((mask & part & away).sum() / max((part & away).sum(), 1)) for name, part in parts.items()}


@pytest.mark.parametrize("polarity", ["dark", "bright"])
def test_prior_frame_segmentation_keeps_vessels_and_drops_devices_borders_text(polarity):
    frame, truth, prior, parts = distractor_frame(polarity=polarity)
    mask = seg.segment_fluoro(frame, prior)
    assert seg.dice(mask, truth) >= 0.85
    taken = _distractors_taken(mask, truth, parts)
    assert max(taken.values()) <= 0.1, taken
    without = seg.segment_fluoro(frame)             # the old call still works (and does worse)
    assert without.shape == frame.shape


def test_prior_frame_segmentation_on_an_unsubtracted_frame_with_spine():
    frame, truth, prior, parts = distractor_frame(subtracted=False)
    mask = seg.segment_fluoro(frame, prior)
    assert seg.dice(mask, truth) >= 0.6
    taken = _distractors_taken(mask, truth, parts)
    assert max(taken[name] for name in ("wire", "catheter", "collimator", "text")) <= 0.1, taken


def test_multi_frame_run_uses_the_frame_with_contrast():
    frame, truth, prior, _ = distractor_frame()
    empty, _, _, _ = distractor_frame(contrast=False)
    run = np.stack([empty, frame, empty])
    assert seg.select_frame(run, prior) == 1
    assert seg.select_frame(run) == 1
    assert seg.dice(seg.segment_fluoro(run, prior), truth) >= 0.85


# ----------------------------------------------------------------------------------------
# Quality gate
# ----------------------------------------------------------------------------------------

def test_frame_gate_passes_an_angiogram_and_refuses_noise_wire_only_and_blank(tmp_path):
    frame, truth, prior, _ = distractor_frame()
    report = quality.check_frame_mask(seg.segment_fluoro(frame, prior), prior, frame=frame)
    assert min(report["coverage"].values()) >= 0.8
    noise = np.random.default_rng(0).normal(2000, 300, frame.shape)
    wire_only, _, _, _ = distractor_frame(contrast=False)
    wire_and_spine, _, _, _ = distractor_frame(contrast=False, subtracted=False)
    for bad in (noise, wire_only, wire_and_spine):
        with pytest.raises(quality.QualityError, match="frame check") as failure:
            quality.check_frame_mask(seg.segment_fluoro(bad, prior), prior, quality.QCData(frame=bad, prior=prior),
                                     frame=bad)
        assert "\n" not in str(failure.value)
        picture = quality.write_segmentation_qc(tmp_path / "qc.png", failure.value.qc, str(failure.value))
        assert picture.stat().st_size > 1000
    with pytest.raises(InputError, match="flat"):
        seg.segment_fluoro(np.full(frame.shape, 1000, np.uint16), prior)


def _without_vessels(centreline, vessels) -> Centerline:
    """``centreline`` with the nodes of ``vessels`` and their edges removed."""
    keep = np.array([label not in vessels for label in centreline.labels])
    index = np.cumsum(keep) - 1
    edges = centreline.edges[keep[centreline.edges].all(axis=1)]
    return Centerline(centreline.points[keep], index[edges], [l for l, k in zip(centreline.labels, keep) if k])


def test_preop_gate_names_the_missing_vessel_and_checks_radii():
    _, truth, case = _phantom_ct()
    centreline = case.preop.to_centerline()
    report = quality.check_preop_tree(centreline, truth)
    assert set(report) == set(quality.MAIN_VESSELS)
    assert 2.0 <= report["renal_left"]["radius_mm"] <= 4.5
    with pytest.raises(quality.QualityError, match="renal_left not found"):
        quality.check_preop_tree(_without_vessels(centreline, ("renal_left",)))
    thin = truth.with_array(ndi.binary_erosion(truth.array, iterations=4))
    with pytest.raises(quality.QualityError, match="radius"):
        quality.check_preop_tree(centreline, thin)
    above_bifurcation = _without_vessels(centreline, ("iliac_left", "iliac_right"))
    with pytest.raises(quality.QualityError, match="iliac_left, iliac_right not found"):
        quality.check_preop_tree(above_bifurcation, thin)      # named before the thin lumen's radii


def _slices_above(volume: Volume, z_mm: float) -> Volume:
    """The slices of ``volume`` whose LPS z lies above ``z_mm`` (a scan that stops there)."""
    z = volume.index_to_lps(np.stack([np.arange(volume.shape[0]), np.zeros(volume.shape[0]),
                                      np.zeros(volume.shape[0])], axis=1))[:, 2]
    keep = np.flatnonzero(z > z_mm)
    first, stop = int(keep.min()), int(keep.max()) + 1
    return Volume(volume.array[first:stop], volume.spacing, volume.index_to_lps([first, 0, 0]), volume.direction)


def test_preop_gate_refuses_a_scan_that_stops_above_the_bifurcation():
    _, truth, case = _phantom_ct()
    centreline = case.preop.to_centerline()
    labels = np.asarray(centreline.labels)
    bifurcation_z = centreline.points[labels == "aorta", 2].min()
    quality.check_preop_tree(centreline, _slices_above(truth, bifurcation_z - 60.0))     # iliacs cut: passes
    cut = _slices_above(truth, bifurcation_z + 25.0)
    with pytest.raises(quality.QualityError, match="ends above the aortic bifurcation") as refusal:
        quality.check_preop_tree(centreline, cut)
    lowest = min(cut.index_to_lps([0, 0, 0])[2], cut.index_to_lps([cut.shape[0] - 1, 0, 0])[2])
    where = [float(v) for v in str(refusal.value).split("LPS (")[1].split(")")[0].split(",")]
    assert abs(where[2] - lowest) <= 1.0 + cut.spacing[2]          # named where the aorta is cut


def test_percentile_among_zeros_matches_the_padded_array():
    rng = np.random.default_rng(5)
    values = rng.random(300) * (rng.random(300) > 0.3)
    padded = np.concatenate([values, np.zeros(1700)])
    for q in (50.0, 90.0, 99.5, 100.0):
        assert seg._percentile_among_zeros(values, q, padded.size) == pytest.approx(np.percentile(padded, q))


def test_block_mean_and_bilinear_upsampling_on_odd_shapes():
    rng = np.random.default_rng(6)
    image = rng.random((37, 42)).astype(np.float32)
    small = seg._downsample(image, 4)
    padded = np.pad(image, ((0, 3), (0, 2)), mode="edge")
    assert np.allclose(small, padded.reshape(10, 4, 11, 4).mean(axis=(1, 3)), atol=1e-6)
    constant = seg._upsample(np.full((10, 11), 2.5, np.float32), 4, (37, 42))
    assert constant.shape == (37, 42) and np.allclose(constant, 2.5)
    ramp = seg._upsample(np.arange(10, dtype=np.float32)[:, None].repeat(11, axis=1), 4, (40, 44))
    assert np.allclose(ramp[4:36, 0], (np.arange(4, 36) + 0.5) / 4 - 0.5)    # linear between block centres


def test_a_ct_only_case_hands_its_segmented_lumen_to_the_quality_gate_and_qc(tmp_path, monkeypatch):
    import shutil

    from FevarPlannerLib import io, pipeline

    case = ph.write_phantom_set(tmp_path / "cases", n=1, seed=7, preset="random")[0]
    image_only = tmp_path / "image_only"
    image_only.mkdir()
    shutil.copytree(case / "ct", image_only / "ct")
    for name in ("fluoro.dcm", "geometry.json", "case.json"):
        shutil.copy2(case / name, image_only / name)
    seen = []
    check = quality.check_preop_tree
    monkeypatch.setattr(quality, "check_preop_tree", lambda centreline, lumen, qc: seen.append(lumen) or
                        check(centreline, lumen, qc))
    result = pipeline.plan_case(image_only)
    assert seen[0] is result.qc.lumen
    assert seg.dice(result.qc.lumen, io.load_case(case).aorta_mask) >= 0.8


def test_a_blurred_vertebral_body_is_not_taken_for_the_aorta():
    """Blurred, the 3 mm cortex falls below BONE_HU and joins the cancellous core into one round
    blob larger and rounder than the lumen; its edge is brighter than its middle, a lumen's is not."""
    jj, ii = np.mgrid[0:128, 0:128]
    axial = np.full((128, 128), 40.0)
    vertebra = np.hypot(jj - 75, ii - 64)
    axial[vertebra <= 18] = 700.0
    axial[vertebra <= 15] = 250.0
    axial[(np.abs(ii - 64) <= 4) & (jj > 88) & (jj < 125)] = 1000.0     # spinous process
    axial[np.hypot(jj - 40, ii - 64) <= 9] = 300.0                       # a lumen narrower than the vertebra
    axial = ndi.gaussian_filter(axial, 1.5)
    ct = Volume(np.repeat(axial[None], 12, axis=0).astype(np.int16), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), np.eye(3))
    k, centre, radius, _ = seg.find_aorta_in_slices(ct)
    assert np.hypot(*(centre - (40, 64))) <= 2 and 7 <= radius <= 10
    from FevarPlannerLib.segmentation import classical

    blobs = {int(round(b["centre"][0])) // 20: b for b in classical._round_blobs(axial, (1.0, 1.0), (150, 600), (7, 22))}
    assert set(blobs) == {2, 3}                          # the lumen (row 40) and the vertebral body (row 75)
    assert blobs[3]["radius"] > blobs[2]["radius"]
    assert classical._inside_bone(axial, blobs[3]["centre"], blobs[3]["radius"], (1.0, 1.0))
    assert not classical._inside_bone(axial, blobs[2]["centre"], blobs[2]["radius"], (1.0, 1.0))

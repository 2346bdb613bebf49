"""The rendering and truth of ``bench_real_drr.py`` on a small synthetic CT (no wheel needed).

A water block with a contrast-filled tube (400 HU, radius 5 mm, along the patient's axis) in
front of a bone block (1000 HU, posterior, covering the tube's right half and beyond), seen AP:
the truth mask must cover the tube's projection, the DSA-like frame must show the tube only
(not the bone), and the rendered tube must lie where ``projection.project`` puts its axis.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from FevarPlannerLib import io, quality
from FevarPlannerLib import segmentation as seg
from FevarPlannerLib.projection import pixels_per_mm, project

BENCHMARKS = Path(__file__).resolve().parent / "benchmarks"

TUBE_X, TUBE_Y, TUBE_RADIUS = 4.0, -6.0, 5.0
SIZE, PIXEL_MM = 128, 0.6


def _bench():
    if "bench_real_drr" in sys.modules:
        return sys.modules["bench_real_drr"]
    sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location("bench_real_drr", BENCHMARKS / "bench_real_drr.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_real_drr"] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def scene():
    """(bench module, CT, tube mask, bone mask, P, integrals, field) of the synthetic scene."""
    bench = _bench()
    shape = (60, 80, 80)                                  # (k, j, i), 1 mm voxels
    origin = np.array([-40.0, -40.0, -30.0])              # LPS of voxel (0, 0, 0)
    ct = io.Volume(np.full(shape, -1000.0, dtype=np.float32), np.ones(3), origin, np.eye(3))
    k, j, i = np.indices(shape)
    x, y = origin[0] + i, origin[1] + j
    hu = np.asarray(ct.array)
    hu[(np.abs(x) < 35) & (np.abs(y) < 30)] = 0.0                                  # the body (water)
    bone = (x > TUBE_X) & (x < 30) & (y > 10) & (y < 25)                           # posterior, right of the tube's axis
    hu[bone] = 1000.0
    tube = (x - TUBE_X) ** 2 + (y - TUBE_Y) ** 2 <= TUBE_RADIUS ** 2
    hu[tube] = 400.0
    isocenter = np.array([TUBE_X, TUBE_Y, 0.0])
    P = bench.carm_projection(0.0, 0.0, isocenter, size=SIZE, pixel_mm=PIXEL_MM)
    integrals = bench.line_integrals(ct, tube, P, (SIZE, SIZE), render_size=SIZE // 2, step_mm=0.5)
    field = bench.open_field(ct, P, (SIZE, SIZE), isocenter, half_depth_mm=20.0, margin_mm=2.0)
    return bench, ct, tube, bone, P, integrals, field


def _axis_uv(P, z):
    return project(P, np.stack([np.full_like(z, TUBE_X), np.full_like(z, TUBE_Y), z], axis=1))


def test_truth_mask_covers_the_tube_projection(scene):
    bench, ct, tube, bone, P, integrals, field = scene
    truth = bench.truth_mask(integrals["L"], field)
    half_width = TUBE_RADIUS * pixels_per_mm(P, np.array([TUBE_X, TUBE_Y, 0.0]))
    u_axis = _axis_uv(P, np.array([0.0]))[0, 0]
    rows = np.nonzero(field.all(axis=1))[0]
    assert len(rows) > SIZE // 2                          # the scan's 60 mm cover most of the field
    columns = np.arange(SIZE)
    for row in rows[::8]:
        inside = columns[truth[row]]
        assert inside.min() >= u_axis - half_width - 1.0 and inside.max() <= u_axis + half_width + 1.0
        assert np.all(truth[row, int(np.ceil(u_axis - half_width + 1.5)):int(u_axis + half_width - 1.5) + 1])
    # the path along the axis is the tube's diameter
    assert integrals["L"][rows, int(round(u_axis))].mean() == pytest.approx(2 * TUBE_RADIUS, abs=0.6)
    # nothing outside the open field counts
    assert not (truth & ~field).any()


def test_rendered_tube_lies_where_project_puts_its_axis(scene):
    bench, ct, tube, bone, P, integrals, field = scene
    rows = np.nonzero(field.all(axis=1))[0][4:-4]
    E = integrals["E"]
    u = np.arange(SIZE, dtype=float)
    centroid = (E[rows] * u).sum(axis=1) / E[rows].sum(axis=1)
    # the rows' depth: the axis point whose projection falls on each row
    z = np.linspace(-40, 40, 801)
    uv = _axis_uv(P, z)
    expected_u = np.interp(rows, uv[::-1, 1] if uv[0, 1] > uv[-1, 1] else uv[:, 1],
                           uv[::-1, 0] if uv[0, 1] > uv[-1, 1] else uv[:, 0])
    assert np.abs(centroid - expected_u).max() < 1.0
    # the iodine's excess on the axis: (400 - 40) / 1000 per mm over the diameter
    assert E[rows, int(round(float(expected_u.mean())))].mean() == pytest.approx(0.36 * 2 * TUBE_RADIUS, rel=0.1)


def test_dsa_frame_shows_the_tube_and_not_the_bone(scene):
    bench, ct, tube, bone, P, integrals, field = scene
    frames = bench.xray_frames(integrals, field, np.random.default_rng(0), quanta=1e9, scatter=0.0, gradient=0.0,
                               px_mm=1.0 / PIXEL_MM)
    truth = bench.truth_mask(integrals["L"], field)
    rows = np.nonzero(field.all(axis=1))[0][4:-4]
    u_axis = int(round(float(_axis_uv(P, np.array([0.0]))[0, 0])))
    ppm = pixels_per_mm(P, np.array([TUBE_X, TUBE_Y, 0.0]))
    behind_bone = u_axis + int(round(15 * ppm))            # beside the tube, the bone block behind
    no_bone = u_axis - int(round(12 * ppm))                # beside the tube, only water
    assert not truth[rows][:, [behind_bone, no_bone]].any()
    for kind in ("plain", "dsa"):
        frame = frames[kind].astype(float)
        tube_contrast = frame[rows, no_bone].mean() - frame[rows, u_axis].mean()
        bone_contrast = frame[rows, no_bone].mean() - frame[rows, behind_bone].mean()
        assert tube_contrast > 300                         # vessels dark in both kinds
        if kind == "plain":
            assert bone_contrast > 300                     # the bone darkens the plain frame ...
        else:
            assert abs(bone_contrast) < 5                  # ... and vanishes from the subtracted one
            background = frame[rows][:, [behind_bone, no_bone]]
            assert background.std() < 10                   # quantum noise only (1e9 quanta)


def test_iodine_excess_volume_is_cropped_to_the_arteries(scene):
    bench, ct, tube, bone, P, integrals, field = scene
    excess = bench.iodine_excess_volume(ct, tube)
    assert excess.shape[1] < ct.shape[1] and excess.shape[2] < ct.shape[2]
    # the crop keeps the LPS of its voxels: the tube's axis still has 400 HU - blood + air
    centre = np.round(excess.lps_to_index(np.array([[TUBE_X, TUBE_Y, 0.0]]))[0]).astype(int)
    assert excess.array[tuple(centre)] == pytest.approx(400.0 - 40.0 - 1000.0)


def test_noisy_dsa_of_a_wide_aorta_is_accepted():
    """A subtracted 1024 x 1024 frame of a 24 mm aorta whose per-pixel contrast to noise is 1.7 (the
    real-CT DSA frames: 1.2-2.0): plainly visible (over 4 x 4 pixel blocks, the grid the
    segmentation works on, its contrast is 7.6 times their noise), so a usable angiogram."""
    bench = _bench()
    size, pixel_mm, radius_mm = 1024, 0.3, 12.0
    z = np.linspace(-70.0, 70.0, 29)
    points = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    P = bench.carm_projection(0.0, 0.0, np.zeros(3), size=size, pixel_mm=pixel_mm)
    prior = quality.FluoroPrior(points, np.stack([np.arange(28), np.arange(1, 29)], axis=1), ["aorta"] * 29, P,
                                np.full(29, radius_mm))
    u0 = project(P, np.zeros((1, 3)))[0, 0]
    radius_px = radius_mm * pixels_per_mm(P, np.zeros(3))
    distance = np.abs(np.arange(size) - u0)
    profile = np.sqrt(np.clip(1.0 - (distance / radius_px) ** 2, 0.0, None))       # chord / diameter
    noise, contrast = 40.0, 100.0
    rng = np.random.default_rng(3)
    frame = np.rint(2500.0 - contrast * profile[None, :] + rng.normal(0.0, noise, (size, size))).astype(np.uint16)
    mask = seg.segment_fluoro(frame, prior)
    truth = np.broadcast_to(distance[None, :] <= radius_px, frame.shape)
    assert seg.dice(mask, truth) > 0.8                  # the segmentation finds it ...
    per_pixel = quality.vessel_contrast_to_noise(frame, mask)
    assert 1.0 < per_pixel < quality.MIN_CONTRAST_TO_NOISE
    assert quality.vessel_contrast_to_noise(frame, mask, block=4) > 6.0       # at the segmentation's scale
    quality.check_frame_mask(mask, prior, frame=frame)  # ... and the check must take it

"""DRR through P: where the attenuation lands and how much of it there is."""

import numpy as np
import pytest
from PIL import Image

from FevarPlannerLib import drr
from FevarPlannerLib.io import Volume
from FevarPlannerLib.projection import CArmGeometry, project, projection_matrix_from_carm


def _ct(shape=(40, 48, 56), spacing=(2.0, 2.0, 2.5), origin=(-55.0, -47.0, -48.0)) -> Volume:
    return Volume(np.full(shape, -1000, dtype=np.int16), spacing, origin, np.eye(3))


CARM = CArmGeometry(sid=1200.0, sod=800.0, pixel_spacing=(0.6, 0.6), primary_angle=20.0, secondary_angle=-10.0,
                    rows=300, cols=400)


def test_a_dense_ball_lands_where_P_projects_its_centre():
    ct = _ct()
    centre = np.array([10.0, -5.0, 12.0])
    kji = np.indices(ct.shape).reshape(3, -1).T
    inside = np.linalg.norm(ct.index_to_lps(kji) - centre, axis=1) < 8.0
    ct.array.reshape(-1)[inside] = 1000
    P = projection_matrix_from_carm(CARM, [0.0, 0.0, 0.0])
    image = drr.render_drr(ct, P, (CARM.rows, CARM.cols), size=200)
    assert image.shape == (150, 200)
    u, v = drr.drr_grid((CARM.rows, CARM.cols), 200)
    peak = np.unravel_index(np.argmax(image), image.shape)
    expected = project(P, centre)
    assert abs(u[peak] - expected[0]) < 4.0 and abs(v[peak] - expected[1]) < 4.0
    # 1000 HU is twice water: a 16 mm chord through the centre integrates to about 32 mm of water
    assert image.max() == pytest.approx(32.0, rel=0.15)
    assert image.min() == 0.0


def test_a_water_slab_integrates_to_its_thickness_on_the_central_ray():
    ct = _ct()
    kji = np.indices(ct.shape)
    y = ct.index_to_lps(kji.reshape(3, -1).T)[:, 1].reshape(ct.shape)
    ct.array[np.abs(y) <= 20.0] = 0  # 40 mm of water across the AP rays
    P = projection_matrix_from_carm(CArmGeometry(1200.0, 800.0, (0.6, 0.6), 0.0, 0.0, 201, 201), [0.0, 0.0, 0.0])
    image = drr.render_drr(ct, P, (201, 201), size=201)
    assert image[100, 100] == pytest.approx(40.0, abs=2.0)


def test_mask_volumes_render_as_angiograms_and_the_check_picture_is_written(tmp_path):
    mask = Volume(np.zeros((10, 10, 10), dtype=np.uint8), (1.0, 1.0, 1.0), (-5.0, -5.0, -5.0), np.eye(3))
    mask.array[3:7, 3:7, 3:7] = 1
    assert drr.attenuation(mask).max() == 1.0
    P = projection_matrix_from_carm(CArmGeometry(1000.0, 700.0, (0.3, 0.3), 0.0, 0.0, 64, 80), [0.0, 0.0, 0.0])
    image = drr.render_drr(mask, P, (64, 80), size=80)
    frame = np.random.default_rng(0).normal(size=(64, 80))
    drr.write_drr_check(tmp_path / "drr_check.png", frame, image, title="proposed, LAO 0 / CRA 0",
                        notes=["isocentre assumed at the CT centre"])
    with Image.open(tmp_path / "drr_check.png") as png:
        assert png.size[0] == 160
    with pytest.raises(ValueError, match="does not match"):
        drr.write_drr_check(tmp_path / "bad.png", frame, image[:10])

import json

import numpy as np
import pytest

from FevarPlannerLib.projection import (
    CArmGeometry, homogeneous_columns, image_directions, in_plane_transform, patient_motion, pixels_per_mm,
    principal_point, project,
    projection_jacobian, projection_matrix_from_carm, pull_back_columns, read_geometry_json, source_position,
    validate_projection_matrix, write_geometry_json)

AP = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(0.4, 0.4), primary_angle=0.0,
                  secondary_angle=0.0, rows=512, cols=640)


def test_isocentre_lands_on_detector_centre():
    iso = np.array([10.0, -20.0, 30.0])
    P = projection_matrix_from_carm(AP, iso)
    np.testing.assert_allclose(project(P, iso), [(640 - 1) / 2, (512 - 1) / 2], atol=1e-9)


def test_ap_view_magnification_and_orientation_by_hand():
    P = projection_matrix_from_carm(AP)
    # 10 mm to the patient's left at the isocentre: magnified by SID/SOD, in pixels of 0.4 mm
    du = project(P, [10.0, 0, 0])[0] - project(P, [0.0, 0, 0])[0]
    assert du == pytest.approx(10.0 * 1100 / 750 / 0.4)
    # superior (+z) goes up the image (smaller v)
    assert project(P, [0, 0, 10.0])[1] < project(P, [0, 0, 0.0])[1]
    np.testing.assert_allclose(source_position(P), [0, 750.0, 0], atol=1e-9)


def test_pixels_per_mm_is_the_magnification_at_the_depth_of_the_point():
    P = projection_matrix_from_carm(AP)
    # SID/SOD at the isocentre, in pixels of 0.4 mm; 150 mm nearer the source, SID/600
    assert pixels_per_mm(P, [0.0, 0.0, 0.0]) == pytest.approx(1100 / 750 / 0.4, rel=1e-12)
    assert pixels_per_mm(P, [0.0, 150.0, 0.0]) == pytest.approx(1100 / 600 / 0.4, rel=1e-12)
    points = np.array([[0.0, 0.0, 0.0], [0.0, 150.0, 0.0], [20.0, -100.0, 40.0]])
    per_point = pixels_per_mm(P, points)
    assert per_point.shape == (3,) and isinstance(pixels_per_mm(P, points[2]), float)
    np.testing.assert_allclose(per_point, [pixels_per_mm(P, p) for p in points], rtol=1e-12)
    assert per_point[2] == pytest.approx(1100 / 850 / 0.4, rel=1e-12)      # 100 mm anterior: farther away


def test_lao_moves_source_to_the_right_posterior():
    lao = CArmGeometry(**{**AP.__dict__, "primary_angle": 30.0})
    src = source_position(projection_matrix_from_carm(lao))
    assert src[0] < 0 and src[1] > 0
    assert np.linalg.norm(src) == pytest.approx(750.0)


def test_image_directions_follow_the_view():
    P = projection_matrix_from_carm(AP)
    left, sup = image_directions(P, np.zeros(3))
    np.testing.assert_allclose(left, [1, 0], atol=1e-9)
    np.testing.assert_allclose(sup, [0, -1], atol=1e-9)
    mirrored = np.diag([-1.0, 1.0, 1.0]) @ P
    mirrored[0] += 639 * mirrored[2]
    left_m, _ = image_directions(mirrored, np.zeros(3))
    np.testing.assert_allclose(left_m, [-1, 0], atol=1e-9)


def test_geometry_json_round_trip(tmp_path):
    P = projection_matrix_from_carm(CArmGeometry(**{**AP.__dict__, "primary_angle": -20.0, "secondary_angle": 15.0}),
                                    [5.0, 6.0, 7.0])
    pts = np.random.default_rng(0).normal(scale=50, size=(20, 3))
    write_geometry_json(tmp_path / "geometry.json", P)
    P2 = read_geometry_json(tmp_path / "geometry.json")
    np.testing.assert_allclose(project(P2, pts), project(P, pts), atol=1e-9)


def test_in_plane_transform_moves_projections():
    P = projection_matrix_from_carm(AP)
    pts = np.random.default_rng(1).normal(scale=30, size=(10, 3))
    moved = project(in_plane_transform(P, translation=(5, -3), rotation_deg=90, center=(0, 0)), pts)
    uv = project(P, pts)
    np.testing.assert_allclose(moved, np.c_[-uv[:, 1] + 5, uv[:, 0] - 3], atol=1e-9)


def test_patient_motion_moves_the_image_in_plane():
    """An LAO 25 / caudal 10 view: a turn about the principal axis is an exact image rotation
    about the principal point; a shift moves the image of ``at`` exactly and of points in an
    80 mm cube round it to within 8 % of the offset (magnification changes with depth)."""
    oblique = CArmGeometry(1100.0, 750.0, (0.6, 0.6), 25.0, -10.0, 700, 800)
    at = np.array([5.0, 20.0, -30.0])
    P = projection_matrix_from_carm(oblique, at)
    np.testing.assert_allclose(principal_point(P), [(800 - 1) / 2, (700 - 1) / 2], atol=1e-9)
    points = at + np.random.default_rng(2).uniform(-40, 40, size=(300, 3))

    def moved(T, x):
        return x @ T[:3, :3].T + T[:3, 3]

    turn = patient_motion(P, at, rotation_deg=12.0)
    np.testing.assert_allclose(turn[:3, :3] @ turn[:3, :3].T, np.eye(3), atol=1e-12)
    expected = project(in_plane_transform(P, rotation_deg=12.0, center=principal_point(P)), points)
    np.testing.assert_allclose(project(P, moved(turn, points)), expected, atol=1e-6)
    shift = patient_motion(P, at, translation_px=(30.0, -20.0), rotation_deg=12.0)
    offset = project(P, moved(shift, points)) - project(P, moved(turn, points))
    np.testing.assert_allclose(project(P, moved(shift, at)) - project(P, moved(turn, at)), [30.0, -20.0], atol=1e-6)
    assert np.max(np.linalg.norm(offset - [30.0, -20.0], axis=1)) < 0.08 * np.hypot(30.0, 20.0)
    np.testing.assert_allclose(patient_motion(P, at), np.eye(4), atol=1e-12)


@pytest.mark.parametrize("bad, why", [
    (np.zeros((3, 4)), "degenerate"), (np.ones((2, 4)), "3x4"), ([[np.nan] * 4] * 3, "NaN")])
def test_bad_projection_matrices_are_named(bad, why, tmp_path):
    path = tmp_path / "geometry.json"
    path.write_text(json.dumps({"projection_matrix": np.asarray(bad).tolist()}).replace("NaN", "NaN"))
    with pytest.raises(ValueError, match=why):
        read_geometry_json(path)
    with pytest.raises(ValueError, match=why):
        validate_projection_matrix(bad)


def test_projection_jacobian_matches_finite_differences_and_spans_no_ray():
    P = projection_matrix_from_carm(CArmGeometry(**{**AP.__dict__, "primary_angle": 35.0, "secondary_angle": -10.0}))
    rng = np.random.default_rng(0)
    points = rng.uniform(-80, 80, size=(5, 3))
    jacobian = projection_jacobian(P, points)
    assert jacobian.shape == (5, 2, 3)
    h = 1e-5
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        numeric = (project(P, points + step) - project(P, points - step)) / (2 * h)
        np.testing.assert_allclose(jacobian[:, :, axis], numeric, rtol=1e-6, atol=1e-8)
    ray = points - source_position(P)                     # moving along the ray leaves f unchanged
    np.testing.assert_allclose(np.einsum("nkj,nj->nk", jacobian, ray), 0.0, atol=1e-9)


def test_component_major_projection_and_its_pull_back_agree_with_the_jacobian():
    P = projection_matrix_from_carm(AP, (5.0, -3.0, 2.0))
    rng = np.random.default_rng(1)
    points = rng.uniform(-60, 60, size=(7, 3))
    h = homogeneous_columns(P, np.ascontiguousarray(points.T))
    np.testing.assert_allclose((h[:2] / h[2]).T, project(P, points), rtol=1e-12)
    g = rng.normal(size=(7, 2))                           # a gradient with respect to f
    fu, fv = h[0] / h[2], h[1] / h[2]
    pulled = pull_back_columns(P, fu, fv, g[:, 0] / h[2], g[:, 1] / h[2])
    np.testing.assert_allclose(pulled.T, np.einsum("nkj,nk->nj", projection_jacobian(P, points), g), rtol=1e-9)


def test_view_spread_is_the_widest_angle_between_the_x_rays_through_the_anatomy():
    from dataclasses import replace

    from FevarPlannerLib.projection import view_spread_deg

    iso = np.array([10.0, -20.0, 30.0])
    at_angle = {angle: projection_matrix_from_carm(replace(AP, primary_angle=angle), iso)
                for angle in (0.0, 30.0, -50.0, 90.0, 180.0)}
    assert view_spread_deg([at_angle[0.0]], iso) == 0.0                          # one view sees no depth
    assert view_spread_deg([at_angle[0.0], at_angle[30.0]], iso) == pytest.approx(30.0, abs=1e-6)
    assert view_spread_deg([at_angle[0.0], at_angle[30.0], at_angle[-50.0]], iso) == pytest.approx(80.0, abs=1e-6)
    assert view_spread_deg([at_angle[0.0], at_angle[90.0]], iso) == pytest.approx(90.0, abs=1e-6)
    assert view_spread_deg([at_angle[0.0], at_angle[180.0]], iso) == pytest.approx(0.0, abs=1e-6)   # AP and PA: one line

"""alignment.pose_residual: a used pose's offset from the true one, along / across a vessel (issue 10)."""

import numpy as np
import pytest

from FevarPlannerLib.alignment import pose_residual
from FevarPlannerLib.projection import CArmGeometry, in_plane_transform, project, projection_matrix_from_carm

P_TRUE = projection_matrix_from_carm(CArmGeometry(1100.0, 750.0, (0.5, 0.5), 0.0, 0.0, 600, 600))


def _upper_aorta(n=80):
    """A straight vertical upper aorta (LPS: from its top down, z falling), slightly tilted in depth."""
    z = np.linspace(60.0, -40.0, n)
    return np.column_stack([np.full(n, 2.0), 0.2 * z, z])


def _image_course(points):
    uv = project(P_TRUE, points)
    course = uv[-1] - uv[0]
    return course / np.linalg.norm(course)


def test_an_offset_along_the_vessel_is_read_as_along_and_nothing_across():
    points = _upper_aorta()
    course = _image_course(points)
    used = in_plane_transform(P_TRUE, translation=-5.0 * course)       # the used pose 5 px up the vessel
    residual = pose_residual(used, P_TRUE, points)
    assert residual["along_px"] == pytest.approx(5.0, abs=1e-6)
    assert abs(residual["across_px"]) < 1e-6 and abs(residual["rotation_deg"]) < 1e-6
    assert residual["mean_px"] == pytest.approx(5.0, abs=1e-6)


def test_across_offset_and_turn_of_a_misaligned_pose_are_recovered():
    points = _upper_aorta()
    course = _image_course(points)
    across = np.array([-course[1], course[0]])
    centre = project(P_TRUE, points).mean(axis=0)
    # the true pose is the used one turned by 3 degrees about the vessel's centre, then moved 2 px across it
    used = in_plane_transform(P_TRUE, rotation_deg=-3.0, center=centre)
    true = in_plane_transform(used, translation=2.0 * across, rotation_deg=3.0, center=centre)
    residual = pose_residual(used, true, points)
    assert residual["rotation_deg"] == pytest.approx(3.0, abs=1e-6)
    assert residual["across_px"] == pytest.approx(2.0, abs=0.05)
    assert abs(residual["along_px"]) < 0.05


def test_the_direction_follows_the_order_of_the_points_and_bad_input_is_refused():
    points = _upper_aorta()
    used = in_plane_transform(P_TRUE, translation=-4.0 * _image_course(points))
    assert pose_residual(used, P_TRUE, points)["along_px"] == pytest.approx(4.0, abs=1e-6)
    assert pose_residual(used, P_TRUE, points[::-1])["along_px"] == pytest.approx(-4.0, abs=1e-6)
    with pytest.raises(ValueError, match="two or more"):
        pose_residual(used, P_TRUE, points[:1])

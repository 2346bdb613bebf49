import numpy as np
import pytest

from FevarPlannerLib.alignment import fit_in_plane_rigid
from FevarPlannerLib.projection import CArmGeometry, in_plane_transform, project, projection_matrix_from_carm

P = projection_matrix_from_carm(CArmGeometry(1100.0, 750.0, (0.5, 0.5), 10.0, -5.0, 600, 600))


def test_recovers_a_rotation_and_translation_of_the_frame():
    points = np.random.default_rng(3).normal(scale=40.0, size=(60, 3))
    moved = in_plane_transform(P, translation=(12.0, -7.0), rotation_deg=6.0, center=(250.0, 320.0))
    fit = fit_in_plane_rigid(project(P, points), project(moved, points), P)
    np.testing.assert_allclose(project(fit.P, points), project(moved, points), atol=1e-9)
    assert fit.rotation_deg == pytest.approx(6.0)
    assert fit.cost_after < 1e-18 < fit.cost_before


def test_least_squares_under_noise_and_bad_input():
    rng = np.random.default_rng(4)
    uv = rng.uniform(0, 500, size=(200, 2))
    fit = fit_in_plane_rigid(uv, uv + rng.normal(scale=0.5, size=uv.shape) + [3.0, 0.0], P)
    assert fit.translation[0] == pytest.approx(3.0, abs=0.15) and abs(fit.rotation_deg) < 0.05
    with pytest.raises(ValueError, match="three or more"):
        fit_in_plane_rigid(uv[:2], uv[:2], P)

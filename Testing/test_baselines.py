"""Tests of the baselines: shape variation (rigid) and ICP-TPS after Groher et al. 2009."""

import numpy as np
import pytest

from FevarPlannerLib.baselines import (_GroherEnergy, annealing_temperatures, icp_tps, lbfgs, rigid,
                                       rpm_soft_assign, select_controls)
from FevarPlannerLib.deformation import ThinPlateSpline3D, energy_terms
from FevarPlannerLib.evaluation import error_2d, error_3d
from FevarPlannerLib.projection import project
from fixtures import synthetic_case


@pytest.fixture(scope="module")
def case():
    """A 300-node AAA-like tree deformed by up to 9 mm in the image plane, 800 skeleton points."""
    return synthetic_case(300, seed=0, skeleton_points=800)


@pytest.fixture(scope="module")
def registered(case):
    return icp_tps(case["preop"].points, case["preop"].edges, case["skeleton_points"], case["P"])


def errors(case, points):
    e2 = error_2d(points, case["P"], case["skeleton_points"], case["skeleton_edges"])
    e3 = error_3d((points, case["preop"].edges), case["truth"])
    return e2["mean"], e3["forward"]["mean"], e3["reverse"]["mean"]


def test_rigid_returns_the_prealigned_points_unchanged(case):
    result = rigid(case["preop"].points)
    np.testing.assert_array_equal(result.points, case["preop"].points)
    assert result.points is not case["preop"].points
    assert result.method == "rigid" and result.n_iter == 0


def test_icp_tps_recovers_an_in_plane_deformation(case, registered):
    rigid_2d, rigid_3d, rigid_3d_reverse = errors(case, case["preop"].points)
    icp_2d, icp_3d, icp_3d_reverse = errors(case, registered.points)
    assert rigid_2d > 10.0                           # the case is far from aligned to start with
    assert icp_2d < rigid_2d / 20.0
    assert icp_3d < 0.7 * rigid_3d and icp_3d_reverse < 0.7 * rigid_3d_reverse
    assert registered.n_iter == 87 and registered.method == "icp-tps"
    assert set(registered.timings) == {"total", "correspondence", "deformation"}
    assert registered.points.shape == case["preop"].points.shape


def test_icp_tps_is_deterministic(case, registered):
    again = icp_tps(case["preop"].points, case["preop"].edges, case["skeleton_points"], case["P"])
    np.testing.assert_array_equal(again.points, registered.points)


def test_icp_tps_tolerates_extra_2d_points(case):
    rng = np.random.default_rng(7)
    spurious_vessel = np.linspace([700.0, 300.0], [900.0, 420.0], 150)
    noise = rng.uniform([300.0, 0.0], [720.0, 1024.0], size=(150, 2))
    skeleton = np.vstack([case["skeleton_points"], spurious_vessel, noise])
    result = icp_tps(case["preop"].points, case["preop"].edges, skeleton, case["P"])
    rigid_2d, rigid_3d, _ = errors(case, case["preop"].points)
    icp_2d, icp_3d, _ = errors(case, result.points)
    assert icp_2d < rigid_2d / 10.0
    assert icp_3d < 0.7 * rigid_3d
    nearest_spurious = np.min(np.linalg.norm(project(case["P"], result.points)[:, None] - spurious_vessel, axis=2))
    assert nearest_spurious > 20.0                   # nothing was dragged onto the spurious vessel


def test_icp_tps_reports_progress_and_checks_input(case):
    seen = []
    icp_tps(case["preop"].points, case["preop"].edges, case["skeleton_points"], case["P"], t_init=20.0,
            t_final=5.0, t_update=0.5, progress=lambda fraction, message: seen.append(fraction))
    assert seen == pytest.approx([1 / 3, 2 / 3, 1.0])
    args = (case["preop"].points, case["preop"].edges, case["skeleton_points"], case["P"])
    with pytest.raises(ValueError, match="T_update"):
        icp_tps(*args, t_update=1.0)
    with pytest.raises(ValueError, match="T_init >= T_final"):
        icp_tps(*args, t_init=0.5)
    with pytest.raises(ValueError, match="NaN"):
        icp_tps(np.full((5, 3), np.nan), [[0, 1]], case["skeleton_points"], case["P"])
    with pytest.raises(ValueError, match="2D skeleton"):
        icp_tps(case["preop"].points, case["preop"].edges, np.empty((0, 2)), case["P"])
    with pytest.raises(ValueError, match="out of range"):
        icp_tps(case["preop"].points, [[0, 10_000]], case["skeleton_points"], case["P"])


def test_annealing_schedule_follows_the_paper():
    temperatures = annealing_temperatures(500.0, 1.0, 0.93)
    assert temperatures[0] == 500.0 and temperatures[-1] == 1.0
    np.testing.assert_allclose(temperatures[1:-1] / temperatures[:-2], 0.93)
    assert len(temperatures) == 87 and np.all(temperatures[:-1] > 1.0)


def test_controls_include_ends_and_junctions_and_spread_out(case):
    tree = case["preop"]
    controls = select_controls(tree.points, tree.edges, 40)
    degree = np.bincount(tree.edges.ravel(), minlength=len(tree))
    assert set(np.flatnonzero(degree != 2)) <= set(controls)
    assert len(controls) == 40
    gaps = np.linalg.norm(tree.points[:, None] - tree.points[controls][None], axis=2).min(axis=1)
    assert gaps.max() < 12.0                         # every node lies near a control
    np.testing.assert_array_equal(controls, select_controls(tree.points, tree.edges, 40))


def test_tps_basis_matches_the_thin_plate_spline_and_its_bending_energy():
    rng = np.random.default_rng(3)
    controls = rng.uniform(-40, 40, size=(12, 3))
    points = rng.uniform(-50, 50, size=(30, 3))
    G, B = ThinPlateSpline3D.control_basis(points, controls)
    moved = controls + rng.normal(scale=5.0, size=controls.shape)
    expected = ThinPlateSpline3D().fit(controls, moved).transform(points)
    np.testing.assert_allclose(G @ moved, expected, atol=1e-8)
    np.testing.assert_allclose(G @ controls, points, atol=1e-8)           # identity reproduced
    affine = controls @ np.diag([1.1, 0.9, 1.2]).T + [3.0, -2.0, 1.0]
    assert np.einsum("ca,cd,da->", affine, B, affine) == pytest.approx(0.0, abs=1e-8)
    assert np.linalg.eigvalsh(B).min() > -1e-10                             # bending energy >= 0
    assert np.einsum("ca,cd,da->", moved, B, moved) > 1e-3


def test_tps_basis_with_coplanar_controls():
    rng = np.random.default_rng(4)
    controls = np.column_stack([rng.uniform(-30, 30, size=(10, 2)), np.zeros(10)])
    points = np.column_stack([rng.uniform(-30, 30, size=(15, 2)), np.zeros(15)])
    G, B = ThinPlateSpline3D.control_basis(points, controls)
    np.testing.assert_allclose(G @ controls, points, atol=1e-8)
    assert np.all(np.isfinite(B))


def test_rpm_soft_assign_finds_partners_and_outliers():
    skeleton = np.column_stack([np.arange(0.0, 100.0), np.full(100, 50.0)])     # a horizontal line, 1 px apart
    on_line = np.column_stack([np.arange(2.5, 100.0, 5.0), np.full(20, 51.0)])  # 3D nodes 1 px beside it
    projected = np.vstack([on_line, [[40.0, 400.0]]])                          # and one far away
    targets, weights = rpm_soft_assign(projected, skeleton, temperature=4.0)
    np.testing.assert_allclose(targets[2:18, 1], 50.0, atol=1e-6)           # pulled onto the line
    np.testing.assert_allclose(targets[2:18, 0], on_line[2:18, 0], atol=0.1)  # without sliding along it
    assert np.all(weights[2:18] > 0.9)
    assert weights[-1] < 1e-6
    np.testing.assert_array_equal(targets[-1], projected[-1])


def groher_energy(case, rng):
    """ICP-TPS's energy on the case's tree with 30 controls and noisy soft targets and weights."""
    tree = case["preop"]
    controls = select_controls(tree.points, tree.edges, 30)
    G, B = ThinPlateSpline3D.control_basis(tree.points, tree.points[controls])
    energy = _GroherEnergy(tree.points, tree.edges, case["P"], G, B, alpha=0.5)
    targets = project(case["P"], tree.points) + rng.normal(scale=3.0, size=(len(tree), 2))
    weights = rng.uniform(0.2, 1.0, size=len(tree))
    energy.set_correspondences(targets, weights)
    return energy, targets, weights


def test_groher_energy_gradient_matches_finite_differences(case):
    rng = np.random.default_rng(5)
    energy, _, _ = groher_energy(case, rng)
    energy.beta = 0.01
    x = rng.normal(scale=1.0, size=energy.B.shape[0] * 3)
    _, grad = energy(x)
    h = 1e-6
    for k in rng.choice(len(x), size=12, replace=False):
        step = np.zeros_like(x)
        step[k] = h
        numeric = (energy(x + step)[0] - energy(x - step)[0]) / (2 * h)
        assert grad[k] == pytest.approx(numeric, rel=1e-5, abs=1e-7)


def test_lbfgs_minimises_the_rosenbrock_function():
    def rosenbrock(x):
        value = 100.0 * (x[1] - x[0] ** 2) ** 2 + (1 - x[0]) ** 2
        grad = np.array([-400.0 * x[0] * (x[1] - x[0] ** 2) - 2 * (1 - x[0]), 200.0 * (x[1] - x[0] ** 2)])
        return value, grad

    x, evaluations = lbfgs(rosenbrock, np.array([-1.2, 1.0]), max_iter=200)
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-4)
    assert evaluations > 10


def test_groher_energy_shares_s_d_and_s_l_with_the_proposed_energy(case):
    """ICP-TPS's data and length terms are eq. 6's, taken at the TPS displacements G V."""
    rng = np.random.default_rng(6)
    energy, targets, weights = groher_energy(case, rng)
    tree, B = case["preop"], energy.B
    displacement = rng.normal(scale=2.0, size=(B.shape[0], 3))
    shared = energy_terms(energy.G @ displacement, tree.points, targets, tree.edges, case["P"], weights=weights)
    terms = energy.terms(displacement)
    assert terms["S_D"] == pytest.approx(shared["S_D"], rel=1e-12)
    assert terms["S_L"] == pytest.approx(shared["S_L"], rel=1e-12)
    assert terms["S_S"] == pytest.approx(float(np.einsum("ca,cd,da->", displacement, B, displacement)))
    assert terms["S_D"] > 1.0 and terms["S_L"] > 0.0

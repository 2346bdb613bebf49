"""Deformation stage: the energy of eq. 6, its gradient (eqs. 7-9), L-BFGS, TPS and the fill."""

import numpy as np
import pytest
import scipy.sparse
from scipy.spatial.transform import Rotation

from FevarPlannerLib.deformation import (
    ThinPlateSpline3D, deform_assigned, energy_and_gradient, energy_terms, fill_unassigned)
from FevarPlannerLib.projection import project
from fixtures import SMALL_VIEW, bent_arc, carm, chain_edges


def mirrored(P):
    """The same view shown left-right flipped: det(P[:, :3]) changes sign."""
    flipped = np.diag([-1.0, 1.0, 1.0]) @ P
    flipped[0] += (SMALL_VIEW.cols - 1) * P[2]
    return flipped


def planar_curve(n, step, turning):
    """Points in the AP image plane (x-z at y = 0) with exactly ``step`` mm between neighbours.

    ``turning(s)`` is the tangent angle (rad) at arc length fraction ``s``.
    """
    s = (np.arange(n - 1) + 0.5) / (n - 1)
    angle = turning(s)
    steps = step * np.column_stack([np.sin(angle), np.zeros(n - 1), -np.cos(angle)])
    points = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    return points - points.mean(axis=0)


def random_skeleton(rng, n=24):
    """A wiggly chain with one side branch, as a graph in the assigned-node index space."""
    trunk = np.column_stack([5 * np.sin(np.linspace(0, 3, n)), 3 * np.cos(np.linspace(0, 2, n)),
                             np.linspace(40, -40, n)])
    branch = trunk[n // 2] + np.outer(np.arange(1, 7), [3.0, 1.0, -0.5])
    points = np.vstack([trunk, branch]) + rng.normal(0, 0.3, (n + 6, 3))
    edges = np.vstack([chain_edges(n), [[n // 2, n]], chain_edges(6) + n])
    return points, edges


# ---------------------------------------------------------------------------- energy


@pytest.mark.parametrize("config", ["ap", "oblique_weighted", "mirrored", "negated_P"])
def test_gradient_matches_central_differences(config):
    rng = np.random.default_rng(["ap", "oblique_weighted", "mirrored", "negated_P"].index(config))
    points, edges = random_skeleton(rng)
    P = {"ap": carm(), "oblique_weighted": carm(30.0, 15.0, (2.0, -3.0, 5.0)),
         "mirrored": mirrored(carm(-20.0)), "negated_P": -carm(10.0, -10.0)}[config]
    if config == "mirrored":
        assert np.linalg.det(P[:, :3]) * np.linalg.det(carm(-20.0)[:, :3]) < 0
    weights = rng.uniform(0.2, 1.5, len(points)) if config == "oblique_weighted" else None
    targets = project(P, points) + rng.normal(0, 8.0, (len(points), 2))
    phi = rng.normal(0, 2.0, points.size)
    args = (points, targets, edges, P, 500.0, 10.0, weights, None)
    _, gradient = energy_and_gradient(phi, *args)
    step = 1e-5
    numeric = np.empty_like(phi)
    for k in range(phi.size):
        delta = np.zeros_like(phi)
        delta[k] = step
        numeric[k] = (energy_and_gradient(phi + delta, *args)[0] - energy_and_gradient(phi - delta, *args)[0]) / (2 * step)
    assert np.abs(numeric - gradient).max() / np.abs(gradient).max() < 1e-5


def test_energy_terms_match_their_definitions():
    rng = np.random.default_rng(7)
    points, edges = random_skeleton(rng)
    P = carm(15.0)
    targets = project(P, points) + rng.normal(0, 5.0, (len(points), 2))
    weights = rng.uniform(0.5, 2.0, len(points))
    phi = rng.normal(0, 1.5, points.shape)
    moved = points + phi
    rest = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    now = np.linalg.norm(moved[edges[:, 0]] - moved[edges[:, 1]], axis=1)
    expected = {
        "S_D": np.mean(weights * np.sum((targets - project(P, moved)) ** 2, axis=1)),
        "S_L": np.mean(((now - rest) / rest) ** 2),
        "S_S": np.mean(np.sum((phi[edges[:, 0]] - phi[edges[:, 1]]) ** 2, axis=1)),
    }
    terms = energy_terms(phi, points, targets, edges, P, weights=weights)
    for name, value in expected.items():
        assert terms[name] == pytest.approx(value, rel=1e-12)
    energy, _ = energy_and_gradient(phi, points, targets, edges, P, 500.0, 10.0, weights)
    assert energy == pytest.approx(expected["S_D"] + 500.0 * expected["S_L"] + 10.0 * expected["S_S"], rel=1e-12)
    # explicit rest lengths replace the pre-operative ones in S_L only
    terms_rest = energy_terms(phi, points, targets, edges, P, weights=weights, rest_lengths=2 * rest)
    assert terms_rest["S_L"] == pytest.approx(np.mean(((now - 2 * rest) / (2 * rest)) ** 2), rel=1e-12)
    assert terms_rest["S_S"] == pytest.approx(expected["S_S"], rel=1e-12)


def test_deformation_lowers_the_energy_and_reports_consistent_terms():
    rng = np.random.default_rng(3)
    points, edges = random_skeleton(rng)
    P = carm(-25.0, 10.0)
    targets = project(P, points + [4.0, 0.0, -3.0]) + rng.normal(0, 1.0, (len(points), 2))
    result = deform_assigned(points, targets, edges, P)
    assert result.energy_final < 0.2 * result.energy_initial
    t = result.terms
    assert result.energy_final == pytest.approx(t["S_D"] + 500.0 * t["S_L"] + 10.0 * t["S_S"], rel=1e-12)
    np.testing.assert_allclose(result.points, points + result.displacements, atol=1e-12)
    assert result.converged and 0 < result.n_iter <= 500 and result.n_evaluations >= result.n_iter
    assert result.energy_initial == pytest.approx(energy_and_gradient(np.zeros(points.size), points, targets,
                                                                      edges, P)[0])


def test_targets_at_the_projection_leave_the_skeleton_where_it_is():
    rng = np.random.default_rng(11)
    points, edges = random_skeleton(rng)
    P = mirrored(carm(20.0))
    result = deform_assigned(points, project(P, points), edges, P)
    assert np.abs(result.displacements).max() < 1e-6
    assert result.converged and result.energy_final < 1e-12


def _in_plane_bend(n=100, step=1.0):
    """A pre-operative curve and its length-preserving bend in the AP image plane."""
    before = planar_curve(n, step, lambda s: 0.3 * np.sin(2 * np.pi * s))
    after = planar_curve(n, step, lambda s: 0.3 * np.sin(2 * np.pi * s) + 0.2 * np.sin(np.pi * s) ** 2)
    after += [2.0, 0.0, -3.0]
    return before, after


@pytest.mark.parametrize("precondition", [False, True])
def test_in_plane_deformation_is_recovered(precondition):
    before, after = _in_plane_bend()
    P = carm()
    targets = project(P, after)
    edges = chain_edges(len(before))
    result = deform_assigned(before, targets, edges, P, precondition=precondition)
    residual = np.linalg.norm(project(P, result.points) - targets, axis=1)
    initial = np.linalg.norm(project(P, before) - targets, axis=1)
    assert initial.mean() > 10.0
    assert residual.max() < 0.1
    error3d = np.linalg.norm(result.points - after, axis=1).mean()
    assert error3d < 0.05 * np.linalg.norm(before - after, axis=1).mean()


def test_length_term_preserves_edge_lengths():
    before, after = _in_plane_bend(n=60, step=1.5)
    P = carm()
    center = project(P, after.mean(axis=0))
    targets = center + 1.06 * (project(P, after) - center)      # the image says 6 % longer
    edges = chain_edges(len(before))
    rest = np.linalg.norm(np.diff(before, axis=0), axis=1)

    def relative_length_change(alpha):
        result = deform_assigned(before, targets, edges, P, alpha=alpha, beta=10.0)
        now = np.linalg.norm(np.diff(result.points, axis=0), axis=1)
        return np.abs(now / rest - 1).max()

    assert relative_length_change(1e5) < 0.01
    assert relative_length_change(0.0) > 0.03


def test_bad_input_is_refused_with_a_message():
    rng = np.random.default_rng(0)
    points, edges = random_skeleton(rng)
    P = carm()
    targets = project(P, points)
    with pytest.raises(ValueError, match="targets"):
        deform_assigned(points, targets[:-1], edges, P)
    with pytest.raises(ValueError, match="edges"):
        deform_assigned(points, targets, edges + len(points), P)
    with pytest.raises(ValueError, match="rest length"):
        deform_assigned(np.vstack([points, points[-1]]), np.vstack([targets, targets[-1]]),
                        np.vstack([edges, [[len(points) - 1, len(points)]]]), P)
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        deform_assigned(bad, targets, edges, P)
    behind = points + [0.0, 2000.0, 0.0]        # past the source (y = +750 mm)
    with pytest.raises(ValueError, match="source"):
        deform_assigned(np.vstack([points, behind]), np.vstack([targets, targets]), edges, P)
    with pytest.raises(ValueError, match="weights"):
        deform_assigned(points, targets, edges, P, weights=-np.ones(len(points)))
    with pytest.raises(ValueError, match="phi"):
        energy_and_gradient(np.zeros(points.size - 3), points, targets, edges, P)


# ---------------------------------------------------------------------------- several views


def numeric_gradient(function, x, step=1e-5):
    numeric = np.empty_like(x)
    for k in range(x.size):
        delta = np.zeros_like(x)
        delta[k] = step
        numeric[k] = (function(x + delta) - function(x - delta)) / (2 * step)
    return numeric


def test_two_view_gradient_matches_central_differences_with_unseen_nodes():
    rng = np.random.default_rng(11)
    points, edges = random_skeleton(rng)
    P1, P2 = carm(0.0), carm(70.0, 10.0)
    targets1 = project(P1, points) + rng.normal(0, 6.0, (len(points), 2))
    targets2 = project(P2, points) + rng.normal(0, 6.0, (len(points), 2))
    weights2 = rng.uniform(0.3, 1.5, len(points))
    weights2[:8] = 0.0                       # not in the second frame: no data term there
    targets2[:8] = np.nan
    views = ((P2, targets2, weights2),)
    phi = rng.normal(0, 2.0, points.size)

    def energy(x):
        return energy_and_gradient(x, points, targets1, edges, P1, extra_views=views)[0]

    _, gradient = energy_and_gradient(phi, points, targets1, edges, P1, extra_views=views)
    numeric = numeric_gradient(energy, phi)
    assert np.abs(numeric - gradient).max() / np.abs(gradient).max() < 1e-5


def test_s_d_is_the_mean_of_the_views_data_terms():
    rng = np.random.default_rng(12)
    points, edges = random_skeleton(rng)
    P1, P2 = carm(0.0), carm(-60.0)
    targets1 = project(P1, points) + rng.normal(0, 4.0, (len(points), 2))
    targets2 = project(P2, points) + rng.normal(0, 4.0, (len(points), 2))
    weights2 = np.r_[np.zeros(5), np.ones(len(points) - 5)]
    phi = rng.normal(0, 1.0, points.size)
    one = energy_terms(phi, points, targets1, edges, P1)
    other = energy_terms(phi, points, targets2, edges, P2, weights=weights2)
    both = energy_terms(phi, points, targets1, edges, P1, extra_views=[(P2, targets2, weights2)])
    assert both["S_D"] == pytest.approx((one["S_D"] + other["S_D"]) / 2, rel=1e-12)
    assert both["S_L"] == one["S_L"] and both["S_S"] == one["S_S"]
    # no extra view: exactly the single-view energy; the same view twice: the same mean
    single = energy_and_gradient(phi, points, targets1, edges, P1)
    assert energy_and_gradient(phi, points, targets1, edges, P1, extra_views=())[0] == single[0]
    twice = energy_and_gradient(phi, points, targets1, edges, P1, extra_views=[(P1, targets1, None)])
    assert twice[0] == pytest.approx(single[0], rel=1e-12)
    np.testing.assert_allclose(twice[1], single[1], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("precondition", [False, True])
def test_a_second_view_recovers_the_depth_that_one_view_cannot(precondition):
    preop, truth, rays, edges = bent_arc()
    P1 = carm(0.0)
    one = deform_assigned(preop, project(P1, truth), edges, P1, precondition=precondition)
    along_one = np.abs(np.einsum("nj,nj->n", one.points - truth, rays))
    assert along_one.mean() > 5.0                                # the bend is invisible in AP
    for angle in (60.0, 90.0):
        P2 = carm(angle)
        two = deform_assigned(preop, project(P1, truth), edges, P1, precondition=precondition,
                              extra_views=[(P2, project(P2, truth), np.ones(len(preop)))])
        along_two = np.abs(np.einsum("nj,nj->n", two.points - truth, rays))
        assert along_two.mean() < 1.0 and along_two.max() < 2.0, (angle, along_two.mean(), along_two.max())
        assert np.linalg.norm(two.points - truth, axis=1).mean() < 1.0


@pytest.mark.parametrize("precondition", [False, True])
def test_a_warm_start_continues_from_the_given_displacements(precondition):
    """``initial``: started at a solution, L-BFGS stays there (same points, no higher energy);
    started at a wrong guess it still reaches the solution of a cold start."""
    from FevarPlannerLib.deformation.energy import _build_model
    from FevarPlannerLib.deformation.solve import _BandedPreconditioner
    preop, truth, _, edges = bent_arc()
    P1, P2 = carm(0.0), carm(60.0)
    views = [(P2, project(P2, truth), None)]
    cold = deform_assigned(preop, project(P1, truth), edges, P1, precondition=precondition, extra_views=views)
    warm = deform_assigned(preop, project(P1, truth), edges, P1, precondition=precondition, extra_views=views,
                           initial=cold.displacements)
    assert warm.energy_initial == cold.energy_initial
    assert warm.energy_final <= cold.energy_final * (1 + 1e-9)
    assert np.linalg.norm(warm.points - cold.points, axis=1).max() < 0.05
    guess = deform_assigned(preop, project(P1, truth), edges, P1, precondition=precondition, extra_views=views,
                            initial=cold.displacements + np.random.default_rng(3).normal(0, 1.0, preop.shape))
    assert np.linalg.norm(guess.points - truth, axis=1).mean() < 1.0
    # the change of variables x = R phi and its inverse
    model = _build_model(preop, project(P1, truth), edges, P1, 500.0, 10.0, None, None, views)
    R = _BandedPreconditioner(model, 0.1)
    phi = np.random.default_rng(4).normal(0, 1.0, (3, len(preop)))
    np.testing.assert_allclose(R.displacement(R.variables(phi)), phi, atol=1e-9)


def test_bad_extra_views_are_refused_with_a_message():
    rng = np.random.default_rng(0)
    points, edges = random_skeleton(rng)
    P = carm()
    targets = project(P, points)
    with pytest.raises(ValueError, match=r"extra_views\[0\]"):
        deform_assigned(points, targets, edges, P, extra_views=[(P, targets)])
    hidden = targets.copy()
    hidden[2] = np.nan
    with pytest.raises(ValueError, match=r"extra_views\[0\] targets.*NaN"):
        deform_assigned(points, targets, edges, P, extra_views=[(P, hidden, None)])
    with pytest.raises(ValueError, match=r"extra_views\[1\] weights"):
        deform_assigned(points, targets, edges, P, extra_views=[(P, targets, None), (P, targets, np.ones(3))])
    with pytest.raises(ValueError, match=r"extra_views\[0\] P"):
        deform_assigned(points, targets, edges, P, extra_views=[(np.zeros((3, 4)), targets, None)])


# ---------------------------------------------------------------------------- TPS


def test_tps_interpolates_its_controls_and_reproduces_affine_maps():
    rng = np.random.default_rng(5)
    source = rng.uniform(-50, 50, (40, 3))
    target = source + rng.normal(0, 4.0, source.shape)
    spline = ThinPlateSpline3D().fit(source, target)
    np.testing.assert_allclose(spline.transform(source), target, atol=1e-8)

    A = np.eye(3) + rng.normal(0, 0.2, (3, 3))
    b = rng.normal(0, 10.0, 3)
    affine = ThinPlateSpline3D().fit(source, source @ A.T + b)
    query = rng.uniform(-80, 80, (25, 3))
    np.testing.assert_allclose(affine.transform(query), query @ A.T + b, atol=1e-8)


def test_tps_with_coplanar_controls_and_regularization():
    rng = np.random.default_rng(6)
    flat = np.column_stack([rng.uniform(-30, 30, (20, 2)), np.zeros(20)])
    A = np.array([[1.1, 0.2, 0.3], [-0.1, 0.9, 0.0], [0.05, 0.1, 1.0]])
    spline = ThinPlateSpline3D().fit(flat, flat @ A.T + [1.0, 2.0, 3.0])
    in_plane = np.column_stack([rng.uniform(-30, 30, (10, 2)), np.zeros(10)])
    np.testing.assert_allclose(spline.transform(in_plane), in_plane @ A.T + [1.0, 2.0, 3.0], atol=1e-8)

    source = rng.uniform(-50, 50, (30, 3))
    target = source + rng.normal(0, 3.0, source.shape)
    smooth = ThinPlateSpline3D().fit(source, target, regularization=1e6)
    design = np.column_stack([np.ones(30), source])
    affine_fit = design @ np.linalg.lstsq(design, target, rcond=None)[0]
    np.testing.assert_allclose(smooth.transform(source), affine_fit, atol=0.05)
    with pytest.raises(ValueError, match="fit"):
        ThinPlateSpline3D().transform(source)
    with pytest.raises(ValueError, match="same"):
        ThinPlateSpline3D().fit(source, target[:-1])


# ---------------------------------------------------------------------------- fill


def y_skeleton():
    """Trunk along -z, a left branch bending out of plane, a right branch; 2 mm spacing."""
    trunk = np.column_stack([np.zeros(30), np.zeros(30), np.linspace(58, 0, 30)])
    s = np.arange(1, 21)[:, None] * 2.0
    left = np.column_stack([0.7 * s[:, 0], 0.02 * s[:, 0] ** 2, -0.7 * s[:, 0]])
    right = np.column_stack([-0.7 * s[:, 0], 0.3 * s[:, 0], -0.65 * s[:, 0]])
    points = np.vstack([trunk, left, right])
    edges = np.vstack([chain_edges(30), [[29, 30]], chain_edges(20) + 30, [[29, 50]], chain_edges(20) + 50])
    adjacency = scipy.sparse.csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(70, 70))
    groups = [np.arange(30), np.r_[29, 30:50], np.r_[29, 50:70]]
    return points, adjacency, groups


def test_fill_moves_an_unassigned_branch_with_its_trunk():
    points, adjacency, groups = y_skeleton()
    assigned = np.ones(len(points), dtype=bool)
    assigned[50:] = False
    rigid = Rotation.from_euler("xyz", [10.0, -6.0, 15.0], degrees=True)
    truth = rigid.apply(points - points[29]) + points[29] + [3.0, -2.0, 5.0]
    filled = fill_unassigned(points, np.where(assigned[:, None], truth, np.nan), assigned, adjacency)
    np.testing.assert_array_equal(filled[assigned], truth[assigned])
    np.testing.assert_allclose(filled[~assigned], truth[~assigned], atol=1e-6)

    # the same motion plus a smooth non-rigid part: the branch follows the trunk's motion
    # (rotation included) far better than staying put or translating with the junction
    x, _, z = points.T
    bent = truth + 2.0 * np.column_stack([np.sin(z / 30), 0.5 * np.cos(x / 25), 0.3 * np.sin((x + z) / 40)])
    for grouped in (None, groups):
        filled = fill_unassigned(points, np.where(assigned[:, None], bent, 0.0), assigned, adjacency,
                                 groups=grouped)
        np.testing.assert_array_equal(filled[:50], bent[:50])
        error = np.linalg.norm(filled[50:] - bent[50:], axis=1).mean()
        staying = np.linalg.norm(points[50:] - bent[50:], axis=1).mean()
        translating = np.linalg.norm(points[50:] + (bent[29] - points[29]) - bent[50:], axis=1).mean()
        assert error < 0.15 * staying and error < 0.3 * translating


def test_fill_moves_an_unseen_side_branch_with_its_trunk_not_with_a_sibling():
    # a trunk along -z; a renal (+x) and, 3 mm above it, an anterior side branch (-y) seen in no frame
    trunk = np.column_stack([np.zeros(40), np.zeros(40), np.linspace(78, 0, 40)])
    s = np.arange(1, 16)[:, None] * 2.0
    renal = np.column_stack([s[:, 0], np.zeros(15), np.full(15, 40.0)])
    side = np.column_stack([np.zeros(15), -s[:, 0], 42.0 - 0.8 * s[:, 0]])
    points = np.vstack([trunk, renal, side])
    edges = np.vstack([chain_edges(40), [[19, 40]], chain_edges(15) + 40, [[18, 55]], chain_edges(15) + 55])
    adjacency = scipy.sparse.csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(70, 70))
    vessels = ["aorta"] * 40 + ["renal"] * 15 + ["other"] * 15
    assigned = np.r_[np.ones(55, bool), np.zeros(15, bool)]
    moved = points + [2.0, 1.0, -3.0]
    moved[40:55] += [0.0, -6.0, 6.0]                           # the wire lifts the renal at its ostium
    truth = points[55:] + [2.0, 1.0, -3.0]                                       # the side branch rides the aorta

    near_everything = fill_unassigned(points, moved, assigned, adjacency)
    by_vessel = fill_unassigned(points, moved, assigned, adjacency, vessels=vessels)
    np.testing.assert_array_equal(by_vessel[:55], moved[:55])
    assert np.linalg.norm(by_vessel[55:] - truth, axis=1).max() < 0.05
    assert np.linalg.norm(near_everything[55:] - truth, axis=1).max() > 0.5
    with pytest.raises(ValueError, match="vessels"):
        fill_unassigned(points, moved, assigned, adjacency, vessels=vessels[:-1])


def test_fill_fills_gaps_and_handles_the_edge_cases():
    points, adjacency, groups = y_skeleton()
    shift = np.array([1.0, -2.0, 3.0])
    assigned = np.ones(len(points), dtype=bool)
    assigned[10:14] = False               # a gap in the trunk
    assigned[66:] = False                 # the tip of the right branch
    filled = fill_unassigned(points, points + shift, assigned, adjacency, groups=groups)
    np.testing.assert_allclose(filled, points + shift, atol=1e-9)
    np.testing.assert_array_equal(fill_unassigned(points, points + shift, np.zeros(70, bool), adjacency), points)
    np.testing.assert_array_equal(fill_unassigned(points, points + shift, np.ones(70, bool), adjacency),
                                  points + shift)
    with pytest.raises(ValueError, match="assigned"):
        fill_unassigned(points, points, np.ones(69, bool), adjacency)

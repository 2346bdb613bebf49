"""The deformation's own driver of scipy's L-BFGS-B routine gives ``scipy.optimize.minimize``'s
answer to the bit (issue 10, per-frame time: the wrapper cost about as much as the routine).

Each solve runs twice, through :func:`deformation.solve._minimize_lbfgsb` and through
``scipy.optimize.minimize(method="L-BFGS-B")``: every stopping rule (energy stall over the
window, iteration limit, gradient, scipy's own relative reduction), one and two views,
preconditioned or not, warm started or not.
"""

import numpy as np
import pytest
import scipy.optimize

from FevarPlannerLib.deformation import deform_assigned
from FevarPlannerLib.deformation import solve as solve_module
from fixtures import carm, vessel_tree

pytestmark = pytest.mark.skipif(not solve_module._LEAN_LBFGSB, reason="scipy's own driver on this scipy version")


def _both(monkeypatch, solve):
    """``solve()`` with the lean driver, then with scipy's."""
    lean = solve()
    monkeypatch.setattr(solve_module, "_LEAN_LBFGSB", False)
    plain = solve()
    monkeypatch.setattr(solve_module, "_LEAN_LBFGSB", True)
    return lean, plain


def _same(lean, plain):
    np.testing.assert_array_equal(lean.points, plain.points)
    assert (lean.energy_final, lean.n_iter, lean.n_evaluations, lean.converged, lean.message) == \
        (plain.energy_final, plain.n_iter, plain.n_evaluations, plain.converged, plain.message)


CASES = {
    "one view, stalls": {},
    "one view, iteration limit": {"max_iter": 7},
    "one view, gradient": {"gtol": 1e3},
    "one view, scipy's reduction test": {"tol": 0.0, "max_iter": 3000},
    "two views, preconditioned": {"extra": True},
    "two views, warm start": {"extra": True, "initial": True, "window": 5},
    "one view, warm start, weights": {"initial": True, "weights": True},
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_lean_driver_solves_as_scipys_minimize_to_the_bit(case, monkeypatch):
    options = dict(CASES[case])
    tree = vessel_tree(90)
    n = len(tree.points)
    rng = np.random.default_rng(len(case))
    targets = rng.normal(256.0, 20.0, (n, 2))
    kwargs = {key: options.pop(key) for key in ("max_iter", "gtol", "tol", "window") if key in options}
    if options.get("extra"):
        kwargs["extra_views"] = [(carm(45.0), rng.normal(256.0, 20.0, (n, 2)), None)]
    if options.get("initial"):
        kwargs["initial"] = rng.normal(0.0, 1.0, (n, 3))
    if options.get("weights"):
        kwargs["weights"] = rng.random(n)
    lean, plain = _both(monkeypatch, lambda: deform_assigned(tree.points, targets, tree.edges, carm(0.0), **kwargs))
    _same(lean, plain)
    assert lean.n_iter > 1


def test_the_messages_name_each_stopping_rule(monkeypatch):
    """The rules the cases above reach: each case's message as scipy words it."""
    tree = vessel_tree(90)
    targets = np.random.default_rng(1).normal(256.0, 20.0, (len(tree.points), 2))
    messages = {deform_assigned(tree.points, targets, tree.edges, carm(0.0), **kwargs).message
                for kwargs in ({}, {"max_iter": 7}, {"gtol": 1e3})}
    assert len(messages) == 3 and any("ITERATIONS REACHED LIMIT" in m for m in messages)


def test_a_plain_function_and_a_halting_callback_match_scipy():
    """Rosenbrock in 6 variables, halted by the callback after 9 iterates."""
    def rosen(x):
        return scipy.optimize.rosen(x), scipy.optimize.rosen_der(x)

    def halting(seen):
        def callback(intermediate_result):
            seen.append((intermediate_result.fun, intermediate_result.x.copy()))
            if len(seen) == 9:
                raise StopIteration
        return callback

    start = np.linspace(-1.2, 1.0, 6)
    options = {"maxiter": 500, "gtol": 1e-8, "ftol": 1e-12, "maxcor": 5}
    lean_seen, plain_seen = [], []
    lean = solve_module._minimize_lbfgsb(rosen, start, halting(lean_seen), **options)
    plain = scipy.optimize.minimize(rosen, start, jac=True, method="L-BFGS-B", callback=halting(plain_seen),
                                    options=options)
    np.testing.assert_array_equal(lean.x, plain.x)
    assert (lean.fun, lean.nit, lean.success, lean.message) == (plain.fun, plain.nit, plain.success, plain.message)
    assert len(lean_seen) == len(plain_seen) == 9
    for (f_lean, x_lean), (f_plain, x_plain) in zip(lean_seen, plain_seen):
        assert f_lean == f_plain
        np.testing.assert_array_equal(x_lean, x_plain)
    free = solve_module._minimize_lbfgsb(rosen, start, lambda result: None, **options)
    reference = scipy.optimize.minimize(rosen, start, jac=True, method="L-BFGS-B", options=options)
    np.testing.assert_array_equal(free.x, reference.x)
    assert free.success and (free.nit, free.message) == (reference.nit, reference.message)

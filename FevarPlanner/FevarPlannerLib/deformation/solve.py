"""Minimising eq. 6 (Algorithm 2 rows 13-15): L-BFGS from ``phi = 0``, optionally preconditioned."""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.optimize
import scipy.sparse
from scipy.sparse import csgraph

from ..projection import projection_jacobian
from .energy import DEFAULT_ALPHA, DEFAULT_BETA, DeformationResult, _build_model, _displacements_cm, _EnergyModel

__all__ = ["deform_assigned"]


class _BandLayout:
    """Where the entries of the Gauss-Newton Hessian go in band storage: a function of the edges only.

    Nodes in reverse Cuthill-McKee order, the (permuted) row and column of every entry of the
    Hessian's 3x3 blocks (the diagonal blocks of the nodes first, then ``ii``, ``jj``, ``ij``,
    ``ji`` of every edge), their upper-band slots and the index maps between the permuted
    variables and the (3, n) displacements. A frame's solves share their edges, so the
    layout is kept (:func:`_band_layout`); its arrays are read-only.
    """

    def __init__(self, edges: np.ndarray, n: int, max_band_nodes: int):
        order = self._node_order(edges, n)
        self.position = np.empty(n, dtype=np.int64)
        self.position[order] = np.arange(n)
        band_nodes = int(np.abs(np.diff(self.position[edges], axis=1)).max()) if len(edges) else 0
        self.usable = band_nodes <= max_band_nodes
        if not self.usable:
            return
        self.band = 3 * band_nodes + 2
        self.rows, self.cols = self._block_entries(edges, n)
        self.upper = self.rows <= self.cols
        self.slots = (self.band + self.rows[self.upper] - self.cols[self.upper]) * (3 * n) + self.cols[self.upper]
        self.to_permuted = (np.arange(3)[None, :] * n + order[:, None]).ravel()   # x index -> (3, n) index
        self.from_permuted = (3 * self.position[None, :] + np.arange(3)[:, None]).ravel()
        for array in (self.position, self.rows, self.cols, self.upper, self.slots, self.to_permuted,
                      self.from_permuted):
            array.flags.writeable = False

    @staticmethod
    def _node_order(edges: np.ndarray, n: int) -> np.ndarray:
        if not len(edges):
            return np.arange(n)
        i, j = edges[:, 0], edges[:, 1]
        adjacency = scipy.sparse.csr_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
        return np.asarray(csgraph.reverse_cuthill_mckee(adjacency, symmetric_mode=True), dtype=np.int64)

    def _block_entries(self, edges: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Permuted (row, column) of every entry of the Hessian blocks, in :meth:`_hessian_blocks` order."""
        pairs = [(np.arange(n), np.arange(n))]
        if len(edges):
            i, j = edges[:, 0], edges[:, 1]
            pairs += [(i, i), (j, j), (i, j), (j, i)]
        rows, cols = [], []
        component = np.arange(3)
        for a, b in pairs:
            r = 3 * self.position[a][:, None, None] + component[None, :, None]
            c = 3 * self.position[b][:, None, None] + component[None, None, :]
            r, c = np.broadcast_arrays(r, c)
            rows.append(r.ravel())
            cols.append(c.ravel())
        return np.concatenate(rows), np.concatenate(cols)


#: Band layouts kept (most recently used last): the edge sets of a few frames.
_LAYOUT_CACHE_SIZE = 8
_layout_cache: OrderedDict = OrderedDict()
_layout_lock = threading.Lock()


def _band_layout(edges: np.ndarray, n: int, max_band_nodes: int) -> _BandLayout:
    """The :class:`_BandLayout` of ``edges`` over ``n`` nodes, from a small LRU cache keyed by content."""
    key = (n, edges.shape, edges.tobytes(), max_band_nodes)
    with _layout_lock:
        layout = _layout_cache.get(key)
        if layout is not None:
            _layout_cache.move_to_end(key)
            return layout
    layout = _BandLayout(edges, n, max_band_nodes)
    with _layout_lock:
        _layout_cache[key] = layout
        while len(_layout_cache) > _LAYOUT_CACHE_SIZE:
            _layout_cache.popitem(last=False)
    return layout


class _BandedPreconditioner:
    """Change of variables ``x = R phi`` with ``R^T R`` the Gauss-Newton Hessian of eq. 6 at ``phi = 0``.

    The length term is far stiffer along the edges than the data term is in the image
    plane, and the data term does not see motion along the rays at all; in ``x`` the
    Hessian is close to the identity. Nodes are put in reverse Cuthill-McKee order so that
    ``R`` is banded (a skeleton is nearly a tree), which makes its Cholesky factor and the
    two triangular solves per evaluation cost O(n * band^2) and O(n * band).
    ``ridge`` (relative to the median in-plane data stiffness) is added to the diagonal; it
    bounds how far one step may run along the nearly flat directions (motion along the rays).
    """

    MAX_BAND_NODES = 40

    def __init__(self, model: _EnergyModel, ridge: float):
        n = len(model.points)
        layout = _band_layout(model.edges, n, self.MAX_BAND_NODES)
        self.position = layout.position
        self.usable = layout.usable
        if not self.usable:
            return
        self.band = layout.band
        values = self._hessian_values(model, model.points, ridge)
        # upper band storage; the entries of a place add up in their order (as np.add.at would)
        ab = np.bincount(layout.slots, values[layout.upper], (self.band + 1) * 3 * n).reshape(self.band + 1, 3 * n)
        self.factor = scipy.linalg.cholesky_banded(ab, lower=False, check_finite=False)
        self.to_permuted = layout.to_permuted
        self.from_permuted = layout.from_permuted
        self._layout = layout

    def _hessian_values(self, model: _EnergyModel, y: np.ndarray, ridge: float) -> np.ndarray:
        """The entries of the GN Hessian of ``n_a * eps`` at ``y``, in :class:`_BandLayout` order."""
        n, m = len(y), len(model.edges)
        data = np.zeros((n, 3, 3))
        for view in model.views:       # the data blocks of every view add up
            jac = projection_jacobian(view.P, y)                                        # (n, 2, 3) d f/d y
            data += 2.0 * (view.data_weights * n)[:, None, None] * np.einsum("nki,nkj->nij", jac, jac)
        stiffness = np.median(np.trace(data, axis1=1, axis2=2)) / 2.0
        if not stiffness > 0:
            stiffness = 1.0
        values = [(data + ridge * stiffness * np.eye(3)).ravel()]
        if m:
            i, j = model.edges[:, 0], model.edges[:, 1]
            vec = y[i] - y[j]
            unit = vec / (np.maximum(np.linalg.norm(vec, axis=1), 1e-12) * model.rest_lengths)[:, None]
            edge = (2.0 * n / m * (model.alpha * np.einsum("ei,ej->eij", unit, unit) + model.beta * np.eye(3))).ravel()
            values += [edge, edge, -edge, -edge]         # blocks ii, jj, ij, ji
        return np.concatenate(values)

    def _hessian_blocks(self, model: _EnergyModel, y: np.ndarray, ridge: float):
        """COO entries (in permuted variable order) of the GN Hessian of ``n_a * eps`` at ``y``."""
        return self._layout.rows, self._layout.cols, self._hessian_values(model, y, ridge)

    def displacement(self, x: np.ndarray) -> np.ndarray:
        """``phi = R^-1 x`` as a (3, n) array."""
        z, _ = scipy.linalg.lapack.dtbtrs(self.factor, x[:, None], uplo="U", trans="N")
        return z[self.from_permuted, 0].reshape(3, -1)

    def variables(self, phi: np.ndarray) -> np.ndarray:
        """``x = R phi`` (flat) for displacements ``phi`` (3, n): the inverse of :meth:`displacement`."""
        z = phi.ravel()[self.to_permuted]
        x = self.factor[self.band] * z
        for offset in range(1, self.band + 1):        # R[i, i + offset] sits at factor[band - offset, i + offset]
            x[:-offset] += self.factor[self.band - offset, offset:] * z[offset:]
        return x

    def gradient(self, grad_phi: np.ndarray) -> np.ndarray:
        """``R^-T grad_phi`` (flat) for a gradient (3, n) with respect to ``phi``."""
        g, _ = scipy.linalg.lapack.dtbtrs(self.factor, grad_phi.ravel()[self.to_permuted][:, None],
                                          uplo="U", trans="T")
        return g[:, 0]


#: Preconditioners kept (most recently used last; 0: none): the passes of one frame's solves that
#: share their nodes, edges and data weights (the Hessian at ``phi = 0`` does not see the targets).
_PRECONDITIONER_CACHE_SIZE = 8
_preconditioner_cache: OrderedDict = OrderedDict()


def _preconditioner(model: _EnergyModel, ridge: float) -> _BandedPreconditioner:
    """The :class:`_BandedPreconditioner` of ``model``, from a small LRU cache keyed by what its
    Hessian at ``phi = 0`` depends on: nodes, edges, rest lengths, alpha, beta, ridge and each
    view's P and data weights (not the targets)."""
    key = (model.points.tobytes(), model.edges.tobytes(), model.rest_lengths.tobytes(), model.alpha, model.beta,
           float(ridge), tuple((np.asarray(v.P, dtype=float).tobytes(), v.data_weights.tobytes()) for v in model.views))
    with _layout_lock:
        found = _preconditioner_cache.get(key)
        if found is not None:
            _preconditioner_cache.move_to_end(key)
            return found
    found = _BandedPreconditioner(model, ridge)
    if _PRECONDITIONER_CACHE_SIZE < 1:
        return found
    with _layout_lock:
        _preconditioner_cache[key] = found
        while len(_preconditioner_cache) > _PRECONDITIONER_CACHE_SIZE:
            _preconditioner_cache.popitem(last=False)
    return found


def deform_assigned(points, targets, edges, P, *, alpha=DEFAULT_ALPHA, beta=DEFAULT_BETA, weights=None,
                    rest_lengths=None, extra_views=(), max_iter=500, tol=1e-2, window=10, gtol=1e-6,
                    memory=5, precondition=None, ridge=0.1, initial=None) -> DeformationResult:
    """Deform the assigned 3D nodes onto their 2D targets (Algorithm 2 rows 13-15).

    Minimises eq. 6 with L-BFGS (scipy ``L-BFGS-B``, analytic gradient) from ``phi = 0``,
    in millimetres. The optimiser sees the *summed* energy ``n_a * eps`` so that ``gtol``
    does not depend on the number of nodes.

    The energy has a long, nearly flat valley: motion along the X-rays is seen only through
    the length and smoothness terms, so after the 2D residual has settled the energy keeps
    creeping down for thousands of iterations while the skeleton moves in depth: towards
    the true shape when the deformation preserves lengths, far away from it when it does
    not or when ``P``'s magnification is slightly off (measured: a 5 % scale error sends the
    fully converged skeleton ~40 mm off in 3D, against ~5 mm when stopped early). The run
    therefore stops when the energy fell by less than ``tol`` (relative) over the last
    ``window`` iterations, when the gradient is below ``gtol``, or after ``max_iter``.

    Parameters
    ----------
    points, targets, edges, P, alpha, beta, weights, rest_lengths, extra_views
        As in :func:`energy_and_gradient`. With ``extra_views`` (further frames of the same
        anatomy, each ``(P_k, targets_k, weights_k)``) ``S_D`` is the mean over the views;
        two views far enough apart (30-90 degrees) see the depth that one view cannot.
    max_iter : int
        Most L-BFGS iterations.
    tol : float
        Relative energy decrease over ``window`` iterations below which the run stops.
    window : int
        Iterations over which ``tol`` is measured.
    gtol : float
        Largest gradient component of ``n_a * eps`` (px^2/mm; in the preconditioned
        variables when ``precondition``) at which L-BFGS stops.
    memory : int
        Number of L-BFGS correction pairs.
    precondition : bool, optional
        Optimise ``x = R phi`` with ``R^T R`` the banded Gauss-Newton Hessian at ``phi = 0``
        (used when the skeleton orders into a narrow band, as trees do). It converges in
        about a third of the iterations and follows the depth valley much further. With one
        view that valley is unobserved: following it helps when lengths are truly preserved
        and the geometry is exact, and hurts badly otherwise. With several views the depth is
        observed and the valley gone. Default (None): on with ``extra_views``, off without
        (Testing/benchmarks/bench_deformation.py, 991 nodes, AP + LAO 60: 24 instead of 323
        iterations, 14 instead of 88 ms CPU, the same 0.08 mm 3D error).
    ridge : float
        Diagonal added to that Hessian, in units of the median in-plane data stiffness.
    initial : array_like, shape (n_a, 3), optional
        Displacements to start from instead of ``phi = 0`` (a warm start, e.g. the previous
        solution when only the targets changed). ``energy_initial`` stays the energy at
        ``phi = 0``.

    Returns
    -------
    DeformationResult
    """
    model = _build_model(points, targets, edges, P, alpha, beta, weights, rest_lengths, extra_views)
    n = len(model.points)
    if n == 0:
        empty = np.zeros((0, 3))
        return DeformationResult(empty, empty, 0.0, 0.0, {"S_D": 0.0, "S_L": 0.0, "S_S": 0.0}, 0, True)
    if max_iter < 0 or window < 1 or not (tol >= 0 and gtol >= 0):
        raise ValueError("deform_assigned: need max_iter >= 0, window >= 1, tol >= 0 and gtol >= 0")
    evaluations = [0]
    if precondition is None:
        precondition = len(model.views) > 1
    preconditioner = _preconditioner(model, ridge) if precondition else None
    if preconditioner is not None and not preconditioner.usable:
        preconditioner = None

    def displacement(x):
        return x.reshape(3, n) if preconditioner is None else preconditioner.displacement(x)

    def objective(x):
        evaluations[0] += 1
        energy, grad, _ = model.evaluate(displacement(x))
        grad *= n
        return energy * n, (grad.ravel() if preconditioner is None else preconditioner.gradient(grad))

    energy0, _, _ = model.evaluate(np.zeros((3, n)), with_gradient=False)
    history = [energy0 * n]
    stalled = [False]

    def stop_when_stalled(intermediate_result):
        history.append(float(intermediate_result.fun))
        if len(history) > window:
            old = history[-1 - window]
            if old - history[-1] <= tol * max(abs(old), 1e-300):
                stalled[0] = True
                raise StopIteration

    start = np.zeros(3 * n)
    if initial is not None:
        phi0 = _displacements_cm(initial, n)
        start = phi0.ravel() if preconditioner is None else preconditioner.variables(phi0)
        history[0] = objective(start)[0]
    options = {"maxiter": int(max_iter), "gtol": float(gtol), "ftol": 1e-12, "maxcor": int(memory)}
    if _LEAN_LBFGSB:
        solution = _minimize_lbfgsb(objective, start, stop_when_stalled, **options)
    else:
        solution = scipy.optimize.minimize(objective, start, jac=True, method="L-BFGS-B", callback=stop_when_stalled,
                                           options=options)
    phi_cm = displacement(solution.x)
    energy, _, terms = model.evaluate(phi_cm, with_gradient=False)
    phi = np.ascontiguousarray(phi_cm.T)
    converged = bool(solution.success) or stalled[0]
    message = f"energy fell by less than {tol:g} over {window} iterations" if stalled[0] else str(solution.message)
    return DeformationResult(points=model.points + phi, displacements=phi, energy_initial=float(energy0),
                             energy_final=float(energy), terms=terms, n_iter=int(solution.nit),
                             converged=converged, n_evaluations=evaluations[0], message=message)


def _scipy_version() -> tuple[int, int]:
    return tuple(int(part) for part in scipy.__version__.split(".")[:2])


#: Drive scipy's compiled L-BFGS-B routine directly (:func:`_minimize_lbfgsb`) on the scipy
#: versions whose ``minimize(method="L-BFGS-B")`` it was checked against, to the bit
#: (Testing/test_fast_paths.py); on any other, ``scipy.optimize.minimize`` itself.
_LEAN_LBFGSB = _scipy_version() == (1, 17)
#: Most evaluations (scipy's ``maxfun`` default) and line-search steps (``maxls``).
_MAX_EVALUATIONS = 15000
_MAX_LINE_SEARCH = 20


def _minimize_lbfgsb(objective, start: np.ndarray, callback, *, maxiter: int, gtol: float, ftol: float,
                     maxcor: int) -> scipy.optimize.OptimizeResult:
    """``scipy.optimize.minimize(objective, start, jac=True, method="L-BFGS-B", callback=callback,
    options=...)`` without bounds, the same calls of scipy's L-BFGS-B routine with the same numbers,
    without the per-call wrapping (its function objects, copies and result records cost about as
    much as the routine itself on a frame's deformation).

    ``objective(x)`` gives (value, gradient) and is evaluated once per distinct ``x`` (scipy
    keeps the last point's values too); ``callback(result)`` sees each new iterate's ``fun`` and
    ``x`` and may raise StopIteration to halt. Returns ``x``, ``fun``, ``nit``, ``success``,
    ``message`` as scipy does.
    """
    from scipy.optimize import _lbfgsb
    from scipy.optimize._lbfgsb_py import status_messages, task_messages

    x = np.array(start, dtype=np.float64).ravel()
    n = x.size
    last = {"x": x.copy(), "evaluations": 1}
    f, g = objective(x.copy())
    f, g = _scalar(f), np.atleast_1d(g)
    bounds_kind = np.zeros(n, np.int32)
    lower, upper = np.zeros(n, np.float64), np.zeros(n, np.float64)
    work = np.zeros(2 * maxcor * n + 5 * n + 11 * maxcor * maxcor + 8 * maxcor, np.float64)
    iwork = np.zeros(3 * n, dtype=np.int32)
    task, line_task = np.zeros(2, dtype=np.int32), np.zeros(2, dtype=np.int32)
    lsave, isave, dsave = np.zeros(4, dtype=np.int32), np.zeros(44, dtype=np.int32), np.zeros(29, dtype=np.float64)
    factr = ftol / np.finfo(float).eps
    iterations, halted = 0, False
    while True:
        g = g.astype(np.float64)
        _lbfgsb.setulb(maxcor, x, lower, upper, bounds_kind, f, g, factr, gtol, work, iwork, task, lsave, isave,
                       dsave, _MAX_LINE_SEARCH, line_task)
        if task[0] == 3:                # f and g wanted at x
            if not np.array_equal(x, last["x"]):
                last["x"] = x.copy()
                last["evaluations"] += 1
                f, g = objective(x.copy())
                f, g = _scalar(f), np.atleast_1d(g)
        elif task[0] == 1:              # a new iterate
            iterations += 1
            try:
                callback(scipy.optimize.OptimizeResult(x=x, fun=f))
            except StopIteration:
                task[0], task[1], halted = 5, 505, True
            if iterations >= maxiter:
                task[0], task[1] = 5, 504
            elif last["evaluations"] > _MAX_EVALUATIONS:
                task[0], task[1] = 5, 502
        else:
            break
    if halted:          # as scipy.optimize.minimize words it
        return scipy.optimize.OptimizeResult(x=x, fun=f, nit=iterations, success=False,
                                             message="`callback` raised `StopIteration`.")
    return scipy.optimize.OptimizeResult(x=x, fun=f, nit=iterations, success=task[0] == 4,
                                         message=status_messages[task[0]] + ": " + task_messages[task[1]])


def _scalar(value):
    """The objective's value as scipy passes it on: a true scalar."""
    return value if np.isscalar(value) else np.asarray(value).item()

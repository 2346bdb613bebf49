"""Skeleton deformation: the 2D/3D energy of the assigned nodes and the TPS fill (paper II-C).

Algorithm 2 rows 13-16 of Zheng et al. (ICRA 2019):

* rows 13-15: the displacements ``Phi`` of the *assigned* 3D skeleton nodes minimise

      eps(Phi) = S_D(Phi) + alpha * S_L(Phi) + beta * S_S(Phi)            (paper eq. 6)

  ``S_D`` (data, Groher 2009) is the weighted mean of the squared pixel distances between
  each node's 2D target ``t_j`` (column ``j`` of ``X M``) and the projection ``f`` (eq. 1)
  of the displaced node; ``S_L`` (length, Groher 2009) the mean over the skeleton edges of
  the squared *relative* change of edge length; ``S_S`` (smoothness, Liao 2010) the mean over
  the edges of the squared difference of the two end displacements (mm^2). The analytic
  gradient (the structure of eqs. 7-9) is derived here from the energy as written and is
  checked against finite differences in ``Testing/test_deformation.py``. The minimiser is
  L-BFGS started from ``Phi = 0``.
* row 16: every unassigned node follows a 3D thin-plate spline (Bookstein 1989) whose
  control points are the assigned nodes of the branches/trunks it is connected to.

Equation numbers are those of the paper's source (eq. 1 projection ... eq. 6 energy,
eq. 7 gradient of ``S_D``, eqs. 8-9 its matrices ``D`` and ``J``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.optimize
import scipy.sparse
from scipy.sparse import csgraph
from scipy.spatial.distance import cdist

from .centerline import as_points
from .projection import validate_projection_matrix

__all__ = [
    "DeformationResult",
    "energy_and_gradient",
    "energy_terms",
    "deform_assigned",
    "ThinPlateSpline3D",
    "fill_unassigned",
]

#: Paper Sec. III: alpha (length) and beta (smoothness).
DEFAULT_ALPHA = 500.0
DEFAULT_BETA = 10.0


# ----------------------------------------------------------------------------------------
# The energy of eq. 6 and its gradient
# ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DeformationResult:
    """The outcome of :func:`deform_assigned`.

    Attributes
    ----------
    points : numpy.ndarray, shape (n_a, 3)
        Deformed assigned nodes ``y + phi`` (LPS mm).
    displacements : numpy.ndarray, shape (n_a, 3)
        ``phi`` (mm).
    energy_initial, energy_final : float
        ``eps`` at ``phi = 0`` and at the solution.
    terms : dict
        ``{"S_D": px^2, "S_L": dimensionless, "S_S": mm^2}`` at the solution (unweighted
        by alpha/beta).
    n_iter : int
        L-BFGS iterations.
    converged : bool
        True when L-BFGS met its gradient or energy-decrease tolerance.
    n_evaluations : int
        Energy/gradient evaluations.
    message : str
        The optimiser's stopping reason.
    """

    points: np.ndarray
    displacements: np.ndarray
    energy_initial: float
    energy_final: float
    terms: dict
    n_iter: int
    converged: bool
    n_evaluations: int = 0
    message: str = ""


@dataclass
class _EnergyModel:
    """Everything of eq. 6 that does not change while ``phi`` does, precomputed once.

    The evaluation works component-major: ``phi`` is (3, n_a), so every operation runs on
    contiguous rows of length n_a or m (L-BFGS does not care how the variables are ordered).
    """

    points: np.ndarray          # (n_a, 3) y
    targets: np.ndarray         # (n_a, 2) t
    P: np.ndarray               # (3, 4)
    alpha: float
    beta: float
    data_weights: np.ndarray    # (n_a,) w_j / n_a
    edges: np.ndarray           # (m, 2)
    rest_lengths: np.ndarray    # (m,) L0
    depth_sign: float = field(init=False)

    def __post_init__(self):
        n, m = len(self.points), len(self.edges)
        w = self.points @ self.P[2, :3] + self.P[2, 3]
        self.depth_sign = 1.0 if np.all(w > 0) else -1.0
        if not (np.all(w * self.depth_sign > 0)):
            raise ValueError("assigned points lie on both sides of (or on) the X-ray source plane of P")
        self._points_cm = np.ascontiguousarray(self.points.T)
        self._targets_cm = np.ascontiguousarray(self.targets.T)
        component = np.arange(3)[:, None] * n
        self._gather_i = (component + self.edges[:, 0]).ravel()          # flat (3, n) index of y_i
        self._gather_j = (component + self.edges[:, 1]).ravel()
        self._scatter = np.concatenate([self._gather_i, self._gather_j])
        flat = self._points_cm.ravel()
        self._rest_vectors = (flat[self._gather_i] - flat[self._gather_j]).reshape(3, m)
        self._inverse_rest = 1.0 / self.rest_lengths

    def evaluate(self, phi: np.ndarray, with_gradient: bool = True):
        """Return ``(eps, grad or None, {"S_D", "S_L", "S_S"})``; ``phi`` and grad are (3, n_a)."""
        n, m = phi.shape[1], len(self.edges)
        y = self._points_cm + phi
        P3 = self.P[:, :3]
        h = P3 @ y + self.P[:, 3:4]                      # eq. 1: rows [w*u, w*v, w]
        if np.any(h[2] * self.depth_sign <= 0):
            return np.inf, (np.zeros_like(phi) if with_gradient else None), {}
        inverse_w = 1.0 / h[2]
        fu, fv = h[0] * inverse_w, h[1] * inverse_w
        ru, rv = self._targets_cm[0] - fu, self._targets_cm[1] - fv     # t_j - f(y_j + phi_j)
        s_d = float(self.data_weights @ (ru * ru + rv * rv))

        if m:
            flat = y.ravel()
            e_vec = (flat[self._gather_i] - flat[self._gather_j]).reshape(3, m)   # y~_i - y~_j
            e_phi = e_vec - self._rest_vectors                                   # phi_i - phi_j
            length = np.sqrt((e_vec * e_vec).sum(axis=0))
            stretch = (length - self.rest_lengths) * self._inverse_rest
            s_l = float(stretch @ stretch) / m
            s_s = float((e_phi * e_phi).sum()) / m
        else:
            s_l = s_s = 0.0
        energy = s_d + self.alpha * s_l + self.beta * s_s
        terms = {"S_D": s_d, "S_L": s_l, "S_S": s_s}
        if not with_gradient:
            return energy, None, terms

        # eqs. 7-9: d f_u/dy = (p1 - u p3)/w, d f_v/dy = (p2 - v p3)/w (first three columns),
        # so dS_D/dphi_j = -(2 w_j/n_a) / w_j * (r_u p1 + r_v p2 - (r_u u + r_v v) p3).
        scale = -2.0 * self.data_weights * inverse_w
        a, b = scale * ru, scale * rv
        grad = P3.T @ np.vstack([a, b, -(a * fu + b * fv)])
        if m:
            # d/dy~_i ((l - L0)/L0)^2 = 2 (l - L0)/L0^2 * e/l and d/dphi_i |phi_i - phi_j|^2 = 2 (phi_i - phi_j);
            # the opposite at j
            along = (2.0 * self.alpha / m) * stretch * self._inverse_rest / np.maximum(length, 1e-12)
            edge_grad = (e_vec * along + (2.0 * self.beta / m) * e_phi).ravel()
            grad += np.bincount(self._scatter, np.concatenate([edge_grad, -edge_grad]), 3 * n).reshape(3, n)
        return energy, grad, terms


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
        n, m = len(model.points), len(model.edges)
        order = self._node_order(model, n)
        self.position = np.empty(n, dtype=np.int64)
        self.position[order] = np.arange(n)
        band_nodes = int(np.abs(np.diff(self.position[model.edges], axis=1)).max()) if m else 0
        self.usable = band_nodes <= self.MAX_BAND_NODES
        if not self.usable:
            return
        self.band = 3 * band_nodes + 2
        rows, cols, values = self._hessian_blocks(model, model.points, ridge)
        upper = rows <= cols
        ab = np.zeros((self.band + 1, 3 * n))
        np.add.at(ab, (self.band + rows[upper] - cols[upper], cols[upper]), values[upper])
        self.factor = scipy.linalg.cholesky_banded(ab, lower=False, check_finite=False)
        n_nodes = len(order)
        self.to_permuted = (np.arange(3)[None, :] * n_nodes + order[:, None]).ravel()   # x index -> (3, n) index
        self.from_permuted = (3 * self.position[None, :] + np.arange(3)[:, None]).ravel()

    @staticmethod
    def _node_order(model: _EnergyModel, n: int) -> np.ndarray:
        if not len(model.edges):
            return np.arange(n)
        i, j = model.edges[:, 0], model.edges[:, 1]
        adjacency = scipy.sparse.csr_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
        return np.asarray(csgraph.reverse_cuthill_mckee(adjacency, symmetric_mode=True), dtype=np.int64)

    def _hessian_blocks(self, model: _EnergyModel, y: np.ndarray, ridge: float):
        """COO entries (in permuted variable order) of the GN Hessian of ``n_a * eps`` at ``y``."""
        n, m = len(y), len(model.edges)
        P3 = model.P[:, :3]
        h = y @ P3.T + model.P[:, 3]
        f = h[:, :2] / h[:, 2:3]
        jac = (P3[None, :2] - f[:, :, None] * P3[None, 2:3]) / h[:, 2, None, None]     # (n, 2, 3) d f/d y
        data = 2.0 * (model.data_weights * n)[:, None, None] * np.einsum("nki,nkj->nij", jac, jac)
        stiffness = np.median(np.trace(data, axis1=1, axis2=2)) / 2.0
        if not stiffness > 0:
            stiffness = 1.0
        blocks = [(np.arange(n), np.arange(n), data + ridge * stiffness * np.eye(3))]
        if m:
            i, j = model.edges[:, 0], model.edges[:, 1]
            vec = y[i] - y[j]
            unit = vec / (np.maximum(np.linalg.norm(vec, axis=1), 1e-12) * model.rest_lengths)[:, None]
            edge = 2.0 * n / m * (model.alpha * np.einsum("ei,ej->eij", unit, unit) + model.beta * np.eye(3))
            blocks += [(i, i, edge), (j, j, edge), (i, j, -edge), (j, i, -edge)]
        rows, cols, values = [], [], []
        component = np.arange(3)
        for a, b, block in blocks:
            r = 3 * self.position[a][:, None, None] + component[None, :, None]
            c = 3 * self.position[b][:, None, None] + component[None, None, :]
            r, c = np.broadcast_arrays(r, c)
            rows.append(r.ravel())
            cols.append(c.ravel())
            values.append(block.ravel())
        return np.concatenate(rows), np.concatenate(cols), np.concatenate(values)

    def displacement(self, x: np.ndarray) -> np.ndarray:
        """``phi = R^-1 x`` as a (3, n) array."""
        z, _ = scipy.linalg.lapack.dtbtrs(self.factor, x[:, None], uplo="U", trans="N")
        return z[self.from_permuted, 0].reshape(3, -1)

    def gradient(self, grad_phi: np.ndarray) -> np.ndarray:
        """``R^-T grad_phi`` (flat) for a gradient (3, n) with respect to ``phi``."""
        g, _ = scipy.linalg.lapack.dtbtrs(self.factor, grad_phi.ravel()[self.to_permuted][:, None],
                                          uplo="U", trans="T")
        return g[:, 0]


def _build_model(points, targets, edges, P, alpha, beta, weights, rest_lengths) -> _EnergyModel:
    points = as_points(points, "points", 3)
    n = len(points)
    targets = as_points(targets, "targets", 2)
    if len(targets) != n:
        raise ValueError(f"targets: {len(targets)} rows for {n} points")
    P = validate_projection_matrix(P)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if edges.size and (edges.min() < 0 or edges.max() >= n):
        raise ValueError(f"edges: indices must lie in [0, {n})")
    if np.any(edges[:, 0] == edges[:, 1]):
        raise ValueError("edges: self-loops are not allowed")
    if weights is None:
        weights = np.ones(n)
    weights = np.asarray(weights, dtype=float).reshape(-1)
    if len(weights) != n or not np.all(np.isfinite(weights)) or np.any(weights < 0):
        raise ValueError(f"weights: need {n} finite non-negative values")
    if rest_lengths is None:
        rest_lengths = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    rest_lengths = np.asarray(rest_lengths, dtype=float).reshape(-1)
    if len(rest_lengths) != len(edges):
        raise ValueError(f"rest_lengths: {len(rest_lengths)} values for {len(edges)} edges")
    if np.any(~(rest_lengths > 0)) or not np.all(np.isfinite(rest_lengths)):
        raise ValueError("edges: every edge needs a positive rest length (duplicate nodes?)")
    if not (np.isfinite(alpha) and np.isfinite(beta) and alpha >= 0 and beta >= 0):
        raise ValueError(f"alpha and beta must be finite and >= 0 (got {alpha}, {beta})")
    return _EnergyModel(points, targets, P, float(alpha), float(beta),
                        weights / max(n, 1), edges, rest_lengths)


def _displacements_cm(phi_flat, n: int) -> np.ndarray:
    """Row-major displacements (n*3,) or (n, 3) as the component-major (3, n) array."""
    phi = np.asarray(phi_flat, dtype=float)
    if phi.size != 3 * n or not np.all(np.isfinite(phi)):
        raise ValueError(f"phi: need {3 * n} finite displacements, got {phi.size} values")
    return np.ascontiguousarray(phi.reshape(n, 3).T)


def energy_and_gradient(phi_flat, points, targets, edges, P, alpha=DEFAULT_ALPHA, beta=DEFAULT_BETA,
                        weights=None, rest_lengths=None) -> tuple[float, np.ndarray]:
    """The energy ``eps`` of eq. 6 and its analytic gradient at ``phi``.

    Parameters
    ----------
    phi_flat : array_like, shape (3 * n_a,) or (n_a, 3)
        Displacements of the assigned nodes (mm), row-major.
    points : array_like, shape (n_a, 3)
        Pre-operative assigned nodes ``y`` (LPS mm).
    targets : array_like, shape (n_a, 2)
        2D targets ``t_j`` (pixels, u = column, v = row).
    edges : array_like of int, shape (m, 2)
        Skeleton edges in the assigned-node index space.
    P : array_like, shape (3, 4)
        Projection matrix (eq. 1).
    alpha, beta : float
        Weights of the length and smoothness terms.
    weights : array_like, shape (n_a,), optional
        Per-node weights ``w_j`` of ``S_D`` (default 1): ``S_D = sum_j w_j |r_j|^2 / n_a``.
    rest_lengths : array_like, shape (m,), optional
        ``L0`` of each edge; defaults to the edge lengths of ``points``.

    Returns
    -------
    energy : float
    gradient : numpy.ndarray, shape (3 * n_a,)
    """
    model = _build_model(points, targets, edges, P, alpha, beta, weights, rest_lengths)
    energy, grad, _ = model.evaluate(_displacements_cm(phi_flat, len(model.points)))
    return energy, grad.T.ravel()


def energy_terms(phi_flat, points, targets, edges, P, weights=None, rest_lengths=None) -> dict:
    """The three terms ``{"S_D", "S_L", "S_S"}`` of eq. 6 at ``phi`` (no alpha/beta)."""
    model = _build_model(points, targets, edges, P, 0.0, 0.0, weights, rest_lengths)
    _, _, terms = model.evaluate(_displacements_cm(phi_flat, len(model.points)), with_gradient=False)
    return terms


def deform_assigned(points, targets, edges, P, *, alpha=DEFAULT_ALPHA, beta=DEFAULT_BETA, weights=None,
                    rest_lengths=None, max_iter=500, tol=1e-2, window=10, gtol=1e-6,
                    memory=5, precondition=False, ridge=0.1) -> DeformationResult:
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
    points, targets, edges, P, alpha, beta, weights, rest_lengths
        As in :func:`energy_and_gradient`.
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
    precondition : bool
        Optimise ``x = R phi`` with ``R^T R`` the banded Gauss-Newton Hessian at ``phi = 0``
        (used when the skeleton orders into a narrow band, as trees do). It converges in
        about a third of the iterations and follows the depth valley much further, which
        helps when lengths are truly preserved and the geometry is exact, and hurts badly
        otherwise; hence off by default.
    ridge : float
        Diagonal added to that Hessian, in units of the median in-plane data stiffness.

    Returns
    -------
    DeformationResult
    """
    model = _build_model(points, targets, edges, P, alpha, beta, weights, rest_lengths)
    n = len(model.points)
    if n == 0:
        empty = np.zeros((0, 3))
        return DeformationResult(empty, empty, 0.0, 0.0, {"S_D": 0.0, "S_L": 0.0, "S_S": 0.0}, 0, True)
    if max_iter < 0 or window < 1 or not (tol >= 0 and gtol >= 0):
        raise ValueError("deform_assigned: need max_iter >= 0, window >= 1, tol >= 0 and gtol >= 0")
    evaluations = [0]
    preconditioner = _BandedPreconditioner(model, ridge) if precondition else None
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

    solution = scipy.optimize.minimize(
        objective, np.zeros(3 * n), jac=True, method="L-BFGS-B", callback=stop_when_stalled,
        options={"maxiter": int(max_iter), "gtol": float(gtol), "ftol": 1e-12, "maxcor": int(memory)})
    phi_cm = displacement(solution.x)
    energy, _, terms = model.evaluate(phi_cm, with_gradient=False)
    phi = np.ascontiguousarray(phi_cm.T)
    converged = bool(solution.success) or stalled[0]
    message = f"energy fell by less than {tol:g} over {window} iterations" if stalled[0] else str(solution.message)
    return DeformationResult(points=model.points + phi, displacements=phi, energy_initial=float(energy0),
                             energy_final=float(energy), terms=terms, n_iter=int(solution.nit),
                             converged=converged, n_evaluations=evaluations[0], message=message)


# ----------------------------------------------------------------------------------------
# Thin-plate spline (Bookstein 1989), 3D kernel U(r) = r
# ----------------------------------------------------------------------------------------

class ThinPlateSpline3D:
    """3D thin-plate spline ``x -> x + sum_i w_i |x - c_i| + a_0 + A V^T (x - c_mean)``.

    ``U(r) = r`` is the biharmonic kernel of 3D (Bookstein 1989); the weights solve the
    ``(k + 1 + r) x (k + 1 + r)`` system ``[[U + lambda I, Q], [Q^T, 0]]``. It interpolates
    the control *displacements*. The affine part spans the affine hull of
    the controls (``V``): with coplanar or collinear controls the directions of no extent
    are left out (the displacement is constant along them) instead of making the system
    singular, so any number ``k >= 1`` of distinct controls gives a well-posed fit. With
    ``k >= 4`` non-coplanar controls and ``regularization = 0`` it is Bookstein's
    interpolating TPS and reproduces affine maps.
    """

    def __init__(self):
        self.controls = None
        self._center = None
        self._basis = None
        self._kernel_weights = None
        self._affine = None

    def fit(self, source, target, regularization: float = 0.0, *, min_extent_ratio: float = 1e-8):
        """Fit the spline that maps ``source`` onto ``target``.

        Parameters
        ----------
        source, target : array_like, shape (k, 3)
            Control points and where they go (mm). Repeated sources are merged (their
            targets averaged).
        regularization : float
            ``lambda >= 0`` added to the kernel diagonal (mm); 0 interpolates exactly.
        min_extent_ratio : float
            An affine direction is kept when the controls' spread along it is at least this
            fraction of their largest spread.

        Returns
        -------
        ThinPlateSpline3D
            ``self``.
        """
        source = as_points(source, "TPS source", 3)
        target = as_points(target, "TPS target", 3)
        if len(source) != len(target) or len(source) == 0:
            raise ValueError(f"TPS: need the same non-zero number of source and target points "
                             f"(got {len(source)} and {len(target)})")
        if not (np.isfinite(regularization) and regularization >= 0):
            raise ValueError(f"TPS: regularization must be finite and >= 0 (got {regularization})")
        source, target = _merge_repeated(source, target)
        k = len(source)
        self._center = source.mean(axis=0)
        self._basis = _affine_hull_basis(source - self._center, min_extent_ratio)
        poly = self._polynomial(source)
        n_poly = poly.shape[1]
        system = np.zeros((k + n_poly, k + n_poly))
        system[:k, :k] = cdist(source, source)
        system[:k, :k].flat[:: k + 1] += regularization
        system[:k, k:] = poly
        system[k:, :k] = poly.T
        rhs = np.zeros((k + n_poly, 3))
        rhs[:k] = target - source          # displacements: dropped affine directions keep the identity
        try:
            coefficients = scipy.linalg.solve(system, rhs, assume_a="sym", check_finite=False)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
            raise ValueError(f"TPS: singular system for {k} controls ({exc})") from None
        self.controls = source
        self._kernel_weights = coefficients[:k]
        self._affine = coefficients[k:]
        return self

    def _polynomial(self, points: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(points)), (points - self._center) @ self._basis])

    def transform(self, points) -> np.ndarray:
        """Map ``points`` (q, 3) through the fitted spline; returns (q, 3)."""
        if self.controls is None:
            raise ValueError("TPS: call fit() before transform()")
        points = as_points(points, "TPS points", 3)
        displacement = cdist(points, self.controls) @ self._kernel_weights + self._polynomial(points) @ self._affine
        return points + displacement


def _merge_repeated(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    unique, inverse, counts = np.unique(source, axis=0, return_inverse=True, return_counts=True)
    if len(unique) == len(source):
        return source, target
    merged = np.zeros((len(unique), 3))
    np.add.at(merged, inverse.ravel(), target)
    return unique, merged / counts[:, None]


def _affine_hull_basis(centred: np.ndarray, min_extent_ratio: float) -> np.ndarray:
    """Orthonormal directions (3, r) along which the centred controls have real extent."""
    if len(centred) < 2:
        return np.zeros((3, 0))
    _, singular, vt = np.linalg.svd(centred, full_matrices=False)
    if singular[0] <= 0:
        return np.zeros((3, 0))
    # centred points span at most k - 1 directions, so [1, kept directions] has full rank
    return vt[singular > min_extent_ratio * singular[0]].T


# ----------------------------------------------------------------------------------------
# Algorithm 2 row 16: branch-wise TPS for the unassigned nodes
# ----------------------------------------------------------------------------------------

def _edge_weighted_graph(points: np.ndarray, adjacency) -> scipy.sparse.csr_matrix:
    """The undirected skeleton graph with Euclidean edge lengths (mm) as weights."""
    coo = scipy.sparse.coo_matrix(adjacency)
    mask = coo.row != coo.col
    rows, cols = coo.row[mask], coo.col[mask]
    lengths = np.linalg.norm(points[rows] - points[cols], axis=1)
    lengths = np.maximum(lengths, 1e-9)          # csgraph treats an explicit 0 as "no edge"
    n = len(points)
    graph = scipy.sparse.csr_matrix((lengths, (rows, cols)), shape=(n, n))
    return graph.maximum(graph.T).tocsr()


#: Largest (sources x nodes) distance table computed in one Dijkstra call.
_DISTANCE_TABLE_LIMIT = 4_000_000


def _nearest_assigned(graph, sources: np.ndarray, assigned: np.ndarray, limit: float,
                      distance=None) -> tuple[np.ndarray, np.ndarray]:
    """Assigned nodes reachable from ``sources`` within ``limit`` mm, and their distances.

    ``distance`` (n,) may hold these geodesic distances already.
    """
    if distance is None:
        distance = csgraph.dijkstra(graph, directed=False, indices=sources, min_only=True, limit=limit)
    found = np.flatnonzero(assigned & np.isfinite(distance))
    return found, distance[found]


def _choose_controls(points, graph, nodes, assigned, candidates, neighbourhood_mm, max_controls, min_controls,
                     distance=None):
    """Control nodes for the unassigned ``nodes``: assigned ``candidates`` nearest along the skeleton.

    Geodesic neighbourhood of ``neighbourhood_mm`` first (``distance``, if given, holds the
    geodesic distances from ``nodes`` within it); if that holds fewer than ``min_controls``,
    the nearest reachable assigned nodes at any distance; if still too few, the
    Euclidean-nearest assigned nodes. At most ``max_controls`` are kept, nearest first.
    """
    allowed = assigned & candidates
    found, distance = _nearest_assigned(graph, nodes, allowed, neighbourhood_mm, distance)
    if len(found) < min_controls:
        found, distance = _nearest_assigned(graph, nodes, allowed, np.inf)
    if len(found) < min_controls:
        pool = np.flatnonzero(assigned)
        distance = cdist(points[pool], points[nodes]).min(axis=1)
        found = pool
    order = np.argsort(distance, kind="stable")[:max_controls]
    return found[order]


def _tps_move(points, moved, controls, nodes, regularization, min_extent_ratio) -> np.ndarray:
    spline = ThinPlateSpline3D().fit(points[controls], moved[controls], regularization,
                                     min_extent_ratio=min_extent_ratio)
    return spline.transform(points[nodes])


def fill_unassigned(points, deformed_assigned, assigned, adjacency, *, groups=None, max_controls=80,
                    neighbourhood_mm=40.0, regularization=0.0, min_extent_ratio=0.05) -> np.ndarray:
    """Move the unassigned skeleton nodes with branch-wise 3D TPS (Algorithm 2 row 16).

    Each connected piece of unassigned nodes (in the skeleton restricted to them) follows a
    TPS whose controls are the assigned nodes within ``neighbourhood_mm`` of it along the
    skeleton: the assigned parts of the branches and trunks it is connected to. With fewer
    than 4 such controls the nearest assigned nodes further away are used. Where ``groups``
    are given, the unassigned nodes of a group use that group's assigned nodes instead.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Pre-operative skeleton nodes (LPS mm).
    deformed_assigned : array_like, shape (n, 3)
        Deformed positions, read only where ``assigned`` is True.
    assigned : array_like of bool, shape (n,)
    adjacency : scipy.sparse matrix, shape (n, n)
        Skeleton adjacency (non-zero = edge; weights are ignored, lengths come from ``points``).
    groups : sequence of int arrays, optional
        Explicit branch/trunk node groups; a node in several groups uses the first.
    max_controls : int
        Most control points of one spline (the nearest along the skeleton are kept).
    neighbourhood_mm : float
        Geodesic radius of the control neighbourhood (mm).
    regularization : float
        TPS ``lambda`` (see :meth:`ThinPlateSpline3D.fit`).
    min_extent_ratio : float
        Affine directions with less relative spread of the controls are dropped, so that
        near-collinear controls (a straight branch) do not extrapolate wildly sideways.

    Returns
    -------
    numpy.ndarray, shape (n, 3)
        All nodes: assigned ones exactly at ``deformed_assigned``, the rest TPS-moved. With no
        assigned node at all, ``points`` unchanged.
    """
    points = as_points(points, "points", 3)
    n = len(points)
    assigned = np.asarray(assigned, dtype=bool).reshape(-1)
    if len(assigned) != n:
        raise ValueError(f"assigned: {len(assigned)} flags for {n} points")
    moved = np.asarray(deformed_assigned, dtype=float)
    if moved.shape != (n, 3):
        raise ValueError(f"deformed_assigned: expected shape ({n}, 3), got {moved.shape}")
    if not np.all(np.isfinite(moved[assigned])):
        raise ValueError("deformed_assigned: NaN or infinite values at assigned nodes")
    if adjacency.shape != (n, n):
        raise ValueError(f"adjacency: expected shape ({n}, {n}), got {adjacency.shape}")
    if max_controls < 1:
        raise ValueError(f"max_controls must be >= 1 (got {max_controls})")
    result = points.copy()
    result[assigned] = moved[assigned]
    if assigned.all() or not assigned.any():
        return result

    graph = _edge_weighted_graph(points, adjacency)
    pending = ~assigned
    everywhere = np.ones(n, dtype=bool)
    for group in groups or ():
        group = np.unique(np.asarray(group, dtype=np.int64).reshape(-1))
        if group.size and (group.min() < 0 or group.max() >= n):
            raise ValueError(f"groups: node indices must lie in [0, {n})")
        nodes = group[pending[group]]
        members = np.zeros(n, dtype=bool)
        members[group] = True
        if nodes.size == 0 or np.count_nonzero(assigned & members) < 4:
            continue
        controls = _choose_controls(points, graph, nodes, assigned, members, np.inf, max_controls, 4)
        result[nodes] = _tps_move(points, moved, controls, nodes, regularization, min_extent_ratio)
        pending[nodes] = False

    remaining = np.flatnonzero(pending)
    if remaining.size == 0:
        return result
    sub = graph[remaining][:, remaining]
    _, component_of = csgraph.connected_components(sub, directed=False)
    table = None
    if remaining.size * n <= _DISTANCE_TABLE_LIMIT:      # one Dijkstra call for all components
        table = csgraph.dijkstra(graph, directed=False, indices=remaining, limit=neighbourhood_mm)
    for label in np.unique(component_of):
        rows = np.flatnonzero(component_of == label)
        nodes = remaining[rows]
        near = None if table is None else table[rows].min(axis=0)
        controls = _choose_controls(points, graph, nodes, assigned, everywhere, neighbourhood_mm,
                                    max_controls, 4, near)
        result[nodes] = _tps_move(points, moved, controls, nodes, regularization, min_extent_ratio)
    return result

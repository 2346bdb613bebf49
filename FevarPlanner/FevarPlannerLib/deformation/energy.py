"""The energy of eq. 6 over the displacements of the assigned nodes, and its gradient.

``S_D`` and ``S_L`` are written here once: the proposed method minimises
``S_D + alpha S_L + beta S_S`` over node displacements, and ICP-TPS
(:mod:`FevarPlannerLib.baselines`) evaluates the same ``S_D + alpha S_L`` at the
displacements its TPS produces and adds its own bending energy.

Several views: ``S_D`` is the mean over the views (frames of the same anatomy, each with its
``P``, targets and weights) of each view's ``sum_j w_j |r_j|^2 / n_a``. With one view this
is the paper's ``S_D`` exactly, computed with the same floating-point operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..centerline import as_points
from ..projection import homogeneous_columns, pull_back_columns, validate_projection_matrix

__all__ = ["DEFAULT_ALPHA", "DEFAULT_BETA", "DeformationResult", "energy_and_gradient", "energy_terms"]

#: Paper Sec. III: alpha (length) and beta (smoothness).
DEFAULT_ALPHA = 500.0
DEFAULT_BETA = 10.0


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


class _View:
    """One frame's share of ``S_D``: its ``P``, the targets and ``w_j / (n_a * n_views)``."""

    def __init__(self, P: np.ndarray, targets: np.ndarray, data_weights: np.ndarray, points: np.ndarray):
        self.P = P
        self.data_weights = data_weights
        self.set_targets(targets)
        w = points @ P[2, :3] + P[2, 3]
        self.depth_sign = 1.0 if np.all(w > 0) else -1.0
        if not np.all(w * self.depth_sign > 0):
            raise ValueError("assigned points lie on both sides of (or on) the X-ray source plane of P")
        # the same test as "w * depth_sign <= 0", without the product
        self._crossed = np.less_equal if self.depth_sign > 0 else np.greater_equal

    @property
    def data_weights(self) -> np.ndarray:
        """``w_j / (n_a * n_views)``; setting it also sets the factor ``-2 w_j / ...`` of eqs. 7-9."""
        return self._data_weights

    @data_weights.setter
    def data_weights(self, weights: np.ndarray) -> None:
        self._data_weights = weights
        self._gradient_weights = -2.0 * weights

    def set_targets(self, targets: np.ndarray) -> None:
        self.targets = targets
        self.targets_cm = np.ascontiguousarray(targets.T)

    def data_term(self, y: np.ndarray, with_gradient: bool):
        """``(S_D share, its gradient (3, n) or None)``, or None when a point crossed the source plane."""
        h = homogeneous_columns(self.P, y)              # eq. 1: rows [w*u, w*v, w]
        if self._crossed(h[2], 0.0).any():
            return None
        inverse_w = 1.0 / h[2]
        fu, fv = h[0] * inverse_w, h[1] * inverse_w
        ru, rv = self.targets_cm[0] - fu, self.targets_cm[1] - fv     # t_j - f(y_j + phi_j)
        s_d = float(self._data_weights @ (ru * ru + rv * rv))
        if not with_gradient:
            return s_d, None
        # eqs. 7-9: dS_D/dphi_j = -2 w_j / n_a * (d f / d y)^T r_j, with (d f / d y) of eq. 1
        scale = self._gradient_weights * inverse_w
        return s_d, pull_back_columns(self.P, fu, fv, scale * ru, scale * rv)


class _EnergyModel:
    """Everything of eq. 6 that does not change while ``phi`` does, precomputed once.

    The evaluation works component-major: ``phi`` is (3, n_a), so every operation runs on
    contiguous rows of length n_a or m (L-BFGS does not care how the variables are ordered).
    ``views`` hold the data term (one per frame); ``edges`` and ``rest_lengths`` the
    length (``S_L``) and smoothness (``S_S``) terms.
    """

    def __init__(self, points: np.ndarray, views: list, alpha: float, beta: float, edges: np.ndarray,
                 rest_lengths: np.ndarray):
        self.points, self.views, self.alpha, self.beta = points, views, alpha, beta
        self.edges, self.rest_lengths = edges, rest_lengths
        n, m = len(points), len(edges)
        self._points_cm = np.ascontiguousarray(points.T)
        component = np.arange(3)[:, None] * n
        self._gather_i = (component + edges[:, 0]).ravel()          # flat (3, n) index of y_i
        self._gather_j = (component + edges[:, 1]).ravel()
        self._scatter = np.concatenate([self._gather_i, self._gather_j])
        flat = self._points_cm.ravel()
        self._rest_vectors = (flat[self._gather_i] - flat[self._gather_j]).reshape(3, m)
        self._inverse_rest = 1.0 / rest_lengths

    def evaluate(self, phi: np.ndarray, with_gradient: bool = True):
        """Return ``(eps, grad or None, {"S_D", "S_L", "S_S"})``; ``phi`` and grad are (3, n_a)."""
        n, m = phi.shape[1], len(self.edges)
        y = self._points_cm + phi
        s_d, grad = 0.0, None
        for view in self.views:
            share = view.data_term(y, with_gradient)
            if share is None:
                return np.inf, (np.zeros_like(phi) if with_gradient else None), {}
            s_d += share[0]
            if with_gradient:
                grad = share[1] if grad is None else grad + share[1]

        if m:
            flat = y.ravel()
            e_vec = (flat[self._gather_i] - flat[self._gather_j]).reshape(3, m)   # y~_i - y~_j
            e_phi = e_vec - self._rest_vectors                                   # phi_i - phi_j
            length = np.sqrt((e_vec * e_vec).sum(axis=0))
            stretch = (length - self.rest_lengths) * self._inverse_rest
            s_l = float(stretch @ stretch) / m                                   # S_L (Groher 2009)
            s_s = float((e_phi * e_phi).sum()) / m                               # S_S (Liao 2010)
        else:
            s_l = s_s = 0.0
        energy = s_d + self.alpha * s_l + self.beta * s_s                        # eq. 6
        terms = {"S_D": s_d, "S_L": s_l, "S_S": s_s}
        if not with_gradient:
            return energy, None, terms
        if m:
            # d/dy~_i ((l - L0)/L0)^2 = 2 (l - L0)/L0^2 * e/l and d/dphi_i |phi_i - phi_j|^2 = 2 (phi_i - phi_j);
            # the opposite at j
            along = (2.0 * self.alpha / m) * stretch * self._inverse_rest / np.maximum(length, 1e-12)
            edge_grad = (e_vec * along + (2.0 * self.beta / m) * e_phi).ravel()
            grad += np.bincount(self._scatter, np.concatenate([edge_grad, -edge_grad]), 3 * n).reshape(3, n)
        return energy, grad, terms


def _check_weights(weights, n: int, name: str) -> np.ndarray:
    if weights is None:
        return np.ones(n)
    weights = np.asarray(weights, dtype=float).reshape(-1)
    if len(weights) != n or not np.all(np.isfinite(weights)) or np.any(weights < 0):
        raise ValueError(f"{name}: need {n} finite non-negative values")
    return weights


def _check_targets(targets, weights: np.ndarray, name: str) -> np.ndarray:
    """(n, 2) targets; a row may be NaN where its weight is 0 (the node is not in that view)."""
    targets = np.array(targets, dtype=float)
    if targets.ndim != 2 or targets.shape[1] != 2:
        raise ValueError(f"{name}: expected an array of shape (n, 2), got {targets.shape}")
    if len(targets) != len(weights):
        raise ValueError(f"{name}: {len(targets)} rows for {len(weights)} points")
    unseen = ~np.all(np.isfinite(targets), axis=1)
    if np.any(unseen & (weights > 0)):
        raise ValueError(f"{name}: contains NaN or infinite values at nodes of non-zero weight")
    targets[unseen] = 0.0
    return targets


def _build_views(points, targets, P, weights, extra_views) -> list:
    """One :class:`_View` per frame: the main one (``P``, ``targets``, ``weights``) and the extra ones."""
    n = len(points)
    frames = [(P, targets, weights)]
    for index, view in enumerate(extra_views):
        if len(view) != 3:
            raise ValueError(f"extra_views[{index}]: expected (P, targets, weights), got {len(view)} items")
        frames.append(tuple(view))
    views = []
    for index, (P_k, targets_k, weights_k) in enumerate(frames):
        where = "" if index == 0 else f"extra_views[{index - 1}] "
        P_k = validate_projection_matrix(P_k, name=f"{where}P".strip() if index else "P")
        weights_k = _check_weights(weights_k, n, f"{where}weights")
        targets_k = _check_targets(targets_k, weights_k, f"{where}targets")
        # S_D = mean over the views of sum_j w_j |r_j|^2 / n_a
        views.append(_View(P_k, targets_k, weights_k / max(n * len(frames), 1), points))
    return views


def _build_model(points, targets, edges, P, alpha, beta, weights, rest_lengths, extra_views=()) -> _EnergyModel:
    points = as_points(points, "points", 3)
    n = len(points)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if edges.size and (edges.min() < 0 or edges.max() >= n):
        raise ValueError(f"edges: indices must lie in [0, {n})")
    if np.any(edges[:, 0] == edges[:, 1]):
        raise ValueError("edges: self-loops are not allowed")
    if rest_lengths is None:
        rest_lengths = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    rest_lengths = np.asarray(rest_lengths, dtype=float).reshape(-1)
    if len(rest_lengths) != len(edges):
        raise ValueError(f"rest_lengths: {len(rest_lengths)} values for {len(edges)} edges")
    if np.any(~(rest_lengths > 0)) or not np.all(np.isfinite(rest_lengths)):
        raise ValueError("edges: every edge needs a positive rest length (duplicate nodes?)")
    if not (np.isfinite(alpha) and np.isfinite(beta) and alpha >= 0 and beta >= 0):
        raise ValueError(f"alpha and beta must be finite and >= 0 (got {alpha}, {beta})")
    views = _build_views(points, targets, P, weights, extra_views)
    return _EnergyModel(points, views, float(alpha), float(beta), edges, rest_lengths)


def _displacements_cm(phi_flat, n: int) -> np.ndarray:
    """Row-major displacements (n*3,) or (n, 3) as the component-major (3, n) array."""
    phi = np.asarray(phi_flat, dtype=float)
    if phi.size != 3 * n or not np.all(np.isfinite(phi)):
        raise ValueError(f"phi: need {3 * n} finite displacements, got {phi.size} values")
    return np.ascontiguousarray(phi.reshape(n, 3).T)


def energy_and_gradient(phi_flat, points, targets, edges, P, alpha=DEFAULT_ALPHA, beta=DEFAULT_BETA,
                        weights=None, rest_lengths=None, *, extra_views=()) -> tuple[float, np.ndarray]:
    """The energy ``eps`` of eq. 6 and its analytic gradient at ``phi``.

    Parameters
    ----------
    phi_flat : array_like, shape (3 * n_a,) or (n_a, 3)
        Displacements of the assigned nodes (mm), row-major.
    points : array_like, shape (n_a, 3)
        Pre-operative assigned nodes ``y`` (LPS mm).
    targets : array_like, shape (n_a, 2)
        2D targets ``t_j`` (pixels, u = column, v = row). A row may be NaN where its weight
        is 0.
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
    extra_views : sequence of (P_k, targets_k, weights_k)
        Further frames of the same anatomy: ``P_k`` (3, 4), ``targets_k`` (n_a, 2) px,
        ``weights_k`` (n_a,) or None (0 = the node is not visible in that frame). ``S_D`` is
        then the mean over all views of each view's ``sum_j w_j |r_j|^2 / n_a``.

    Returns
    -------
    energy : float
    gradient : numpy.ndarray, shape (3 * n_a,)
    """
    model = _build_model(points, targets, edges, P, alpha, beta, weights, rest_lengths, extra_views)
    energy, grad, _ = model.evaluate(_displacements_cm(phi_flat, len(model.points)))
    return energy, grad.T.ravel()


def energy_terms(phi_flat, points, targets, edges, P, weights=None, rest_lengths=None, *, extra_views=()) -> dict:
    """The three terms ``{"S_D", "S_L", "S_S"}`` of eq. 6 at ``phi`` (no alpha/beta); views as above."""
    model = _build_model(points, targets, edges, P, 0.0, 0.0, weights, rest_lengths, extra_views)
    _, _, terms = model.evaluate(_displacements_cm(phi_flat, len(model.points)), with_gradient=False)
    return terms

"""The one 3D thin-plate spline (Bookstein 1989), kernel ``U(r) = r``.

Used twice: fitted to control displacements (Algorithm 2 row 16, :func:`fill_unassigned`)
and, in ICP-TPS, written as a linear map of the displaced controls with its bending matrix
(:meth:`ThinPlateSpline3D.control_basis`).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.spatial.distance import cdist

from ..centerline import as_points

__all__ = ["FixedControlsTPS", "ThinPlateSpline3D"]


class ThinPlateSpline3D:
    """3D thin-plate spline ``x -> x + sum_i w_i |x - c_i| + a_0 + A V^T (x - c_mean)``.

    ``U(r) = r`` is the biharmonic kernel of 3D (Bookstein 1989); the weights solve the
    ``(k + 1 + r) x (k + 1 + r)`` system ``[[U + lambda I, Q], [Q^T, 0]]``. It interpolates
    the control *displacements*. The affine part spans the affine hull of
    the controls (``V``): with coplanar or collinear controls the directions of no extent
    are left out (the displacement is constant along them) instead of making the system
    singular, so any number ``k >= 1`` of distinct controls gives a well-posed fit. With
    ``k >= 4`` non-coplanar controls and ``regularization = 0`` it is Bookstein's
    interpolating TPS and reproduces affine maps, and the same spline as
    :meth:`control_basis` gives in linear form: ``fit(C, V).transform(y) == G V``.
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
        merge = _RepeatMerge(source)
        source, target = merge.sources, merge.targets(target)
        self._center = source.mean(axis=0)
        self._basis = _affine_hull_basis(source - self._center, min_extent_ratio)
        system = self._system(source, regularization)
        self._solve(system, source, target)
        return self

    def _system(self, source: np.ndarray, regularization: float) -> np.ndarray:
        """The ``(k + 1 + r)`` square matrix ``[[U + lambda I, Q], [Q^T, 0]]`` of the merged controls."""
        k = len(source)
        poly = self._polynomial(source)
        n_poly = poly.shape[1]
        system = np.zeros((k + n_poly, k + n_poly))
        system[:k, :k] = cdist(source, source)
        system[:k, :k].flat[:: k + 1] += regularization
        system[:k, k:] = poly
        system[k:, :k] = poly.T
        return system

    def _solve(self, system: np.ndarray, source: np.ndarray, target: np.ndarray) -> None:
        k = len(source)
        rhs = np.zeros((len(system), 3))
        rhs[:k] = target - source          # displacements: dropped affine directions keep the identity
        try:
            coefficients = scipy.linalg.solve(system, rhs, assume_a="sym", check_finite=False)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
            raise ValueError(f"TPS: singular system for {k} controls ({exc})") from None
        self.controls = source
        self._kernel_weights = coefficients[:k]
        self._affine = coefficients[k:]

    def _polynomial(self, points: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(points)), (points - self._center) @ self._basis])

    def transform(self, points) -> np.ndarray:
        """Map ``points`` (q, 3) through the fitted spline; returns (q, 3)."""
        if self.controls is None:
            raise ValueError("TPS: call fit() before transform()")
        points = as_points(points, "TPS points", 3)
        return self._transform_with(points, cdist(points, self.controls), self._polynomial(points))

    def _transform_with(self, points: np.ndarray, kernel: np.ndarray, poly: np.ndarray) -> np.ndarray:
        """:meth:`transform` of ``points`` given their kernel values and polynomial terms."""
        displacement = kernel @ self._kernel_weights + poly @ self._affine
        return points + displacement

    @staticmethod
    def control_basis(points: np.ndarray, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 3D TPS written as a linear map of the displaced control positions.

        With kernel ``U(r) = r``, ``K_ab = |c_a - c_b|`` and ``Q = [C 1]``, the spline that
        takes the controls ``C`` to ``V`` moves a point ``y`` to
        ``U(y, C) W + [y 1] A`` with ``W = -B V`` and ``A = Q^+ (V - K W)``, where
        ``B = -Z (Z^T K Z)^-1 Z^T`` and ``Z`` is an orthonormal basis of the null space of
        ``Q^T``. ``trace(V^T B V)`` is the bending energy (``B C = 0``: affine maps cost
        nothing). Working through ``Z`` and ``Q^+`` keeps it well defined when the controls
        are coplanar.

        Parameters
        ----------
        points : numpy.ndarray, shape (n, 3)
            Where the spline is evaluated (the nodes).
        controls : numpy.ndarray, shape (c, 3)
            Distinct control positions.

        Returns
        -------
        G : numpy.ndarray, shape (n, c)
            ``Y(V) = G V``; since the spline reproduces affine maps, ``Y(V) - points = G (V - C)``.
        B : numpy.ndarray, shape (c, c)
            Symmetric positive semi-definite bending matrix.
        """
        c = len(controls)
        K = cdist(controls, controls)
        Q = np.hstack([controls, np.ones((c, 1))])
        left, singular, _ = np.linalg.svd(Q, full_matrices=True)
        rank = int((singular > singular[0] * 1e-10).sum())
        Z = left[:, rank:]
        B = -Z @ np.linalg.solve(Z.T @ K @ Z, Z.T)
        B = 0.5 * (B + B.T)
        affine = np.linalg.pinv(Q, rcond=1e-10) @ (np.eye(c) + K @ B)
        G = -cdist(points, controls) @ B + np.hstack([points, np.ones((len(points), 1))]) @ affine
        return G, B


class _RepeatMerge:
    """Which control sources repeat: the distinct ``sources`` and how to average their targets."""

    def __init__(self, source: np.ndarray):
        unique, inverse, counts = np.unique(source, axis=0, return_inverse=True, return_counts=True)
        self.repeated = len(unique) != len(source)
        self.sources = unique if self.repeated else source
        self._inverse, self._counts = inverse.ravel(), counts

    def targets(self, target: np.ndarray) -> np.ndarray:
        """``target`` (k, 3) with the targets of repeated sources averaged."""
        if not self.repeated:
            return target
        merged = np.zeros((len(self.sources), 3))
        np.add.at(merged, self._inverse, target)
        return merged / self._counts[:, None]


class FixedControlsTPS:
    """The TPS from fixed controls to fixed query points, refitted for ever new control targets.

    Everything that depends only on the control sources and the query points (merged
    repeats, affine hull, the system matrix, the kernel at the queries) is computed once;
    :meth:`apply` then solves the system for the targets and evaluates it, giving exactly
    ``ThinPlateSpline3D().fit(source, target, ...).transform(queries)`` (the same
    floating-point operations on the same arrays).

    Parameters
    ----------
    source : array_like, shape (k, 3)
        Control points (mm).
    queries : array_like, shape (q, 3)
        Where the spline is evaluated (mm).
    regularization, min_extent_ratio : float
        As in :meth:`ThinPlateSpline3D.fit`.
    """

    def __init__(self, source, queries, regularization: float = 0.0, *, min_extent_ratio: float = 1e-8):
        source = as_points(source, "TPS source", 3)
        self.queries = as_points(queries, "TPS points", 3)
        if len(source) == 0:
            raise ValueError("TPS: need the same non-zero number of source and target points (got 0 and 0)")
        if not (np.isfinite(regularization) and regularization >= 0):
            raise ValueError(f"TPS: regularization must be finite and >= 0 (got {regularization})")
        self.n_controls = len(source)
        self._merge = _RepeatMerge(source)
        self._spline = ThinPlateSpline3D()
        merged = self._merge.sources
        self._spline._center = merged.mean(axis=0)
        self._spline._basis = _affine_hull_basis(merged - self._spline._center, min_extent_ratio)
        self._system = self._spline._system(merged, regularization)
        self._kernel = cdist(self.queries, merged)
        self._poly = self._spline._polynomial(self.queries)

    def apply(self, target) -> np.ndarray:
        """The queries moved by the spline that takes the controls to ``target`` (k, 3); (q, 3)."""
        target = as_points(target, "TPS target", 3)
        if len(target) != self.n_controls:
            raise ValueError(f"TPS: need the same non-zero number of source and target points "
                             f"(got {self.n_controls} and {len(target)})")
        self._spline._solve(self._system, self._merge.sources, self._merge.targets(target))
        return self._spline._transform_with(self.queries, self._kernel, self._poly)


def _affine_hull_basis(centred: np.ndarray, min_extent_ratio: float) -> np.ndarray:
    """Orthonormal directions (3, r) along which the centred controls have real extent."""
    if len(centred) < 2:
        return np.zeros((3, 0))
    _, singular, vt = np.linalg.svd(centred, full_matrices=False)
    if singular[0] <= 0:
        return np.zeros((3, 0))
    # centred points span at most k - 1 directions, so [1, kept directions] has full rank
    return vt[singular > min_extent_ratio * singular[0]].T

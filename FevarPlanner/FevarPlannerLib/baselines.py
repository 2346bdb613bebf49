"""The paper's two baselines (Sec. III): ICP-TPS after Groher et al. and shape variation.

Shape variation (SV)
--------------------
:func:`rigid` is the rigidly aligned pre-operative centreline itself: ``P`` already holds the
rigid pre-alignment (eq. 1), so the SV result is the input nodes, unchanged.

ICP-TPS (Groher, Zikic and Navab, "Deformable 2D-3D registration of vascular structures in a
one view scenario", IEEE TMI 28(6), 2009)
------------------------------------------------------------------------------------------
Groher et al. deform the 3D vessel centreline so that its projection meets the 2D
centreline, without known correspondences. Two steps alternate under deterministic
annealing of a temperature ``T`` (``T_init = 500``, ``T <- T_update * T`` with
``T_update = 0.93``, down to ``T_final = 1``; paper Sec. III):

1. **Soft correspondences** (soft-assign, as in Gold/Rangarajan's RPM and Chui and
   Rangarajan's TPS-RPM). Between the projected 3D nodes ``f(y_j)`` (eq. 1) and the 2D
   centreline points ``x_i``, ``m_ji ~ exp(-|x_i - f(y_j)|^2 / T)``, completed with an
   outlier column (a 3D node that the frame does not show) and an outlier row (a 2D point
   with no 3D counterpart: another vessel, a catheter, noise) and balanced by alternating
   row and column normalisation (Sinkhorn). Each 3D node gets the soft target
   ``x_hat_j = sum_i m_ji x_i / sum_i m_ji`` and the confidence ``w_j = sum_i m_ji`` (the
   part of its mass not sent to the outlier column).
2. **Deformation** of the 3D nodes by a 3D thin-plate spline whose parameters are the
   displaced positions ``V`` of a set of control nodes on the 3D centreline; the spline
   is linear in them, ``Y(V) = Y0 + G (V - C)``. ``V`` minimises Groher's energy

       E(V) = S_D + alpha * S_L + beta(T) * S_S
       S_D  = 1/n  sum_j w_j |f(y_j(V)) - x_hat_j|^2                   (projected distance, px^2)
       S_L  = 1/|E| sum_(a,b) ((|y_a - y_b| - L0_ab) / L0_ab)^2        (length preservation)
       S_S  = the TPS bending energy of V,  trace(V^T B V)             (smoothness)

   with ``alpha = 0.01`` and ``beta(T) = beta_final * T / T_final``, ``beta_final = 3e-7``
   (annealed with the temperature like the TPS regulariser of TPS-RPM), by L-BFGS with the
   analytic gradient, warm-started from the previous temperature.

Choices where the papers are silent (or where we had to fix a detail)
---------------------------------------------------------------------
* Normalisation of the terms: those of the proposed method's energy (docs/DESIGN.md, "Registration"),
  whose ``S_D`` and ``S_L`` the paper takes from Groher et al.: ``S_D`` the mean over the
  nodes in px^2 (the paper's gradient of ``S_D`` carries ``2 / n``), ``S_L`` the mean over
  the edges of the squared relative length change. The paper's ``alpha = 0.01`` then
  makes length preservation weak, and the depth along the rays is held mostly by the
  TPS and the annealing. On five pairs of an early version of ``phantom.paper_protocol``
  with strong out-of-plane bending (457 nodes, the true centrelines) this reduced the mean 3D error from 6.7 / 6.8 /
  2.9 / 4.7 / 8.7 mm (shape variation) to 5.9 / 5.8 / 2.0 / 0.6 / 2.1 mm; a summed
  ``S_L`` (``alpha * n_edges``) gave 5.8 / 5.9 / 2.0 / 0.5 / 4.7 mm.
  On small graphs (150 nodes, 50 controls) the weak term lets parts drift in depth
  (up to 34 mm on the 150-node synthetic tree of Testing/benchmarks/bench_baselines.py).
  ``S_S`` uses the 3D biharmonic kernel ``U(r) = r`` in millimetres (as
  :class:`deformation.ThinPlateSpline3D`, whose :meth:`~deformation.ThinPlateSpline3D.control_basis`
  gives ``G`` and ``B``): ``B = -Z (Z^T K Z)^-1 Z^T`` with
  ``K_ab = |c_a - c_b|`` and ``Z`` spanning the complement of the affine part, so ``S_S``
  is in mm; with ``beta_final = 3e-7`` it is small, and the annealing (wide Gaussians
  average over many 2D points early on) and the finite number of TPS controls carry the
  smoothing, as in TPS-RPM.
* Controls: every end and junction node (graph degree other than 2), then farthest-point
  sampling in 3D up to ``n_controls`` (default ``clip(n // 6, 50, 150)``, all nodes for
  small graphs); deterministic, ties to the lowest index. TPS-RPM takes every point as a
  control: on the 20 simulation cases (seed 0, about 420 nodes) that gives 1.06 mm instead
  of 1.17 mm but varies more between cases (up to 3.0 mm) and takes 1.25 s instead of 0.78 s.
* Soft-assign: ``exp(-d^2 / T)`` (a Gaussian of variance ``T / 2`` px^2); the outlier bins
  hold ``exp(-9/2)``, i.e. a node counts as an outlier when its nearest partner is more
  than 3 standard deviations away. Row masses 1 and column masses ``n3 / n2`` (or the
  other way round when the 2D set is the smaller), so that a dense 2D skeleton and a
  sparser 3D graph balance instead of forcing most 2D points into the outlier row.
  Pairs farther than where the kernel drops below ``1e-8`` of the outlier weight are
  skipped (a KD-tree finds the rest); at most 30 Sinkhorn sweeps, stopping when the
  column scalings change by less than 1e-3.
* Per temperature: one soft-assign, then at most ``iterations_per_temperature`` L-BFGS
  iterations (default 10, Armijo backtracking, memory 8, restarted at each temperature);
  the schedule runs ``T_init, 0.93 T_init, ...`` while ``T`` is above ``T_final`` and ends
  with one step at ``T_final`` (87 temperatures with the paper's values). The few
  iterations also regularise: the data term does not see depth and the paper's weights
  hardly do, so with 30 iterations per temperature the same 20 cases drift along the rays
  to a mean 3D error of 28.6 mm (3.6 mm with every node a control).

Everything is deterministic: no random numbers, fixed iteration counts and tolerances.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from .centerline import as_points
from .deformation import ThinPlateSpline3D
from .deformation.energy import _build_model
from .projection import project, validate_projection_matrix

__all__ = ["BaselineResult", "rigid", "icp_tps", "annealing_temperatures", "default_control_count", "select_controls",
           "rpm_soft_assign", "lbfgs"]

#: Outlier bins: a partner more than this many standard deviations away counts as missing.
OUTLIER_SIGMAS = 3.0
#: Kernel entries below this fraction of the outlier weight are not computed.
_NEGLIGIBLE = 1e-8
_SINKHORN_SWEEPS = 30
_SINKHORN_TOL = 1e-3


@dataclass
class BaselineResult:
    """What a baseline returns.

    Attributes
    ----------
    points : numpy.ndarray, shape (n, 3)
        The result's node positions, LPS mm, in the input order.
    n_iter : int
        Annealing steps (temperatures) run; 0 for the rigid baseline.
    timings : dict
        Seconds: ``total`` and, for ICP-TPS, ``correspondence`` and ``deformation``.
    method : str
        ``"rigid"`` or ``"icp-tps"``.
    info : dict
        Method details (ICP-TPS: control indices, final energy terms, L-BFGS evaluations).
    """

    points: np.ndarray
    n_iter: int
    timings: dict
    method: str
    info: dict = field(default_factory=dict)


def rigid(points) -> BaselineResult:
    """Shape variation (SV): the rigidly pre-aligned pre-operative centreline, unchanged.

    ``P`` already carries the rigid pre-alignment, so the SV result is the input nodes.
    """
    start = time.perf_counter()
    points = as_points(points, "3D centreline points", 3, min_count=1)
    return BaselineResult(points.copy(), 0, {"total": time.perf_counter() - start}, "rigid")


def _check_edges(edges, n: int) -> np.ndarray:
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if len(edges) and (edges.min() < 0 or edges.max() >= n):
        raise ValueError(f"3D centreline edges: index out of range for {n} nodes")
    return edges


def _check_schedule(t_init: float, t_final: float, t_update: float, alpha: float, beta_final: float) -> None:
    if not (t_init >= t_final > 0):
        raise ValueError(f"annealing: need T_init >= T_final > 0 (got {t_init}, {t_final})")
    if not (0 < t_update < 1):
        raise ValueError(f"annealing: T_update must lie in (0, 1), got {t_update}")
    if alpha < 0 or beta_final < 0:
        raise ValueError(f"weights must be non-negative (alpha={alpha}, beta_final={beta_final})")


def default_control_count(n_nodes: int) -> int:
    """``clip(n // 6, 50, 150)``, capped at the number of nodes."""
    return int(min(n_nodes, np.clip(n_nodes // 6, 50, 150)))


def select_controls(points: np.ndarray, edges: np.ndarray, n_controls: int) -> np.ndarray:
    """Indices of the TPS control nodes: end and junction nodes, then farthest-point sampling.

    Parameters
    ----------
    points : numpy.ndarray, shape (n, 3)
    edges : numpy.ndarray of int, shape (m, 2)
    n_controls : int
        How many controls (at least the number of end and junction nodes, at most ``n``).

    Returns
    -------
    numpy.ndarray of int
        Sorted node indices of distinct positions.
    """
    n = len(points)
    _, first_of_position = np.unique(points, axis=0, return_index=True)
    distinct = np.zeros(n, dtype=bool)
    distinct[first_of_position] = True
    degree = np.bincount(edges.ravel(), minlength=n)
    chosen = list(np.flatnonzero((degree != 2) & distinct))
    if not chosen:
        chosen = [int(np.flatnonzero(distinct)[0])]
    target = min(max(n_controls, len(chosen)), int(distinct.sum()))
    gap = cdist(points, points[chosen]).min(axis=1)
    gap[~distinct] = -1.0
    while len(chosen) < target:
        farthest = int(np.argmax(gap))
        chosen.append(farthest)
        gap = np.minimum(gap, np.linalg.norm(points - points[farthest], axis=1))
        gap[~distinct] = -1.0
    return np.sort(np.asarray(chosen, dtype=np.int64))


def _outlier_weight() -> float:
    # exp(-d^2 / T) at d = OUTLIER_SIGMAS standard deviations of the Gaussian (variance T / 2)
    return float(np.exp(-0.5 * OUTLIER_SIGMAS ** 2))


def rpm_soft_assign(projected: np.ndarray, skeleton: np.ndarray, temperature: float,
                    skeleton_tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Soft correspondences between projected 3D nodes and 2D points (RPM soft-assign, Sinkhorn).

    Not the paper's soft assignment (eqs. 3-5, :func:`matching.soft_assign`): this is
    Gold/Rangarajan's, with outlier bins, for ICP-TPS.

    Parameters
    ----------
    projected : numpy.ndarray, shape (n, 2)
        Projected 3D nodes, pixels.
    skeleton : numpy.ndarray, shape (k, 2)
        2D centreline points, pixels.
    temperature : float
        ``T`` in px^2: ``m_ji ~ exp(-|x_i - f(y_j)|^2 / T)`` before normalisation.
    skeleton_tree : scipy.spatial.cKDTree, optional
        A tree of ``skeleton``, to reuse across calls.

    Returns
    -------
    targets : numpy.ndarray, shape (n, 2)
        ``sum_i m_ji x_i / sum_i m_ji``; the node's own projection where it has no partner.
    weights : numpy.ndarray, shape (n,)
        ``sum_i m_ji`` over the row mass: 1 for a fully matched node, 0 for an outlier.
    """
    n, k = len(projected), len(skeleton)
    outlier = _outlier_weight()
    radius = np.sqrt(temperature * (0.5 * OUTLIER_SIGMAS ** 2 - np.log(_NEGLIGIBLE)))
    tree = skeleton_tree if skeleton_tree is not None else cKDTree(skeleton)
    pairs = cKDTree(projected).sparse_distance_matrix(tree, radius, output_type="ndarray")
    kernel = sp.csr_matrix((np.exp(-pairs["v"] ** 2 / temperature), (pairs["i"], pairs["j"])), shape=(n, k))
    row_mass, column_mass = min(1.0, k / n), min(1.0, n / k)
    row_scale, column_scale = np.ones(n), np.ones(k)
    kernel_t = kernel.T.tocsr()
    for _ in range(_SINKHORN_SWEEPS):
        row_scale = row_mass / (kernel @ column_scale + outlier)
        new_column_scale = column_mass / (kernel_t @ row_scale + outlier)
        change = np.max(np.abs(new_column_scale / column_scale - 1.0))
        column_scale = new_column_scale
        if change < _SINKHORN_TOL:
            break
    row_scale = row_mass / (kernel @ column_scale + outlier)
    matched = row_scale * (kernel @ column_scale)
    pulled = row_scale[:, None] * (kernel @ (column_scale[:, None] * skeleton))
    has_partner = matched > 0
    targets = projected.copy()
    targets[has_partner] = pulled[has_partner] / matched[has_partner, None]
    return targets, matched / row_mass


class _GroherEnergy:
    """``E(V) = S_D + alpha S_L + beta S_S`` over the control displacements, with its gradient.

    ``S_D`` and ``S_L`` are those of the proposed method (:mod:`deformation.energy`), taken
    at the node displacements ``G V`` that the TPS makes of the control displacements ``V``;
    ``S_S`` is the TPS bending energy ``trace(V^T B V)``.
    """

    def __init__(self, points: np.ndarray, edges: np.ndarray, P: np.ndarray, G: np.ndarray, B: np.ndarray,
                 alpha: float):
        self.points, self.G, self.B = points, G, B
        rest = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
        n = len(points)
        # S_D + alpha S_L (beta = 0: the smoothness here is the TPS bending, below)
        self.model = _build_model(points, np.zeros((n, 2)), edges[rest > 0], P, alpha, 0.0, np.zeros(n),
                                  rest[rest > 0])
        self.beta = 0.0

    def set_correspondences(self, targets: np.ndarray, weights: np.ndarray) -> None:
        """The soft targets ``x_hat_j`` (n, 2) px and confidences ``w_j`` (n,) of the data term."""
        view = self.model.views[0]
        view.set_targets(targets)
        view.data_weights = weights / len(self.points)

    def positions(self, displacement: np.ndarray) -> np.ndarray:
        return self.points + self.G @ displacement

    def _node_displacements(self, displacement: np.ndarray) -> np.ndarray:
        """``G V`` component-major (3, n), as the energy model takes it."""
        return np.ascontiguousarray((self.G @ displacement).T)

    def terms(self, displacement: np.ndarray) -> dict:
        """The three energy terms at a control displacement (c, 3), for reporting."""
        _, _, terms = self.model.evaluate(self._node_displacements(displacement), with_gradient=False)
        return {**terms, "S_S": float(np.einsum("ca,cd,da->", displacement, self.B, displacement))}

    def __call__(self, flat: np.ndarray) -> tuple[float, np.ndarray]:
        displacement = flat.reshape(-1, 3)
        energy, grad_nodes, _ = self.model.evaluate(self._node_displacements(displacement))
        grad = self.G.T @ grad_nodes.T                   # chain rule through Y = points + G V
        if self.beta > 0:
            # S_S: TPS bending energy trace(V^T B V); B C = 0, so it depends on the displacement only
            bent = self.B @ displacement
            energy += self.beta * float((displacement * bent).sum())
            grad += 2.0 * self.beta * bent
        return energy, grad.ravel()


def _two_loop_direction(gradient: np.ndarray, steps: list, changes: list) -> np.ndarray:
    """L-BFGS search direction ``-H g`` from the stored (step, gradient change) pairs."""
    direction = -gradient
    if not steps:
        return direction / max(1.0, float(np.linalg.norm(gradient)))
    coefficients = []
    for s, y in zip(reversed(steps), reversed(changes)):
        rho = 1.0 / float(y @ s)
        a = rho * float(s @ direction)
        coefficients.append((rho, a))
        direction = direction - a * y
    direction *= float(steps[-1] @ changes[-1]) / float(changes[-1] @ changes[-1])
    for (s, y), (rho, a) in zip(zip(steps, changes), reversed(coefficients)):
        direction = direction + (a - rho * float(y @ direction)) * s
    return direction


def lbfgs(function: Callable[[np.ndarray], tuple[float, np.ndarray]], x0: np.ndarray, max_iter: int,
          memory: int = 8, gradient_tol: float = 1e-8) -> tuple[np.ndarray, int]:
    """Minimise a smooth function by limited-memory BFGS with Armijo backtracking.

    ICP-TPS keeps this optimiser rather than the proposed method's SciPy L-BFGS-B because
    the baseline is defined by a fixed 10 Armijo steps per temperature, restarted at each,
    which SciPy's Wolfe line search does not reproduce: with SciPy's (10 iterations, memory
    8) the mean 3D error of 5 synthetic 420-node cases (``fixtures.synthetic_case``, seeds
    0-4) goes from 1.37 to 1.49 mm, at no gain in time.

    Parameters
    ----------
    function : callable
        ``function(x) -> (value, gradient)``.
    x0 : numpy.ndarray
        Start point.
    max_iter : int
        Iterations (accepted steps) at most.
    memory : int
        Stored correction pairs.
    gradient_tol : float
        Stop when the largest gradient component is below this.

    Returns
    -------
    x : numpy.ndarray
    evaluations : int
        Function evaluations used.
    """
    x = np.array(x0, dtype=float)
    value, gradient = function(x)
    evaluations = 1
    steps, changes = [], []
    for _ in range(max_iter):
        if np.max(np.abs(gradient)) < gradient_tol:
            break
        direction = _two_loop_direction(gradient, steps, changes)
        slope = float(gradient @ direction)
        if slope >= 0:
            steps, changes = [], []
            direction = _two_loop_direction(gradient, steps, changes)
            slope = float(gradient @ direction)
        t = 1.0
        for _ in range(40):
            new_value, new_gradient = function(x + t * direction)
            evaluations += 1
            if new_value <= value + 1e-4 * t * slope:
                break
            t *= 0.5
        else:
            break
        step, change = t * direction, new_gradient - gradient
        if float(step @ change) > 1e-12 * float(change @ change):
            steps.append(step)
            changes.append(change)
            del steps[:-memory], changes[:-memory]
        x, value, gradient = x + step, new_value, new_gradient
    return x, evaluations


def annealing_temperatures(t_init: float, t_final: float, t_update: float) -> np.ndarray:
    """``T_init, T_update T_init, ...`` while above ``T_final``, then ``T_final`` itself."""
    steps = int(np.floor(np.log(t_final / t_init) / np.log(t_update) + 1e-9)) + 1
    temperatures = t_init * t_update ** np.arange(steps)
    temperatures = temperatures[temperatures > t_final * (1 + 1e-12)]
    return np.append(temperatures, t_final)


def icp_tps(points, edges, skeleton2d, P, *, alpha: float = 0.01, beta_final: float = 3e-7,
            t_init: float = 500.0, t_final: float = 1.0, t_update: float = 0.93,
            n_controls: int | None = None, iterations_per_temperature: int = 10,
            progress: Callable[[float, str], None] | None = None) -> BaselineResult:
    """ICP-TPS (Groher et al. 2009): deform a 3D centreline to one 2D centreline.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Rigidly pre-aligned pre-operative centreline nodes, LPS mm.
    edges : array_like of int, shape (m, 2)
        Its edges (used by the length-preservation term and to find end/junction nodes).
    skeleton2d : array_like, shape (k, 2)
        2D centreline points of the frame, pixels; extra points (other vessels) are allowed.
    P : array_like, shape (3, 4)
        Projection matrix (eq. 1).
    alpha, beta_final : float
        Weights of length preservation and (final) TPS bending; the paper's 0.01 and 3e-7.
    t_init, t_final, t_update : float
        Annealing schedule, ``T <- t_update * T`` (the paper's 500, 1, 0.93).
    n_controls : int, optional
        TPS control nodes; default ``clip(n // 6, 50, 150)`` (all nodes when fewer).
    iterations_per_temperature : int
        L-BFGS iterations after each soft-assign.
    progress : callable, optional
        Called as ``progress(fraction_done, message)`` after each temperature.

    Returns
    -------
    BaselineResult
        ``points`` the deformed nodes (n, 3); ``n_iter`` the temperatures run; ``timings``.
    """
    start = time.perf_counter()
    points = as_points(points, "3D centreline points", 3, min_count=1)
    edges = _check_edges(edges, len(points))
    skeleton = as_points(skeleton2d, "2D skeleton points", 2, min_count=1)
    P = validate_projection_matrix(P)
    _check_schedule(t_init, t_final, t_update, alpha, beta_final)
    if iterations_per_temperature < 1:
        raise ValueError(f"iterations_per_temperature must be at least 1, got {iterations_per_temperature}")
    controls = select_controls(points, edges, default_control_count(len(points)) if n_controls is None
                               else int(n_controls))
    G, B = ThinPlateSpline3D.control_basis(points, points[controls])
    energy = _GroherEnergy(points, edges, P, G, B, alpha)
    skeleton_tree = cKDTree(skeleton)
    displacement = np.zeros((len(controls), 3))
    temperatures = annealing_temperatures(t_init, t_final, t_update)
    timings = {"correspondence": 0.0, "deformation": 0.0}
    evaluations = 0
    for step, temperature in enumerate(temperatures):
        tick = time.perf_counter()
        energy.set_correspondences(*rpm_soft_assign(project(P, energy.positions(displacement)), skeleton,
                                                    temperature, skeleton_tree))
        energy.beta = beta_final * temperature / t_final
        tock = time.perf_counter()
        flat, calls = lbfgs(energy, displacement.ravel(), iterations_per_temperature)
        displacement = flat.reshape(-1, 3)
        evaluations += calls
        timings["correspondence"] += tock - tick
        timings["deformation"] += time.perf_counter() - tock
        if progress is not None:
            progress((step + 1) / len(temperatures), f"ICP-TPS T = {temperature:.3g}")
    timings["total"] = time.perf_counter() - start
    info = {"controls": controls, "temperatures": len(temperatures), "function_evaluations": evaluations,
            "final_terms": energy.terms(displacement)}
    return BaselineResult(energy.positions(displacement), len(temperatures), timings, "icp-tps", info)

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
* several views (beyond the paper): further frames of the same anatomy add their own
  ``S_D``; the data term is the mean over the views (``extra_views``).

Modules: :mod:`.energy` (eq. 6, its terms and gradient, one view or several),
:mod:`.solve` (L-BFGS, the banded preconditioner), :mod:`.tps` (the one 3D TPS, also in
its linear control form for ICP-TPS) and :mod:`.fill` (row 16).

Equation numbers are those of the paper's source (eq. 1 projection ... eq. 6 energy,
eq. 7 gradient of ``S_D``, eqs. 8-9 its matrices ``D`` and ``J``).
"""

from .energy import DEFAULT_ALPHA, DEFAULT_BETA, DeformationResult, energy_and_gradient, energy_terms
from .fill import fill_unassigned
from .solve import deform_assigned
from .tps import ThinPlateSpline3D

__all__ = [
    "DeformationResult",
    "energy_and_gradient",
    "energy_terms",
    "deform_assigned",
    "ThinPlateSpline3D",
    "fill_unassigned",
]

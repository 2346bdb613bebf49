"""Graph matching and soft assignment between the 3D and the 2D skeleton graphs (Sec. II-B).

A package along the module's seams, re-exporting every name the old ``matching.py`` had:

==========  ===========================================================================
paper       the paper's matching: trunks and junctions by ranked geodesic length, branches
            by tangent similarity, soft assignment (eqs. 3-5)
projected   beyond the paper: matching against the projected pre-operative tree
            (:func:`match_by_projection`)
centring    the 2D skeleton's nodes moved to the midline between their vessel's walls
            (:func:`centre_in_outline`)
candidates  every correspondence worth deforming with (the paper's, the labels', the
            projection's) and the score that picks among the deformed candidates
==========  ===========================================================================
"""

from . import candidates, centring, paper, projected
from .centring import RouteOffsets, centre_in_outline, offset_targets, render_lumen, route_offsets, targets_at
from .candidates import UNASSIGNED_PX2, candidate_correspondences, candidate_score
from .paper import (ETA_S, ETA_T, Correspondence, SoftAssignment, branch_tangents, match_branches, match_trunks,
                    soft_assign, soft_assign_with_and_without_exits)
from .paper import _assign_by_arc_length  # the tests check eq. 4's arc-length assignment alone
from .projected import (AMBIGUOUS_PX, COVERAGE_PX, MAX_ALTERNATIVES, NO_PARTNER_PX, TIP_RADII, TURN_PX_PER_RAD,
                        match_by_projection)
from .projected import _SAMPLES, _curve_distances, _turned_residual  # the tests check the curve costs alone

__all__ = [*paper.__all__, *projected.__all__, *candidates.__all__, *centring.__all__]

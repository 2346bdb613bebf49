"""The paper's experiments on our phantoms: SV (rigid) / ICP-TPS / proposed.

``fevar-planner benchmark --out DIR [--quick]`` runs

1. the simulation protocol (paper Sec. III-A, Fig. 4): one phantom in five states bent in
   the frontal plane (as the paper's phantom, bent by a string on a table), cross-paired
   into 20 pre-op / intra-op cases; the 2D skeleton is the projection of the
   intra-operative 3D skeleton (drawn into the frame and thinned); then the same protocol
   with the sac also bent out of the image plane by up to +-1 degree (``OUT_OF_PLANE_DEG``),
   which one view cannot see: the sensitivity of both methods to it;
2. robustness (Fig. 5): in-plane translations and rotations of the frame of one simulation
   case, the methods given the unmoved ``P``; 3D errors against the moved anatomy (the
   patient moved) and against the unmoved one (``P`` is off instead), see ``_robustness``;
3. phantom-like cases (Fig. 6): masks as real data gives them (3D skeleton thinned from the
   pre-op lumen, 2D skeleton thinned from the projected intra-op lumen), and hard variants
   (strong deformation, extra branches, C-arm angulation);

and writes ``benchmark.json``, ``table.md`` (shaped like Table II) and figures
``fig4_simulation.png``, ``fig4b_simulation_out_of_plane.png``, ``fig5_robustness.png``,
``fig6_phantom.png``. ``acceptance`` in benchmark.json holds the 3D error ratio (ICP-TPS /
proposed) and the speed-up on the simulation set; ``comparisons`` the same for both
simulation sets.
Errors are the paper's: mean 2D point-to-curve distance of the projected result to the 2D
skeleton (px), mean 3D point-to-curve distance to the ground-truth centreline (mm), plus the
reverse 3D distance (ground truth to result). Time is the intra-operative part (2D skeleton
and graph, matching, assignment, deformation, TPS; for ICP-TPS its whole loop).

``fevar-planner benchmark --sets independent`` (or ``all``) runs the independent sets of
issue 10 beside them (:func:`run_independent_benchmark`): case folders of the
:mod:`scenarios` family, which shares no geometry or deformation code with :mod:`phantom`,
run through the case-folder route (:func:`pipeline.plan_case`, what a user gets), scored
with the depth floor and the in-plane / along-ray split per vessel
(:func:`evaluation.depth_analysis`); files ``independent.json``, ``independent_table.md``,
``independent_sets.png`` and ``independent_vessels.png``.

A package along three seams, re-exporting the old ``benchmark.py``'s names: ``paper`` (the
paper's protocol, items 1-3), ``independent`` (the independent sets) and ``figures``.
"""

from .independent import (DEFAULT_INDEPENDENT_KINDS, FLOOR_TOLERANCE_MM, INDEPENDENT_CASES, INDEPENDENT_SETS,
                          independent_case_folders, run_independent_benchmark)
from .independent import _independent_summary, _judge_against_sv_and_floor  # the tests judge summaries alone
from .paper import (HARD_VARIANTS, METHODS, OUT_OF_PLANE, OUT_OF_PLANE_DEG, ROTATIONS_DEG, SIMULATION,
                    TRANSLATIONS_PX, draw_skeleton_mask, phantom_cases, run_benchmark, simulation_cases)
from .paper import _robustness  # the tests run one robustness curve alone

__all__ = ["METHODS", "run_benchmark", "simulation_cases", "phantom_cases", "INDEPENDENT_SETS",
           "run_independent_benchmark"]

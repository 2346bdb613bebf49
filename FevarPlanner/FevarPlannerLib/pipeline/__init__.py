"""The one logic entry point that the CLI, the Slicer module, the workstation and the tests call.

Pre-operative work (CT side) is done once per patient by :func:`prepare_preop`; the
intra-operative side (:func:`register_frame`) runs per fluoroscopic frame and is kept
free of anything that does not depend on the frame (paper Algorithm 2):

    rows 1-2   3D skeleton graph and node classification          prepare_preop (preop.build_preop)
    rows 3-4   2D skeleton graph and node classification          register_frame (frame)
    row  5     branch / trunk matching                             matching
    rows 6-12  soft assignment (eqs. 3-5)                          matching
    rows 13-15 deformation S_D + alpha S_L + beta S_S (eqs. 6-9)   deformation (multiview)
    row  16    branch-wise TPS for the unassigned nodes            deformation

The package, one module per stage of a case (every name is re-exported here):

    results      FrameResult, ViewFrame, PlanResult: what a registration and a case return
    visibility   partial visibility: the part of the frame that shows vessels
    frame        register_frame / register_views: Algorithm 2 rows 3-16 for one or more views
    workers      a persistent worker process for a second view's 2D side (and a view's frame check)
    multiview    the deformation over several views, unseen pieces carried rigidly
    fallback     never worse than SV: per-vessel length and 2D-fit checks with fallback
    case         prepare_preop, run_case, check_result, plan_case: a whole case, gated and evaluated
    outputs      write_outputs: the output set, staged and swapped in whole; refusal_picture
"""

from __future__ import annotations

from ..preop import (Preoperative, SMOOTHING_ITERATIONS, _induced_edges, _timed, build_preop, preop_from_lumen,
                     preop_from_skeleton)
from .case import _read_ground_truth, _vessel_mask, check_result, plan_case, prepare_preop, run_case
from .fallback import FIT_TOLERANCE_PX, LENGTH_TOLERANCE, SV_NAME, _never_worse_than_sv, _vessels
from .frame import (POSE_MODES, STABLE_VESSELS, ViewSource, _classify_2d, _prepare_view, _skeleton2d_graph,
                    prepare_views, register_flipped, register_frame, register_prepared, register_view_flipped,
                    register_views, segment_frame, segment_frame_and_field)
from .multiview import (CLOSEST_POINT_OUTLIER, CLOSEST_POINT_PASSES, CLOSEST_POINT_SETTLED_MM,
                        MAX_CANDIDATE_COMBINATIONS, TANGENT_MM)
from .outputs import (DRR_NAME, OUTPUT_NAMES, OUTPUT_SUFFIXES, QC_NAME, check_output_folder, picture_title,
                      refusal_picture, write_outputs)
from .results import FrameResult, METHODS, PlanResult, ViewDrawing, ViewFrame
from .visibility import FLAT_BAND_FRACTION, MIN_BORDER_PIXELS, Visibility, frame_visibility

__all__ = ["METHODS", "Preoperative", "Visibility", "ViewFrame", "ViewDrawing", "FrameResult", "PlanResult",
           "preop_from_skeleton", "preop_from_lumen", "build_preop", "prepare_preop", "picture_title",
           "frame_visibility", "register_frame", "register_flipped", "register_view_flipped", "register_views",
           "ViewSource", "prepare_views", "register_prepared", "segment_frame", "segment_frame_and_field",
           "run_case", "check_result", "plan_case",
           "write_outputs", "refusal_picture"]

"""An independent phantom family for the benchmark (issue 10): data the method was not tuned on.

Nothing here shares geometry or deformation code with :mod:`phantom`; only the file
writers (:mod:`io`) and the projection (:mod:`projection`) are common. A scenario is

* a **vessel tree** of its own generator (:func:`build_tree`): an aorta with a fusiform sac
  (narrow or wide), both renals, common iliacs that can fork distally into an internal
  (label ``other``) and an external iliac (which keeps the common iliac's label),
  optional SMA, coeliac trunk, an accessory renal artery and lumbar stubs (``other``), and
  tortuous iliacs. Every tube is a dense polyline (1 mm steps) with a lumen radius;
* its **deformations** (:func:`deform_tree`), each a length-preserving move of part of the
  tree: a 3D bend of the lower aorta, a 3D bend at the aortic bifurcation and one along
  each iliac, in any direction (not only the frontal plane), wire straightening of the
  iliacs towards the chord between their ends (directions blended towards the chord,
  segment lengths kept), and a shift and tilt of the renal ostia;
* its **frames**: one or more C-arm views with their true and given projections, masks
  drawn from the intra-operative tree by a capsule rasteriser of its own: clipped frames
  (the upper aorta leaves the image at the top border), tubes the frame shows but the CT
  tree lacks (distal iliac forks, lumbar stubs), misaligned given poses, angulated views
  and two-view cases;
* the **patient-like** kind: every side branch a CT angiogram shows (coeliac trunk, SMA,
  IMA, four lumbar arteries, internal iliacs) in the CT tree and in the frame, an accessory
  renal artery beside the main one (narrower) on one side or both, a tortuous neck and
  tortuous iliacs that loop in projection (issue 10, point 4: real patient trees);
* the **bench-phantom** kind ``bench_pinhole`` (:mod:`scenarios.bench`): a short pinhole
  (SOD 180-280 mm, a fixed 512 x 512 frame that clips what it does not hold), the
  pre-operative tree voxelised at about 0.45 mm with a rough wall and thinned raw into
  ``skeleton3d.nrrd``, and the frame's label as a JPEG returns it (``fluoro_mask.png``
  with the compression's grey halo), phantom-size anatomy bent by hand.

Case folders follow docs/DESIGN.md section 4: ``aorta_mask.nrrd`` (the pre-operative lumen on a
1 mm CT grid), ``fluoro_mask.png`` + ``geometry.json`` (the main view, given ``P``),
``views/<name>/fluoro_mask.png`` + ``geometry.json`` for a second view, ``gt.json`` (the
intra- and pre-operative centrelines of the CT's tubes, node ``n`` of one is node ``n`` of
the other, and every view's true projection) and ``scenario.json`` (everything drawn).

A package along those seams, re-exporting every name of the old ``scenarios.py``: ``tree``,
``deformations``, ``plans`` (what each kind draws from its seed), ``frames`` (views, masks,
CT and DSA images) and ``cases`` (the case folders).

Coordinates are LPS mm (+x left, +y posterior, +z superior). Every random number comes
from the scenario's seed: the same seed writes the same files.
"""

from __future__ import annotations

from .cases import write_scenario, write_scenario_set
from .deformations import bend_subtree, deform_tree, Deformation, straighten_tube
from .frames import (CT_HU, CT_MARGIN_MM, CT_NOISE_HU, CT_SPACING_MM, DETECTOR_MARGIN_PX, DSA_ATTENUATION_PER_MM,
                     DSA_NOISE, IMAGE_CT_MARGIN_MM, SPINE_MM, generate, mask_end_points,
                     paint_capsules, render_ct, render_dsa, RenderedView, ScenarioCase)
from .plans import (ANGULATED_VIEWS_DEG, EXTRA_KINDS, KINDS, OUT_OF_PLANE_SEVERITIES_DEG, SECOND_VIEW_DEG, plan_scenarios,
                    Scenario, View)
from .tree import MAIN_VESSELS, SIDES, STEP_MM, build_tree, random_shape, TreeShape, Tube, VesselTree

__all__ = [
    "KINDS",
    "EXTRA_KINDS",
    "MAIN_VESSELS",
    "Tube",
    "VesselTree",
    "TreeShape",
    "random_shape",
    "build_tree",
    "Deformation",
    "bend_subtree",
    "straighten_tube",
    "deform_tree",
    "View",
    "Scenario",
    "plan_scenarios",
    "RenderedView",
    "ScenarioCase",
    "generate",
    "paint_capsules",
    "mask_end_points",
    "render_ct",
    "render_dsa",
    "write_scenario",
    "write_scenario_set",
]

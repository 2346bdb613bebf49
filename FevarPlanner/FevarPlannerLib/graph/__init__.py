"""Skeleton graphs (paper Definition 1) and skeleton node classification (Definitions 2-4, Alg. 1).

The package, one module per stage (this file re-exports every public name):

==================  =====================================================================
``skeleton_graph``  :class:`SkeletonGraph` (Definition 1), the result types
                    :class:`Branch`, :class:`Trunk`, :class:`Classification`, the defaults
``repair``          gaps bridged and short loops broken before Algorithm 1 (departure 6)
``algorithm1``      :func:`classify` (Algorithm 1) and :func:`spur_length`
``anatomy``         :func:`anatomical_roles` and :func:`label_anatomy`
``smoothing``       :func:`smooth_positions` and :func:`centre_in_lumen`
``builders``        :func:`skeleton_graph_3d`, :func:`skeleton_graph_2d`
==================  =====================================================================

A :class:`SkeletonGraph` has one node per skeleton voxel (3D, positions in LPS mm) or pixel
(2D, positions ``(u, v)`` in pixels), edges between grid points at Chebyshev distance 1
(Definition 1) weighted by the Euclidean distance of their positions, and a sparse
symmetric adjacency matrix. :func:`classify` runs Algorithm 1 on it and
:func:`label_anatomy` names the five preserved branches and the trunks.

Where this departs from Algorithm 1, and why
--------------------------------------------
1. Geodesic lengths are physical (Dijkstra on Euclidean edge weights: mm in 3D, pixels in
   2D) instead of hop counts; branches are still found in order of growing geodesic length
   and ``iota`` is a length, not a node count. Hop counts make a diagonal run of voxels look
   shorter than an axial one of the same length and tie ``iota`` to the voxel size.
2. Preservation counts the current end node: a branch is omitted/deleted while more than
   ``tau`` end nodes are still marked *including its own*. Taken literally (count after
   unmarking) the rule preserves ``tau + 1`` branches whenever there are spurs.
3. A junction turns into a connection node only when fewer than three of its arms are left
   (arms that are neither deleted nor omitted). The paper converts it unconditionally; that
   is the same for the usual degree-3 junction, but where a spur leaves a four-armed junction
   (both renals and a spur at one point of a 2D projection) converting it would make a
   renal branch swallow the whole aortic trunk.
4. A deleted spur loses its nodes from the end node up to, not including, the first node
   that still has two other neighbours; the paper deletes the whole path including the
   junction node, which would cut the skeleton there.
5. Trunks are the shortest paths between junctions whose geodesic "waves" meet (multi-source
   Dijkstra); this is the bidirectional BFS of rows 20-31, with each pair reported once.
6. Repairs that the paper does not need on hand-segmented phantoms but real skeletons do,
   all applied before Algorithm 1 on a copy of the graph (``Classification.graph``):
   * triangle pruning in the graph constructors (see :func:`skeleton.grid_edges`);
   * gaps: components whose nearest nodes lie within ``max_gap`` of the main component are
     bridged by one straight edge; farther ones are dropped with a warning;
   * loops: every cycle shorter than ``max_loop`` is broken by removing its longest arc
     between consecutive attachment nodes (a loop closing on itself at one node keeps the
     half next to that node), so two parallel paths through a sac become the shorter one;
     longer cycles are kept (noted).
7. Spurs relative to the vessel: when the graph knows its local radii (the mask it was
   thinned from was given), a branch is a spur when it is shorter than
   ``max(iota, spur_radius_factor * r)``, ``r`` the radius at its junction. Thinning grows a
   branch of one to two radii from every bump of a wide vessel (an aneurysm sac in a raw
   DSA frame: 15-25 mm from a 13 mm lumen), longer than a fixed ``iota`` of one small
   vessel's diameter; a real side branch is several parent radii long.
"""

from __future__ import annotations

from ..conventions import BRANCH_LABELS
from .algorithm1 import classify, spur_length
from .anatomy import DEPTH_PENALTY, ROLE_LATERAL_WEIGHT, anatomical_roles, label_anatomy
from .builders import skeleton_graph_2d, skeleton_graph_3d
from .skeleton_graph import (DEFAULT_IOTA_MM, DEFAULT_MAX_GAP_MM, DEFAULT_MAX_LOOP_MM, SPUR_RADIUS_FACTOR, Branch,
                             Classification, SkeletonGraph, Trunk, row_norms)
from .smoothing import centre_in_lumen, smooth_positions, smoothed_positions

__all__ = [
    "SkeletonGraph",
    "Branch",
    "Trunk",
    "Classification",
    "classify",
    "label_anatomy",
    "anatomical_roles",
    "smooth_positions",
    "smoothed_positions",
    "row_norms",
    "centre_in_lumen",
    "spur_length",
    "skeleton_graph_3d",
    "skeleton_graph_2d",
    "DEFAULT_IOTA_MM",
    "SPUR_RADIUS_FACTOR",
    "DEFAULT_MAX_GAP_MM",
    "DEFAULT_MAX_LOOP_MM",
    "BRANCH_LABELS",
    "ROLE_LATERAL_WEIGHT",
    "DEPTH_PENALTY",
]

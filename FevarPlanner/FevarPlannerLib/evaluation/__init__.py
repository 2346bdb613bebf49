"""The paper's evaluation metrics: 2D and 3D point-to-curve distances (Sec. III, Figs. 4-6,
Tables I-II).

The paper measured errors with MATLAB's ``distance2curve`` (File Exchange): the distance from
each point to the *nearest point on a curve made of straight segments*, not to the nearest
vertex. Here a curve is any centreline graph: every edge is one segment, and an isolated
node is a segment of length zero.

* **2D error** (pixels): every node of the result, projected with ``P`` (eq. 1), to the 2D
  skeleton graph of the fluoroscopic frame. ``2d_reverse_px`` is the other way round
  (skeleton points to the projected result graph); it exposes a result whose projection
  covers only part of the skeleton, but it also counts skeleton pieces the 3D centreline
  has no counterpart for (catheters, small side branches).
* **3D error** (mm): every node of the result to the ground-truth 3D centreline graph
  (``forward``, the paper's measure), every ground-truth node to the result
  (``reverse``), so that a collapsed or shrunken result cannot look good, and
  ``symmetric``: the statistics of both sets of distances pooled (its ``max`` is the
  Hausdorff distance between the two graphs).

Every statistic is a dict ``{"mean", "std", "median", "max"}``; ``std`` is the sample
standard deviation (``ddof = 1``, MATLAB's default) and 0 for a single distance.

Restricting the comparison to vessels present in both
-----------------------------------------------------
A ground-truth centreline may hold vessels that the result does not (or the other way
round), and a fluoroscopic frame may not show every vessel of the CT. :func:`evaluate`
therefore compares only nodes whose anatomy labels occur in the chosen label set: by
default the labels that the result and the ground truth *both* carry; a caller that knows
which vessels the frame shows passes them as ``labels`` (:func:`restrict_to_labels` does
the cut: the subgraph of the kept nodes and of the edges between them). The 2D skeleton
carries no labels and is never cut.

Depth (issue 10)
----------------
One view fixes each point's ray but not its depth along it. :func:`depth_floor` scores the
oracle that puts every true intra-operative point on its true ray at its pre-operative
depth, with the same metric (oracle points to the true graph): a method that does not
recover depth cannot go below it. :func:`depth_analysis` splits each result node's error
into its along-ray and in-plane parts (:func:`ray_components`), overall and per vessel,
and reports the fraction of the true along-ray motion recovered. With two views the
floor is reported for the main view's rays.

Files
-----
A package along those seams, re-exporting every name of the old ``evaluation.py``:
``distances`` (points to segments and graphs, :class:`SegmentIndex`), ``metrics`` (the 2D
and 3D errors, their statistics, the label restriction) and ``depth``.
"""

from __future__ import annotations

from . import depth, distances, metrics
from .depth import (MAIN_VESSELS, MIN_OUT_OF_PLANE_MM, closest_points_on_graph, depth_analysis, depth_floor,
                    depth_floor_points, ray_components)
from .distances import SegmentIndex, graph_index, point_to_graph, point_to_segments
from .metrics import common_labels, distance_statistics, error_2d, error_3d, evaluate, restrict_to_labels

__all__ = [*distances.__all__, *metrics.__all__, *depth.__all__]

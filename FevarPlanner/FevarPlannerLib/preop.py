"""The pre-operative model: Algorithm 2 rows 1-2, computed once per patient.

The CT side of the method: the 3D skeleton (given, or thinned from the lumen, which is
segmented from the CT when only a CT is given), its graph classified (Algorithm 1),
smoothed, centred in the lumen and labelled. :mod:`pipeline` calls it through
``prepare_preop`` and :mod:`cache` keeps its result; neither is imported here.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from . import graph, skeleton
from .centerline import Centerline
from .conventions import IOTA_MM, LPS_DIRECTIONS
from .io import Case

__all__ = ["SMOOTHING_ITERATIONS", "Preoperative", "preop_from_skeleton", "preop_from_lumen", "build_preop"]

#: Laplacian smoothing passes over both skeletons (graph.smooth_positions), which takes out
#: the voxel / pixel staircase that eq. (4)'s path lengths and the targets inherit. On the
#: simulation protocol with +-1 degree out-of-plane bending, before the 3D skeleton was also
#: centred in the lumen (Testing/benchmarks/bench_registration.py), the mean 2D error fell
#: from 0.61 to 0.13 px and the 3D error from 1.06 to 0.91 mm.
SMOOTHING_ITERATIONS = 10


@contextmanager
def _timed(timings: dict, name: str):
    start = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - start


def _report(progress, fraction: float, message: str) -> None:
    if progress is not None:
        progress(fraction, message)


@dataclass
class Preoperative:
    """The pre-operative 3D skeleton graph, classified and labelled (computed once per patient).

    ``route_offsets`` keeps, per frame geometry, what the single-view route gets wrong on this
    tree's own projected lumen (:func:`pipeline.frame._route_offsets`): computed on the first
    frame of a geometry, reused by the frames after it.
    """

    graph: graph.SkeletonGraph
    classification: graph.Classification
    kept: np.ndarray
    centerline: Centerline
    timings: dict = field(default_factory=dict)

    def __post_init__(self):
        # the kept nodes' own graph (node t is graph node kept[t]), for the per-frame TPS fill
        self.kept_adjacency = self.graph.subgraph(self.kept).adjacency
        self.centre = self.centerline.points.mean(axis=0)
        self.route_offsets = {}      # per frame geometry, oldest first, filled as frames come


def _induced_edges(graph_: graph.SkeletonGraph, nodes: np.ndarray) -> np.ndarray:
    """Edges of ``graph_`` between ``nodes``, renumbered to positions in ``nodes``."""
    index = np.full(len(graph_.positions), -1)
    index[nodes] = np.arange(len(nodes))
    edges = index[graph_.edges()]
    return edges[np.all(edges >= 0, axis=1)]


def _skeleton3d_and_lumen(case: Case, progress=None, segmenter: str = "classical"):
    """The case's 3D skeleton volume (given, or thinned from the lumen) and its lumen mask (or None)."""
    mask = case.aorta_mask
    if case.skeleton3d is not None:
        return case.skeleton3d, mask
    if mask is None:
        from . import segmentation

        _report(progress, 0.05, "segmenting the aorta in the CT")
        # the classical route and the UNet report slice by slice: move the bar from 5 to 15 %
        kwargs = {"progress": lambda done, total: _report(progress, 0.05 + 0.1 * done / max(total, 1),
                                                          f"segmenting the aorta: slice {done}/{total}")}
        mask = segmentation.segment_ct(case.ct, segmenter, **(kwargs if segmenter != "threshold" else {}))
    _report(progress, 0.15, "thinning the 3D lumen")
    return skeleton.skeletonize_3d(mask), mask


def preop_from_skeleton(skeleton_volume, timings: dict | None = None, lumen=None) -> Preoperative:
    """Classify (Alg. 1) and label a binary 3D skeleton volume: Algorithm 2 rows 1-2.

    With the ``lumen`` mask it was thinned from, the smoothed skeleton is also centred in
    the lumen's cross-sections (graph.centre_in_lumen, sub-voxel).
    """
    timings = {} if timings is None else timings
    with _timed(timings, "preop_graph3d"):
        # with the lumen, spurs are also judged against the local radius (graph.spur_length)
        g3 = graph.SkeletonGraph.from_volume(skeleton_volume, lumen=lumen)
        c3 = graph.classify(g3, iota=IOTA_MM, directions=LPS_DIRECTIONS)
        # the repaired graph (gaps bridged, small loops broken, spurs isolated), its voxel
        # staircase smoothed away
        g3 = graph.smooth_positions(c3.graph, SMOOTHING_ITERATIONS)
    if lumen is not None:
        with _timed(timings, "preop_centring"):
            g3 = graph.centre_in_lumen(g3, lumen)
    with _timed(timings, "preop_graph3d"):
        c3 = graph.label_anatomy(g3, c3, **LPS_DIRECTIONS)
    kept = np.asarray(c3.kept_nodes())
    labels = [c3.node_labels[i] for i in kept]
    centerline = Centerline(g3.positions[kept], _induced_edges(g3, kept), labels)
    return Preoperative(g3, c3, kept, centerline, timings)


def preop_from_lumen(lumen, timings: dict | None = None) -> Preoperative:
    """Thin a binary 3D lumen mask (a Volume) and build its :class:`Preoperative`, centred in it."""
    return preop_from_skeleton(skeleton.skeletonize_3d(lumen), timings, lumen)


def build_preop(case: Case, progress=None, segmenter: str = "classical"):
    """(:class:`Preoperative`, lumen mask or None) of a case, computed (see :func:`prepare_preop`)."""
    timings = {}
    with _timed(timings, "preop_skeleton3d"):
        skeleton_volume, lumen = _skeleton3d_and_lumen(case, progress, segmenter)
    _report(progress, 0.25, "3D skeleton graph and Algorithm 1")
    return preop_from_skeleton(skeleton_volume, timings, lumen), lumen

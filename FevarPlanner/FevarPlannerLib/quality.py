"""Quality gate before registering, on both sides, and the QC picture that shows why.

A confident wrong answer is the worst outcome: before the frame is registered,

- the 3D tree must hold the five main vessels (aorta, both renals, both common iliacs) with
  lengths (and, when the lumen is at hand, radii) in anatomical ranges
  (:func:`check_preop_tree`);
- the 2D vessel mask must look like an angiogram of that tree: not empty, not covering the
  frame, and, after the best in-plane shift, most of each projected main vessel must lie
  close to the mask's skeleton, and the mask's aorta must run along a band denser than both
  sides, not along a bone's edge, and denser than its surroundings where the metal shows which
  side of the grey scale is dense (:func:`check_frame_mask`, :func:`dense_side`).

A failure raises :class:`QualityError` (an :class:`files.InputError`: one line, exit code 2)
naming the vessel and where it was expected; it carries what :func:`write_segmentation_qc`
needs to draw the picture (the frame with the mask and the projected tree; CT slices and a
MIP with the lumen), which callers write before reporting the error.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from .conventions import PALETTE
from .files import InputError, atomic_path
from .io import Volume

__all__ = ["FluoroPrior", "TYPICAL_RADIUS_MM", "DEFORMATION_MARGIN_MM", "MAIN_VESSELS", "LENGTH_RANGE_MM", "RADIUS_RANGE_MM", "QualityError", "QCData", "check_preop_tree",
           "check_frame_mask", "dense_side", "vessel_contrast_to_noise", "write_segmentation_qc"]

MAIN_VESSELS = ("aorta", "renal_left", "renal_right", "iliac_left", "iliac_right")
#: A lumen leaving the scan's most inferior slice as one section this wide (equivalent radius,
#: mm) is the aorta: the scan stops above the bifurcation.
AORTA_CUT_RADIUS_MM = 6.0
#: Centreline length (mm) each main vessel's labelled part may have.
LENGTH_RANGE_MM = {"aorta": (40.0, 700.0), "renal_left": (5.0, 160.0), "renal_right": (5.0, 160.0),
                   "iliac_left": (10.0, 300.0), "iliac_right": (10.0, 300.0)}
#: Median lumen radius (mm) each main vessel may have (aneurysmal sacs included for the aorta).
RADIUS_RANGE_MM = {"aorta": (4.0, 40.0), "renal_left": (1.0, 8.0), "renal_right": (1.0, 8.0),
                   "iliac_left": (2.0, 16.0), "iliac_right": (2.0, 16.0)}
#: A projected vessel counts as seen when this fraction of it lies within TOLERANCE_MM of the
#: 2D skeleton after the best in-plane shift (searched up to SHIFT_MM).
MIN_SEEN_FRACTION = 0.5
SHIFT_MM = 40.0
#: An angiogram's mask is one tree (plus small disconnected side branches): its largest
#: 8-connected piece holds at least this fraction of it. On an unsubtracted frame the tree
#: breaks where vessels cross bone edges; it still passes when the pieces lying along the
#: projected tree (at least ON_PRIOR_PIECE of a piece's pixels inside the prior's band) hold
#: this fraction of the mask, each on its own stretch of the tree (MAX_REACHED_AGAIN), and
#: cover at least MIN_PRIOR_COVERED of the projected tree's length.
MIN_LARGEST_PIECE = 0.75
ON_PRIOR_PIECE = 0.5
MIN_PRIOR_COVERED = 0.6
#: A piece whose nearest projected-tree nodes are more than this fraction already reached by
#: larger pieces lies beside them (a slab of background), not along the tree.
MAX_REACHED_AGAIN = 0.5
#: The masked vessels must differ from their surroundings by this many noise standard deviations.
MIN_CONTRAST_TO_NOISE = 3.0
#: A vessel mask covering more of the frame than this is noise, not an angiogram.
MAX_MASK_FRACTION = 0.35
#: A contrast-filled vessel is a band: across it, its core (within BAND_CORE of its projected
#: radius R of the mask's centre line) attenuates more than BOTH flanks (from (1 + BAND_GAP) R to
#: (2 + BAND_GAP) R on either side); its band contrast is the core's excess over the higher
#: flank. A bone's or a soft tissue's edge is a step: one flank as dense as the core, no band
#: contrast. A mask that follows such an edge beside the vessel has the vessel's band beside its
#: centre line: at a point of the centre line the band contrast must be at least BAND_MIN_NOISE
#: times the noise of a working-scale block and BAND_OF_BEST of the best band contrast with the
#: centre moved across by BAND_BESIDE to BAND_SEARCH R (nearer, a band centred a little off the
#: centre line is the vessel itself). At least MIN_BAND_SHARE of the aorta's centre line must
#: pass; centre-line pixels where the mask is narrower than BAND_SPUR of its median half-width
#: there (the skeleton's spurs into its edge) are not judged. Chosen on bench frames (seeds
#: 231-250, every distractor, both polarities: 0.82-1.0 of the segmented masks' aorta passes
#: unsubtracted, 0.99-1.0 subtracted) and on frames with the vertebral column under the aorta
#: (``render_bench_frame(spine_offset_mm=0 or +-6, spine_gain=2 or 4)``, seeds 301-308: true and
#: segmented masks 0.76-1.0; a mask moved onto the column's edge 0-0.10 with the column centred,
#: 0.02-0.54 when its edge lies 6 mm nearer the aorta and the moved mask overlaps it).
BAND_CORE = 0.5
BAND_ALONG = 0.5
BAND_GAP = 0.25
BAND_BESIDE = 1.0
BAND_SEARCH = 2.0
BAND_OF_BEST = 0.5
BAND_MIN_NOISE = 1.0
MIN_BAND_SHARE = 0.5
#: A contrast-filled lumen is densest in its middle (its chord is longest there); a vessel
#: phantom's empty or unfilled silicone tube is densest at its walls, where the rays run along
#: them (a tram track): across the mask's aorta, at the mask's own half-width H, the middle
#: (within FILLED_CORE H) must attenuate more than the rim (FILLED_RIM H) on at least
#: MIN_FILLED_SHARE of its centre line. Chosen on the realbench family (Testing/benchmarks/
#: realbench_frames.py, development seeds 480-485): contrast-filled aortas 0.86-1.0 with plan's
#: masks (1.0 with the true masks), an empty silicone phantom in air 0.46 / 0.56. A water-filled
#: phantom in air is a weak positive angiogram and an air-filled one in a water bath a negative
#: one (0.92-1.0): their profiles are a filled lumen's, this rule does not see them.
FILLED_CORE = (0.0, 0.25, 0.5)
FILLED_RIM = (0.75, 0.9)
MIN_FILLED_SHARE = 0.7
#: Metal (guidewire, catheter marker, sheath band) attenuates most and lies in and along the
#: vessels: around the mask (within METAL_REACH working-scale blocks of it), thin structures (a
#: top-hat of 2 f - 1 px for a working scale of f px, :func:`_working_scale`) darker than their
#: surroundings and thin ones brighter are compared by their METAL_TAIL percentile; when one side
#: exceeds the other METAL_RATIO times (and METAL_MIN_NOISE pixel noises), it is the display's
#: dense side. A mask whose vessels lie on the other side of their surroundings is a lumen
#: less dense than around it: air or CO2 in a water bath or tissue (a negative angiogram), not
#: iodine. Subtracted frames have no metal left: no verdict, the rule is silent. Chosen on the
#: realbench family (development seeds 480-485) and the older bench family
#: (``bench_frame_masks.py --seeds 231 ... 240 --kinds every every_dsa``).
METAL_REACH = 2
METAL_SMOOTH = 0.375
METAL_TAIL = 99.0
METAL_RATIO = 2.0
METAL_MIN_NOISE = 4.0
#: The vessels whose cross profile is checked, and the fewest centre-line samples that judge one.
BAND_VESSELS = ("aorta",)
BAND_MIN_SAMPLES = 10
BAND_SPUR = 0.5


#: Typical lumen radius (mm) of each labelled vessel, used when the lumen is not at hand.
TYPICAL_RADIUS_MM = {"aorta": 10.0, "renal_left": 3.0, "renal_right": 3.0, "iliac_left": 5.0, "iliac_right": 5.0,
                     "other": 3.0}
#: How far (mm) the intra-operative vessel may lie from its projected pre-operative position:
#: the stiff wires straighten the iliacs most.
DEFORMATION_MARGIN_MM = {"aorta": 20.0, "renal_left": 20.0, "renal_right": 20.0, "iliac_left": 35.0,
                         "iliac_right": 35.0, "other": 20.0}


class FluoroPrior:
    """Where the vessels must be in a frame: the pre-operative tree projected through ``P``.

    Parameters
    ----------
    points : (n, 3) array
        Centreline nodes, LPS mm.
    edges : (m, 2) int array
    labels : list of str
        Anatomy label per node (``centerline.ANATOMY_LABELS``).
    P : (3, 4) array
        Projection matrix (eq. 1).
    radii_mm : (n,) array, optional
        Lumen radius per node; default :data:`TYPICAL_RADIUS_MM` by label.
    """

    def __init__(self, points, edges, labels, P, radii_mm=None):
        from .projection import pixels_per_mm, project

        self.points = np.asarray(points, dtype=float)
        self.edges = np.asarray(edges, dtype=int).reshape(-1, 2)
        self.labels = list(labels)
        self.P = np.asarray(P, dtype=float)
        self.radii_mm = (np.array([TYPICAL_RADIUS_MM.get(label, 3.0) for label in self.labels])
                         if radii_mm is None else np.asarray(radii_mm, dtype=float))
        self.uv = project(self.P, self.points)
        self.px_per_mm = pixels_per_mm(self.P, self.points)
        self.radii_px = self.radii_mm * self.px_per_mm
        self.margin_px = np.array([DEFORMATION_MARGIN_MM.get(label, 20.0) for label in self.labels]) * self.px_per_mm
        self._raster_cache = {}

    @classmethod
    def from_centerline(cls, centerline, P, lumen: Volume | None = None) -> "FluoroPrior":
        """The prior of a labelled :class:`Centerline`; radii from ``lumen``'s distance map if given."""
        radii = None
        if lumen is not None:
            radii = np.maximum(_radii(centerline, lumen), 1.0)
        return cls(centerline.points, centerline.edges, centerline.labels, P, radii)

    def rasterise(self, shape, factor: int = 1):
        """Distance (px of the reduced grid) to the projected tree, and the nearest node's index.

        The tree's edges are sampled every half pixel on a grid reduced by ``factor``; the
        Euclidean distance transform gives, per pixel, how far the nearest drawn pixel is and
        which node it came from (the nearer end of its edge). Cached per (shape, factor).
        """
        key = (tuple(shape), int(factor))
        if key not in self._raster_cache:
            self._raster_cache[key] = self._rasterise(tuple(shape), int(factor))
        return self._raster_cache[key]

    def band(self, shape, factor: int = 1, pad: int = 0) -> "PriorBand":
        """Where to look on a grid of ``shape`` reduced by ``factor`` (cached per arguments).

        Returns
        -------
        PriorBand
            ``box``: the band's bounding box widened by ``pad`` pixels (clipped to the grid);
            within it ``distance`` to the projected tree, the ``nearest`` node (>= 0),
            its projected ``radius`` and the ``band`` (distance <= radius + deformation margin),
            all in pixels of the reduced grid.
        """
        key = ("band", tuple(shape), int(factor), int(pad))
        if key not in self._raster_cache:
            distance, nearest = self.rasterise(shape, factor)
            nearest = np.maximum(nearest, 0)
            radius = (self.radii_px[nearest] / factor).astype(np.float32)
            band = distance <= radius + self.margin_px[nearest] / factor
            box = _padded_box(band, pad) if band.any() else (slice(0, shape[0]), slice(0, shape[1]))
            self._raster_cache[key] = PriorBand(box, distance[box], nearest[box], radius[box], band[box])
        return self._raster_cache[key]

    def derived(self, key, compute):
        """``compute()``, once per ``key``: what a segmenter derives from a :meth:`band` of this
        prior (a frame's per-pixel label codes, a widened radius map) and reuses per frame."""
        key = ("derived",) + tuple(key)
        if key not in self._raster_cache:
            self._raster_cache[key] = compute()
        return self._raster_cache[key]

    def _rasterise(self, shape, factor: int):
        uv = (self.uv + 0.5) / factor - 0.5
        finite = np.all(np.isfinite(uv[self.edges].reshape(len(self.edges), -1)), axis=1) if len(self.edges) else []
        edges = self.edges[finite] if len(self.edges) else self.edges
        node_of_pixel = np.full(shape, -1, dtype=np.int64)
        if len(edges):
            a, b = uv[edges[:, 0]], uv[edges[:, 1]]
            counts = np.ceil(2.0 * np.linalg.norm(b - a, axis=1)).astype(int) + 1
            edge_index = np.repeat(np.arange(len(edges)), counts)
            t = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)) / np.repeat(
                np.maximum(counts - 1, 1), counts)
            points = a[edge_index] + t[:, None] * (b - a)[edge_index]
            cols, rows = np.round(points[:, 0]).astype(int), np.round(points[:, 1]).astype(int)
            inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
            nodes = np.where(t < 0.5, edges[edge_index, 0], edges[edge_index, 1])
            # the widest vessel drawn on a pixel owns it (written last): a side branch projecting
            # along the aorta (an SMA in an AP view) does not take the aorta's pixels and radius
            order = np.flatnonzero(inside)[np.argsort(self.radii_px[nodes[inside]], kind="stable")]
            node_of_pixel[rows[order], cols[order]] = nodes[order]
        if not (node_of_pixel >= 0).any():
            return np.full(shape, np.inf, dtype=np.float32), np.full(shape, -1, dtype=np.int64)
        distance, (ri, ci) = ndi.distance_transform_edt(node_of_pixel < 0, return_indices=True)
        return distance.astype(np.float32), node_of_pixel[ri, ci]


def _padded_box(mask: np.ndarray, pad: int) -> tuple:
    """The bounding box (slices) of a non-empty ``mask`` widened by ``pad`` along each axis, clipped to it."""
    box = []
    for axis, size in enumerate(mask.shape):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(mask.ndim) if a != axis)))
        box.append(slice(max(int(hit[0]) - pad, 0), min(int(hit[-1]) + pad + 1, size)))
    return tuple(box)


@dataclass(frozen=True)
class PriorBand:
    """The part of a reduced frame grid the prior lets the segmentation look at (:meth:`FluoroPrior.band`)."""

    box: tuple
    distance: np.ndarray
    nearest: np.ndarray
    radius: np.ndarray
    band: np.ndarray


@dataclass
class QCData:
    """What the QC picture shows: any of the CT and its lumen, the frame, its mask, the prior,
    and ``registered``: the registered tree's projection ``(uv (n, 2), edges (m, 2))`` when the
    registration check (:func:`plausibility.check_registration`) refused it; ``flipped``: the
    projection of the tree registered to the frame flipped left-right, in the flipped frame's
    pixels, when the mirror test (:func:`plausibility.check_not_mirrored`) refused it."""

    ct: Volume | None = None
    lumen: Volume | None = None
    frame: np.ndarray | None = None
    mask2d: np.ndarray | None = None
    prior: object | None = None
    notes: list = field(default_factory=list)
    registered: tuple | None = None
    flipped: tuple | None = None


class QualityError(InputError):
    """The segmentation failed the gate; ``qc`` holds what the QC picture shows."""

    def __init__(self, message: str, qc: QCData | None = None):
        super().__init__(message)
        self.qc = qc


def _vessel_lengths(centerline) -> dict:
    """Total edge length (mm) per label, counting edges whose two nodes share the label."""
    labels = np.asarray(centerline.labels)
    edges = np.asarray(centerline.edges, dtype=int).reshape(-1, 2)
    lengths = {}
    if len(edges):
        same = labels[edges[:, 0]] == labels[edges[:, 1]]
        seg = np.linalg.norm(centerline.points[edges[:, 0]] - centerline.points[edges[:, 1]], axis=1)
        for label in MAIN_VESSELS:
            lengths[label] = float(seg[same & (labels[edges[:, 0]] == label)].sum())
    return lengths


def _radii(centerline, lumen: Volume) -> np.ndarray:
    """Lumen radius (mm) at each centreline node: its voxel's Euclidean distance to the nearest
    background voxel, computed only in the lumen's bounding box (zero outside it)."""
    inside = np.asarray(lumen.array) > 0
    index = np.clip(np.round(lumen.lps_to_index(centerline.points)).astype(int), 0, np.array(lumen.shape) - 1)
    radii = np.zeros(len(index))
    if not inside.any():
        return radii
    box = _padded_box(inside, 1)      # the widening is background: every nearest background voxel lies in it
    distance = ndi.distance_transform_edt(inside[box], sampling=np.asarray(lumen.spacing)[::-1])
    start, stop = np.array([b.start for b in box]), np.array([b.stop for b in box])
    within = np.all((index >= start) & (index < stop), axis=1)
    radii[within] = distance[tuple((index[within] - start).T)]
    return radii


def _where_aorta_ends(centerline) -> str:
    labels = np.asarray(centerline.labels)
    aorta = centerline.points[labels == "aorta"] if (labels == "aorta").any() else centerline.points
    low, high = aorta[np.argmin(aorta[:, 2])], aorta[np.argmax(aorta[:, 2])]
    return (f"the aorta found runs from LPS z={high[2]:.0f} down to z={low[2]:.0f} mm "
            f"(x={low[0]:.0f}, y={low[1]:.0f})")


def _aorta_leaves_scan_below(lumen: Volume) -> str | None:
    """Where the lumen leaves the scan through its most inferior slice as one aorta-wide
    cross-section (the CT stops above the aortic bifurcation), as a phrase; else ``None``.

    Two cut iliacs leave as two similar sections; an aorta leaves as one section of at least
    :data:`AORTA_CUT_RADIUS_MM` (equivalent radius) with nothing half its size beside it.
    """
    k = 0 if lumen.superior_step > 0 else lumen.shape[0] - 1       # the most inferior slice
    pieces, count = ndi.label(np.asarray(lumen.array[k]) > 0)
    if count == 0:
        return None
    areas = np.bincount(pieces.ravel())[1:] * float(lumen.spacing[0] * lumen.spacing[1])
    order = np.argsort(areas)[::-1]
    radius = math.sqrt(areas[order[0]] / math.pi)
    if radius < AORTA_CUT_RADIUS_MM or (count > 1 and areas[order[1]] >= 0.5 * areas[order[0]]):
        return None
    j, i = np.argwhere(pieces == order[0] + 1).mean(axis=0)
    where = "LPS ({:.0f}, {:.0f}, {:.0f}) mm".format(*lumen.index_to_lps([k, j, i]))
    return f"the aorta leaves the scan through its lower edge near {where}, {radius:.0f} mm in radius"


def check_preop_tree(centerline, lumen: Volume | None = None, qc: QCData | None = None) -> dict:
    """Check the labelled 3D centreline before registering.

    Parameters
    ----------
    centerline : Centerline
        The pre-operative tree, labelled (``pipeline.Preoperative.centerline``).
    lumen : Volume, optional
        The lumen mask it came from; when given, the median radius of each vessel is checked.
    qc : QCData, optional
        Attached to the error for the QC picture.

    Returns
    -------
    dict
        ``{vessel: {"length_mm": ..., "radius_mm": ...}}``.

    Raises
    ------
    QualityError
        One line: the scan stops above the bifurcation (the lumen is given), or every vessel
        that is missing, or else the first one out of range, and where.
    """
    lengths = _vessel_lengths(centerline)
    radii = _radii(centerline, lumen) if lumen is not None else None
    labels = np.asarray(centerline.labels)
    cut = _aorta_leaves_scan_below(lumen) if lumen is not None else None
    if cut:     # whatever the tree's labels say, a scan that stops above the bifurcation holds no iliac
        raise QualityError(f"3D segmentation check: the CT ends above the aortic bifurcation, so the iliacs cannot be "
                           f"found: {cut} (see segmentation_qc.png; the scan must reach the pelvis)", qc)
    missing = [vessel for vessel in MAIN_VESSELS if not (labels == vessel).any() or lengths.get(vessel, 0.0) <= 0]
    if missing:     # every missing vessel is named first: a CT that stops above the bifurcation says so
        raise QualityError(f"3D segmentation check: {', '.join(missing)} not found in the CT tree; "
                           f"{_where_aorta_ends(centerline)} (see segmentation_qc.png; give an aorta_mask to override)", qc)
    report = {}
    for vessel in MAIN_VESSELS:
        length = lengths[vessel]
        lo, hi = LENGTH_RANGE_MM[vessel]
        nodes = centerline.points[labels == vessel]
        where = "LPS ({:.0f}, {:.0f}, {:.0f}) mm".format(*nodes.mean(axis=0))
        if not lo <= length <= hi:
            raise QualityError(f"3D segmentation check: {vessel} is {length:.0f} mm long near {where}, expected "
                               f"{lo:.0f}-{hi:.0f} mm (see segmentation_qc.png)", qc)
        report[vessel] = {"length_mm": length}
        if radii is not None:
            radius = float(np.median(radii[labels == vessel]))
            lo, hi = RADIUS_RANGE_MM[vessel]
            if not lo <= radius <= hi:
                raise QualityError(f"3D segmentation check: {vessel} has a lumen radius of {radius:.1f} mm near "
                                   f"{where}, expected {lo:.0f}-{hi:.0f} mm (see segmentation_qc.png)", qc)
            report[vessel]["radius_mm"] = radius
    return report


def _shift_scores(distance: np.ndarray, uv: np.ndarray, tolerance_px, offsets: np.ndarray) -> np.ndarray:
    """Number of points within their tolerance of the skeleton per shift (du = offsets[i],
    dv = offsets[j]): one look-up per point and shift in a stack of "within tolerance" maps,
    one map per distinct tolerance, a block of du at a time."""
    rows, cols = distance.shape
    tolerance = np.broadcast_to(np.asarray(tolerance_px, dtype=float), (len(uv),))
    levels, level_of_point = np.unique(tolerance, return_inverse=True)
    within = (distance[None] <= levels[:, None, None]).ravel()
    us = np.clip(np.round(uv[:, 0] + offsets[:, None]).astype(int), 0, cols - 1)
    vs = np.clip(np.round(uv[:, 1] + offsets[:, None]).astype(int), 0, rows - 1)
    row_starts = level_of_point * (rows * cols) + vs * cols
    scores = np.empty((len(offsets), len(offsets)), dtype=np.int64)
    block = max(1, 2_000_000 // max(len(offsets) * len(uv), 1))
    for first in range(0, len(offsets), block):
        flat = row_starts[None, :, :] + us[first:first + block, None, :]
        scores[first:first + block] = np.count_nonzero(within[flat], axis=2)
    return scores


def _best_shift_coverage(distance: np.ndarray, uv: np.ndarray, groups: dict, tolerance_px: float,
                         shift_px: float, step_px: float) -> tuple[dict, np.ndarray]:
    """Fraction of each group's points within ``tolerance_px`` of the skeleton, for the shift that
    maximises the overall fraction (an exhaustive search over in-plane translations; of equal
    scores the first in the order du, then dv, both ascending)."""
    offsets = np.arange(-shift_px, shift_px + step_px / 2, step_px)
    rows, cols = distance.shape
    best = np.unravel_index(np.argmax(_shift_scores(distance, uv, tolerance_px, offsets)), (len(offsets),) * 2)
    best_shift = offsets[np.array(best)]
    u = np.clip(np.round(uv[:, 0] + best_shift[0]).astype(int), 0, cols - 1)
    v = np.clip(np.round(uv[:, 1] + best_shift[1]).astype(int), 0, rows - 1)
    close = distance[v, u] <= tolerance_px
    inside = (uv[:, 0] + best_shift[0] >= 0) & (uv[:, 0] + best_shift[0] < cols) & \
             (uv[:, 1] + best_shift[1] >= 0) & (uv[:, 1] + best_shift[1] < rows)
    coverage = {name: float(close[idx & inside].mean()) if (idx & inside).any() else None
                for name, idx in groups.items()}
    return coverage, best_shift


def _prior_reach_small(prior, small_shape, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of a grid reduced by ``factor``: whether it lies in the prior's band (within the
    vessel's radius plus its deformation margin of the projected tree), and that reach in pixels."""
    distance, nearest = prior.rasterise(small_shape, factor)
    nearest = np.maximum(nearest, 0)
    reach = (prior.radii_px[nearest] + prior.margin_px[nearest]) / factor
    return distance <= reach, reach


def _on_prior_pieces(labels: np.ndarray, count: int, prior, factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per piece (8-connected, ``labels`` 1..count): the fraction of its pixels inside the prior's
    band, the fraction of the projected tree's nodes nearest to its pixels that larger pieces
    already reach (a tree broken by bones reaches each stretch once; slabs lying beside a piece
    reach the same stretch again), and its size in pixels."""
    small_shape = tuple(int(round(n / factor)) for n in labels.shape)
    band, _ = _prior_reach_small(prior, small_shape, factor)
    nearest = np.maximum(prior.rasterise(small_shape, factor)[1], 0)
    rows = np.minimum(np.arange(labels.shape[0]) // factor, small_shape[0] - 1)
    cols = np.minimum(np.arange(labels.shape[1]) // factor, small_shape[1] - 1)
    inside = band[np.ix_(rows, cols)]
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    in_band = np.bincount(labels.ravel(), weights=inside.ravel(), minlength=count + 1)[1:]
    where = labels > 0
    pairs = np.unique(labels[where].astype(np.int64) * len(prior.uv) + nearest[np.ix_(rows, cols)][where])
    nodes_of = np.split(pairs % len(prior.uv), np.searchsorted(pairs // len(prior.uv), np.arange(2, count + 1)))
    reached, again = np.zeros(len(prior.uv), dtype=bool), np.zeros(count)
    for piece in np.argsort(-sizes, kind="stable"):
        nodes = nodes_of[piece]
        again[piece] = reached[nodes].mean() if len(nodes) else 0.0
        reached[nodes] = True
    return in_band / np.maximum(sizes, 1), again, sizes


def _prior_covered(mask: np.ndarray, prior, factor: int) -> tuple[float, np.ndarray | None]:
    """Fraction of the projected tree's length inside the frame (its drawn pixels on the grid
    reduced by ``factor``) within its vessel's radius plus deformation margin of ``mask``, and
    the frame pixel (u, v) of the tree farthest from ``mask`` (None when all is covered)."""
    small = ndi.zoom(mask.astype(np.float32), 1.0 / factor, order=1) > 0.25
    _, reach = _prior_reach_small(prior, small.shape, factor)
    drawn = prior.rasterise(small.shape, factor)[0] == 0
    if not drawn.any():
        return 0.0, None
    away = ndi.distance_transform_edt(~small)[drawn]
    covered = away <= reach[drawn]
    if covered.all():
        return 1.0, None
    rows, cols = np.nonzero(drawn)
    farthest = np.argmax(away)
    return float(covered.mean()), (np.array([cols[farthest], rows[farthest]]) + 0.5) * factor - 0.5


def _in_frame(part: np.ndarray, box: tuple, shape) -> np.ndarray:
    """``part`` (of a frame's ``box``) placed in a zero frame of ``shape``."""
    whole = np.zeros(shape, dtype=part.dtype)
    whole[box] = part
    return whole


def _check_one_tree(mask: np.ndarray, prior, qc: QCData | None) -> None:
    """Refuse a mask that is not one vessel tree (:data:`MIN_LARGEST_PIECE`).

    A mask whose largest 8-connected piece holds less than :data:`MIN_LARGEST_PIECE` of it still
    passes as a tree broken by bone edges when the pieces lying along the projected tree (at
    least :data:`ON_PRIOR_PIECE` of their pixels in the prior's band, and at most
    :data:`MAX_REACHED_AGAIN` of their stretch of it reached by larger pieces) hold that
    fraction of the mask and cover at least :data:`MIN_PRIOR_COVERED` of the projected tree's length.
    """
    box = _padded_box(mask, 0)        # the pieces, and their numbers in raster order, of the whole frame
    labels, count = ndi.label(mask[box], structure=np.ones((3, 3), dtype=bool))
    sizes = np.bincount(labels.ravel())[1:]
    if sizes.max() >= MIN_LARGEST_PIECE * sizes.sum():
        return
    labels = _in_frame(labels, box, mask.shape)
    factor = max(1, int(round(max(mask.shape) / 256)))
    in_band, again, sizes = _on_prior_pieces(labels, count, prior, factor)
    away, beside = in_band < ON_PRIOR_PIECE, (in_band >= ON_PRIOR_PIECE) & (again > MAX_REACHED_AGAIN)
    along = ~away & ~beside
    share = float(sizes[along].sum() / sizes.sum())
    start = (f"frame check: the segmented vessels fall apart into {count} pieces (the largest holds "
             f"{100 * sizes.max() / sizes.sum():.0f}%)")
    if share < MIN_LARGEST_PIECE:
        stray = np.flatnonzero(~along)
        biggest = stray[np.argmax(sizes[stray])] + 1
        rows, cols = np.nonzero(labels == biggest)
        raise QualityError(f"{start}: {away.sum()} lie away from the projected tree and {beside.sum()} beside a "
                           f"larger piece on the same stretch of it ({100 * (1 - share):.0f}% of the mask, the "
                           f"largest near pixel (u={cols.mean():.0f}, v={rows.mean():.0f})): not a contrast-filled "
                           f"vessel tree (bones or devices only? see segmentation_qc.png)", qc)
    covered, gap = _prior_covered(np.isin(labels, np.flatnonzero(along) + 1), prior, factor)
    if covered < MIN_PRIOR_COVERED:
        where = "" if gap is None else f" (missing near pixel (u={gap[0]:.0f}, v={gap[1]:.0f}))"
        raise QualityError(f"{start} and those along the projected tree cover {100 * covered:.0f}% of its length, "
                           f"less than {100 * MIN_PRIOR_COVERED:.0f}%{where}: not a contrast-filled vessel tree "
                           f"(bones or devices only? see segmentation_qc.png)", qc)


def _median_reordering(values: np.ndarray):
    """``np.median`` of a 1-D float array, which it reorders: one partition at the middle, the
    lower middle of an even count being the largest value below it (NaN when any value is NaN)."""
    middle = values.size // 2
    values.partition(middle)
    if np.isnan(values[middle:].max()):
        return values.dtype.type(np.nan)
    if values.size % 2:
        return values[middle]
    return np.mean(np.array([values[:middle].max(), values[middle]], dtype=values.dtype))


#: Radius (pixels) of the 1-pixel Gaussian blur of the noise estimate (SciPy's: 4 sigma).
NOISE_BLUR_RADIUS = 4
#: The noise estimate samples a regular grid of at least this many pixels (stride 1 below it).
NOISE_MIN_SAMPLES = 1 << 16
#: ... and at most every NOISE_MAX_STRIDE-th row and column (1/16 of a large frame's pixels).
NOISE_MAX_STRIDE = 4


def _noise_stride(shape) -> int:
    """Stride of the regular grid the noise is sampled on: as coarse as keeps
    :data:`NOISE_MIN_SAMPLES` pixels, at most :data:`NOISE_MAX_STRIDE`."""
    return int(np.clip(math.isqrt(int(np.prod(shape)) // NOISE_MIN_SAMPLES), 1, NOISE_MAX_STRIDE))


def _detail_on_grid(grey: np.ndarray, stride: int) -> np.ndarray:
    """The frame minus its 1-pixel Gaussian blur (sigma 1, radius :data:`NOISE_BLUR_RADIUS`), on
    every ``stride``-th row and column of the frame's interior (no pixel within the blur's radius
    of the border, so no border rule): the separable blur, each pass only where the next needs it."""
    r = NOISE_BLUR_RADIUS
    weights = np.exp(-0.5 * np.arange(-r, r + 1, dtype=np.float32) ** 2)
    weights /= weights.sum()
    rows, cols = ((n - 2 * r - 1) // stride + 1 for n in grey.shape)
    span_rows, span_cols = stride * (rows - 1) + 1, stride * (cols - 1) + 1
    down = np.zeros((rows, grey.shape[1]), dtype=np.float32)
    for k, w in enumerate(weights):
        down += w * grey[k:k + span_rows:stride]
    blur = np.zeros((rows, cols), dtype=np.float32)
    for k, w in enumerate(weights):
        blur += w * down[:, k:k + span_cols:stride]
    return grey[r:r + span_rows:stride, r:r + span_cols:stride] - blur


def _pixel_noise(grey: np.ndarray) -> float:
    """Robust noise of one pixel: 1.4826 MAD of the frame minus its 1-pixel Gaussian blur, / 0.78.

    The MAD is taken on a regular grid of the frame's interior (:func:`_noise_stride`: 1/16 of
    the pixels of a 1024 x 1024 frame, every interior pixel below 512 x 512): the noise is the frame's,
    not the pixels', and a robust MAD of 65536 pixels is as good as of all (issue 10: the
    full-frame blur and medians cost 30 ms a frame). A frame too small for the blur: every pixel.
    """
    if min(grey.shape) <= 2 * NOISE_BLUR_RADIUS:
        detail = grey - ndi.gaussian_filter(grey, 1.0)
    else:
        detail = _detail_on_grid(grey, _noise_stride(grey.shape))
    detail = detail.ravel()
    centre = _median_reordering(detail)
    np.subtract(detail, centre, out=detail)
    np.abs(detail, out=detail)
    return 1.4826 * float(_median_reordering(detail)) / 0.78 + 1e-6


def block_means(image: np.ndarray, block: int) -> np.ndarray:
    """``image`` averaged over ``block`` x ``block`` pixel blocks (rows and columns beyond the
    last whole block dropped); ``image`` itself, as float32, for ``block`` 1."""
    grey = np.asarray(image, dtype=np.float32)
    if block <= 1:
        return grey
    rows, cols = (n // block * block for n in grey.shape)
    whole = grey[:rows, :cols]
    across = whole[:, 0::block].copy()          # strided sums: 10x faster than a 4D reshape's mean
    for k in range(1, block):
        across += whole[:, k::block]
    down = across[0::block].copy()
    for k in range(1, block):
        down += across[k::block]
    return down * np.float32(1.0 / block ** 2)


def vessel_contrast_to_noise(frame: np.ndarray, mask: np.ndarray, ring_px: int = 6, block: int = 1) -> float:
    """|median inside the mask - median of a ring around it| over the frame's noise at the
    scale of ``block`` x ``block`` pixels (robust: 1.4826 MAD of the difference between the
    block-averaged frame and its 1-pixel Gaussian blur, rescaled to the noise of one block).

    The ring (between 2 and ``ring_px`` dilations of the mask by the 4-neighbour cross: the
    pixels at city-block distance 3 to ``ring_px`` from it) is built in the mask's bounding box
    widened by ``ring_px``: the dilations cannot reach past it. The noise is measured on the
    averaged frame itself, so noise correlated between neighbouring pixels (a real detector's)
    is not taken to average out.
    """
    grey = _grey(frame)
    contrast = _mask_contrast(grey, np.asarray(mask) > 0, ring_px)
    return 0.0 if contrast is None else abs(contrast) / _block_noise(grey, block_means(grey, block), block)


def _mask_contrast(grey: np.ndarray, mask: np.ndarray, ring_px: int) -> float | None:
    """median of ``grey`` inside ``mask`` - median of the ring around it
    (:func:`vessel_contrast_to_noise`), signed; None without a mask or a ring."""
    if not mask.any():
        return None
    box = _padded_box(mask, ring_px)
    steps = ndi.distance_transform_cdt(~mask[box], metric="taxicab")
    ring = (steps > 2) & (steps <= ring_px)
    if not ring.any():
        return None
    values = grey[box]
    return float(np.median(values[mask[box]]) - np.median(values[ring]))


def _block_noise(grey: np.ndarray, blocks: np.ndarray, block: int) -> float:
    """The noise of ``block`` x ``block`` pixel blocks of ``grey`` (their means ``blocks``,
    :func:`block_means`), or of one pixel when the frame is under 4 blocks across."""
    return _pixel_noise(blocks) if min(grey.shape) >= 4 * block else _pixel_noise(grey)


def _working_scale(shape) -> int:
    """Pixels per side of the blocks a frame's vessel tree is judged on: about 256 of them across."""
    return max(1, int(round(max(shape) / 256)))


def _band_contrast(oriented: np.ndarray, rows: np.ndarray, cols: np.ndarray, angle: np.ndarray,
                   radius: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Band contrast across a vessel at centre-line pixels ``rows, cols`` of the working grid (its
    projected direction ``angle`` of (du, dv), its projected ``radius`` R in px of the grid), with
    the centre moved across by each of ``shifts`` (multiples of R/4): the core's mean (within
    :data:`BAND_CORE` R of the centre) less the higher flank's mean (from R + :data:`BAND_GAP` R to
    2 R + :data:`BAND_GAP` R on either side); (n, len(shifts)).

    The profile across is sampled once per centre-line pixel, every R/4, each sample averaged
    along the vessel over +-:data:`BAND_ALONG` R (a disc or an end plate across it is not the
    vessel's edge), bilinearly; core and flanks are its means over their quarter steps."""
    core = np.arange(-round(4 * BAND_CORE), round(4 * BAND_CORE) + 1)
    flank = round(4 * (1.0 + BAND_GAP)) + np.arange(5)
    reach = int(np.abs(shifts).max()) + int(flank[-1])
    profile = _samples_across(oriented, rows, cols, angle, 0.25 * radius, np.arange(-reach, reach + 1)).mean(axis=2)
    centre = reach + np.asarray(shifts, dtype=int)[:, None]

    def mean_over(offsets):
        return profile[:, centre + offsets[None, :]].mean(axis=2)

    return mean_over(core) - np.maximum(mean_over(-flank), mean_over(flank))


def _band_shares(oriented: np.ndarray, rows: np.ndarray, cols: np.ndarray, half_width: np.ndarray, grid_shape,
                 prior, factor: int, shift: np.ndarray, noise: float) -> dict:
    """Per vessel of :data:`BAND_VESSELS` with at least :data:`BAND_MIN_SAMPLES` centre-line pixels
    (of the mask's skeleton pixels ``rows, cols`` on the working grid of ``grid_shape``, those
    nearest to it, within its radius and deformation margin after the in-plane ``shift`` (du, dv)
    of the grid; ``half_width``: the mask's distance to its outside there, :data:`BAND_SPUR`): the
    share of them that are a band centred on the centre line (:func:`_band_contrast`, rule at
    :data:`BAND_OF_BEST`), and the frame pixel (u, v) around which the others lie (None when all are)."""
    from .segmentation.fluoro import _node_directions

    distance, nearest = prior.rasterise(grid_shape, factor)
    at_r = np.clip(np.round(rows - shift[1]).astype(int), 0, grid_shape[0] - 1)
    at_c = np.clip(np.round(cols - shift[0]).astype(int), 0, grid_shape[1] - 1)
    node = np.maximum(nearest[at_r, at_c], 0)
    radius = np.maximum(prior.radii_px[node] / factor, 1.0)
    near = distance[at_r, at_c] <= radius + prior.margin_px[node] / factor
    labels = prior.derived(("label_array",), lambda: np.asarray(prior.labels))
    angles = prior.derived(("node_directions",), lambda: _node_directions(prior))
    beside = np.arange(round(4 * BAND_BESIDE), round(4 * BAND_SEARCH) + 1)        # quarter radii
    shares = {}
    for vessel in BAND_VESSELS:
        on = near & (labels[node] == vessel)
        if on.sum() < BAND_MIN_SAMPLES:
            continue
        on &= half_width >= BAND_SPUR * np.median(half_width[on])
        contrast = _band_contrast(oriented, rows[on], cols[on], angles[node[on]], radius[on],
                                  np.concatenate([[0], beside, -beside]))
        centred = contrast[:, 0]
        band = (centred >= BAND_MIN_NOISE * noise) & (centred >= BAND_OF_BEST * contrast[:, 1:].max(axis=1))
        off = ~band
        where = (np.array([cols[on][off].mean(), rows[on][off].mean()]) + 0.5) * factor - 0.5 if off.any() else None
        filled = _filled_middle(oriented, rows[on], cols[on], angles[node[on]], np.maximum(half_width[on], 1.0))
        shares[vessel] = (float(band.mean()), where, float(filled.mean()))
    return shares


def _filled_middle(oriented: np.ndarray, rows: np.ndarray, cols: np.ndarray, angle: np.ndarray,
                   half_width: np.ndarray) -> np.ndarray:
    """Per centre-line pixel, whether the vessel's middle attenuates more than its rim
    (:data:`FILLED_CORE`, :data:`FILLED_RIM`, in the mask's half-widths across its direction
    ``angle``; each sample averaged along the vessel over +-:data:`BAND_ALONG` of it)."""
    def mean_at(fractions):
        both_sides = np.concatenate([np.asarray(fractions), -np.asarray(fractions)])
        return _samples_across(oriented, rows, cols, angle, half_width, both_sides, along=half_width).mean(axis=(1, 2))

    return mean_at(FILLED_CORE) > mean_at(FILLED_RIM)


def _samples_across(oriented: np.ndarray, rows: np.ndarray, cols: np.ndarray, angle: np.ndarray, step: np.ndarray,
                    offsets: np.ndarray, along: np.ndarray | None = None) -> np.ndarray:
    """Bilinear samples of ``oriented`` across a vessel at centre-line pixels ``rows, cols`` (its
    projected direction ``angle`` of (du, dv)), at ``offsets`` times each pixel's ``step``, each
    also at +-:data:`BAND_ALONG` of ``along`` along the vessel (default: 4 ``step``, the
    radius whose quarter :func:`_band_contrast` steps by); (n, len(offsets), 3): the three
    samples along of each offset."""
    along = 4.0 * step if along is None else along
    across_uv = np.column_stack([-np.sin(angle), np.cos(angle)])          # (du, dv) across the vessel
    along_uv = np.column_stack([np.cos(angle), np.sin(angle)])
    t = step[:, None, None] * np.asarray(offsets)[None, :, None]
    s = BAND_ALONG * along[:, None, None] * np.array([-1.0, 0.0, 1.0])[None, None, :]
    v = rows[:, None, None] + t * across_uv[:, 1, None, None] + s * along_uv[:, 1, None, None]
    u = cols[:, None, None] + t * across_uv[:, 0, None, None] + s * along_uv[:, 0, None, None]
    samples = ndi.map_coordinates(oriented, [v.ravel(), u.ravel()], order=1, mode="nearest")
    return samples.reshape(v.shape)


def dense_side(grey: np.ndarray, mask: np.ndarray) -> int:
    """The display polarity read from the metal around a vessel mask (:data:`METAL_RATIO`): -1
    where the densest thin structures (guidewire, markers) are darker than their surroundings,
    +1 where brighter, 0 when neither side stands out (a subtracted frame, no metal)."""
    dark, bright, floor = _metal_tails(grey, mask)
    if dark >= max(METAL_RATIO * bright, floor):
        return -1
    if bright >= max(METAL_RATIO * dark, floor):
        return 1
    return 0


def _metal_tails(grey: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """(dark, bright, floor) of :func:`dense_side`: the :data:`METAL_TAIL` percentiles, near the
    mask, of the thin structures darker (grey closing less the frame) and brighter (the frame less
    its grey opening) than around them, and :data:`METAL_MIN_NOISE` pixel noises; all on the
    frame smoothed by :data:`METAL_SMOOTH` working-scale blocks in the mask's box widened by the
    reach and the top-hat. The square filters by doubling spans and the cross dilation by shifted
    ORs (:mod:`segmentation.fluoro`) give SciPy's grey and binary morphology to the bit, 5 x faster."""
    from .segmentation.fluoro import _cross_dilation, _local_contrast

    factor = _working_scale(mask.shape)
    box = _padded_box(mask, METAL_REACH * factor + 2 * factor)
    values = ndi.gaussian_filter(np.asarray(grey[box], dtype=np.float32), METAL_SMOOTH * factor)
    near = _cross_dilation(mask[box], METAL_REACH * factor)
    radius = max(1, factor - 1)         # top-hats of 2 f - 1 px (closing less values = white top-hat of -values)
    dark = float(np.percentile(_local_contrast(-values, radius)[near], METAL_TAIL))
    bright = float(np.percentile(_local_contrast(values, radius)[near], METAL_TAIL))
    return dark, bright, METAL_MIN_NOISE * _pixel_noise(values)


def _check_polarity(grey: np.ndarray, mask: np.ndarray, contrast: float, qc: QCData | None,
                    known: int | None = None) -> int:
    """Refuse a mask whose vessels attenuate less than their surroundings (``contrast``: the
    mask's median less its ring's, in the frame's grey) while the metal says which side is
    dense (:func:`dense_side`, or the side ``known`` already: a run's, read on an earlier frame
    of it); returns that side (0: no verdict)."""
    side = dense_side(grey, mask) if known is None else known
    if side * contrast < 0:
        dense, light = ("darker", "brighter") if side < 0 else ("brighter", "darker")
        raise QualityError(f"frame check: the vessels are less dense than their surroundings: air or CO2, not iodine; "
                           f"this product needs an iodine angiogram (the metal, the densest, shows {dense} than "
                           f"around it, the segmented vessels {light} by {abs(contrast):.0f} grey levels; see "
                           f"segmentation_qc.png)", qc)
    return side


def _check_bands(blocks: np.ndarray, noise: float, sign: float, small: np.ndarray, skeleton: np.ndarray, prior,
                 factor: int, shift: np.ndarray, qc: QCData | None) -> tuple[dict, dict]:
    """Refuse a mask whose aorta is not a band centred on its centre line (:data:`MIN_BAND_SHARE`),
    or whose middle is not denser than its rim (:data:`MIN_FILLED_SHARE`, :func:`_filled_middle`):
    a bone's or a soft tissue's edge followed beside the vessel, which the projected tree's
    tolerance lets through (a confident wrong answer). ``blocks``: the frame's ``factor`` x
    ``factor`` block means, ``noise`` theirs, ``sign`` +1 where the masked vessels are brighter
    than around them (-1: darker); ``small``, ``skeleton``: the mask and its skeleton on the
    working grid. Returns ``{vessel: share of its centre line}`` for both rules."""
    oriented = blocks if sign >= 0 else -blocks        # may lack the grid's last partial block: sampled clamped
    box = _padded_box(small, 1)
    rows, cols = np.nonzero(skeleton[box])
    half_width = ndi.distance_transform_edt(small[box])[rows, cols]
    rows, cols = rows + box[0].start, cols + box[1].start
    shares = _band_shares(oriented, rows, cols, half_width, small.shape, prior, factor, shift, noise)
    for vessel, (share, where, filled) in shares.items():
        if filled < MIN_FILLED_SHARE:
            raise QualityError(f"frame check: {vessel} is not filled with contrast: on {100 * (1 - filled):.0f}% of its "
                               f"segmented centre line its walls attenuate more than its middle (a hollow tube: a "
                               f"vessel phantom without contrast?); not a usable angiogram (see segmentation_qc.png)", qc)
        if share < MIN_BAND_SHARE:
            raise QualityError(f"frame check: {vessel} not found as a contrast-filled vessel near pixel (u={where[0]:.0f}, "
                               f"v={where[1]:.0f}): {100 * share:.0f}% of its segmented centre line runs along a band "
                               f"denser than both sides (at least {100 * MIN_BAND_SHARE:.0f}% expected); the rest is a "
                               f"step with one side as dense, or beside such a band: a bone's or soft tissue's edge "
                               f"followed beside the vessel? (see segmentation_qc.png)", qc)
    return {vessel: share for vessel, (share, _, _) in shares.items()}, {vessel: filled for vessel, (_, _, filled) in shares.items()}


def check_frame_mask(mask: np.ndarray, prior, qc: QCData | None = None, *, frame: np.ndarray | None = None,
                     min_fraction: float = MIN_SEEN_FRACTION, tolerance_mm: float | None = None,
                     shift_mm: float = SHIFT_MM, min_cnr: float = MIN_CONTRAST_TO_NOISE,
                     run_dense_side: int | None = None) -> dict:
    """Check that a frame's vessel mask is an angiogram of the projected pre-operative tree.

    The mask must be neither empty nor cover more than :data:`MAX_MASK_FRACTION` of the frame,
    and be one tree rather than scattered pieces (:data:`MIN_LARGEST_PIECE`), or a tree broken
    by bone edges into pieces that lie along the projected tree and cover most of it
    (:func:`_check_one_tree`);
    with the ``frame``, the masked vessels must stand out of the noise at the scale the tree is
    segmented and judged on (:func:`_working_scale`: contrast to the noise of 4 x 4 pixel blocks
    of a 1024 x 1024 frame at least ``min_cnr``; noise and blank frames do not, while a low-dose
    subtracted frame of a wide vessel does); after the in-plane shift (up
    to ``shift_mm``) that best lays the projected tree onto the mask's skeleton, at least
    ``min_fraction`` of each main vessel projected inside the frame must lie within
    ``tolerance_mm`` of the skeleton (default: the vessel's expected deformation,
    :data:`DEFORMATION_MARGIN_MM`; rigid alignment, translations only: the pose is refined
    later, this is only a plausibility check). With the ``frame``, finally, the mask's aorta
    must run along a contrast-filled band, denser than both sides and centred on the mask, on
    at least :data:`MIN_BAND_SHARE` of its centre line (:func:`_check_bands`): a mask that
    follows a vertebral column's edge beside the aorta lies within its tolerance but along a
    step (issue 11: a confident wrong answer on unsubtracted frames); and, where metal around
    the mask shows which side of the grey scale is dense (:func:`dense_side`), the masked
    vessels must lie on that side of their surroundings (:func:`_check_polarity`: an air- or
    CO2-filled lumen is a negative angiogram, which either display polarity would otherwise
    let through).

    Parameters
    ----------
    mask : numpy.ndarray of bool
    prior : segmentation.FluoroPrior
    qc : QCData, optional
    run_dense_side : {-1, 1}, optional
        The display's dense side when it is known already (a run's, read by :func:`dense_side`
        on an earlier frame of the same run: the display does not change within a run): the
        polarity rule uses it instead of reading the frame's metal again.

    Returns
    -------
    dict
        ``{"coverage": {vessel: fraction}, "shift_px": [du, dv]}``; with the ``frame`` also
        ``"band_share"`` and ``"filled_share"``: ``{vessel: fraction}`` (:func:`_check_bands`),
        and ``"dense_side"`` (:func:`dense_side`: -1 dense is dark, +1 bright, 0 no verdict).

    Raises
    ------
    QualityError
    """
    from skimage.morphology import skeletonize

    mask = np.asarray(mask) > 0
    fraction = float(mask.mean()) if mask.size else 0.0
    if not mask.any():
        raise QualityError("frame check: no vessel found in the frame (not a usable angiogram: blank, noise, "
                           "no contrast, or bones or devices only; see segmentation_qc.png)", qc)
    if fraction > MAX_MASK_FRACTION:
        raise QualityError(f"frame check: the vessel mask covers {100 * fraction:.0f}% of the frame (noise, not an "
                           f"angiogram; see segmentation_qc.png)", qc)
    _check_one_tree(mask, prior, qc)
    factor = _working_scale(mask.shape)
    if frame is not None:      # at the scale the segmentation works on (a 1024 frame: 4 x 4 pixel blocks)
        grey = _grey(frame)
        blocks = block_means(grey, factor)
        noise = _block_noise(grey, blocks, factor)
        contrast = _mask_contrast(grey, mask, 6)
        cnr = 0.0 if contrast is None else abs(contrast) / noise
        if cnr < min_cnr:
            raise QualityError(f"frame check: the segmented vessels do not stand out of the noise (contrast to noise "
                               f"{cnr:.1f} < {min_cnr:.1f}): not a usable angiogram (see segmentation_qc.png)", qc)
    px_per_mm = float(np.median(prior.px_per_mm))
    small = ndi.zoom(mask.astype(np.float32), 1.0 / factor, order=1) > 0.25
    skeleton = skeletonize(small)
    distance = ndi.distance_transform_edt(~skeleton)
    uv = (prior.uv + 0.5) / factor - 0.5
    labels = np.asarray(prior.labels)
    groups = {vessel: labels == vessel for vessel in MAIN_VESSELS if (labels == vessel).any()}
    tolerance = np.array([tolerance_mm if tolerance_mm is not None else DEFORMATION_MARGIN_MM.get(label, 20.0)
                          for label in labels]) * px_per_mm / factor
    coverage, shift = _best_shift_coverage(distance, uv, groups, tolerance, shift_mm * px_per_mm / factor,
                                           max(1.0, 2.0 * px_per_mm / factor))
    for vessel, seen in coverage.items():
        if seen is not None and seen < min_fraction:
            u, v = prior.uv[groups[vessel]].mean(axis=0)
            within = tolerance_mm if tolerance_mm is not None else DEFORMATION_MARGIN_MM.get(vessel, 20.0)
            raise QualityError(f"frame check: {vessel} not found in the frame near pixel (u={u:.0f}, v={v:.0f}): "
                               f"{100 * seen:.0f}% of its projection lies within {within:.0f} mm of the "
                               f"segmented vessels (see segmentation_qc.png)", qc)
    report = {"coverage": coverage, "shift_px": (shift * factor).tolist()}
    if frame is not None:
        report["band_share"], report["filled_share"] = _check_bands(blocks, noise, float(np.sign(contrast)), small,
                                                                    skeleton, prior, factor, shift, qc)
        report["dense_side"] = _check_polarity(grey, mask, contrast, qc, run_dense_side)
    return report


def _ct_panels(fig, grid, ct: Volume, lumen: Volume | None):
    import matplotlib.pyplot as plt

    array = np.asarray(ct.array)
    flip = (lambda image: image[::-1]) if ct.direction[1, 1] < 0 else (lambda image: image)
    mask = np.asarray(lumen.array) > 0 if lumen is not None else None
    if mask is not None and mask.any():
        ks = np.nonzero(mask.any(axis=(1, 2)))[0]
        picks = [int(ks[len(ks) // 6]), int(ks[len(ks) // 2]), int(ks[5 * len(ks) // 6])]
    else:
        picks = [array.shape[0] // 4, array.shape[0] // 2, 3 * array.shape[0] // 4]
    for n, k in enumerate(picks):
        ax = fig.add_subplot(grid[n])
        ax.imshow(flip(np.clip(array[k], -200, 600)), cmap="gray")
        if mask is not None and mask[k].any():
            ax.contour(flip(mask[k]), [0.5], colors="red", linewidths=0.8)
        ax.set_title(f"CT slice {k}", fontsize=8)
        ax.axis("off")
    ax = fig.add_subplot(grid[3])
    ax.imshow(np.clip(array.max(axis=1), -200, 1200), cmap="gray", origin="lower" if ct.direction[2, 2] > 0 else "upper",
              aspect=ct.spacing[2] / ct.spacing[0])
    if mask is not None and mask.any():
        ax.contour(mask.any(axis=1), [0.5], colors="red", linewidths=0.8)
    ax.set_title("coronal MIP, lumen in red", fontsize=8)
    ax.axis("off")
    plt.setp(ax.spines.values(), visible=False)


def _grey(frame: np.ndarray) -> np.ndarray:
    """The frame as one grey image (a multi-frame run's first frame, colour averaged)."""
    grey = np.asarray(frame, dtype=np.float32)
    if grey.ndim == 3 and grey.shape[-1] not in (3, 4):
        grey = grey[0]
    return grey[..., :3].mean(axis=-1) if grey.ndim == 3 else grey


def _frame_panel(ax, grey: np.ndarray, mask2d, prior, registered=None, heading: str = "frame") -> None:
    ax.imshow(grey, cmap="gray")
    if mask2d is not None and np.asarray(mask2d).any():
        ax.contour(np.asarray(mask2d) > 0, [0.5], colors="red", linewidths=0.6)
    if prior is not None:
        for a, b in prior.edges:
            ax.plot(prior.uv[[a, b], 0], prior.uv[[a, b], 1], color=PALETTE["preop"], linewidth=0.8)
    title = f"{heading}: mask red" + (", projected pre-op tree orange" if prior is not None else "")
    if registered is not None:
        uv, edges = registered
        for a, b in edges:
            ax.plot(uv[[a, b], 0], uv[[a, b], 1], color=PALETTE["deformed"], linewidth=0.8)
        title += ", registered cyan"
    ax.set_xlim(0, grey.shape[1])
    ax.set_ylim(grey.shape[0], 0)
    ax.set_title(title, fontsize=8)
    ax.axis("off")


def _frame_panels(qc: QCData) -> list:
    """The frame panels' arguments (:func:`_frame_panel`): the frame as given, and beside it,
    when the mirror test refused it, the frame flipped left-right with the tree registered there."""
    if qc.frame is None:
        return []
    grey = _grey(qc.frame)
    panels = [(grey, qc.mask2d, qc.prior, qc.registered, "frame as given" if qc.flipped is not None else "frame")]
    if qc.flipped is not None:
        mask = None if qc.mask2d is None else np.asarray(qc.mask2d)[:, ::-1]
        panels.append((grey[:, ::-1], mask, qc.prior, qc.flipped, "frame flipped left-right"))
    return panels


def write_segmentation_qc(path, qc: QCData, message: str | None = None) -> Path:
    """Write the QC picture (PNG, atomically): CT slices + MIP with the lumen, the frame with the
    mask and the projected tree, and ``message`` (the gate's verdict) as the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.gridspec import GridSpec

    path = Path(path)
    frames = _frame_panels(qc)
    if qc.ct is not None:
        fig = plt.figure(figsize=(15 + 4.5 * (len(frames) - 1), 4.2))
        grid = GridSpec(1, 5 + len(frames), figure=fig, width_ratios=[1, 1, 1, 1, 0.05] + [1.6] * len(frames))
        _ct_panels(fig, [grid[0, n] for n in range(4)], qc.ct, qc.lumen)
        places, width = [grid[0, 5 + k] for k in range(len(frames))], 190
    else:       # the frame alone (a case given as masks): no empty CT panels beside it
        fig = plt.figure(figsize=(7 * max(1, len(frames)), 7.5))
        places, width = [(1, len(frames), k + 1) for k in range(len(frames))], 85 * max(1, len(frames))
    for place, panel in zip(places, frames):
        _frame_panel(fig.add_subplot(*place) if isinstance(place, tuple) else fig.add_subplot(place), *panel)
    title = textwrap.fill(message, width) if message else "segmentation passed the quality gate"
    fig.suptitle(title, fontsize=9, color="darkred" if message else "black")
    fig.subplots_adjust(top=0.88 - 0.05 * title.count("\n"))      # a long verdict wraps above the panels
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return path

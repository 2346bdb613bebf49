"""CT without learning: trace the aorta slice by slice, grow the lumen, follow the branches.

One file, about 900 lines, on purpose: the seed search, the aorta trace, the bifurcation, the
iliac traces and the branch growing all work on the same in-slice helpers (the disc box around
a traced centre, the smoothed window, the blob tests against bone, the flap bridging), and
splitting them would leave each half importing most of the other.

What real aortas add to a clean lumen, and how the route copes (each built as a CT stressor
in :mod:`..phantom.stressors` and tested in ``Testing/test_ct_stressors.py``):

- a dissection flap splits the lumen into two channels, neither round nor aorta-sized: seeds
  are also looked for with thin dark lines closed (:func:`_bridge_thin_gaps`), the trace reads
  a narrowing slice again with the flap bridged inside the last cross-section, and only the
  downward trace takes two separate lumens of similar size for the bifurcation;
- a seed on something else that is round and bright (a vertebral body between two discs, a
  bowel loop) traces short: the next seed is tried (:data:`MIN_AORTA_TRACE_MM`);
- an enhancing IVC is as round and bright as the aorta: seeds with the spine well to their
  left come last (:data:`IVC_SPINE_OFFSET_MM`);
- metal struts and calcified plaque are above the lumen's HU range (the seed's statistics,
  capped below cortical bone) and stay out of it;
- a neighbour touching the wall (heart, vein, bowel, bone) makes the cross-section jump in
  area: it is cut back to the traced disc (:data:`MAX_AREA_JUMP`);
- contrast fades along the aorta (late-arterial or slow-flow timing, a false lumen feeding the
  abdomen): each trace re-estimates its lumen range from its last cross-sections (a running
  median and MAD, :func:`_lumen_range_of`, never below :data:`LUMEN_FLOOR_HU`), the branches
  are thresholded against the traced level at their height (:func:`_lumen_profile`), and a
  lumen fading below :data:`MIN_LUMEN_HU` is refused (no contrast route separates it from
  soft tissue);
- a chest-abdomen-pelvis field of view (the ascending aorta, the arch, the heart, the pulmonary
  arteries, the neck's arteries, a bright superior vena cava): seeds below the diaphragm come
  first (:func:`chest_slices`: lungs in the slice), the upward trace stops where the aorta
  turns into the arch (:data:`TURN_WINDOW_MM`, :data:`MAX_TURN_SLOPE`; a slice-by-slice trace
  that ran on would follow the arch sideways and the ascending aorta down into the heart), and
  no side branch is grown in the chest (there the branch growing took the arch and the neck's
  arteries on the phantoms; on a real dissected chest CT such a mask, spread in the thorax,
  gave the 3D gate an aorta 1449 mm long). The traced aorta is one cross-section per slice,
  and above the seed its slope stays below :data:`MAX_TURN_SLOPE`: it cannot loop. FEVAR's
  region, the coeliac trunk to the iliacs, is what the route delivers;
- a thin flap sampled by a coarse grid and smoothed with noise dips below soft tissue: it is
  bridged down to :data:`FLAP_MIN_HU` (fat, the gap to a neighbour, stays open);
- an aorta lost in the abdomen (the downward trace ends without the bifurcation well above
  the scan's lower end, :data:`MAX_UNTRACED_BELOW_MM`) is refused in one line naming where.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy import ndimage as ndi
from skimage import measure

from ..io import Volume
from ..quality import QCData, QualityError
from .threshold import _bounding_box, _check_ct, postprocess_mask


#: Lumen radii (mm) a traced aorta may have, and the HU window of contrast-filled blood used
#: to find it before the seed's own statistics are known.
AORTA_RADIUS_MM = (7.0, 22.0)
CONTRAST_HU = (150.0, 600.0)
#: Cortical bone: denser than any contrast lumen.
BONE_HU = 700.0
#: Soft tissue around the vessels; the lumen edge is taken half way between it and the lumen.
SOFT_TISSUE_HU = 40.0
#: Smallest radius (mm) of a traced common iliac, and the scales (mm) of the branch vesselness.
ILIAC_MIN_RADIUS_MM = 2.5
BRANCH_SIGMAS_MM = (1.5, 2.5, 4.0)
#: How far (mm along the branch) a branch may reach from the aorta or iliacs.
BRANCH_REACH_MM = 70.0
#: Thin dark lines inside a lumen (a dissection flap) up to about twice this width (mm) are bridged.
FLAP_BRIDGE_MM = 1.5
#: A bridged flap pixel is at least this dense (HU): a thin flap sampled by a coarse grid and
#: smoothed with noise dips below soft tissue, but not down to fat (the gap to a neighbour).
FLAP_MIN_HU = 0.0
#: A traced aorta shorter than this (mm along z, or half the scan's height if that is less) is not
#: the aorta (a vertebral body between two discs, a bowel loop): the next seed is tried.
MIN_AORTA_TRACE_MM = 60.0
#: A seed blob with the spine's bone centroid this far (mm) to its left lies where the IVC runs.
IVC_SPINE_OFFSET_MM = 12.0
#: A scan in which under this fraction of the voxels is cortical bone (:data:`BONE_HU`) has no
#: skeleton: a vessel phantom (a silicone or printed aorta in water or air, as on a bench), where
#: no spine lies behind the aorta to confirm it. A patient's lumbar spine and pelvis take several
#: per cent of an abdominal scan; one vertebral body in a tight field of view about 1 %.
BONELESS_FRACTION = 1e-3
#: How many distinct seeds are tried before the CT is refused.
MAX_SEED_TRIES = 5
#: A traced cross-section more than this many times the area of the one before is a leak into a
#: neighbour (heart, vein, bowel, bone) and is cut back to the traced disc.
MAX_AREA_JUMP = 1.25
#: A lumen whose running median falls below this (HU; soft tissue is 40-80) cannot be told from
#: soft tissue by its enhancement: the trace stops there and the CT is refused.
MIN_LUMEN_HU = 100.0
#: The lumen range's lower bound never drops below this (HU), whatever the lumen's level.
LUMEN_FLOOR_HU = 0.5 * (MIN_LUMEN_HU + SOFT_TISSUE_HU)
#: The lumen range of a trace is re-estimated from its last this many traced slices.
RUNNING_SLICES = 6
#: Over this much height (mm), an upward aorta trace whose centre moves further sideways than
#: :data:`MAX_TURN_SLOPE` times that height has entered the arch (the descending aorta is close
#: to vertical; the arch turns forwards and back down into the ascending aorta): it stops there.
TURN_WINDOW_MM, MAX_TURN_SLOPE = 20.0, 1.0
#: An axial slice whose lungs (air enclosed by the body) cover at least this fraction of the
#: body's cross-section is in the chest: the heart and pulmonary vessels lie there, FEVAR's
#: region (coeliac trunk to iliacs) does not. Seeds there come last; no side branch is grown there.
CHEST_LUNG_FRACTION = 0.15
#: A downward aorta trace that ends this far (mm) above the scan's lower end without the
#: iliac bifurcation has lost the aorta in the abdomen: the CT is refused, naming where.
MAX_UNTRACED_BELOW_MM = 40.0


def _slice_axes_mm(ct: Volume) -> tuple[float, float]:
    """In-plane spacing (row = j, column = i) in mm."""
    return float(ct.spacing[1]), float(ct.spacing[0])


def _posterior_sign_j(ct: Volume) -> float:
    """+1 when increasing j goes posterior (towards +y in LPS), else -1 (or 0 if oblique)."""
    return float(np.sign(ct.direction[1, 1]))


def _left_sign_i(ct: Volume) -> float:
    """+1 when increasing i goes to the patient's left (towards +x in LPS), else -1 (or 0 if oblique)."""
    return float(np.sign(ct.direction[0, 0]))


def chest_slices(ct: Volume, lung_fraction: float = CHEST_LUNG_FRACTION, step_mm: float = 4.0) -> np.ndarray:
    """Boolean per axial slice: True where the lungs cover at least ``lung_fraction`` of the
    body's cross-section (the chest above the diaphragm).

    The body is what is denser than -500 HU with its enclosed holes filled; the lungs are the
    air inside it. Computed on slices subsampled to about ``step_mm`` in plane (the lungs are
    large), every slice. Only the run of such slices that begins with the most superior one
    is the chest (the lungs run down from the top to the diaphragm): gas-filled bowel lower
    down, enclosed by the body too, is not.
    """
    spacing_ji = _slice_axes_mm(ct)
    stride = tuple(max(1, int(round(step_mm / s))) for s in spacing_ji)
    chest = np.zeros(ct.shape[0], dtype=bool)
    for k in range(ct.shape[0]):
        hu = np.asarray(ct.array[k, ::stride[0], ::stride[1]])
        body = ndi.binary_fill_holes(hu > -500.0)
        area = int(body.sum())
        lungs = int((body & (hu <= -500.0)).sum())
        chest[k] = area > 0 and lungs >= lung_fraction * area
    return _run_from_the_top(chest, ct.superior_step)


def _run_from_the_top(flags: np.ndarray, up: int) -> np.ndarray:
    """``flags`` kept only in the run of consecutive True slices that holds the most superior
    True slice (``up``: +1 when increasing k goes superior)."""
    ordered = flags[::-1] if up > 0 else flags           # from the top down
    if not ordered.any():
        return np.zeros_like(flags)
    first = int(np.argmax(ordered))
    end = first + int(np.argmin(np.append(ordered[first:], False)))
    kept = np.zeros_like(ordered)
    kept[first:end] = True
    return kept[::-1] if up > 0 else kept


def _spine_to_the_left_mm(hu_slice: np.ndarray, centre_ji, radius_mm: float, spacing_ji, posterior: float,
                          left: float, reach_mm: float = 60.0, half_width_mm: float = 50.0) -> float:
    """How far (mm) the cortical bone behind a blob lies to the patient's left of it (centroid).

    The abdominal aorta runs in front of the vertebral body or left of it, the IVC right of it:
    a bright round tube with the spine well to its left is the IVC (the same size and, in a
    venous or late phase, as bright as the aorta). 0 when the axes are oblique or no bone is seen.
    """
    if posterior == 0 or left == 0:
        return 0.0
    j0, i0 = centre_ji
    start = j0 + posterior * radius_mm / spacing_ji[0]
    stop = start + posterior * reach_mm / spacing_ji[0]
    rows = slice(int(max(min(start, stop), 0)), int(min(max(start, stop) + 1, hu_slice.shape[0])))
    half = int(round(half_width_mm / spacing_ji[1]))
    first = int(max(i0 - half, 0))
    cols = np.nonzero(hu_slice[rows, first:int(min(i0 + half + 1, hu_slice.shape[1]))] > BONE_HU)[1]
    if len(cols) < 3:
        return 0.0
    return float((cols.mean() + first - i0) * spacing_ji[1] * left)


def _round_blobs(hu_slice: np.ndarray, spacing_ji, hu_window, radius_mm) -> list[dict]:
    """Round bright blobs of one axial slice: centre (j, i), inscribed radius (mm), circle score.

    The circle score is the area of the inscribed disc over the blob's area (1 for a disc,
    small for an elongated or branched blob) times the blob's solidity. The blobs of the slice
    with thin dark lines closed (:func:`_bridge_thin_gaps`) are listed too: a lumen split by a
    dissection flap is one round blob again.
    """
    lo, hi = hu_window
    smooth = ndi.gaussian_filter(hu_slice.astype(np.float32), 0.7 / np.asarray(spacing_ji))
    inside = ndi.binary_opening((smooth >= lo) & (smooth <= hi), iterations=1)
    blobs = _blobs_of(inside, smooth, spacing_ji, radius_mm)
    bridged = _bridge_thin_gaps(inside, spacing_ji)      # a lumen split by a flap is one round blob again
    if (bridged != inside).any():
        blobs += _blobs_of(bridged, smooth, spacing_ji, radius_mm)
    return blobs


def _disc_element(radius_mm: float, spacing_ji) -> np.ndarray:
    """A boolean disc of ``radius_mm`` (at least 1.5 pixels: the 3 x 3 square) on the slice's pixel grid."""
    radius_mm = max(radius_mm, 1.5 * max(spacing_ji))
    half = np.ceil(radius_mm / np.asarray(spacing_ji)).astype(int)
    rows, cols = np.ogrid[-half[0]:half[0] + 1, -half[1]:half[1] + 1]
    return np.hypot(rows * spacing_ji[0], cols * spacing_ji[1]) <= radius_mm


def _bridge_thin_gaps(inside: np.ndarray, spacing_ji, width_mm: float = FLAP_BRIDGE_MM) -> np.ndarray:
    """``inside`` with dark lines narrower than about 2 ``width_mm`` closed (binary closing)."""
    element = _disc_element(width_mm, spacing_ji)
    pad = max(element.shape)
    closed = ndi.binary_closing(np.pad(inside, pad), structure=element)[pad:-pad, pad:-pad]
    return closed | inside


def _blobs_of(inside: np.ndarray, smooth: np.ndarray, spacing_ji, radius_mm) -> list[dict]:
    """The blobs of one thresholded slice whose inscribed radius lies in ``radius_mm`` (see :func:`_round_blobs`)."""
    labels, n = ndi.label(inside)
    if n == 0:
        return []
    pixel_mm2 = spacing_ji[0] * spacing_ji[1]
    min_px = math.pi * radius_mm[0] ** 2 / pixel_mm2
    max_px = 4.0 * math.pi * radius_mm[1] ** 2 / pixel_mm2
    blobs = []
    for region in measure.regionprops(labels, intensity_image=smooth):
        if not min_px <= region.area <= max_px:
            continue
        r0, c0, r1, c1 = region.bbox
        edt = ndi.distance_transform_edt(np.pad(region.image, 1), sampling=spacing_ji)[1:-1, 1:-1]
        radius = float(edt.max())
        if not radius_mm[0] <= radius <= radius_mm[1]:
            continue
        peak = np.unravel_index(np.argmax(edt), edt.shape)
        disc_fraction = math.pi * radius ** 2 / (region.area * pixel_mm2)
        blobs.append({"centre": np.array([r0 + peak[0], c0 + peak[1]], dtype=float), "radius": radius,
                      "score": min(disc_fraction, 1.0) * region.solidity, "hu": float(region.intensity_mean)})
    return blobs


def _spine_behind(hu_slice: np.ndarray, centre_ji, radius_mm: float, spacing_ji, posterior: float,
                  reach_mm: float = 45.0, half_width_mm: float = 12.0) -> bool:
    """True if cortical bone lies within ``reach_mm`` posterior of a blob's edge (a vertebra)."""
    if posterior == 0:
        return True
    j0, i0 = centre_ji
    start = j0 + posterior * radius_mm / spacing_ji[0]
    stop = start + posterior * reach_mm / spacing_ji[0]
    rows = slice(int(max(min(start, stop), 0)), int(min(max(start, stop) + 1, hu_slice.shape[0])))
    half = int(round(half_width_mm / spacing_ji[1]))
    cols = slice(int(max(i0 - half, 0)), int(min(i0 + half + 1, hu_slice.shape[1])))
    strip = hu_slice[rows, cols]
    return strip.size > 0 and bool((strip > BONE_HU).sum() >= 3)


def _inside_bone(hu_slice: np.ndarray, centre_ji, radius_mm: float, spacing_ji, ring_mm: float = 4.0,
                 max_fraction: float = 0.25) -> bool:
    """True if a ring just outside the blob is largely cortical bone, or if the blob brightens
    towards its edge (a vertebral body's cancellous core is as bright and as round as the aorta,
    but the aorta is never walled by bone; blurred, a thin cortex falls below :data:`BONE_HU`
    and joins the blob, whose edge is then brighter than its middle, while a lumen fades
    towards its wall)."""
    reach = radius_mm + ring_mm
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int) + 1
    lo = np.maximum(np.floor(centre_ji).astype(int) - half, 0)
    hi = np.minimum(np.floor(centre_ji).astype(int) + half + 1, hu_slice.shape)
    rows, cols = np.ogrid[lo[0]:hi[0], lo[1]:hi[1]]
    dist = np.hypot((rows - centre_ji[0]) * spacing_ji[0], (cols - centre_ji[1]) * spacing_ji[1])
    ring = (dist > radius_mm + 0.5) & (dist <= reach)
    if not ring.any():
        return False
    window = hu_slice[lo[0]:hi[0], lo[1]:hi[1]]
    shell = (dist > radius_mm - ring_mm) & (dist <= radius_mm)
    middle = dist <= max(radius_mm - ring_mm, 0.5 * radius_mm)
    walled = bool(shell.any() and middle.any() and np.median(window[shell]) > np.median(window[middle]))
    return walled or bool((window[ring] > BONE_HU).mean() > max_fraction)


def find_aorta_in_slices(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, step_mm: float = 5.0):
    """The best aorta cross-section of the CT: a bright round blob in front of the spine.

    Axial slices every ``step_mm`` are searched for round blobs inside ``hu_window`` with an
    inscribed radius in ``radius_mm`` and cortical bone behind them (the vertebral body);
    the blob with the best circle score wins (:func:`aorta_seed_candidates` lists them all).

    Returns
    -------
    (k, centre_ji, radius_mm, score) or None
    """
    candidates = aorta_seed_candidates(ct, hu_window=hu_window, radius_mm=radius_mm, step_mm=step_mm)
    return candidates[0] if candidates else None


def is_boneless(ct: Volume, fraction: float = BONELESS_FRACTION) -> bool:
    """True for a scan without a skeleton (under ``fraction`` of its voxels denser than
    :data:`BONE_HU`, counted on every second voxel): a vessel phantom, not a patient."""
    sample = np.asarray(ct.array[::2, ::2, ::2])
    return bool(np.count_nonzero(sample > BONE_HU) < fraction * sample.size)


def aorta_seed_candidates(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, step_mm: float = 5.0,
                          chest: np.ndarray | None = None, need_spine: bool | None = None) -> list:
    """Every aorta-like cross-section of :func:`find_aorta_in_slices`, best circle score first,
    those in the chest (:func:`chest_slices`: the heart, the pulmonary trunk, the ascending
    aorta and the arch are as round and bright, and a dissected or late-phase aorta is brightest
    there) after those below the diaphragm, and those with the spine more than
    :data:`IVC_SPINE_OFFSET_MM` to their left (the IVC's place, :func:`_spine_to_the_left_mm`)
    after all others. ``need_spine``: a blob must have a vertebral body behind it; by default
    unless the scan has no bone at all (:func:`is_boneless`: a vessel phantom).

    Returns
    -------
    list of (k, centre_ji, radius_mm, score)
    """
    spacing_ji = _slice_axes_mm(ct)
    posterior, left = _posterior_sign_j(ct), _left_sign_i(ct)
    need_spine = not is_boneless(ct) if need_spine is None else need_spine
    step = max(1, int(round(step_mm / ct.spacing[2])))
    found, right_of_spine = [], []
    for k in range(step // 2, ct.shape[0], step):
        hu_slice = np.asarray(ct.array[k])
        for blob in _round_blobs(hu_slice, spacing_ji, hu_window, radius_mm):
            if need_spine and not _spine_behind(hu_slice, blob["centre"], blob["radius"], spacing_ji, posterior):
                continue
            if _inside_bone(hu_slice, blob["centre"], blob["radius"], spacing_ji):
                continue
            spine_left = _spine_to_the_left_mm(hu_slice, blob["centre"], blob["radius"], spacing_ji, posterior, left)
            found.append((k, blob["centre"], blob["radius"], blob["score"]))
            right_of_spine.append(spine_left > IVC_SPINE_OFFSET_MM)
    in_chest = chest_slices(ct) if chest is None else chest
    order = sorted(range(len(found)), key=lambda n: (right_of_spine[n], bool(in_chest[found[n][0]]), -found[n][3]))
    return [found[n] for n in order]


class _Trace:
    """One vessel followed through the axial slices: centre (j, i) and radius (mm) per slice."""

    def __init__(self, name: str, k: int, centre, radius: float, step: int, min_radius: float, lumen_hu,
                 recent=()):
        self.name, self.step, self.min_radius = name, step, min_radius
        self.centres = {k: np.asarray(centre, dtype=float)}
        self.radii = {k: float(radius)}
        self.k, self.centre, self.radius = k, np.asarray(centre, dtype=float), float(radius)
        self.previous = None        # (cross-section mask, its (row, col) offset) in the last slice
        self.lumen_hu = tuple(lumen_hu)             # the lumen range now, re-estimated as the trace goes
        self.ranges = {k: self.lumen_hu}            # the range used in each traced slice
        self.recent = deque(recent, maxlen=RUNNING_SLICES)   # (median, MAD) of the last cross-sections' cores
        self.faded = None           # (k, lumen HU) where the lumen fell below MIN_LUMEN_HU
        self.turned = None          # the slice where an upward aorta trace entered the arch

    def take_level(self, k: int, hu_slice: np.ndarray, mask: np.ndarray, offset, centre, radius: float,
                   spacing_ji) -> None:
        """Add the core of the cross-section just traced in slice ``k`` to the running estimate
        and re-estimate the lumen range (:func:`_lumen_range_of`); mark the trace faded when
        the running median falls below :data:`MIN_LUMEN_HU`."""
        rows, cols = np.nonzero(mask)
        core = np.hypot((rows + offset[0] - centre[0]) * spacing_ji[0],
                        (cols + offset[1] - centre[1]) * spacing_ji[1]) <= 0.6 * radius
        if core.sum() < 3:
            return
        values = hu_slice[rows[core] + offset[0], cols[core] + offset[1]].astype(np.float64)
        median = float(np.median(values))
        self.recent.append((median, float(np.median(np.abs(values - median)))))
        level = float(np.median([m for m, _ in self.recent]))
        spread = 1.4826 * float(np.median([d for _, d in self.recent]))
        self.lumen_hu = _lumen_range_of(level, spread)
        if level < MIN_LUMEN_HU and len(self.recent) == RUNNING_SLICES:
            self.faded = (k, level)


def _lumen_in_slice(hu_slice: np.ndarray, centre, radius: float, spacing_ji, lumen_hu, min_radius: float,
                    max_growth: float = 1.45, previous=None, reference_radius: float | None = None,
                    detect_split: bool = True):
    """The lumen cross-section continuing a trace into the next slice (:func:`_lumen_cross_section`).

    Where the lumen seems to narrow, split or end, a thin dark line inside the traced disc
    may be a dissection flap: the slice is read again with such lines bridged
    (:func:`_bridge_thin_gaps`, within 0.85 ``radius`` and within the last cross-section less
    its rim, down to half way between the lumen's lower bound and soft tissue: a false lumen
    fills later), and that reading is kept if it is wider (or the plain one ended) and keeps
    the trace's width (0.6 of it, as a plain reading must). Where the plain reading saw two
    separate lumens of similar size (:func:`_two_separate_lumens`: a bifurcation, or a flap
    through the middle) it must restore 0.85 of it: two channels bridged are one round lumen
    nearly as wide as the aorta, two iliacs bridged at the crotch are not.
    """
    args = (hu_slice, centre, radius, spacing_ji, lumen_hu, min_radius, max_growth, previous, reference_radius)
    plain = _lumen_cross_section(*args, detect_split, bridge=False)
    width = (reference_radius or radius)
    if plain is not None and plain[0] is not None and plain[3] >= 0.85 * width:
        return plain
    bridged = _lumen_cross_section(*args, False, bridge=True)     # read as one lumen: no split
    if bridged is None or bridged[0] is None:
        return plain
    ended = plain is None or plain[0] is None
    two_alike = ended and plain is not None and _two_separate_lumens(plain[4], spacing_ji)
    wider = ended or bridged[3] >= plain[3] + 0.5 * min(spacing_ji)
    if wider and bridged[3] >= (0.85 if two_alike else 0.6) * min(width, radius):
        return bridged
    return plain


def _lumen_cross_section(hu_slice: np.ndarray, centre, radius: float, spacing_ji, lumen_hu, min_radius: float,
                         max_growth: float = 1.45, previous=None, reference_radius: float | None = None,
                         detect_split: bool = True, bridge: bool = False):
    """One reading of the lumen cross-section continuing a trace into the next slice.

    Pixels within ``lumen_hu`` (after a light smoothing) in a window around the predicted
    ``centre`` are labelled; the components touching the predicted core (a disc of 0.6
    ``radius``) form the candidate, clipped to ``max_growth`` ``radius`` + 2 mm. Its inscribed
    radius and the position of that maximum give the new radius and centre.

    Returns
    -------
    (mask, offset, centre, radius, split) or None
        ``mask`` is the cross-section in a window starting at ``offset`` (row, col);
        ``split`` lists (centre, radius) of the blobs the lumen split into when it is
        much narrower than before (the bifurcation).
    """
    reach = radius * max_growth + 12.0
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int)
    lo_ji = np.maximum(np.floor(centre).astype(int) - half, 0)
    hi_ji = np.minimum(np.floor(centre).astype(int) + half + 1, hu_slice.shape)
    window = hu_slice[lo_ji[0]:hi_ji[0], lo_ji[1]:hi_ji[1]].astype(np.float32)
    if min(window.shape) < 3:
        return None
    smooth = ndi.gaussian_filter(window, 0.6 / np.asarray(spacing_ji))
    inside = (smooth >= lumen_hu[0]) & (smooth <= lumen_hu[1])
    rows, cols = np.ogrid[:window.shape[0], :window.shape[1]]
    local = centre - lo_ji
    dist = np.hypot((rows - local[0]) * spacing_ji[0], (cols - local[1]) * spacing_ji[1])
    if bridge:      # a flap inside the traced lumen joins the two channels; gaps to neighbours at the wall stay open
        zone = dist <= 0.85 * max(radius, reference_radius or 0.0)     # the trace's typical width: a channel
        if previous is not None:        # the last cross-section less its rim (the wall): both channels
            before = _paste(previous[0], previous[1] - lo_ji, window.shape)
            zone |= ndi.binary_erosion(before, structure=_disc_element(FLAP_BRIDGE_MM, spacing_ji))
        dimmer = (smooth >= 0.5 * (lumen_hu[0] + SOFT_TISSUE_HU)) & (smooth <= lumen_hu[1])   # a false lumen
        inside |= _bridge_thin_gaps(dimmer, spacing_ji) & zone & (smooth >= FLAP_MIN_HU)     # a flap: soft tissue, not fat
    labels, _ = ndi.label(inside)
    core = dist <= 0.6 * radius
    if previous is not None:        # overlap with the last cross-section counts as well
        core |= _paste(previous[0], previous[1] - lo_ji, window.shape)
    touching = np.unique(labels[core & inside])
    touching = touching[touching > 0]
    if len(touching) == 0:      # the lumen left the predicted core: ended, or split into two
        near = np.unique(labels[(dist <= radius) & inside])
        candidate = np.isin(labels, near[near > 0]) & (dist <= max_growth * radius + 2.0)
        if not candidate.any():
            return None
        edt = ndi.distance_transform_edt(candidate, sampling=spacing_ji)
        return None, lo_ji, None, float(edt.max()), _split_blobs(candidate, edt, lo_ji, spacing_ji, ILIAC_MIN_RADIUS_MM)
    candidate = np.isin(labels, touching) & (dist <= max_growth * radius + 2.0)
    edt = ndi.distance_transform_edt(candidate, sampling=spacing_ji)
    new_radius = float(edt.max())
    split = _split_blobs(candidate, edt, lo_ji, spacing_ji, ILIAC_MIN_RADIUS_MM) if detect_split else []
    if _two_separate_lumens(split, spacing_ji):     # two lumens of similar size: a bifurcation
        return None, lo_ji, None, new_radius, split
    if new_radius < min_radius:
        return None
    if new_radius < 0.6 * (reference_radius or radius):
        return None, lo_ji, None, new_radius, _split_blobs(candidate, edt, lo_ji, spacing_ji, ILIAC_MIN_RADIUS_MM)
    own = np.where(dist <= max(radius, 2.0 * max(spacing_ji)), edt, 0.0)   # this vessel's centre, not a neighbour's
    peak = np.array(np.unravel_index(np.argmax(own), own.shape), dtype=float)
    new_radius = float(own.max()) if own.max() >= min_radius else new_radius
    new_dist = np.hypot((rows - peak[0]) * spacing_ji[0], (cols - peak[1]) * spacing_ji[1])
    mask = candidate & (new_dist <= 1.25 * new_radius + 1.5)
    if previous is not None and mask.sum() > MAX_AREA_JUMP * previous[0].sum():   # a sudden area jump: a leak
        mask &= new_dist <= 1.05 * new_radius + 1.0
    return mask, lo_ji, peak + lo_ji, new_radius, []


def _two_separate_lumens(split: list, spacing_ji) -> bool:
    """True for two (centre, radius) lumens of similar size (radius ratio >= 0.7) at least 0.8
    times the sum of their radii apart, as :func:`_two_lumens` asks of the iliacs (two maxima
    along the ridge of one flattened lumen are not two lumens)."""
    if len(split) != 2:
        return False
    (c0, r0), (c1, r1) = split
    apart = float(np.hypot(*((np.asarray(c0) - np.asarray(c1)) * np.asarray(spacing_ji))))
    return r1 >= 0.7 * r0 and apart >= 0.8 * (r0 + r1)


def _paste(mask: np.ndarray, offset, shape) -> np.ndarray:
    """``mask`` placed at ``offset`` (row, col) in an empty array of ``shape`` (clipped)."""
    out = np.zeros(shape, dtype=bool)
    r0, c0 = int(offset[0]), int(offset[1])
    rs, cs = max(r0, 0), max(c0, 0)
    re, ce = min(r0 + mask.shape[0], shape[0]), min(c0 + mask.shape[1], shape[1])
    if re > rs and ce > cs:
        out[rs:re, cs:ce] = mask[rs - r0:re - r0, cs - c0:ce - c0]
    return out


def _split_blobs(candidate, edt, offset, spacing_ji, min_radius: float) -> list:
    """(centre, radius) of the (at most two) widest separate lumens in ``candidate``: maxima of the
    distance map at least ``min_radius`` deep and two radii apart (the two iliacs below the
    bifurcation, still joined by partial volume or already apart)."""
    from skimage.feature import peak_local_max

    min_distance = max(1, int(round(2 * min_radius / max(spacing_ji))))
    peaks = peak_local_max(edt, min_distance=min_distance, threshold_abs=min_radius, num_peaks=2,
                           exclude_border=False)
    return [(np.asarray(p, dtype=float) + offset, float(edt[tuple(p)])) for p in peaks]


def _follow(trace: _Trace, ct: Volume, out: np.ndarray, label: int, progress=None, check_turn: bool = False) -> list:
    """Extend ``trace`` slice by slice until the lumen ends; paint it into ``out``.

    Radius continuity (the new radius between 0.6 and ``max_growth`` times the last one,
    smoothed) keeps the trace out of the heart, the arch's far side and side branches. Only
    the downward aorta trace looks for the bifurcation (two separate lumens of similar size):
    going up, two such lumens are the channels of a dissection, never a split.
    The lumen range is the trace's running estimate (:meth:`_Trace.take_level`); the trace
    stops where the lumen has faded below :data:`MIN_LUMEN_HU`. With ``check_turn`` (the
    upward aorta trace) it stops where the aorta turns into the arch (:func:`_turning`), cut
    back to where the turn began (``trace.turned``): a slice-by-slice trace must not run
    along the arch, nor down the ascending aorta into the heart.
    Returns the blobs the lumen split into where it stopped (for the iliacs), else [].
    """
    spacing_ji = _slice_axes_mm(ct)
    k = trace.k + trace.step
    while 0 <= k < ct.shape[0] and trace.faded is None:
        recent = [trace.radii[j] for j in sorted(trace.radii, key=lambda j: -abs(j - k))[-15:]]
        hu_slice = np.asarray(ct.array[k])
        found = _lumen_in_slice(hu_slice, trace.centre, trace.radius, spacing_ji, trace.lumen_hu,
                                trace.min_radius, previous=trace.previous, reference_radius=float(np.median(recent)),
                                detect_split=trace.name == "aorta" and trace.step != ct.superior_step)
        if found is None:
            return []
        mask, offset, centre, radius, split = found
        if mask is None:
            return [(k, c, r) for c, r in split]
        view = out[k, offset[0]:offset[0] + mask.shape[0], offset[1]:offset[1] + mask.shape[1]]
        view[mask & (view == 0)] = label
        trace.centres[k], trace.radii[k], trace.ranges[k] = centre, radius, trace.lumen_hu
        trace.take_level(k, hu_slice, mask, offset, centre, radius, spacing_ji)
        trace.previous = (mask, offset)
        trace.centre = centre
        trace.radius = 0.7 * trace.radius + 0.3 * radius
        trace.k = k
        if progress is not None:
            progress()
        if check_turn and _turning(trace, ct):
            trace.turned = k - trace.step * _slices_in(ct, TURN_WINDOW_MM)
            _cut_trace_below(trace, trace.turned, out)
            return []
        k += trace.step
    return []


def _slices_in(ct: Volume, height_mm: float) -> int:
    """How many axial slices span ``height_mm`` (at least one)."""
    return max(1, int(round(height_mm / float(ct.spacing[2]))))


def _turning(trace: _Trace, ct: Volume) -> bool:
    """True when the trace's centre moved sideways more than :data:`MAX_TURN_SLOPE` times the
    height it climbed over the last :data:`TURN_WINDOW_MM` (the arch, where the aorta turns
    forwards: a slice-by-slice trace there runs along the arch in the axial plane)."""
    n = _slices_in(ct, TURN_WINDOW_MM)
    earlier = trace.k - trace.step * n
    if earlier not in trace.centres:
        return False
    moved = (trace.centres[trace.k] - trace.centres[earlier]) * np.asarray(_slice_axes_mm(ct))
    return float(np.hypot(*moved)) > MAX_TURN_SLOPE * n * float(ct.spacing[2])


def trace_aorta(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, progress=None,
                chest: np.ndarray | None = None):
    """Find the aorta and follow it up and down the CT, then the common iliacs below it.

    The seeds of :func:`aorta_seed_candidates` are tried best first (at most
    :data:`MAX_SEED_TRIES`, skipping seeds inside the footprint of one already rejected): the
    first whose trace runs at least :data:`MIN_AORTA_TRACE_MM` (or half the scan's height) is
    the aorta; a shorter trace is a vertebral body between two discs or a bowel loop.

    Raises
    ------
    quality.QualityError
        "no aorta found: ..." (one line, an :class:`InputError`: exit code 2) when no seed
        qualifies; its QC data show the CT with the rejected traces. "contrast too faint: ..."
        when the aorta's lumen fades below :data:`MIN_LUMEN_HU` along the trace. "aorta lost in
        the abdomen: ..." when the downward trace ends without the bifurcation more than
        :data:`MAX_UNTRACED_BELOW_MM` above the scan's lower end.

    Returns
    -------
    labels : numpy.ndarray of uint8
        1 = aorta lumen, 2 = iliac lumen, per slice (no side branches yet).
    traces : list of _Trace
    lumen_hu : numpy.ndarray, shape (n_slices, 2)
        The lumen intensity range per axial slice (:func:`_lumen_profile`): each trace's
        running estimate where it ran, interpolated between.
    """
    chest = chest_slices(ct) if chest is None else chest
    need_spine = not is_boneless(ct)
    where = "in front of the spine" if need_spine else "(a scan without bone, a vessel phantom: no spine needed)"
    candidates = aorta_seed_candidates(ct, hu_window=hu_window, radius_mm=radius_mm, chest=chest,
                                       need_spine=need_spine)
    if not candidates:
        raise QualityError(f"no aorta found: no round blob of {radius_mm[0]:.0f}-{radius_mm[1]:.0f} mm radius in "
                           f"HU {hu_window[0]:.0f}-{hu_window[1]:.0f} {where} in any axial slice", QCData(ct=ct))
    counter = _SliceCounter(ct.shape[0], progress)
    needed = min(MIN_AORTA_TRACE_MM, 0.5 * ct.shape[0] * ct.spacing[2])
    rejected = np.zeros(ct.shape[1:], dtype=bool)       # in-plane footprint of the seeds' traces that were too short
    tried, longest, shown = 0, 0.0, np.zeros(ct.shape, dtype=bool)
    for k0, centre, radius, _ in candidates:
        if rejected[tuple(np.round(centre).astype(int))]:
            continue
        if tried == MAX_SEED_TRIES:
            break
        tried += 1
        attempt = _trace_from_seed(ct, k0, centre, radius, radius_mm, counter)
        if attempt is None:
            continue
        labels, traces = attempt
        traced = np.nonzero((labels == 1).any(axis=(1, 2)))[0]
        length = float(np.ptp(traced) + 1) * float(ct.spacing[2])
        if length >= needed:
            _refuse_a_faded_lumen(ct, traces, labels)
            iliacs = _trace_iliacs(ct, traces, labels, counter)
            if not iliacs:
                _refuse_an_aorta_lost_above_the_scan_end(ct, traces[1], labels)
            return labels, traces + iliacs, _lumen_profile(ct, traces + iliacs)
        rejected |= ndi.binary_dilation((labels == 1).any(axis=0), iterations=2)
        longest = max(longest, length)
        shown |= labels == 1
    raise QualityError(f"no aorta found: the {tried} best round bright blobs {where} trace at most "
                       f"{longest:.0f} mm along the body, an aorta at least {needed:.0f} mm (vertebral bodies or bowel?)",
                       QCData(ct=ct, lumen=ct.with_array(shown)))


def _refuse_a_faded_lumen(ct: Volume, traces: list, labels: np.ndarray) -> None:
    """Raise a one-line QualityError if an aorta trace stopped where the lumen faded below
    :data:`MIN_LUMEN_HU` (an iliac trace fading out just ends there)."""
    for trace in traces:
        if trace.faded is not None:
            k, level = trace.faded
            z = float(ct.index_to_lps(np.array([k, 0.0, 0.0]))[2])
            raise QualityError(f"contrast too faint: the {trace.name} lumen fades to {level:.0f} HU at z = {z:.0f} mm, "
                               f"below the {MIN_LUMEN_HU:.0f} HU a contrast route can tell from soft tissue "
                               f"({SOFT_TISSUE_HU:.0f}-80 HU); rescan with arterial timing or segment by hand",
                               QCData(ct=ct, lumen=ct.with_array(labels > 0)))


def _untraced_below_mm(ct: Volume, down: _Trace) -> tuple[int, float]:
    """The downward trace's last slice and how far (mm) the scan runs on below it."""
    k_end = min(down.centres, key=lambda k: -k * down.step)
    k_scan_end = ct.shape[0] - 1 if down.step > 0 else 0
    return k_end, abs(k_scan_end - k_end) * float(ct.spacing[2])


def _refuse_an_aorta_lost_above_the_scan_end(ct: Volume, down: _Trace, labels: np.ndarray) -> None:
    """Raise a one-line QualityError if the downward aorta trace ended, without the iliac
    bifurcation, more than :data:`MAX_UNTRACED_BELOW_MM` above the scan's lower end: the aorta
    was lost in the abdomen (FEVAR's region), not cut by the field of view."""
    k_end, untraced = _untraced_below_mm(ct, down)
    if untraced > MAX_UNTRACED_BELOW_MM:
        z = float(ct.index_to_lps(np.array([k_end, 0.0, 0.0]))[2])
        raise QualityError(f"aorta lost in the abdomen: the trace stops at z = {z:.0f} mm, {untraced:.0f} mm above the "
                           f"scan's lower end, without reaching the iliac bifurcation (lumen "
                           f"{down.lumen_hu[0]:.0f}-{down.lumen_hu[1]:.0f} HU there); segment by hand",
                           QCData(ct=ct, lumen=ct.with_array(labels > 0)))


def _lumen_profile(ct: Volume, traces: list) -> np.ndarray:
    """The lumen range (lo, hi) per axial slice: the widest of the traces' ranges in each traced
    slice, linearly interpolated between traced slices and held constant beyond them."""
    lo, hi = {}, {}
    for trace in traces:
        for k, (a, b) in trace.ranges.items():
            lo[k], hi[k] = min(lo.get(k, a), a), max(hi.get(k, b), b)
    ks = np.array(sorted(lo))
    every = np.arange(ct.shape[0])
    return np.column_stack([np.interp(every, ks, [lo[k] for k in ks]), np.interp(every, ks, [hi[k] for k in ks])])


def _trace_from_seed(ct: Volume, k0: int, centre, radius: float, radius_mm, counter):
    """The aorta traced up and down from one seed cross-section: (labels, [up, down traces]),
    or None if the seed blob does not hold the lumen intensity taken from it."""
    lumen_hu = _lumen_range(np.asarray(ct.array[k0]), centre, radius, _slice_axes_mm(ct))
    first = _lumen_in_slice(np.asarray(ct.array[k0]), centre, radius, _slice_axes_mm(ct), lumen_hu, radius_mm[0])
    if first is None or first[0] is None:
        return None
    labels = np.zeros(ct.shape, dtype=np.uint8)
    mask, offset, centre, radius, _ = first
    labels[k0, offset[0]:offset[0] + mask.shape[0], offset[1]:offset[1] + mask.shape[1]][mask] = 1
    up = ct.superior_step
    traces = []
    for step in (up, -up):
        trace = _Trace("aorta", k0, centre, radius, step, radius_mm[0] * 0.6, lumen_hu)
        trace.take_level(k0, np.asarray(ct.array[k0]), mask, offset, centre, radius, _slice_axes_mm(ct))
        traces.append(trace)
        _follow(trace, ct, labels, 1, counter, check_turn=step == up)
    return labels, traces


def _trace_iliacs(ct: Volume, traces_of_aorta: list, labels: np.ndarray, counter) -> list:
    """The common iliacs from where the downward aorta trace (the second of ``traces_of_aorta``)
    splits; the aorta trace is cut there and the crotch filled. Returns the iliac traces, which
    start from the aorta's lumen range at its lower end."""
    down = traces_of_aorta[1]
    lumen_hu = down.lumen_hu
    seeds = _bifurcation(ct, down, lumen_hu, distal_radius=_distal_radius(traces_of_aorta))
    if not seeds and _untraced_below_mm(ct, down)[1] > MAX_UNTRACED_BELOW_MM:
        # the trace ran on down one iliac (the other left it gradually, never as a second lumen of
        # its cross-section) and lost it: its typical radius is the iliac's, so look again from
        # where the upper half of the downward trace, or of the whole traced aorta (a seed just
        # above the bifurcation), last had the aorta's own width
        for traces in ([down], traces_of_aorta):
            seeds = _bifurcation(ct, down, lumen_hu, distal_radius=_distal_radius(traces_of_aorta),
                                 typical=_upper_half_radius(traces, down.step))
            if seeds:
                break
    if seeds:
        _cut_trace_below(down, seeds[0][0], labels)
        _fill_crotch(ct, down, seeds[0][0], lumen_hu, labels)
    iliacs = []
    for k, c, r in seeds:
        iliac = _Trace("iliac", k - down.step, c, r, down.step, ILIAC_MIN_RADIUS_MM, lumen_hu, down.recent)
        iliacs.append(iliac)
        _follow(iliac, ct, labels, 2, counter)
    return iliacs


def _disc_box(ct: Volume, centre, reach: float):
    """The in-slice box ``[lo, hi)`` around ``centre`` (j, i) that holds a disc of ``reach`` mm, and the disc in it."""
    spacing_ji = _slice_axes_mm(ct)
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int)
    lo = np.maximum(np.floor(centre).astype(int) - half, 0)
    hi = np.minimum(np.floor(centre).astype(int) + half + 1, ct.shape[1:])
    rows, cols = np.ogrid[lo[0]:hi[0], lo[1]:hi[1]]
    disc = np.hypot((rows - centre[0]) * spacing_ji[0], (cols - centre[1]) * spacing_ji[1]) <= reach
    return lo, hi, disc


def _smoothed_window(ct: Volume, k: int, lo, hi) -> np.ndarray:
    """Slice ``k`` of the CT inside the box ``[lo, hi)``, lightly smoothed (0.6 mm Gaussian)."""
    spacing_ji = _slice_axes_mm(ct)
    return ndi.gaussian_filter(np.asarray(ct.array[k, lo[0]:hi[0], lo[1]:hi[1]], dtype=np.float32),
                               0.6 / np.asarray(spacing_ji))


def _two_lumens(ct: Volume, k: int, centre, radius: float, lumen_hu) -> list:
    """The two common iliacs in slice ``k`` just below an aortic cross-section (``centre``,
    ``radius`` in the slice above), or [].

    Two distance-map maxima of the lumen near the aorta, each at least ILIAC_MIN_RADIUS_MM
    deep and at most 0.9 ``radius``, of similar size (ratio >= 0.7: the common iliacs are
    nearly symmetric, a visceral or renal branch beside the aorta is not), at least 0.8 times the
    sum of their radii apart (two lumens, not one flattened one), and both inside the aortic
    cross-section above (+ 3 mm): the iliacs come out of the aorta, a neighbour (IVC, SMA) does not.
    """
    from skimage.feature import peak_local_max

    spacing_ji = _slice_axes_mm(ct)
    lo, hi, disc = _disc_box(ct, centre, 1.6 * radius + 8.0)
    window = _smoothed_window(ct, k, lo, hi)
    edt = ndi.distance_transform_edt((window >= lumen_hu[0]) & (window <= lumen_hu[1]) & disc, sampling=spacing_ji)
    min_distance = max(1, int(round(2 * ILIAC_MIN_RADIUS_MM / max(spacing_ji))))
    peaks = peak_local_max(edt, min_distance=min_distance, threshold_abs=ILIAC_MIN_RADIUS_MM, num_peaks=2,
                           exclude_border=False)
    if len(peaks) < 2:
        return []
    radii = edt[tuple(peaks.T)]
    centres = peaks.astype(float) + lo
    apart = np.hypot(*((peaks[0] - peaks[1]) * np.asarray(spacing_ji)))
    from_aorta = np.hypot(*((centres - centre) * np.asarray(spacing_ji)).T)
    if (apart >= 0.8 * radii.sum() and radii.min() >= 0.7 * radii.max() and radii.max() <= 0.9 * radius
            and np.all(from_aorta <= radius + 3.0)):
        return [(k, c, float(r)) for c, r in zip(centres, radii)]
    return []


def _distal_radius(traces_of_aorta: list, n_slices: int = 10) -> float:
    """Median traced aortic radius over the ``n_slices`` lowest traced slices (both traces: a
    seed near the bifurcation leaves the downward trace only a slice or two, at the crotch)."""
    radii = {}
    for trace in traces_of_aorta:
        radii.update(trace.radii)
    down = traces_of_aorta[1].step
    lowest = sorted(radii, key=lambda k: -k * down)[:n_slices]
    return float(np.median([radii[k] for k in lowest]))


def _upper_half_radius(traces: list, down: int) -> float:
    """Median radius over the upper half of the slices ``traces`` ran through (``down``: the
    slice step towards the feet)."""
    radii = {}
    for trace in traces:
        radii.update(trace.radii)
    ks = sorted(radii, key=lambda k: k * down)
    return float(np.median([radii[k] for k in ks[:max(1, len(ks) // 2)]]))


def _bifurcation(ct: Volume, aorta: _Trace, lumen_hu, search_mm: float = 30.0, tolerance_mm: float = 10.0,
                 distal_radius: float = 0.0, typical: float | None = None) -> list:
    """Where the downward aorta trace splits into the common iliacs, or [].

    The split lies near or below the last slice where the trace still had the aorta's width
    (beyond it the trace may have followed one iliac): from ``tolerance_mm`` above that slice
    down to the trace's end, the first traced slice whose next slice holds :func:`_two_lumens`;
    else the first such slice within ``search_mm`` below that last full-width slice or below
    the trace's end. An aorta that keeps its width to the end of the scan has no split. The
    aortic radius each test uses is at least ``distal_radius`` (:func:`_distal_radius`); the
    aorta's full width is 0.85 of ``typical`` (default: the median over the whole trace).

    Returns
    -------
    list of (k, centre_ji, radius_mm), two entries or none
    """
    ks = sorted(aorta.centres, key=lambda k: k * aorta.step)
    typical = float(np.median([aorta.radii[k] for k in ks])) if typical is None else typical
    wide = [k for k in ks if aorta.radii[k] >= 0.85 * typical] or ks[:1]
    k_wide = wide[-1]     # the last slice of full aortic width
    first = k_wide - aorta.step * int(round(tolerance_mm / ct.spacing[2]))
    for k in ks:
        below = k + aorta.step
        if (k - first) * aorta.step >= 0 and 0 <= below < ct.shape[0]:
            found = _two_lumens(ct, below, aorta.centres[k], max(aorta.radii[k], distal_radius), lumen_hu)
            if found:
                return found
    for k_ref in dict.fromkeys((k_wide, ks[-1])):
        for n in range(1, int(search_mm / ct.spacing[2]) + 1):
            below = k_ref + n * aorta.step
            if not 0 <= below < ct.shape[0]:
                break
            found = _two_lumens(ct, below, aorta.centres[k_ref], max(aorta.radii[k_ref], distal_radius), lumen_hu)
            if found:
                return found
    return []


def _fill_crotch(ct: Volume, aorta: _Trace, k_split: int, lumen_hu, labels: np.ndarray) -> None:
    """Label as iliac (2) the lumen between the aorta's last slice and the slice where the two
    iliacs are first apart (the crotch), within the aorta's reach, so the tree stays connected."""
    k_last = max(aorta.centres, key=lambda k: k * aorta.step)
    centre, radius = aorta.centres[k_last], aorta.radii[k_last]
    lo, hi, disc = _disc_box(ct, centre, 1.45 * radius + 2.0)
    for k in range(k_last + aorta.step, k_split + aorta.step, aorta.step):
        window = _smoothed_window(ct, k, lo, hi)
        view = labels[k, lo[0]:hi[0], lo[1]:hi[1]]
        view[(window >= lumen_hu[0]) & (window <= lumen_hu[1]) & disc & (view == 0)] = 2


def _cut_trace_below(trace: _Trace, k_cut: int, labels: np.ndarray) -> None:
    """Forget the part of a downward trace at and beyond slice ``k_cut`` (it followed one iliac)."""
    for k in [k for k in trace.centres if (k - k_cut) * trace.step >= 0]:
        labels[k][labels[k] == 1] = 0
        del trace.centres[k], trace.radii[k]


class _SliceCounter:
    """Calls ``progress(done, total)`` once per traced slice (capped at ``total``)."""

    def __init__(self, total: int, progress):
        self.total, self.progress, self.done = total, progress, 0

    def __call__(self):
        self.done = min(self.done + 1, self.total)
        if self.progress is not None:
            self.progress(self.done, self.total)


def _lumen_range(hu_slice: np.ndarray, centre, radius: float, spacing_ji) -> tuple[float, float]:
    """Lumen HU range from the seed disc (:func:`_lumen_range_of` its median and spread)."""
    rows, cols = np.ogrid[:hu_slice.shape[0], :hu_slice.shape[1]]
    disc = np.hypot((rows - centre[0]) * spacing_ji[0], (cols - centre[1]) * spacing_ji[1]) <= 0.6 * radius
    values = hu_slice[disc].astype(np.float64)
    return _lumen_range_of(float(np.median(values)), float(np.std(values)))


def _lumen_range_of(level: float, spread: float) -> tuple[float, float]:
    """Lumen HU range around a lumen ``level`` with noise ``spread`` (HU): from half way to soft
    tissue (never below :data:`LUMEN_FLOOR_HU`) up to ``level`` + max(4 ``spread``, 250),
    capped below bone."""
    lo = max(0.5 * (level + SOFT_TISSUE_HU), LUMEN_FLOOR_HU)
    hi = min(level + max(4.0 * spread, 250.0), BONE_HU + 200.0)
    return lo, hi


def _coarse_factor(ct: Volume, target_mm: float) -> np.ndarray:
    """Integer (k, j, i) block sizes bringing the voxels near ``target_mm``."""
    spacing_kji = np.asarray(ct.spacing, dtype=float)[::-1]
    return np.maximum(1, np.round(target_mm / spacing_kji)).astype(int)


def _block_reduce(array: np.ndarray, factor, func) -> np.ndarray:
    """``func`` (np.mean / np.max) over ``factor`` blocks, the array cropped to whole blocks."""
    factor = tuple(int(f) for f in factor)
    shape = tuple(s // f for s, f in zip(array.shape, factor))
    cropped = array[:shape[0] * factor[0], :shape[1] * factor[1], :shape[2] * factor[2]]
    blocks = cropped.reshape(shape[0], factor[0], shape[1], factor[1], shape[2], factor[2])
    return func(blocks, axis=(1, 3, 5))


def _trunk_box(labels: np.ndarray, ct: Volume, margin_mm: float) -> tuple[slice, ...]:
    """Index box of the traced lumen grown by ``margin_mm`` in plane and along z."""
    box = _bounding_box(labels > 0)
    margins = np.ceil(margin_mm / np.asarray(ct.spacing)[::-1]).astype(int)
    return tuple(slice(max(b.start - m, 0), min(b.stop + m, n)) for b, m, n in zip(box, margins, labels.shape))


def _symmetric_eigenvalues_3d(hxx, hyy, hzz, hxy, hxz, hyz) -> np.ndarray:
    """Eigenvalues of symmetric 3x3 matrices given by their six fields, sorted by absolute value
    (|l1| <= |l2| <= |l3|), in closed form (trigonometric solution of the characteristic cubic)."""
    q = (hxx + hyy + hzz) / 3.0
    p1 = hxy ** 2 + hxz ** 2 + hyz ** 2
    p2 = (hxx - q) ** 2 + (hyy - q) ** 2 + (hzz - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0) + 1e-12
    bxx, byy, bzz = (hxx - q) / p, (hyy - q) / p, (hzz - q) / p
    det = (bxx * (byy * bzz - (hyz / p) ** 2) - (hxy / p) * ((hxy / p) * bzz - (hyz / p) * (hxz / p))
           + (hxz / p) * ((hxy / p) * (hyz / p) - byy * (hxz / p)))
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    e1 = q + 2.0 * p * np.cos(phi)
    e3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    values = np.stack([e1, e2, e3])
    order = np.argsort(np.abs(values), axis=0)
    return np.take_along_axis(values, order, axis=0)


def tubularity_3d(volume: np.ndarray, sigmas_vox, *, blob_beta: float = 0.5) -> np.ndarray:
    """Bright-tube response of a 3D array, maximum over scales (Sato / Frangi family).

    At each scale the Hessian of the Gaussian-smoothed volume (finite differences) gives
    eigenvalues ``|l1| <= |l2| <= |l3|``; a bright tube has ``l2, l3 < 0`` and ``l1 ~ 0``. The
    response is ``sigma^2 (-l2)`` where ``l2, l3 < 0``, damped by ``exp(-(l1 / l2)^2 / (2
    blob_beta^2))`` when ``l1 < 0`` too (a blob: kidney, heart chamber, bowel loop).
    """
    volume = np.asarray(volume, dtype=np.float32)
    best = np.zeros_like(volume)
    for sigma in sigmas_vox:
        smooth = ndi.gaussian_filter(volume, sigma, mode="nearest")
        gk, gj, gi = np.gradient(smooth)
        hkk, hkj, hki = np.gradient(gk)
        hjj, hji = np.gradient(gj, axis=(1, 2))
        hii = np.gradient(gi, axis=2)
        l1, l2, l3 = _symmetric_eigenvalues_3d(hii, hjj, hkk, hji, hki, hkj)
        tube = (l2 < 0) & (l3 < 0)
        blob = np.where(l1 < 0, np.exp(-(l1 / np.where(l2 == 0, -1e-12, l2)) ** 2 / (2 * blob_beta ** 2)), 1.0)
        np.maximum(best, np.where(tube, sigma ** 2 * -l2 * blob, 0.0).astype(np.float32), out=best)
    return best


def _connected_to(seeds: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """The face-connected components of ``allowed`` that hold a seed."""
    components, _ = ndi.label(allowed)
    hit = np.unique(components[seeds & allowed])
    return np.isin(components, hit[hit > 0])


def geodesic_reach(seeds: np.ndarray, allowed: np.ndarray, spacing_kji, reach_mm: float) -> np.ndarray:
    """Voxels of ``allowed`` within ``reach_mm`` of ``seeds`` along a path inside ``allowed``.

    Connectivity is by faces (a branch must touch, not merely graze, the next voxel); the path
    length is measured in millimetres, as the shortest path through the 26-neighbour graph of
    the connected voxels with each step weighted by its length in mm (so a branch running
    obliquely, or along the slices of an anisotropic CT, reaches as far as a straight one: a
    count of face steps would charge it up to sqrt(3) times its length).

    Parameters
    ----------
    seeds, allowed : numpy.ndarray of bool, same shape (k, j, i)
    spacing_kji : sequence of 3 floats
        Voxel size in mm along (k, j, i).
    reach_mm : float

    Returns
    -------
    numpy.ndarray of bool
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    inside = _connected_to(seeds, allowed)
    n = int(inside.sum())
    if n == 0:
        return inside
    index = np.full(inside.shape, -1, dtype=np.int64)
    index[inside] = np.arange(n)
    rows, cols, weights = [], [], []
    spacing = np.asarray(spacing_kji, dtype=float)
    for offset in _half_neighbourhood():
        src = tuple(slice(max(-o, 0), s - max(o, 0)) for o, s in zip(offset, inside.shape))
        dst = tuple(slice(max(o, 0), s - max(-o, 0)) for o, s in zip(offset, inside.shape))
        a, b = index[src], index[dst]
        both = (a >= 0) & (b >= 0)
        rows.append(a[both])
        cols.append(b[both])
        weights.append(np.full(int(both.sum()), float(np.linalg.norm(np.asarray(offset) * spacing))))
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    distance = dijkstra(graph, directed=False, indices=index[seeds & inside], min_only=True, limit=reach_mm)
    out = np.zeros(inside.shape, dtype=bool)
    out[inside] = distance <= reach_mm
    return out


def _half_neighbourhood() -> list:
    """The 13 offsets of the 26-neighbourhood with a positive first non-zero component."""
    offsets = [(dk, dj, di) for dk in (-1, 0, 1) for dj in (-1, 0, 1) for di in (-1, 0, 1)]
    return [o for o in offsets if next((c for c in o if c), 0) > 0]


def grow_branches(ct: Volume, trunk: np.ndarray, lumen_hu, *, sigmas_mm=BRANCH_SIGMAS_MM,
                  reach_mm: float = BRANCH_REACH_MM, voxel_mm: float = 1.5, min_vesselness: float = 0.04,
                  excluded_slices: np.ndarray | None = None):
    """Side branches (renal, visceral, iliac continuations) connected to the traced trunk.

    On a copy reduced to about ``voxel_mm`` voxels around the trunk, bright tubular voxels
    (:func:`tubularity_3d` over ``sigmas_mm`` above ``min_vesselness`` of the lumen contrast, inside
    ``lumen_hu`` (one (lo, hi) pair, or one per axial slice: the traced aorta's level at that
    height), away from cortical bone) are kept if they connect to the trunk within
    ``reach_mm`` (path length in mm through the candidates, :func:`geodesic_reach`); round blobs (kidneys, heart, bowel)
    respond weakly to the tubular filter and stay out. No branch is grown in the axial slices
    flagged in ``excluded_slices`` (the chest: the arch, ascending aorta and pulmonary arteries
    are tubes too). The result is brought back to the CT grid and intersected with the lumen
    intensity range.

    Returns
    -------
    numpy.ndarray of bool
        Branch voxels on the CT grid (not including ``trunk``).
    """
    box = _trunk_box(trunk, ct, reach_mm)
    factor = _coarse_factor(ct, voxel_mm)
    hu = np.asarray(ct.array[box], dtype=np.float32)
    coarse = _block_reduce(hu, factor, np.mean)
    coarse_trunk = _block_reduce(trunk[box] > 0, factor, np.max)
    bone = ndi.binary_dilation(_block_reduce(hu > BONE_HU, factor, np.max), iterations=1)
    coarse_mm = np.asarray(ct.spacing, dtype=float)[::-1] * factor
    sigmas = [s / float(coarse_mm.mean()) for s in sigmas_mm]
    lo, hi = _range_per_slice(ct, lumen_hu, box[0])
    n_coarse = coarse.shape[0]
    coarse_lo = lo[:n_coarse * factor[0]].reshape(n_coarse, factor[0]).mean(axis=1)[:, None, None]
    coarse_hi = hi[:n_coarse * factor[0]].reshape(n_coarse, factor[0]).mean(axis=1)[:, None, None]
    contrast = 2.0 * (coarse_lo - SOFT_TISSUE_HU)       # the lumen's level above soft tissue at that height
    tubular = tubularity_3d(np.clip(coarse, SOFT_TISSUE_HU - 200, coarse_hi), sigmas) > min_vesselness * contrast
    candidate = tubular & (coarse >= 0.5 * (coarse_lo + SOFT_TISSUE_HU)) & (coarse <= coarse_hi) & ~bone
    if excluded_slices is not None:
        excluded = np.asarray(excluded_slices, dtype=bool)[box[0]][:n_coarse * factor[0]]
        candidate &= ~excluded.reshape(n_coarse, factor[0]).any(axis=1)[:, None, None]
    seeds = ndi.binary_dilation(coarse_trunk, iterations=1) & candidate
    reached = geodesic_reach(seeds, candidate, coarse_mm, reach_mm) & ~coarse_trunk
    full = np.zeros(trunk.shape, dtype=bool)
    if reached.any():
        grown = ndi.binary_dilation(reached, iterations=1)
        upsampled = np.repeat(np.repeat(np.repeat(grown, factor[0], 0), factor[1], 1), factor[2], 2)
        region = tuple(slice(b.start, b.start + n) for b, n in zip(box, upsampled.shape))
        smooth = ndi.gaussian_filter(np.asarray(ct.array[region], dtype=np.float32),
                                     0.6 / np.asarray(ct.spacing)[::-1])
        ks = np.arange(region[0].start, region[0].stop) - box[0].start
        full[region] = upsampled & (smooth >= lo[ks][:, None, None]) & (smooth <= hi[ks][:, None, None])
    return full & (trunk == 0)


def _range_per_slice(ct: Volume, lumen_hu, ks: slice) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) arrays over the slices ``ks`` from one (lo, hi) pair or a per-slice profile (n_slices, 2)."""
    lumen_hu = np.asarray(lumen_hu, dtype=float)
    n = ks.stop - ks.start
    if lumen_hu.ndim == 1:
        return np.full(n, lumen_hu[0]), np.full(n, lumen_hu[1])
    return lumen_hu[ks, 0], lumen_hu[ks, 1]


def segment_ct_classical(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, branches: bool = True,
                         progress=None, postprocess: bool = True, return_labels: bool = False):
    """Lumen mask of the aorta tree without any training (the fallback that always works).

    1. :func:`aorta_seed_candidates`: round bright blobs in front of the spine, roundest first
       (those where the IVC runs last).
    2. :func:`trace_aorta`: follow the first seed whose trace is aorta-long up and down slice
       by slice (overlap with the predicted core, radius continuity, flaps bridged), then the
       two common iliacs below the bifurcation; the lumen range comes from the seed's own
       statistics, then from each trace's last cross-sections (contrast may fade along the
       aorta; a lumen fading below :data:`MIN_LUMEN_HU` is refused).
    3. :func:`grow_branches`: tubular bright voxels connected to the trunk within
       :data:`BRANCH_REACH_MM` along the branch, in mm whatever its course (renals, visceral
       arteries, iliac continuations); heart, kidneys, bowel and bone are not tubes.

    Parameters
    ----------
    ct : Volume
        Contrast CT in HU (any spacing, slice thickness and field of view).
    progress : callable, optional
        ``progress(done_slices, total_slices)`` while tracing.
    return_labels : bool
        Also return a label Volume: 1 aorta, 2 iliacs, 3 side branches.

    Returns
    -------
    Volume (and the label Volume)
        Boolean lumen mask on the CT grid.
    """
    _check_ct(ct)
    chest = chest_slices(ct)
    labels, _, lumen_hu = trace_aorta(ct, hu_window=hu_window, radius_mm=radius_mm, progress=progress, chest=chest)
    if branches:
        labels[grow_branches(ct, labels, lumen_hu, excluded_slices=chest)] = 3
    mask = ct.with_array(labels > 0)
    if postprocess:
        mask = postprocess_mask(mask)
    if progress is not None:
        progress(ct.shape[0], ct.shape[0])
    if return_labels:
        return mask, ct.with_array(np.where(mask.array, labels, 0).astype(np.uint8))
    return mask

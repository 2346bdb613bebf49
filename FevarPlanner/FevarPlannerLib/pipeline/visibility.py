"""Partial visibility: which part of the image plane a frame shows (collimator bands, vessels
running into a border), so that projections outside it get no data term.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass
class Visibility:
    """What part of the image plane one frame shows (partial visibility).

    Attributes
    ----------
    shape : (rows, cols)
        The frame's pixel grid.
    exposed : (row_min, row_max, col_min, col_max)
        The exposed rectangle (inclusive pixel indices): the frame less its collimated bands.
    clipped_border : list of str
        Sides of ``exposed`` ("top", "bottom", "left", "right") that the vessel mask runs into.
    margin_px : dict
        Per clipped side, the vessel half-width there (px): within it the 2D skeleton is
        the thinning's artefact of the cut (it bends or forks towards the corners), so
        projections closer to the border than this get no data term.
    field : Field or None
        A round (image intensifier) or otherwise shaped exposed field inside ``exposed``;
        None when the whole rectangle is exposed.
    """

    shape: tuple
    exposed: tuple
    clipped_border: list
    margin_px: dict
    field: "Field | None" = None

    def shows(self, uv: np.ndarray) -> np.ndarray:
        """True for the 2D points (u, v) inside the part of the frame that shows vessels."""
        r0, r1, c0, c1 = self.exposed
        m = {side: self.margin_px.get(side, 0.0) for side in _SIDES}
        u, v = uv[:, 0], uv[:, 1]
        inside = ((v >= r0 - 0.5 + m["top"]) & (v <= r1 + 0.5 - m["bottom"])
                  & (u >= c0 - 0.5 + m["left"]) & (u <= c1 + 0.5 - m["right"]))
        return inside & self.field.shows(uv) if self.field is not None else inside

    def exposed_mask(self) -> np.ndarray:
        """The frame's exposed pixels: the rectangle, less what the shaped field leaves dark."""
        shown = np.zeros(self.shape, dtype=bool)
        r0, r1, c0, c1 = self.exposed
        shown[r0:r1 + 1, c0:c1 + 1] = True
        return shown & ~self.field.unexposed if self.field is not None else shown

    def key(self) -> tuple:
        """What the exposed part of the frame depends on, hashable (a cache key)."""
        return self.shape, self.exposed, None if self.field is None else self.field.unexposed.tobytes()

    def to_dict(self, nodes_outside: int | None = None) -> dict:
        data = {"clipped_border": list(self.clipped_border), "exposed_rows_cols": list(map(int, self.exposed)),
                "margin_px": {k: round(float(v), 2) for k, v in self.margin_px.items()}}
        if self.field is not None:
            data["shaped_field"] = {"exposed_fraction": round(float(1.0 - self.field.unexposed.mean()), 4),
                                    "margin_px": round(float(self.field.margin_px), 2)}
        if nodes_outside is not None:
            data["nodes_outside"] = int(nodes_outside)
        return data


@dataclass
class Field:
    """A shaped exposed field: the dark (or white) shutter around a round image-intensifier
    field or a shaped collimator, flat and connected to the rectangle's corners.

    Attributes
    ----------
    unexposed : (rows, cols) bool
        Shutter pixels (no anatomy shown).
    distance_px : (rows // FIELD_STEP + 1, cols // FIELD_STEP + 1) float
        Distance (px) of each coarse grid point to the shutter.
    margin_px : float
        The vessel half-width where the vessel mask meets the shutter (0 when it does not):
        projections closer to the shutter than this get no data term, as at a straight border.
    """

    unexposed: np.ndarray
    distance_px: np.ndarray
    margin_px: float

    def shows(self, uv: np.ndarray) -> np.ndarray:
        """True for the points (u, v) farther than ``margin_px`` from the shutter (on the frame)."""
        rows, cols = self.distance_px.shape
        r = np.clip(np.rint(uv[:, 1] / FIELD_STEP), 0, rows - 1).astype(int)
        c = np.clip(np.rint(uv[:, 0] / FIELD_STEP), 0, cols - 1).astype(int)
        return self.distance_px[r, c] > max(self.margin_px, FIELD_STEP)


_SIDES = ("top", "bottom", "left", "right")
#: A border row or column whose grey values vary by less than this fraction of the frame's
#: range (1st to 99th percentile) is a collimator (shutter) band: it shows no anatomy.
FLAT_BAND_FRACTION = 0.01
#: The vessel mask runs into a border when at least this many of its pixels lie on it.
MIN_BORDER_PIXELS = 2


def _collimated_bands(image: np.ndarray) -> dict:
    """Number of flat (shutter) rows / columns on each side of a raw frame."""
    image = np.asarray(image)
    could_be_flat = _borders_could_be_flat(image)
    if not any(could_be_flat.values()):
        return dict.fromkeys(_SIDES, 0)
    image = image.astype(float)
    low, high = np.percentile(image, [1, 99])
    limit = FLAT_BAND_FRACTION * max(high - low, 1e-12)

    def run(flags):
        return int(np.argmin(flags)) if not flags.all() else len(flags)

    bands = dict.fromkeys(_SIDES, 0)
    for axis, (first, last) in ((1, ("top", "bottom")), (0, ("left", "right"))):
        if could_be_flat[first] or could_be_flat[last]:
            flat = image.std(axis=axis) < limit
            bands[first], bands[last] = run(flat), run(flat[::-1])
    return bands


def _borders_could_be_flat(image: np.ndarray) -> dict:
    """Per side, whether the frame's outermost line there might count as flat.

    The flatness limit is :data:`FLAT_BAND_FRACTION` of the 1st-99th percentile range, which
    is at most the full range (max - min, exact on the frame's own dtype); a border line
    varying by more than that fraction of the full range (with a margin for rounding) is not
    flat whatever the percentiles, and then no band can start on that side. Checking the
    four lines first spares the percentiles and the row / column spreads of a frame
    without shutters (about 10 ms on 1024 x 1024).
    """
    brightest, darkest = float(image.max()), float(image.min())
    span = brightest - darkest + 1e-9 * (abs(brightest) + abs(darkest))
    bound = FLAT_BAND_FRACTION * max(span, 1e-12) * (1 + 1e-6)
    lines = {"top": image[0], "bottom": image[-1], "left": image[:, 0], "right": image[:, -1]}
    return {side: bool(np.std(line.astype(float)) < bound) for side, line in lines.items()}


#: A shaped field's shutter: a corner patch this many pixels square, flat to
#: :data:`FLAT_BAND_FRACTION` of the frame's range and at its darkest or brightest value.
CORNER_PATCH_PX = 8
#: Shutter regions smaller than this fraction of the rectangle (burned-in text boxes) are ignored.
MIN_SHUTTER_FRACTION = 0.005
#: A field exposes at least this fraction of its rectangle (an inscribed disc: 79 %); less is a
#: flat background around the vessels themselves (a mask's stand-in frame), not a shutter.
MIN_FIELD_FRACTION = 0.25
#: The distance to a shaped field's shutter is kept on a grid of this step (px).
FIELD_STEP = 4
#: A vessel's contact with a shaped field's shutter holds at least this many mask pixels.
MIN_TOUCH_PX = 20
#: The shutter is filled with the median of the exposed ring this wide (px) along its edge (the
#: field's level there, vignetting included).
EDGE_RING_PX = 8
#: A vessel runs into a shaped field's shutter when its mask comes this close (px): the
#: segmentation stops a pixel or two short of the shutter's step edge.
SHUTTER_REACH_PX = 3


def _corners(shape: tuple) -> list:
    """(row, col) of the first pixel of each corner patch of a frame of ``shape``."""
    rows, cols = shape
    k = CORNER_PATCH_PX
    return [(0, 0), (0, cols - k), (rows - k, 0), (rows - k, cols - k)]


def _flat_corners(image: np.ndarray) -> list:
    """The corners whose patch varies by less than :data:`FLAT_BAND_FRACTION` of its
    difference from the frame's centre: a cheap first look (no whole-frame statistics), so that
    a frame without a shaped shutter costs almost nothing."""
    rows, cols = image.shape
    k = CORNER_PATCH_PX
    middle = float(np.median(image[rows // 2 - 2 * k:rows // 2 + 2 * k, cols // 2 - 2 * k:cols // 2 + 2 * k]))
    flat = []
    for r, c in _corners(image.shape):
        patch = image[r:r + k, c:c + k].astype(float)
        if float(patch.std()) < FLAT_BAND_FRACTION * abs(float(np.median(patch)) - middle):
            flat.append((r, c))
    return flat


def _shutter_levels(image: np.ndarray, corners: list, limit: float) -> list:
    """(row, col, level) of each of ``corners`` whose patch is flat to ``limit`` and at the
    frame's darkest or brightest value (a shutter, not a subtracted frame's grey background)."""
    darkest, brightest = float(image.min()), float(image.max())
    k = CORNER_PATCH_PX
    found = []
    for r, c in corners:
        patch = image[r:r + k, c:c + k].astype(float)
        level = float(np.median(patch))
        if float(patch.std()) < limit and min(abs(level - darkest), abs(level - brightest)) <= limit:
            found.append((r, c, level))
    return found


def _shutter(image: np.ndarray) -> np.ndarray | None:
    """The flat shutter of a rectangle's ``image`` flooded from its corners, or None."""
    from skimage.segmentation import flood

    if min(image.shape) < 4 * CORNER_PATCH_PX:
        return None
    corners = _flat_corners(image)
    if not corners:
        return None
    low, high = np.percentile(image[::FIELD_STEP, ::FIELD_STEP], [1, 99])
    limit = FLAT_BAND_FRACTION * max(float(high - low), 1e-12)
    unexposed = np.zeros(image.shape, dtype=bool)
    for r, c, level in _shutter_levels(image, corners, limit):
        if not unexposed[r, c]:         # the corner's 4-connected flat piece (ndimage.label's, 3 x faster)
            unexposed |= flood(np.abs(image.astype(np.float32) - np.float32(level)) <= limit, (r, c), connectivity=1)
    share = float(unexposed.mean())
    return unexposed if MIN_SHUTTER_FRACTION <= share <= 1.0 - MIN_FIELD_FRACTION else None


#: Collimator leaves inside the field: a band along a side, from the field's edge to a straight
#: edge (turned up to LEAF_MAX_TURN_DEG from the side), that lets a few per cent of the beam
#: through, so that the display holds it at the field's extreme level (its 1st or 99th
#: percentile, to within LEAF_FLATNESS of the field's range: either polarity). Across the band,
#: at least LEAF_BAND_SHARE of each line's pixels lie at that level; within LEAF_EDGE_PX beyond
#: its edge at most LEAF_FIELD_SHARE do (a subtracted frame's flat background stays at its level
#: past any vessel). The band is at least LEAF_MIN_DEPTH_PX deep and reaches at most
#: LEAF_MAX_DEPTH of the field's extent. Judged on LEAF_BLOCK x LEAF_BLOCK block means. Noisy or
#: holding a dim image of the anatomy, such a band is no flat shutter to the corner flood, and the
#: segmentation took it as vessel where a vessel ran into it (realbench development seeds 480-485).
LEAF_MAX_TURN_DEG = 6.0
LEAF_TURN_STEP_DEG = 1.5
LEAF_FLATNESS = 0.03
LEAF_BAND_SHARE = 0.8
LEAF_FIELD_SHARE = 0.2
LEAF_EDGE_PX = 16
LEAF_MIN_DEPTH_PX = 24
LEAF_MAX_DEPTH = 0.3
LEAF_BLOCK = 8
#: Fewest field pixels (blocks) a distance bin of a leaf's profile needs.
LEAF_MIN_BIN = 4
#: Fewest of the field's pixels at an extreme level for a leaf to be looked for.
LEAF_MIN_SHARE = 0.005


def _leaf_distances(rr: np.ndarray, cc: np.ndarray) -> np.ndarray:
    """Distance (blocks) of each field block (``rr, cc``) from each side of the field, the sides
    turned by each leaf turn (:data:`LEAF_MAX_TURN_DEG` in :data:`LEAF_TURN_STEP_DEG` steps): one
    row per turn and side (top, bottom, left, right), all turns at once."""
    turns = np.arange(-LEAF_MAX_TURN_DEG, LEAF_MAX_TURN_DEG + 1e-9, LEAF_TURN_STEP_DEG)
    c, s_ = np.cos(np.deg2rad(turns))[:, None], np.sin(np.deg2rad(turns))[:, None]
    across_rows = rr * c - cc * s_
    across_cols = cc * c + rr * s_
    sides = [across_rows - across_rows.min(axis=1, keepdims=True), across_rows.max(axis=1, keepdims=True) - across_rows,
             across_cols - across_cols.min(axis=1, keepdims=True), across_cols.max(axis=1, keepdims=True) - across_cols]
    return np.stack(sides, axis=1).reshape(4 * len(turns), -1)


def _leaf_profiles(distance: np.ndarray, flags_of: list) -> list:
    """Per row of ``distance`` (:func:`_leaf_distances`) and per bool ``flags`` of ``flags_of``:
    the share of flagged blocks per whole-block distance bin and which bins hold enough blocks
    (:data:`LEAF_MIN_BIN`), up to the row's farthest bin: ``[[(share, valid) per row] per flags]``.
    Every row's bins are numbered apart in one range, counted by one bincount (the flagged
    blocks' by one more each)."""
    bins = np.floor(distance).astype(int)
    lengths = bins.max(axis=1) + 1
    width = int(lengths.max())
    numbered = bins + width * np.arange(len(bins))[:, None]
    counts = np.bincount(numbered.ravel(), minlength=width * len(bins)).reshape(len(bins), width)
    valid = counts >= LEAF_MIN_BIN
    profiles = []
    for flags in flags_of:
        flagged = np.bincount(numbered[:, flags].ravel(), minlength=width * len(bins)).reshape(len(bins), width)
        share = flagged / np.maximum(counts, 1)
        profiles.append([(share[k, :n], valid[k, :n]) for k, n in enumerate(lengths)])
    return profiles


def _leaf_depth(share: np.ndarray, valid: np.ndarray) -> int:
    """Depth (bins) of a collimator leaf at the start of a side's profile, or 0: ``share`` is the
    fraction of each bin's field pixels at one extreme level; the band holds at least
    :data:`LEAF_BAND_SHARE` of them from the field's edge for :data:`LEAF_MIN_DEPTH_PX` at least,
    and within :data:`LEAF_EDGE_PX` after it at most :data:`LEAF_FIELD_SHARE`."""
    filled = np.flatnonzero(valid)
    min_depth = max(2, int(np.ceil(LEAF_MIN_DEPTH_PX / LEAF_BLOCK)))
    edge = max(1, int(np.ceil(LEAF_EDGE_PX / LEAF_BLOCK)))
    if len(filled) < 4 * min_depth:
        return 0
    start, stop = filled[0], filled[-1]
    inside = share[start:stop + 1] >= LEAF_BAND_SHARE
    depth = int(np.argmin(inside)) if not inside.all() else 0
    if depth < min_depth or depth > LEAF_MAX_DEPTH * (stop - start):
        return 0
    after = share[start + depth:start + depth + edge + 1]
    return start + depth if np.min(after) <= LEAF_FIELD_SHARE else 0


def _collimator_leaves(image: np.ndarray, unexposed: np.ndarray | None) -> np.ndarray | None:
    """The collimator leaves inside a rectangle's ``image`` (not flat, so not part of the corner
    flood's ``unexposed``), as a bool image, or None (:data:`LEAF_MAX_TURN_DEG` ...)."""
    from ..quality import block_means

    rows, cols = image.shape
    if min(rows, cols) < 16 * LEAF_BLOCK:
        return None
    blocks = block_means(image, LEAF_BLOCK).astype(float)
    field = np.ones(blocks.shape, dtype=bool)
    if unexposed is not None:
        field = ~unexposed[:blocks.shape[0] * LEAF_BLOCK:LEAF_BLOCK, :blocks.shape[1] * LEAF_BLOCK:LEAF_BLOCK]
    field &= ~ndimage.binary_dilation(~field, iterations=2) if (~field).any() else field
    values = blocks[field]
    if values.size < 64:
        return None
    p1, p99 = np.percentile(values, [1, 99])
    span = float(p99 - p1)
    if span <= 0:
        return None
    at_extreme = [flags for flags in (np.abs(values - level) <= LEAF_FLATNESS * span for level in (p1, p99))
                  if LEAF_MIN_SHARE <= flags.mean() <= 0.5]      # more: a flat background, not a band
    if not at_extreme:
        return None
    rr, cc = np.nonzero(field)
    distance = _leaf_distances(rr, cc)
    leaves = np.zeros(blocks.shape, dtype=bool)
    for profiles in _leaf_profiles(distance, at_extreme):
        for row, (share, valid) in zip(distance, profiles):
            depth = _leaf_depth(share, valid)
            if depth:
                inside = row < depth
                leaves[rr[inside], cc[inside]] = True
    if not leaves.any():
        return None
    full = np.zeros((rows, cols), dtype=bool)
    grown = np.repeat(np.repeat(leaves, LEAF_BLOCK, axis=0), LEAF_BLOCK, axis=1)
    full[:grown.shape[0], :grown.shape[1]] = grown
    return full


def _shutter_and_leaves(image: np.ndarray) -> np.ndarray | None:
    """The flat shutter flooded from the corners (:func:`_shutter`) and, around a shaped (round)
    field, the collimator leaves inside it (:func:`_collimator_leaves`), together; None without
    a shaped field (a frame without one costs nothing more: its flat bands are found by
    :func:`_collimated_bands`)."""
    shutter = _shutter(image)
    if shutter is None:
        return None
    leaves = _collimator_leaves(image, shutter)
    return shutter if leaves is None else shutter | leaves


def _square_dilation(mask: np.ndarray, radius: int) -> np.ndarray:
    """``ndimage.binary_dilation(mask, structure=np.ones((3, 3)), iterations=radius)`` (nothing
    beyond the grid): the (2 radius + 1)^2 square's, by doubling spans along rows then columns
    (:func:`segmentation.fluoro._centred_square_extreme`), 10 x faster on a 1024 x 1024 frame."""
    from ..segmentation.fluoro import _centred_square_extreme

    return _centred_square_extreme(np.asarray(mask, dtype=bool), radius, np.maximum, False)


def _half_width(mask: np.ndarray, where: np.ndarray) -> float:
    """The largest half-width (px) of ``mask`` at the pixels ``where``: its distance to the
    background, on the box around them padded by the mask's extent there (the caller counts
    the shutter as vessel, so that a vessel cut by it is measured across, not to its cut end)."""
    rows, cols = np.nonzero(where)
    pad = max(int(rows.max() - rows.min()), int(cols.max() - cols.min())) + 2
    r0, c0 = max(rows.min() - pad, 0), max(cols.min() - pad, 0)
    box = mask[r0:rows.max() + pad + 1, c0:cols.max() + pad + 1]
    return float(ndimage.distance_transform_edt(box)[rows - r0, cols - c0].max())


def _piece_sizes_and_centres(touching: np.ndarray, pieces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Per piece 1 ... ``count`` of ``pieces``, its number of ``touching`` pixels and their mean
    (row, col): ``ndimage.sum`` and ``ndimage.center_of_mass`` of ``touching`` by ``pieces`` (the
    same sums of whole numbers), counted over the touching pixels only, not the whole frame."""
    rows, cols = np.nonzero(touching)
    at = pieces[rows, cols]
    sizes = np.bincount(at, minlength=count + 1)[1:].astype(float)
    centres = np.column_stack([np.bincount(at, weights=rows.astype(float), minlength=count + 1)[1:] / sizes,
                               np.bincount(at, weights=cols.astype(float), minlength=count + 1)[1:] / sizes])
    return sizes, centres


def _sides_towards(touching: np.ndarray, exposed: tuple) -> list:
    """Sides ("top" ... "right") of the rectangle ``exposed`` towards which the ``touching``
    pixels lie, each piece (fragments a few pixels apart joined; pieces under
    :data:`MIN_TOUCH_PX`, a compressed frame's specks along the edge, left out) by its
    direction from the rectangle's centre; each side once."""
    joined = _square_dilation(touching, SHUTTER_REACH_PX)
    pieces, count = ndimage.label(joined)
    sizes, centres = _piece_sizes_and_centres(touching, pieces, count)
    r0, r1, c0, c1 = exposed
    sides = []
    for (row, col), size in zip(centres, sizes):
        dr, dc = row - (r0 + r1) / 2.0, col - (c0 + c1) / 2.0
        side = ("bottom" if dr > 0 else "top") if abs(dr) >= abs(dc) else ("right" if dc > 0 else "left")
        if size >= MIN_TOUCH_PX and side not in sides:
            sides.append(side)
    return sides


@dataclass(frozen=True, eq=False)
class FieldSearch:
    """The surround search of one raw frame (:func:`find_field`): done once per frame, it serves
    both the segmentation (:func:`shutter_filled`) and the visibility (:func:`frame_visibility`).

    Attributes
    ----------
    exposed : (row_min, row_max, col_min, col_max)
        The frame less its collimated bands (:func:`_exposed_rectangle`).
    shutter : (rows, cols) bool array (read-only) or None
        The shaped field's flat shutter and collimator leaves inside ``exposed``
        (:func:`_shutter_and_leaves`, on the rectangle's own pixels); None without a shaped field.
    """

    exposed: tuple
    shutter: np.ndarray | None


def find_field(image: np.ndarray) -> FieldSearch | None:
    """The collimated bands and the shaped field's shutter of a raw frame (:class:`FieldSearch`),
    or None for a run of frames (3D), which neither use searches."""
    image = np.asarray(image)
    if image.ndim != 2:
        return None
    r0, r1, c0, c1 = exposed = _exposed_rectangle(image)
    shutter = _shutter_and_leaves(image[r0:r1 + 1, c0:c1 + 1])
    if shutter is not None:
        shutter.flags.writeable = False         # shared by both uses
    return FieldSearch(exposed, shutter)


def shutter_filled(image: np.ndarray, search: FieldSearch | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """A raw frame with its shaped field's shutter (a round image intensifier's dark surround)
    set to the exposed field's level along the shutter's edge, for the vessel segmentation;
    and the shutter's pixels (None when the frame has none), which no vessel mask may hold.

    The shutter's step edge and its extreme level otherwise reach the segmentation's band
    around the projected tree: they change its normalisation and its judgement of a flat
    (subtracted) background, and a faint renal was lost. Collimator bands along the sides stay
    as they are on a frame without a shaped field; with one, they are filled too (a white
    surround's bands otherwise reach the segmentation's box as its brightest pixels); a run of
    frames (3D) is returned unchanged. ``search``: the frame's :func:`find_field`, when done
    already (the visibility uses it too).
    """
    image = np.asarray(image)
    if image.ndim != 2:
        return image, None
    search = find_field(image) if search is None else search
    if search.shutter is None:
        return image, None
    r0, r1, c0, c1 = search.exposed
    shutter = search.shutter
    inside = image[r0:r1 + 1, c0:c1 + 1]
    edge = _square_dilation(shutter, EDGE_RING_PX) & ~shutter
    unexposed = _unexposed(shutter, image.shape, (r0, r1, c0, c1))
    filled = image.copy()
    filled[unexposed] = np.median(inside[edge]).astype(image.dtype)
    return filled, unexposed


def _exposed_rectangle(image: np.ndarray) -> tuple:
    """(row_min, row_max, col_min, col_max) of ``image`` less its collimator bands."""
    rows, cols = image.shape
    bands = _collimated_bands(image)
    r0, r1, c0, c1 = bands["top"], rows - 1 - bands["bottom"], bands["left"], cols - 1 - bands["right"]
    return (r0, r1, c0, c1) if r0 <= r1 and c0 <= c1 else (0, rows - 1, 0, cols - 1)


def frame_visibility(mask2d: np.ndarray, image: np.ndarray | None = None,
                     search: FieldSearch | None = None) -> Visibility:
    """Where a frame shows anatomy and where its vessels run out of it.

    Parameters
    ----------
    mask2d : (rows, cols) bool
        The vessel mask.
    image : (rows, cols) array, optional
        The raw frame; flat bands along its borders are collimator shutters
        (:data:`FLAT_BAND_FRACTION`) and are excluded from the exposed rectangle. Without it
        the whole frame is exposed.
    search : FieldSearch, optional
        ``image``'s :func:`find_field`, when done already (the segmentation's,
        :func:`shutter_filled`); found here when not given. Unused without ``image``.

    Returns
    -------
    Visibility
        The exposed rectangle, the sides of it that the vessel mask touches (the vessel
        continues beyond them unseen) and the vessel half-width at each such side.
    """
    mask = np.asarray(mask2d, dtype=bool)
    rows, cols = mask.shape
    has_image = image is not None and np.shape(image) == mask.shape
    if has_image and search is None:
        search = find_field(image)
    r0, r1, c0, c1 = search.exposed if has_image else (0, rows - 1, 0, cols - 1)
    shown = mask[r0:r1 + 1, c0:c1 + 1]
    sides = {"top": (0, slice(None)), "bottom": (-1, slice(None)), "left": (slice(None), 0),
             "right": (slice(None), -1)}
    clipped, margin = [], {}
    for side, index in sides.items():
        on_border = shown[index]
        if np.count_nonzero(on_border) >= MIN_BORDER_PIXELS:
            clipped.append(side)
            margin[side] = _half_width_at_border(shown, side, index, on_border)
    shutter = search.shutter if has_image else None
    field = None
    if shutter is not None:         # a round or shaped field inside the rectangle
        inner = _placed(shutter, (rows, cols), (r0, r1, c0, c1))
        unexposed = _unexposed(shutter, (rows, cols), (r0, r1, c0, c1))
        touching = mask & _square_dilation(inner, SHUTTER_REACH_PX)
        distance = ndimage.distance_transform_edt(~unexposed[::FIELD_STEP, ::FIELD_STEP]) * FIELD_STEP
        field = Field(unexposed, distance, _half_width(mask | unexposed, touching) if touching.any() else 0.0)
        clipped += [side for side in _sides_towards(touching, (r0, r1, c0, c1)) if side not in clipped]
    return Visibility((rows, cols), (r0, r1, c0, c1), clipped, margin, field)


def _unexposed(shutter: np.ndarray, shape: tuple, exposed: tuple) -> np.ndarray:
    """Every pixel of a frame of ``shape`` that a shaped field leaves dark: its ``shutter``
    inside the rectangle ``exposed`` and the bands around the rectangle."""
    return _placed(shutter, shape, exposed) | ~_placed(np.ones(shutter.shape, dtype=bool), shape, exposed)


def _placed(part: np.ndarray, shape: tuple, exposed: tuple) -> np.ndarray:
    """A bool image of ``shape``: ``part`` (the rectangle ``exposed``'s own pixels) in place,
    False around it."""
    r0, r1, c0, c1 = exposed
    whole = np.zeros(shape, dtype=bool)
    whole[r0:r1 + 1, c0:c1 + 1] = part
    return whole


def _longest_run(flags: np.ndarray) -> int:
    """Length of the longest run of True in a 1D bool array."""
    edges = np.flatnonzero(np.diff(np.concatenate([[False], flags, [False]]).astype(np.int8)))
    return int((edges[1::2] - edges[::2]).max()) if len(edges) else 0


def _half_width_at_border(shown: np.ndarray, side: str, index, on_border: np.ndarray) -> float:
    """The vessel's largest half-width (px) on one side of the exposed rectangle ``shown``.

    The distance of each vessel pixel on the border line to the nearest background pixel
    inside the rectangle (its edges repeated outwards). A pixel in a run of ``L`` vessel
    pixels along the line that does not fill the whole line has background on the line
    within ``L``; background deeper than ``L`` from the border is farther than that, so
    the distance transform of a strip ``L + 1`` deep along the side gives the same values
    as that of the whole rectangle (45 ms on a 1024 x 1024 frame) at a fraction of the cost.
    """
    across = 0 if side in ("top", "bottom") else 1
    run = _longest_run(on_border)
    depth = shown.shape[across] if run == len(on_border) else min(run + 1, shown.shape[across])
    strip = {"top": shown[:depth], "bottom": shown[shown.shape[0] - depth:], "left": shown[:, :depth],
             "right": shown[:, shown.shape[1] - depth:]}[side]
    half_width = ndimage.distance_transform_edt(np.pad(strip, 1, mode="edge"))[1:-1, 1:-1]
    return float(half_width[index][on_border].max())

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
    """

    shape: tuple
    exposed: tuple
    clipped_border: list
    margin_px: dict

    def shows(self, uv: np.ndarray) -> np.ndarray:
        """True for the 2D points (u, v) inside the part of the frame that shows vessels."""
        r0, r1, c0, c1 = self.exposed
        m = {side: self.margin_px.get(side, 0.0) for side in _SIDES}
        u, v = uv[:, 0], uv[:, 1]
        return ((v >= r0 - 0.5 + m["top"]) & (v <= r1 + 0.5 - m["bottom"])
                & (u >= c0 - 0.5 + m["left"]) & (u <= c1 + 0.5 - m["right"]))

    def to_dict(self, nodes_outside: int | None = None) -> dict:
        data = {"clipped_border": list(self.clipped_border), "exposed_rows_cols": list(map(int, self.exposed)),
                "margin_px": {k: round(float(v), 2) for k, v in self.margin_px.items()}}
        if nodes_outside is not None:
            data["nodes_outside"] = int(nodes_outside)
        return data


_SIDES = ("top", "bottom", "left", "right")
#: A border row or column whose grey values vary by less than this fraction of the frame's
#: range (1st to 99th percentile) is a collimator (shutter) band: it shows no anatomy.
FLAT_BAND_FRACTION = 0.01
#: The vessel mask runs into a border when at least this many of its pixels lie on it.
MIN_BORDER_PIXELS = 2


def _collimated_bands(image: np.ndarray) -> dict:
    """Number of flat (shutter) rows / columns on each side of a raw frame."""
    image = np.asarray(image, dtype=float)
    low, high = np.percentile(image, [1, 99])
    limit = FLAT_BAND_FRACTION * max(high - low, 1e-12)
    flat_rows, flat_cols = image.std(axis=1) < limit, image.std(axis=0) < limit

    def run(flags):
        return int(np.argmin(flags)) if not flags.all() else len(flags)

    return {"top": run(flat_rows), "bottom": run(flat_rows[::-1]), "left": run(flat_cols),
            "right": run(flat_cols[::-1])}


def frame_visibility(mask2d: np.ndarray, image: np.ndarray | None = None) -> Visibility:
    """Where a frame shows anatomy and where its vessels run out of it.

    Parameters
    ----------
    mask2d : (rows, cols) bool
        The vessel mask.
    image : (rows, cols) array, optional
        The raw frame; flat bands along its borders are collimator shutters
        (:data:`FLAT_BAND_FRACTION`) and are excluded from the exposed rectangle. Without it
        the whole frame is exposed.

    Returns
    -------
    Visibility
        The exposed rectangle, the sides of it that the vessel mask touches (the vessel
        continues beyond them unseen) and the vessel half-width at each such side.
    """
    mask = np.asarray(mask2d, dtype=bool)
    rows, cols = mask.shape
    has_image = image is not None and np.shape(image) == mask.shape
    bands = _collimated_bands(image) if has_image else dict.fromkeys(_SIDES, 0)
    r0, r1 = bands["top"], rows - 1 - bands["bottom"]
    c0, c1 = bands["left"], cols - 1 - bands["right"]
    if r0 > r1 or c0 > c1:
        r0, r1, c0, c1 = 0, rows - 1, 0, cols - 1
    shown = mask[r0:r1 + 1, c0:c1 + 1]
    sides = {"top": (0, slice(None)), "bottom": (-1, slice(None)), "left": (slice(None), 0),
             "right": (slice(None), -1)}
    clipped, margin, half_width = [], {}, None
    for side, index in sides.items():
        on_border = shown[index]
        if np.count_nonzero(on_border) >= MIN_BORDER_PIXELS:
            if half_width is None:      # only for a clipped frame: 45 ms on a 1024 x 1024 frame
                # distance to the nearest background pixel inside the exposed rectangle (its
                # edges repeated outwards): at a side the vessel runs into, its half-width there
                half_width = ndimage.distance_transform_edt(np.pad(shown, 1, mode="edge"))[1:-1, 1:-1]
            clipped.append(side)
            margin[side] = float(half_width[index][on_border].max())
    return Visibility((rows, cols), (r0, r1, c0, c1), clipped, margin)

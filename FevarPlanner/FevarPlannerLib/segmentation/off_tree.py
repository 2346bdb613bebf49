"""Branches of an unsubtracted frame's vessel mask that run across the projected tree (issue 11).

On an unsubtracted frame the vessel mask keeps what touches the vessels and is about as dark:
the vertebral bodies beside the aorta, the pelvic plates and a ruler or a rail crossing the
iliacs. Thinned, each grows a branch off the vessel it touches, and the 2D skeleton graph
then has branches that no pre-operative vessel explains: Algorithm 1 may take one for a
missing renal, the matching pairs a renal with a ruler, and the registration check refuses
the frame ("30% of the frame's vessels lie over 5 mm from the registered tree").

A vessel, however deformed, runs roughly along its projected pre-operative direction; these
branches run across it (a vertebral body's blob off the aorta's side, a ruler across an
iliac). :func:`without_cross_branches` thins the mask (on the reduced grid of the
segmentation), takes each skeleton pixel's direction from the skeleton pixels around it,
and calls it *across* when that direction is more than :data:`ACROSS_DEG` off the direction
of the nearest projected vessel and the pixel lies outside a lumen: outside the projected
lumen (:func:`beyond_projected_lumen`) or outside the lumen of the mask's vessel it leaves
(farther from the nearest skeleton pixel that runs along than that pixel's distance to the
background). Inside both, at a junction, every direction meets (a renal's first pixels lie
inside the aorta). Both lumens count: a deformed iliac lies beside its projection, and a ruler
leaving it there lies inside the projected lumen; a thick vertebral blob off the aorta is its
own lumen. Runs of at least :data:`MIN_RUN_PX` across pixels are dropped with the mask pixels
only they explain; the mask pixels inside the lumen of a kept skeleton pixel (its distance to
the background) stay.

On development bench seeds 231-240 (every distractor, unsubtracted) this halves the share of
the 2D skeleton lying over 5 mm off the vessels (seed 231: 32 % -> 15 %).

Only frames whose background had to be flattened go through this (unsubtracted frames, and
subtracted ones with a collimator shutter across the vessels); a flat subtracted frame's mask
is left as it is.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

__all__ = ["tidy_unsubtracted", "without_cross_branches", "beyond_projected_lumen", "skeleton_directions",
           "ACROSS_DEG", "MIN_RUN_PX"]

#: A skeleton pixel runs across the projected tree when its direction is more than this many
#: degrees off the nearest projected vessel's.
ACROSS_DEG = 50.0
#: A run of across pixels this long (px of the reduced grid) or longer is dropped.
MIN_RUN_PX = 3
#: Radius (px of the reduced grid) of the window whose skeleton pixels give a pixel's direction.
DIRECTION_RADIUS_PX = 3
#: Pixels this close (px) beyond a lumen still count as inside it: at a junction (renal ostium,
#: bifurcation) the skeleton's local direction is mixed.
JUNCTION_SLACK_PX = 1.0

_EIGHT = np.ones((3, 3), dtype=bool)


def skeleton_directions(skeleton: np.ndarray, pixels: np.ndarray, radius: int = DIRECTION_RADIUS_PX) -> np.ndarray:
    """Axis angle (radians, of (d_col, d_row), modulo pi) of a 2D skeleton at some of its pixels,
    from the second moments of the skeleton pixels within a (2 radius + 1)^2 window.

    Parameters
    ----------
    skeleton : numpy.ndarray of bool, shape (rows, cols)
    pixels : numpy.ndarray of int, shape (n, 2)
        ``(row, col)`` of the pixels to measure.
    radius : int

    Returns
    -------
    numpy.ndarray, shape (n,)
    """
    steps = np.arange(-radius, radius + 1)
    d_row, d_col = (grid.ravel() for grid in np.meshgrid(steps, steps, indexing="ij"))
    padded = np.pad(skeleton, radius)
    window = padded[pixels[:, :1] + radius + d_row, pixels[:, 1:] + radius + d_col].astype(np.float32)
    uu, vv, uv = window @ (d_col * d_col).astype(np.float32), window @ (d_row * d_row).astype(np.float32), \
        window @ (d_col * d_row).astype(np.float32)
    return 0.5 * np.arctan2(2.0 * uv, uu - vv)


def _axis_difference(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Angle (radians, 0 to pi/2) between two axes given as angles modulo pi."""
    return 0.5 * np.abs(np.angle(np.exp(2j * (first - second))))


def tidy_unsubtracted(vessel: np.ndarray, prior, where, widest: np.ndarray, grid_key: tuple,
                      min_area: float) -> np.ndarray:
    """The last clean-up of an unsubtracted frame's reduced-grid ``vessel`` mask: branches across
    the projected tree dropped (:func:`without_cross_branches`), then pieces smaller than
    ``min_area`` pixels (as on every frame).

    ``prior`` is the :class:`quality.FluoroPrior`, ``where`` its band on this grid
    (:meth:`FluoroPrior.band`), ``widest`` the widest projected radius nearby (px);
    ``grid_key`` names the grid for the prior's cache.
    """
    from .fluoro import _node_directions
    from .threshold import _remove_small_objects

    node_angle = prior.derived(("node_angle",) + tuple(grid_key),
                               lambda: _node_directions(prior).astype(np.float32)[where.nearest])
    beyond = prior.derived(("beyond_lumen",) + tuple(grid_key), lambda: beyond_projected_lumen(where, widest))
    vessel = without_cross_branches(vessel, node_angle, beyond)
    if not vessel.any():
        return vessel
    return _remove_small_objects(vessel, min_area)


def beyond_projected_lumen(where, widest: np.ndarray) -> np.ndarray:
    """Pixels of the band ``where`` (:meth:`FluoroPrior.band`) outside the projected lumen by more
    than :data:`JUNCTION_SLACK_PX`: the nearest vessel's own radius where it is wide (aorta,
    iliacs), the ``widest`` radius nearby where it is thin (a renal's first pixels lie inside
    the aorta)."""
    from .fluoro import WIDE_RADIUS_PX

    lumen = np.where(where.radius >= WIDE_RADIUS_PX, where.radius, widest)
    return where.distance > lumen + JUNCTION_SLACK_PX


def without_cross_branches(vessel: np.ndarray, node_angle: np.ndarray, beyond: np.ndarray | None = None) -> np.ndarray:
    """``vessel`` without the branches that run across the projected tree (module docstring).

    Parameters
    ----------
    vessel : numpy.ndarray of bool, shape (rows, cols)
        The vessel mask on the segmentation's reduced grid.
    node_angle : numpy.ndarray, same shape
        Per pixel, the axis angle (radians, of (d_col, d_row)) of the nearest projected vessel.
    beyond : numpy.ndarray of bool, same shape, optional
        Pixels outside the projected lumen (:func:`beyond_projected_lumen`); None: only the
        mask's own lumen counts.

    Returns
    -------
    numpy.ndarray of bool, same shape: a subset of ``vessel``.
    """
    from skimage.morphology import skeletonize

    from ..skeleton import local_radius

    if not vessel.any():
        return vessel
    skeleton = skeletonize(vessel)
    pixels = np.argwhere(skeleton)
    rows, cols = pixels.T
    turned = _axis_difference(skeleton_directions(skeleton, pixels), node_angle[rows, cols]) > math.radians(ACROSS_DEG)
    if not turned.any() or turned.all():
        return vessel
    depth = local_radius(vessel, pixels) + 0.5          # distance to the nearest background pixel
    # a turned pixel inside both lumens is a junction, not a branch across
    to_along, nearest = cKDTree(pixels[~turned]).query(pixels[turned])
    across = np.zeros_like(skeleton)
    outside = to_along > depth[~turned][nearest] + JUNCTION_SLACK_PX
    if beyond is not None:
        outside |= beyond[rows[turned], cols[turned]]
    across[rows[turned][outside], cols[turned][outside]] = True
    runs, count = ndi.label(across, structure=_EIGHT)
    dropped = np.bincount(runs.ravel(), minlength=count + 1) >= MIN_RUN_PX
    dropped[0] = False
    if not dropped.any():
        return vessel
    kept = ~dropped[runs[rows, cols]]
    return _explained_by(vessel, pixels, depth, kept)


def _explained_by(vessel: np.ndarray, skeleton: np.ndarray, depth: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """``vessel`` less the pixels that only dropped skeleton pixels explain: a pixel stays when its
    nearest skeleton pixel is kept, or when it lies inside the lumen of the nearest kept one (its
    ``depth``, the distance to the background, + 1). ``skeleton``: (n, 2) pixel indices,
    ``depth`` and ``kept`` per skeleton pixel. Only pixels within reach of a dropped skeleton
    pixel (twice its depth + 2) are looked at: the others are nearer to a kept one."""
    inside = np.argwhere(vessel)
    reach = 2.0 * float(depth[~kept].max()) + 2.0
    candidates = inside[np.isfinite(cKDTree(skeleton[~kept]).query(inside, distance_upper_bound=reach)[0])]
    nearest_is_kept = kept[cKDTree(skeleton).query(candidates)[1]]
    to_kept, nearest = cKDTree(skeleton[kept]).query(candidates)
    lost = ~(nearest_is_kept | (to_kept <= depth[kept][nearest] + 1.0))
    out = vessel.copy()
    out[tuple(candidates[lost].T)] = False
    return out

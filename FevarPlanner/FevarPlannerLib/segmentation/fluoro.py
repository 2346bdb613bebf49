"""Fluoroscopy frame -> vessel mask: Frangi vesselness, hysteresis and local contrast, with or without
the pre-operative tree as a prior; choosing the frame of a run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from ..files import InputError
from ..quality import DEFORMATION_MARGIN_MM, FluoroPrior
from .off_tree import tidy_unsubtracted, without_small_pieces
from .threshold import _remove_small_objects


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Block mean (float32) by an integer ``factor``; the last rows / columns padded by replication.

    Sums of strided views: no float64 copy and no copy of the full-resolution ``image`` (any
    numeric dtype) beyond one float32 pass over its rows.
    """
    if factor == 1:
        return np.asarray(image, dtype=np.float32)
    pad = ((0, (-image.shape[0]) % factor), (0, (-image.shape[1]) % factor))
    if any(p for _, p in pad):
        image = np.pad(image, pad, mode="edge")
    rows = image[0::factor].astype(np.float32)
    for k in range(1, factor):
        rows += image[k::factor]
    blocks = rows[:, 0::factor].copy()
    for k in range(1, factor):
        blocks += rows[:, k::factor]
    blocks *= np.float32(1.0 / factor ** 2)
    return blocks


def _linear_weights(n_coarse: int, factor: int, n_fine: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices and weights of linear interpolation from a block-mean grid to the fine grid.

    Fine pixel centres sit at ``(u + 0.5) / factor - 0.5`` on the coarse grid, where the block
    means sit (``align_corners=False``); positions outside the coarse grid take the edge value.
    """
    position = np.clip((np.arange(n_fine) + 0.5) / factor - 0.5, 0.0, n_coarse - 1)
    below = np.floor(position).astype(np.intp)
    above = np.minimum(below + 1, n_coarse - 1)
    return below, above, (position - below).astype(np.float32)


def _upsample(image: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling (float32) of a block-mean grid back onto the full grid of ``shape``,
    done separably: rows, then columns."""
    if factor == 1:
        return image
    image = np.asarray(image, dtype=np.float32)
    below, above, weight = _linear_weights(image.shape[0], factor, shape[0])
    rows = image[below]
    rows += weight[:, None] * (image[above] - rows)
    below, above, weight = _linear_weights(image.shape[1], factor, shape[1])
    full = rows[:, below]
    full += weight * (rows[:, above] - full)
    return full


def _fine_span(below: np.ndarray, above: np.ndarray, first: int, last: int) -> slice:
    """The fine indices whose interpolation reads a coarse index in ``first..last`` (``below`` and
    ``above`` are non-decreasing)."""
    return slice(int(np.searchsorted(above, first)), int(np.searchsorted(below, last, side="right")))


def _upsample_above(image: np.ndarray, factor: int, shape: tuple[int, int], level: float) -> np.ndarray:
    """``_upsample(image, factor, shape) > level`` for ``level >= 0`` and ``image >= 0``, interpolating
    only where ``image`` is non-zero: elsewhere the interpolation of zeros is 0 (not above ``level``).

    The same float32 operations on the same values as :func:`_upsample`, on the box of fine
    pixels that read a non-zero coarse value.
    """
    found = np.zeros(shape, dtype=bool)
    rows, cols = np.flatnonzero(image.any(axis=1)), np.flatnonzero(image.any(axis=0))
    if not len(rows):
        return found
    if factor == 1:
        return np.asarray(image) > level
    image = np.asarray(image, dtype=np.float32)
    below_r, above_r, weight_r = _linear_weights(image.shape[0], factor, shape[0])
    below_c, above_c, weight_c = _linear_weights(image.shape[1], factor, shape[1])
    span_r = _fine_span(below_r, above_r, rows[0], rows[-1])
    span_c = _fine_span(below_c, above_c, cols[0], cols[-1])
    part = image[below_r[span_r]]
    part += weight_r[span_r, None] * (image[above_r[span_r]] - part)
    full = part[:, below_c[span_c]]
    full += weight_c[span_c] * (part[:, above_c[span_c]] - full)
    found[span_r, span_c] = full > level
    return found


def _hessian_pair(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale-normalised Hessian eigenvalues of a Gaussian-smoothed image, unordered:
    (half trace + root, half trace - root). Second differences (edges copied from their
    neighbours) and the gradient of the gradient for the cross term, worked in place."""
    smooth = ndi.gaussian_filter(image, sigma, mode="nearest")
    hrr = np.empty_like(smooth)
    hcc = np.empty_like(smooth)
    _second_difference(smooth, hrr[1:-1], smooth[2:], smooth[1:-1], smooth[:-2])
    hrr[0], hrr[-1] = hrr[1], hrr[-2]
    _second_difference(smooth, hcc[:, 1:-1], smooth[:, 2:], smooth[:, 1:-1], smooth[:, :-2])
    hcc[:, 0], hcc[:, -1] = hcc[:, 1], hcc[:, -2]
    hrc = np.gradient(np.gradient(smooth, axis=0), axis=1)
    scale = np.float32(sigma ** 2)
    root = np.subtract(hrr, hcc)
    root *= np.float32(0.5)
    np.square(root, out=root)
    np.square(hrc, out=hrc)
    root += hrc
    np.sqrt(root, out=root)
    root *= scale
    half_trace = hrr
    half_trace += hcc
    half_trace *= np.float32(0.5)
    half_trace *= scale
    return half_trace + root, np.subtract(half_trace, root, out=hcc)


def _second_difference(smooth: np.ndarray, out: np.ndarray, after: np.ndarray, at: np.ndarray,
                       before: np.ndarray) -> None:
    """``out = after - 2 at + before`` (in that order of operations), without temporaries."""
    np.multiply(at, smooth.dtype.type(2), out=out)
    np.subtract(after, out, out=out)
    out += before


def _ordered(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a, b`` ordered element by element so that the first has the smaller magnitude."""
    swap = np.abs(a) > np.abs(b)
    return np.where(swap, b, a), np.where(swap, a, b)


def _hessian_eigenvalues(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale-normalised Hessian eigenvalues (|l1| <= |l2|) of a Gaussian-smoothed image."""
    return _ordered(*_hessian_pair(image, sigma))


def vesselness(image: np.ndarray, sigmas=(1.0, 2.0, 3.0, 4.5), *, polarities=("bright",), beta: float = 0.5,
               c_fraction: float = 0.5, inside: np.ndarray | None = None) -> dict:
    """Multi-scale Frangi vesselness of a 2D image, for bright and / or dark vessels.

    For each scale the Hessian eigenvalues ``l1, l2`` (``|l1| <= |l2|``) give
    ``V = exp(-Rb^2 / (2 beta^2)) (1 - exp(-S^2 / (2 c^2)))`` with ``Rb = l1 / l2``,
    ``S = sqrt(l1^2 + l2^2)`` and ``c = c_fraction * max S``; ``V = 0`` where ``l2`` has the
    wrong sign for the polarity (``l2 < 0`` for bright vessels, ``> 0`` for dark ones).

    ``inside`` (bool, the image's shape): ``V`` is computed only there and is 0 elsewhere,
    the same values as the whole image's ``V`` times ``inside`` (``c`` still comes from the
    whole image; ``S^2`` does not depend on the order of ``l1, l2``).

    Returns
    -------
    dict
        ``polarity -> V``, the maximum over scales (float32, same shape as ``image``).
    """
    image = np.asarray(image, dtype=np.float32)
    picked = None if inside is None else np.flatnonzero(inside)
    size = image.size if picked is None else len(picked)
    best = {polarity: np.zeros(size, dtype=np.float32) for polarity in polarities}
    for sigma in sigmas:
        a, b = _hessian_pair(image, float(sigma))
        structure = a ** 2 + b ** 2                     # = l1^2 + l2^2: a sum does not depend on the order
        c2 = (c_fraction ** 2) * float(structure.max()) + 1e-12
        if picked is not None:
            a, b, structure = a.reshape(-1)[picked], b.reshape(-1)[picked], structure.reshape(-1)[picked]
        l1, l2 = _ordered(a.reshape(-1), b.reshape(-1))
        rb2 = (l1 / np.where(l2 == 0, 1e-12, l2)) ** 2
        response = np.exp(-rb2 / (2 * beta ** 2)) * (1 - np.exp(-structure.reshape(-1) / (2 * c2)))
        for polarity, running in best.items():
            right_sign = (l2 < 0) if polarity == "bright" else (l2 > 0)
            np.maximum(running, np.where(right_sign, response, 0.0), out=running)
    if picked is None:
        return {polarity: running.reshape(image.shape) for polarity, running in best.items()}
    out = {}
    for polarity, running in best.items():
        out[polarity] = np.zeros(image.shape, dtype=np.float32)
        out[polarity].reshape(-1)[picked] = running
    return out


def _hysteresis(image: np.ndarray, low: float, high: float) -> np.ndarray:
    """``skimage.filters.apply_hysteresis_threshold``: the 4-connected pieces above ``low`` that hold a
    pixel above ``high``; each piece marked by indexing its label, without a sum per label."""
    low = np.clip(low, a_min=None, a_max=high)
    labels, count = ndi.label(image > low)
    touched = np.zeros(count + 1, dtype=bool)
    touched[labels[image > high]] = True
    return touched[labels]


def _cross_dilation(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``ndi.binary_dilation(mask, iterations=iterations)`` (the 4-connected cross, nothing beyond
    the grid) of a 2D bool mask, by shifted ORs."""
    out = np.array(mask, dtype=bool)
    for _ in range(iterations):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out


def _cross_erosion(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``ndi.binary_erosion(mask, iterations=iterations)`` (the 4-connected cross; beyond the grid
    counts as background) of a 2D bool mask, by shifted ANDs."""
    out = np.array(mask, dtype=bool)
    for _ in range(iterations):
        kept = out.copy()
        kept[1:] &= out[:-1]
        kept[:-1] &= out[1:]
        kept[:, 1:] &= out[:, :-1]
        kept[:, :-1] &= out[:, 1:]
        kept[[0, -1]] = False
        kept[:, [0, -1]] = False
        out = kept
    return out


def _diamond_opening(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary opening of a 2D bool mask by the diamond of ``radius`` (pixels at city-block distance
    <= radius): erosion then dilation by the cross, ``radius`` times each (the diamond is the
    cross added to itself ``radius`` times; on the grid's box the steps can always stay inside)."""
    return _cross_dilation(_cross_erosion(mask, radius), radius)


def _grey_frame(image: np.ndarray, photometric: str | None) -> np.ndarray:
    """The frame as a grey image (RGB averaged), MONOCHROME1 turned to MONOCHROME2: float32, or
    an integer frame as it is (always finite; :func:`_downsample` turns what is used to float32,
    sparing a float copy of the whole frame)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[-1] in (3, 4):
        image = image[..., :3].mean(axis=-1)
    if image.ndim != 2 or min(image.shape) < 1:
        raise InputError(f"fluoroscopy frame must be 2D (or RGB), got shape {image.shape}")
    monochrome1 = photometric is not None and photometric.upper() == "MONOCHROME1"
    if (np.issubdtype(image.dtype, np.integer) or image.dtype == bool) and not monochrome1:
        return image
    image = image.astype(np.float32, copy=False)
    if not np.isfinite(image).all():
        raise InputError("fluoroscopy frame contains NaN or infinite values")
    if monochrome1:
        image = -image
    return image


def _normalise(image: np.ndarray) -> np.ndarray:
    """``image`` scaled to [0, 1] by its 0.5 / 99.5 percentiles."""
    lo, hi = np.percentile(image, [0.5, 99.5])
    if hi <= lo:
        raise InputError("fluoroscopy frame is flat (no contrast)")
    return np.clip((image - lo) / (hi - lo), 0.0, 1.0)


def _local_contrast(image: np.ndarray, radius: int) -> np.ndarray:
    """White top-hat: ``image`` minus its grey opening with a (2 radius + 1)^2 square (centred,
    as ``ndi.grey_dilation(ndi.grey_erosion(image, size), size)``)."""
    eroded = _centred_square_extreme(image, radius, np.minimum, np.inf)
    return image - _centred_square_extreme(eroded, radius, np.maximum, -np.inf)


def _centred_square_extreme(image: np.ndarray, radius: int, reduce, fill: float) -> np.ndarray:
    """``reduce`` (np.minimum / np.maximum) of ``image`` over the (2 radius + 1)^2 square centred on
    each pixel, cut at the grid's edge: ``ndi.minimum_filter`` / ``ndi.maximum_filter`` with that
    size, whose mirrored pixels beyond the edge repeat pixels already in the window. Along
    rows, then columns, each by doubling spans over the axis padded with ``fill``."""
    out = np.asarray(image)
    n = 2 * radius + 1
    for axis in range(2):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (radius, radius)
        current, span = np.pad(out, pad, constant_values=fill), 1
        while span < n:         # current[k] = reduce over span pixels from k (of the padded axis)
            count = span if 2 * span <= n else n - span
            ahead = current[count:] if axis == 0 else current[:, count:]
            current = reduce(current[:-count] if axis == 0 else current[:, :-count], ahead)
            span += count
        out = current
    return out


def segment_fluoro(image: np.ndarray, prior: "FluoroPrior | None" = None, *, vessels: str = "auto",
                   photometric: str | None = None,
                   sigmas=(1.0, 2.0, 3.0, 4.5), work_size: int = 256, high: float = 0.25, low: float = 0.08,
                   contrast_fraction: float = 0.35, min_area_fraction: float = 0.002) -> np.ndarray:
    """Binary vessel mask of a fluoroscopy / DSA frame on the frame's pixel grid.

    The frame (MONOCHROME1 inverted when ``photometric`` says so) is reduced by a block mean
    to about ``work_size`` pixels, normalised, and turned so that vessels are bright. Frangi
    vesselness over ``sigmas`` (pixels of the reduced grid) is hysteresis-thresholded at
    ``high`` / ``low`` times its 99.5th percentile to find the vessel tree; its extent is then
    refined by local contrast (white top-hat above ``contrast_fraction`` of the tree's median
    contrast), objects smaller than ``min_area_fraction`` of the frame are dropped, and the
    slightly smoothed result is upsampled bilinearly to the input grid and cut at 0.5.

    With a ``prior`` (the pre-operative tree projected through P, :class:`FluoroPrior`) the
    search is confined to a band around the projected tree, widened by the expected
    deformation (:data:`DEFORMATION_MARGIN_MM`); the polarity is read off the frame (inside
    the projected tree darker or brighter than around it, so subtracted and plain frames of
    either polarity work); the Frangi scales follow the projected radii; the hysteresis
    thresholds are fractions of each labelled vessel's own response, so that a faint thin
    renal artery is not measured against the aorta, and a renal whose faint outer part the
    hysteresis cannot reach (its response gone over a few pixels at the aorta's edge, a bubble
    or a clip) is tracked along its projection from the part found (:func:`_renals_tracked`);
    each pixel's contrast is taken relative
    to the contrast on the vessel's centre line nearby and the edge is placed where it falls
    to :data:`EDGE_LEVEL` on the upsampled grid (the mask keeps the lumen's width and the
    branch its tip); a white top-hat
    removes bone, soft tissue, table and collimator edges (broad or step-like structures); on
    an unsubtracted frame with bone under the vessels the aorta's extent is read from bands
    between two matching edges (:func:`_bands_between_edges`), which a vertebral body's edge
    inside its lumen does not cut; long, straight components thinner than the vessel expected there (wires, catheters,
    sheaths) are dropped. A (n, rows, cols) run is reduced to its frame with the most
    contrast inside the projected tree (:func:`select_frame`).

    Parameters
    ----------
    image : numpy.ndarray
        2D frame (any numeric dtype; RGB is averaged) or a (n, rows, cols) run.
    prior : FluoroPrior, optional
        Where the vessels must be; None keeps the prior-free behaviour.
    vessels : {'dark', 'bright', 'auto'}
        Vessel polarity after the photometric correction; ``'auto'`` picks the one with the
        stronger tubular response (without a prior) or the one the prior sees (with it).
    photometric : str, optional
        DICOM Photometric Interpretation; ``'MONOCHROME1'`` inverts the grey scale.

    Returns
    -------
    numpy.ndarray of bool
        Vessel mask, same shape as (one frame of) ``image``.
    """
    if vessels not in ("dark", "bright", "auto"):
        raise ValueError(f"vessels must be 'dark', 'bright' or 'auto', got {vessels!r}")
    frames = _frames(image)
    image = frames[select_frame(image, prior, photometric=photometric)] if len(frames) > 1 else image
    frame = _grey_frame(image, photometric)
    if prior is not None:
        return _segment_fluoro_with_prior(frame, prior, vessels, work_size, high, low, contrast_fraction,
                                          min_area_fraction)
    factor = max(1, int(round(max(frame.shape) / work_size)))
    small = _normalise(_downsample(frame, factor))
    responses = vesselness(small, sigmas, polarities=("bright", "dark") if vessels == "auto" else (vessels,))
    if vessels == "auto":    # the polarity with the stronger tubular responses
        vessels = max(responses, key=lambda polarity: float(np.percentile(responses[polarity], 98)))
    oriented = small if vessels == "bright" else 1.0 - small
    vessel = _vessel_region(oriented, responses[vessels], max(sigmas), high, low, contrast_fraction)
    vessel = _remove_small_objects(vessel, min_area_fraction * vessel.size)
    soft = ndi.gaussian_filter(vessel.astype(np.float32), 0.5)     # smooth edges before upsampling
    return _upsample_above(soft, factor, frame.shape, 0.5)


def _vessel_region(oriented: np.ndarray, response: np.ndarray, max_sigma: float, high: float, low: float,
                   contrast_fraction: float, reference: float | None = None) -> np.ndarray:
    """Binary vessel mask on the reduced grid: the hysteresis tree widened by local contrast.

    ``reference`` (default: the 99.5th percentile of ``response``) is what ``high`` and ``low``
    are fractions of."""
    reference = (float(np.percentile(response, 99.5)) if reference is None else reference) + 1e-12
    tree = _hysteresis(response / reference, low, high)
    if not tree.any():
        return tree
    radius = int(math.ceil(3 * max_sigma))
    contrast = _local_contrast(oriented, radius)
    tree_contrast = float(np.median(contrast[tree]))
    if tree_contrast <= 0:
        return tree
    near_tree = _cross_dilation(tree, int(math.ceil(max_sigma)))
    vessel = (contrast > contrast_fraction * tree_contrast) & near_tree
    labels, _ = ndi.label(vessel)
    touching = np.unique(labels[tree & vessel])
    return np.isin(labels, touching[touching > 0])


# ----------------------------------------------------------------------------------------
# Fluoroscopy with the pre-operative tree as a prior
# ----------------------------------------------------------------------------------------

def _frames(image: np.ndarray) -> list[np.ndarray]:
    """The frames of a run: a (n, rows, cols) stack, or one 2D (or RGB) frame."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[-1] not in (3, 4):
        return [image[n] for n in range(image.shape[0])]
    return [image]


def _polarity_by_prior(small: np.ndarray, distance: np.ndarray, nearest: np.ndarray, prior: FluoroPrior,
                       factor: int) -> str:
    """'dark' or 'bright': the sign of (inside the projected tree) - (a ring just outside it)."""
    radius = prior.radii_px[nearest] / factor
    core = distance <= np.maximum(0.5 * radius, 1.0)
    ring = (distance > radius + 2.0) & (distance <= 2.0 * radius + 6.0)
    if not core.any() or not ring.any():
        return "dark"
    return "dark" if np.median(small[core]) < np.median(small[ring]) else "bright"


def frame_contrast_in_prior(frame: np.ndarray, prior: FluoroPrior, *, photometric=None, work_size: int = 256) -> float:
    """|median inside the projected tree - median of a ring around it| over the frame's spread."""
    grey = _grey_frame(frame, photometric)
    factor = max(1, int(round(max(grey.shape) / work_size)))
    small = _downsample(grey, factor)
    spread = float(np.subtract(*np.percentile(small, [99.5, 0.5])))
    if spread <= 0:
        return 0.0
    distance, nearest = prior.rasterise(small.shape, factor)
    radius = prior.radii_px[np.maximum(nearest, 0)] / factor
    core = distance <= np.maximum(0.5 * radius, 1.0)
    ring = (distance > radius + 2.0) & (distance <= 2.0 * radius + 6.0)
    if not core.any() or not ring.any():
        return 0.0
    return abs(float(np.median(small[core]) - np.median(small[ring]))) / spread


def select_frame(image: np.ndarray, prior: FluoroPrior | None = None, *, photometric=None) -> int:
    """Index of the frame of a run with the most contrast inside the projected tree.

    Without a prior: the frame with the strongest top-hat contrast (the fullest vessels).
    """
    frames = _frames(image)
    if len(frames) == 1:
        return 0
    if prior is not None:
        scores = [frame_contrast_in_prior(f, prior, photometric=photometric) for f in frames]
    else:
        scores = []
        for f in frames:
            small = _downsample(_grey_frame(f, photometric), max(1, int(round(max(f.shape[:2]) / 128))))
            lo, hi = np.percentile(small, [0.5, 99.5])
            scores.append(0.0 if hi <= lo else float(np.percentile(_local_contrast(-(small - lo) / (hi - lo), 4), 99)))
    return int(np.argmax(scores))


def _piece_shapes(labels: np.ndarray, n: int, value: np.ndarray) -> tuple:
    """Per labelled piece 1..n: (pixel count, length, elongation, median of ``value``). The length is
    that of a bar with the piece's spread along its principal axis (2 sqrt(3) sigma_major), the
    elongation sigma_minor / sigma_major; from the pieces' moments, all pieces at once."""
    rows, cols = np.nonzero(labels)
    index = labels[rows, cols]
    rows, cols = rows.astype(float), cols.astype(float)

    def per_piece(values):
        return np.bincount(index, weights=values, minlength=n + 1)[1:]

    count = np.bincount(index, minlength=n + 1)[1:].astype(float)
    safe = np.maximum(count, 1.0)
    mean_r, mean_c = per_piece(rows) / safe, per_piece(cols) / safe
    var_r = per_piece(rows ** 2) / safe - mean_r ** 2
    var_c = per_piece(cols ** 2) / safe - mean_c ** 2
    cov = per_piece(rows * cols) / safe - mean_r * mean_c
    half_trace, root = 0.5 * (var_r + var_c), np.sqrt((0.5 * (var_r - var_c)) ** 2 + cov ** 2)
    major = np.sqrt(np.maximum(half_trace + root, 0.0))
    minor = np.sqrt(np.maximum(half_trace - root, 0.0))
    return count, 2.0 * math.sqrt(3.0) * major, minor / np.maximum(major, 1e-9), _piece_medians(index, value[labels > 0], n)


def _piece_medians(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``np.median`` of ``values`` per piece 1..n (``index``: each value's piece), all at once."""
    order = np.lexsort((values, index))
    ranked = values[order].astype(float)
    count = np.bincount(index, minlength=n + 1)[1:]
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    low = start + np.maximum(count - 1, 0) // 2
    high = start + count // 2
    medians = np.zeros(n)
    present = count > 0
    medians[present] = 0.5 * (ranked[low[present]] + ranked[np.minimum(high[present], len(ranked) - 1)])
    return medians


def _straight_thin_devices(mask: np.ndarray, expected_width: np.ndarray, *, straightness: float = 0.08,
                           width_ratio: float = 0.55, min_length: float = 20.0) -> np.ndarray:
    """Components that look like a wire, catheter or sheath: long, very straight and thinner than
    the vessel expected where they lie. Returns the mask of those components."""
    labels, n = ndi.label(mask)
    if n == 0:
        return np.zeros_like(mask)
    count, length, elongation, expected = _piece_shapes(labels, n, expected_width)
    width = count / np.maximum(length, 1.0)
    device = (count >= 3) & (length >= min_length) & (elongation <= straightness) & (width < width_ratio * expected)
    return np.concatenate([[False], device])[labels]


#: A wide vessel's lumen (its core: what an opening by a disk of CORE_RADII times
#: WIDE_RADIUS_PX keeps, so that a wire, catheter or sheath no longer joins pieces, less the
#: pixels whose contrast per px of expected radius falls under GAP_FRACTION of the wide vessels'
#: median) runs on: its longest core piece spans at least LONGEST_SHARE of the projected wide
#: vessels' length. Vertebral bodies, pelvic fragments and box corners without contrast in the
#: lumen (the discs between the vertebrae, the devices cut away) are short pieces.
CORE_RADII = 0.67
GAP_FRACTION = 0.5
LONGEST_SHARE = 0.4


def _wide_vessels_are_blocks(vessel: np.ndarray, radius: np.ndarray, contrast: np.ndarray,
                             expected_length: float) -> bool:
    """True when the wide part of ``vessel`` (where ``radius``, the widest projected radius nearby
    (:func:`_widest_nearby`), is at least :data:`WIDE_RADIUS_PX`) has no core piece as long as
    :data:`LONGEST_SHARE` of ``expected_length`` (px, the projected wide vessels'): short blocks
    (vertebral bodies without contrast), not an aorta. ``contrast``: the frame with vessels
    bright and the background flattened.

    The widest radius nearby, not the nearest node's: the aorta's pixels at a renal ostium lie
    nearest to the renal's first nodes; measured by the renal's radius they were not wide, cut
    the aorta's core in pieces and a whole angiogram was refused (bench seed 238, Dice 0)."""
    wide = vessel & (radius >= WIDE_RADIUS_PX)
    if not wide.any():
        return False
    core_radius = max(1, int(round(CORE_RADII * WIDE_RADIUS_PX)))
    offsets = np.mgrid[-core_radius:core_radius + 1, -core_radius:core_radius + 1]
    disk = np.hypot(*offsets) <= core_radius
    per_radius = contrast / np.maximum(radius, 1.0)        # a lumen's contrast grows with its chord
    lumen = wide & (per_radius >= GAP_FRACTION * float(np.median(per_radius[wide])))
    if np.array_equal(disk, np.abs(offsets).sum(axis=0) <= core_radius):    # a diamond (radius <= 2)
        core = _diamond_opening(lumen, core_radius)
    else:
        core = ndi.binary_opening(lumen, structure=disk)
    labels, n = ndi.label(core)
    if n == 0:
        return True
    _, length, _, _ = _piece_shapes(labels, n, radius)
    return float(length.max()) < LONGEST_SHARE * expected_length


def _wide_tree_length(prior: FluoroPrior, factor: int, shape: tuple) -> float:
    """The length (px of the grid reduced by ``factor``) of the projected wide vessels inside the
    frame: the principal extent (2 sqrt(3) sigma) of their nodes."""
    uv = (prior.uv + 0.5) / factor - 0.5
    inside = (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] >= 0)
              & (uv[:, 1] < shape[0]) & (prior.radii_px / factor >= WIDE_RADIUS_PX))
    if inside.sum() < 2:
        return 0.0
    centred = uv[inside] - uv[inside].mean(axis=0)
    return 2.0 * math.sqrt(3.0) * math.sqrt(max(float(np.linalg.eigvalsh(centred.T @ centred / len(centred))[-1]), 0.0))


def _within_expected_width(vessel: np.ndarray, radius: np.ndarray, slack: float = 1.4, spine=None) -> np.ndarray:
    """Pixels no farther from the mask's centre line than ``slack`` times the expected radius
    (+1 px): a vessel cannot be wider than the pre-operative lumen allows, a vertebra or a
    bowel loop touching it can. ``spine``: the centre line's (distance, (rows, cols)) from
    :func:`_spine_lookup` when already at hand (default: that of ``vessel``).

    The radius is read at the nearest centre-line pixel, and also at the nearest pixel of a wide
    vessel's centre line (:data:`WIDE_RADIUS_PX`): where a renal's centre line stops short of
    the aorta and a thin vessel projected along the aorta (the superior mesenteric) gives the
    aorta's half its thin radius, the aorta's wall beside the renal's ostium is nearer to the
    renal's line and would be cut at the renal's width."""
    if not vessel.any():
        return vessel
    distance, (ri, ci) = _spine_lookup(vessel) if spine is None else spine
    within = distance <= slack * radius[ri, ci] + 1.0
    wide = (distance == 0) & (radius >= WIDE_RADIUS_PX)
    if wide.any():
        wide_distance, (wi, wj) = ndi.distance_transform_edt(~wide, return_indices=True)
        within |= wide_distance <= slack * radius[wi, wj] + 1.0
    return within


def _spine_lookup(region: np.ndarray):
    """Distance to the skeleton of ``region`` and, per pixel, the nearest skeleton pixel."""
    from skimage.morphology import skeletonize

    return ndi.distance_transform_edt(~skeletonize(region), return_indices=True)


def _prior_scales(prior: FluoroPrior, factor: int, n_scales: int) -> np.ndarray:
    """Frangi scales (px of the reduced grid) spanning 0.6 x the projected radii (5th-99th percentile)."""
    r_min = max(float(np.percentile(prior.radii_px, 5)) / factor, 0.8)
    r_max = max(float(np.percentile(prior.radii_px, 99)) / factor, r_min)
    return np.geomspace(max(0.6 * r_min, 0.8), max(0.6 * r_max, 1.0), n_scales)


def _percentile_among_zeros(values: np.ndarray, q: float, total: int) -> float:
    """``np.percentile`` (linear) of ``values`` (>= 0) padded with zeros to ``total`` entries,
    without building the padded array: the cropped response ranks as the whole grid's would."""
    values = values.ravel()
    zeros = total - values.size
    position = q / 100.0 * (total - 1) - zeros
    if position < 0:
        return 0.0
    below = int(math.floor(position))
    low_high = np.partition(values, [below, min(below + 1, values.size - 1)])
    low, high = float(low_high[below]), float(low_high[min(below + 1, values.size - 1)])
    if below == -1:
        low = 0.0
    return low + (position - below) * (high - low)


def _segment_fluoro_with_prior(frame: np.ndarray, prior: FluoroPrior, vessels: str, work_size: int,
                               high: float, low: float, contrast_fraction: float, min_area_fraction: float,
                               n_scales: int = 4):
    """Vessel mask of one grey frame, looking only in the band around the projected tree.

    Everything runs on the band's bounding box (padded by the filters' reach), read off the
    prior once per grid (:meth:`FluoroPrior.band`); thresholds that are fractions of the
    whole reduced grid (response percentile, smallest object) keep counting the whole grid.
    """
    factor = max(1, int(round(max(frame.shape) / work_size)))
    small_shape = (-(-frame.shape[0] // factor), -(-frame.shape[1] // factor))
    sigmas = _prior_scales(prior, factor, n_scales)
    reach = int(math.ceil(4 * sigmas[-1])) + int(math.ceil(3 * sigmas[-1])) + 2
    where = prior.band(small_shape, factor, reach)
    rows, cols = where.box
    crop = frame[rows.start * factor:rows.stop * factor, cols.start * factor:cols.stop * factor]
    small = _normalise(_downsample(crop, factor))
    distance, nearest, radius, band = where.distance, where.nearest, where.radius, where.band
    if vessels == "auto":
        vessels = _polarity_by_prior(small, distance, nearest, prior, factor)
    oriented = small if vessels == "bright" else 1.0 - small
    widest = prior.derived(("widest", small_shape, factor, reach), lambda: _widest_nearby(radius))
    pedestal, bright_share, level = _background_reading(oriented, where)
    flat = pedestal < FLAT_PEDESTAL and bright_share <= FLAT_BRIGHT_SHARE
    if flat:
        oriented = oriented - np.float32(level)         # already flat: only its level goes
        extent = oriented
    else:
        across = prior.derived(("across", small_shape, factor, reach), lambda: _lines_across(prior, nearest, radius))
        flattened = _flatten_across(oriented, across)
        extent = flattened
        if pedestal >= BONE_PEDESTAL:       # bone under the vessels: its edges may cross the aorta's lumen
            over_bone = prior.derived(("aorta_lumen", small_shape, factor, reach),
                                      lambda: _projected_aorta_lumen(prior, where))
            extent = _with_bands_between_edges(flattened, oriented, across, over_bone)
        oriented = flattened
    response = vesselness(oriented, sigmas, polarities=("bright",), inside=band)["bright"]
    total = small_shape[0] * small_shape[1]
    reference = _percentile_among_zeros(response, 99.5, total)
    codes = prior.derived(("label_codes", small_shape, factor, reach), lambda: _label_codes(prior, nearest))
    response = response / _per_vessel_reference(response, codes, band, reference)
    tree = _hysteresis(response, low, high)
    if not tree.any():
        return np.zeros(frame.shape, dtype=bool)
    grid_key = (small_shape, factor, reach)
    tree |= _renals_tracked(tree, response, prior, where, grid_key, low)
    spine = _spine_lookup(tree)
    vessel, relative = _vessel_region_relative(extent, tree, spine, radius, float(sigmas[-1]), contrast_fraction)
    vessel &= band
    vessel &= _within_expected_width(vessel, widest, spine=spine)
    thin = vessel & ~_diamond_opening(vessel, 1)
    vessel &= ~(thin & (radius >= 2.0) & (distance > radius + 2.0))   # lines off a wide vessel's projection
    vessel &= ~_straight_thin_devices(vessel, 2.0 * radius)
    expected_length = prior.derived(("wide_length", small_shape, factor), lambda: _wide_tree_length(prior, factor, small_shape))
    if _wide_vessels_are_blocks(vessel, widest, oriented, expected_length):
        return np.zeros(frame.shape, dtype=bool)        # bones, no contrast: nothing to segment
    if flat:    # subtracted: only a renal cut off at the aorta's edge is bridged (off_tree.py)
        vessel, relative = without_small_pieces(vessel, prior, where, grid_key, min_area_fraction * total, relative)
    else:       # unsubtracted: bones and rulers across the vessels, cut-off branches (off_tree.py)
        vessel, relative = tidy_unsubtracted(vessel, prior, where, widest, grid_key, min_area_fraction * total,
                                             relative)
    soft = _soft_extent(vessel, relative, contrast_fraction)
    full = np.zeros(frame.shape, dtype=bool)
    full[rows.start * factor:rows.stop * factor, cols.start * factor:cols.stop * factor] = \
        _upsample_above(soft, factor, crop.shape, EDGE_LEVEL)
    return full


# ----------------------------------------------------------------------------------------
# Faint thin branches and the mask's width (with the prior): thresholds local to each vessel
# ----------------------------------------------------------------------------------------

#: A vessel's own strong response (this percentile over the pixels nearest to it) is what the
#: hysteresis thresholds are fractions of; never less than REFERENCE_FLOOR times the frame's.
VESSEL_REFERENCE_PERCENTILE = 99.0
REFERENCE_FLOOR = 0.2
#: The vessel's edge: where the local contrast falls to this fraction of the contrast on the
#: vessel's centre line nearby, after bilinear upsampling of the reduced grid. Chosen on rendered
#: phantom frames (``render_fluoro``, seeds 7 and 8, no benchmark set): the masked area of the
#: renals matches the lumen's within 1%, of the iliacs and the aorta 2-4% less (0.25: renals 4%
#: too wide; 0.35: everything 4-5% too narrow).
EDGE_LEVEL = 0.3
#: Projected radius (px of the reduced grid) from which a vessel counts as wide (aorta, iliacs).
WIDE_RADIUS_PX = 3.0
#: See :func:`_contrast_noise_floor`.
NOISE_FLOOR = 6.0


def _label_codes(prior: FluoroPrior, nearest: np.ndarray) -> tuple[int, np.ndarray]:
    """(number of labels, per pixel the code of the label of the ``nearest`` prior node)."""
    names, code_of_node = np.unique(np.asarray(prior.labels), return_inverse=True)
    return len(names), code_of_node[nearest]


def _per_vessel_reference(response: np.ndarray, codes: tuple, band: np.ndarray, reference: float) -> np.ndarray:
    """Per pixel, what the vesselness is measured against: the strong response of the labelled
    vessel whose projection is nearest (clipped to ``[REFERENCE_FLOOR, 1] x reference``).

    A thin renal artery responds far less than the aorta; against the aorta's reference its
    faint parts fall below the hysteresis thresholds and the branch ends early or is lost.
    """
    n_labels, code = codes
    scale = np.full(n_labels, reference, dtype=np.float32)
    sampled = response[::2, ::2][band[::2, ::2]]       # every fourth pixel is plenty for a percentile
    sampled_code = code[::2, ::2][band[::2, ::2]]
    for k in range(n_labels):
        values = sampled[sampled_code == k]
        if values.size:
            own = float(np.percentile(values, VESSEL_REFERENCE_PERCENTILE))
            scale[k] = min(max(own, REFERENCE_FLOOR * reference), reference)
    return scale[code] + np.float32(1e-12)


def _vessel_region_relative(oriented: np.ndarray, tree: np.ndarray, spine, radius: np.ndarray, max_sigma: float,
                            contrast_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The hysteresis ``tree`` widened by local contrast, each pixel's contrast taken relative to
    the contrast on the tree's centre line nearest to it (``spine``: :func:`_spine_lookup` of
    the tree), so that a faint thin branch keeps its full width and its tip.

    Returns the binary region (pixels above ``contrast_fraction`` of their local centre-line
    contrast, connected to the tree) and the relative contrast (for the sub-pixel edge)."""
    contrast = _local_contrast(oriented, int(math.ceil(3 * max_sigma)))
    near_tree = _cross_dilation(tree, int(math.ceil(max_sigma)))
    distance, (ri, ci) = spine
    on_spine = np.zeros(contrast.shape, dtype=np.float32)
    rows, cols = np.nonzero(distance == 0)
    on_spine[rows, cols] = np.maximum(_centre_line_contrast(contrast, tree, radius[rows, cols], rows, cols),
                                      _contrast_noise_floor(contrast, near_tree))
    peak = on_spine[ri, ci]
    relative = np.zeros(oriented.shape, dtype=np.float32)
    np.divide(contrast, peak, out=relative, where=peak > 0)
    vessel = (relative > contrast_fraction) & near_tree
    labels, _ = ndi.label(vessel)
    touching = np.unique(labels[tree & vessel])
    return np.isin(labels, touching[touching > 0]), relative


def _centre_line_contrast(contrast: np.ndarray, tree: np.ndarray, radius: np.ndarray, rows: np.ndarray,
                          cols: np.ndarray) -> np.ndarray:
    """What a vessel's edge is measured against, at the tree's centre-line pixels ``rows, cols``.

    On thin vessels (projected ``radius`` under :data:`WIDE_RADIUS_PX` px of the reduced grid) the
    3 x 3 maximum of the contrast. On wide ones the 5 x 5 median, so that a small dark spot
    inside the lumen (a branch seen end-on, a calcification) does not raise the reference and
    notch the edge; where the tree is thin although the vessel there must be wide (a catheter
    or wire along the aorta, a spur), the median reference of the wide centre line instead, so
    that the device is measured against the vessel and not against itself.
    """
    padded = np.pad(contrast, 2, mode="edge")
    padded_tree = np.pad(tree, 2)
    offsets = np.arange(-2, 3)
    index = ((rows + 2)[:, None, None] + offsets[:, None], (cols + 2)[:, None, None] + offsets)
    window = padded[index]
    thin = window[:, 1:4, 1:4].reshape(len(rows), -1).max(axis=1)
    wide = np.median(window.reshape(len(rows), -1), axis=1)
    is_wide = radius >= WIDE_RADIUS_PX
    full = padded_tree[index].reshape(len(rows), -1).mean(axis=1) >= 0.6
    if (is_wide & full).any():
        wide = np.where(full, wide, np.median(wide[is_wide & full]))
    return np.where(is_wide, wide, thin)


def _widest_nearby(radius: np.ndarray) -> np.ndarray:
    """The projected radius map's maximum over a window as wide as the widest vessel: where a
    thin branch seen end-on projects onto the aorta, the aorta's radius, not the branch's,
    bounds the mask's width."""
    reach = int(math.ceil(float(radius.max()))) if radius.size else 0
    return _centred_square_extreme(radius, reach, np.maximum, -np.inf) if reach > 0 else radius


def _contrast_noise_floor(contrast: np.ndarray, near_tree: np.ndarray) -> float:
    """The least centre-line contrast an edge may be measured against: NOISE_FLOOR times the
    median contrast away from the tree (what the noise alone gives), so that next to a faint
    thin branch the noise does not pass for the branch's edge."""
    away = contrast[::2, ::2][~near_tree[::2, ::2]]    # every fourth pixel is plenty for a median
    return NOISE_FLOOR * float(np.median(away)) if away.size else 0.0


def _soft_extent(vessel: np.ndarray, relative: np.ndarray, contrast_fraction: float) -> np.ndarray:
    """The mask's extent on the reduced grid as a continuous map whose :data:`EDGE_LEVEL` crossing,
    after bilinear upsampling, is the vessel's edge: the relative contrast (at most 1) on the
    region, and on the pixels just around it the partial contrast of an edge (below
    ``contrast_fraction``; a pixel above it that is not in the region was dropped on purpose,
    as a device, a bone or too wide, and stays out)."""
    rim = _cross_dilation(vessel) & ~vessel & (relative < contrast_fraction)
    return np.where(vessel | rim, np.clip(relative, 0.0, 1.0), 0.0).astype(np.float32)


# ----------------------------------------------------------------------------------------
# Unsubtracted frames: the background flattened across each vessel's expected direction
# ----------------------------------------------------------------------------------------

#: Line directions (d_row, d_col) of the openings that flatten the background: along u, the
#: rising diagonal, along v, the falling diagonal (0, 45, 90, 135 degrees).
LINE_STEPS = ((0, 1), (1, 1), (1, 0), (1, -1))
#: The opening's line spans this many times the widest expected radius (+ LINE_PAD_PX): it
#: must bridge the lumen even when the vessel runs up to ~40 degrees off its projected
#: direction (deformation, the 22.5 degree binning of the direction), and stay shorter than
#: a vertebral body or a pelvic plate so that they stay background.
LINE_RADII = 2.8
LINE_PAD_PX = 3.0
LINE_CLASS_RATIO = 1.25
#: A frame whose background next to the projected vessels stands less than this fraction of the
#: vessels' contrast above the background away from them (:func:`_background_reading`) is not
#: flattened: it is already flat (a subtracted frame), and the openings cost ~4 ms at 1024^2.
#: Between subtracted frames (< 0.12) and the unsubtracted bench frames (>= 0.2; seeds 102,
#: 201-203, every distractor or the spine alone). And at most FLAT_BRIGHT_SHARE of the pixels
#: away from the vessels may be brighter than they are (0 under an even or a falling exposure,
#: >= 0.003 with a shutter in view; see :func:`_background_reading`).
FLAT_PEDESTAL = 0.13
FLAT_BRIGHT_SHARE = 0.001
FLAT_RING_PERCENTILE = 75.0
FLAT_RING_GAP_PX = 2.0
#: The least background transmission a residue is divided by (:func:`_flatten_across`).
TRANSMISSION_FLOOR = 0.1
#: A diagonal line across a vessel does not fit in the corners of an upright block (a vertebral
#: body by a renal or an iliac), which would stay as bright triangles; a square as wide as the
#: line is long fits there and not in the vessel (:func:`_flatten_across`).
SQUARE_ON_DIAGONALS = True


@dataclass(frozen=True)
class LinesAcross:
    """Per line direction of :data:`LINE_STEPS` and line length (px of the reduced grid), where
    an opening by that line flattens the background: ``{(step index, length): bool map}``."""

    where: dict


def _node_directions(prior: FluoroPrior) -> np.ndarray:
    """Per node of the prior, the angle (radians, of (du, dv)) of its projected edges (their mean axis)."""
    tangent = np.zeros((len(prior.uv), 2))
    if len(prior.edges):
        d = prior.uv[prior.edges[:, 1]] - prior.uv[prior.edges[:, 0]]
        d = np.where(np.isfinite(d), d, 0.0)
        doubled = np.column_stack([d[:, 0] ** 2 - d[:, 1] ** 2, 2 * d[:, 0] * d[:, 1]])   # axis, not sign
        np.add.at(tangent, prior.edges[:, 0], doubled)
        np.add.at(tangent, prior.edges[:, 1], doubled)
    return 0.5 * np.arctan2(tangent[:, 1], tangent[:, 0])


def _lines_across(prior: FluoroPrior, nearest: np.ndarray, radius: np.ndarray) -> LinesAcross:
    """Which opening flattens the background where: a line across the projected vessel nearest
    to each pixel (the direction of :data:`LINE_STEPS` closest to the perpendicular of the
    vessel's projected direction), long enough to bridge it (:data:`LINE_RADII` times its
    projected ``radius``, in length classes a factor :data:`LINE_CLASS_RATIO` apart). Each
    direction is also allowed within its vessel's radius around where it is nearest, with the
    longest length met there: near a junction (a renal ostium, the bifurcation) a pixel of the
    wider vessel may lie nearest to a branch's first nodes."""
    node_step = np.round((_node_directions(prior) + 0.5 * np.pi) / (0.25 * np.pi)).astype(int) % len(LINE_STEPS)
    node_radius = np.zeros(len(prior.uv), dtype=radius.dtype)
    node_radius[nearest] = radius                       # per node: one radius on the grid
    needed = LINE_RADII * node_radius + LINE_PAD_PX
    node_class = LINE_PAD_PX * LINE_CLASS_RATIO ** np.ceil(np.log(needed / LINE_PAD_PX) / np.log(LINE_CLASS_RATIO))
    step_index, classes = node_step[nearest], node_class.astype(np.float32)[nearest]
    where = {}
    for k in range(len(LINE_STEPS)):
        own = step_index == k
        if not own.any():
            continue
        reach = max(1, int(math.ceil(float(radius[own].max()))))
        box, _ = _box_around(own, (reach, reach))
        length = ndi.maximum_filter(np.where(own[box], classes[box], np.float32(0.0)), size=2 * reach + 1)
        for value in np.unique(node_class.astype(np.float32)[node_step == k]):    # its nodes' classes
            found = length == value
            if found.any():
                where[(k, float(value))] = np.zeros(own.shape, dtype=bool)
                where[(k, float(value))][box] = found
    return LinesAcross(where)


def _line_extreme(image: np.ndarray, step: tuple, n: int, reduce, fill: float) -> np.ndarray:
    """``reduce`` (np.minimum / np.maximum) of ``image`` over ``n`` pixels along ``step`` (d_row,
    d_col) from each pixel (``fill`` beyond the grid), by doubling spans: log2(n) + 1 array
    operations between two padded buffers, no allocation per operation."""
    rows, cols = image.shape
    pad_r, pad_c = abs(step[0]) * n, abs(step[1]) * n
    buffers = [np.full((rows + 2 * pad_r, cols + 2 * pad_c), fill, dtype=image.dtype) for _ in range(2)]
    inside = (slice(pad_r, pad_r + rows), slice(pad_c, pad_c + cols))
    buffers[0][inside] = image

    def ahead(buffer, count):
        dr, dc = step[0] * count, step[1] * count
        return buffer[pad_r + dr:pad_r + dr + rows, pad_c + dc:pad_c + dc + cols]

    current, span = 0, 1
    while span < n:
        count = span if 2 * span <= n else n - span
        reduce(buffers[current][inside], ahead(buffers[current], count), out=buffers[1 - current][inside])
        current, span = 1 - current, span + count
    return buffers[current][inside]


def _line_opening(image: np.ndarray, step: tuple, length: float, closing: bool = False) -> np.ndarray:
    """Grey opening (``closing``: closing) of ``image`` by a straight line of ``length`` px along ``step``."""
    n = max(2, int(math.ceil(length / math.hypot(*step))) + 1)
    first, second = ((np.maximum, -np.inf), (np.minimum, np.inf)) if closing else \
        ((np.minimum, np.inf), (np.maximum, -np.inf))
    return _line_extreme(_line_extreme(image, step, n, *first), (-step[0], -step[1]), n, *second)


def _flatten_across(oriented: np.ndarray, across: LinesAcross) -> np.ndarray:
    """``oriented`` (vessels bright) less its background: per pixel, the largest residue of the
    openings :class:`LinesAcross` allows there. A line across a vessel does not fit in its lumen,
    so the vessel stays; it fits in what is wider than the vessel across it (vertebral bodies,
    the pelvis, a step at a table or box edge, the exposure's slope), so that goes. On diagonal
    lines the opening by a square as wide as the line is long joins the background
    (:data:`SQUARE_ON_DIAGONALS`)."""
    flat = np.zeros_like(oriented)
    boxes = {key: _box_around(chosen, 2 * (int(math.ceil(key[1])) + 2) * np.abs(LINE_STEPS[key[0]]))
             for key, chosen in across.where.items()}
    squares = _diagonal_squares(oriented, across) if SQUARE_ON_DIAGONALS else {}
    for (k, length), chosen in across.where.items():
        step = LINE_STEPS[k]
        box, inner = boxes[(k, length)]
        part = oriented[box]
        background = _line_opening(part, step, length)
        if (k, length) in squares:
            np.maximum(background[inner], squares[(k, length)], out=background[inner])
        residue = (part - background) / np.maximum(1.0 - background, np.float32(TRANSMISSION_FLOOR))
        target = flat[box][inner]
        np.maximum(target, np.where(chosen[box][inner], residue[inner], 0.0), out=target)
    return flat


# ----------------------------------------------------------------------------------------
# A bone's edge inside the aorta's lumen: a vessel is a band between two matching edges
# ----------------------------------------------------------------------------------------

#: A band's width along the line, in diameters of the projected vessel (the upper end + 1 px):
#: the line runs up to 22.5 degrees off the vessel's perpendicular, and the vessel may turn.
BAND_WIDTH_DIAMETERS = (0.75, 1.2)
#: The weaker of a band's two edges is at least this fraction of the stronger.
BAND_EDGE_BALANCE = 0.5
#: A band's inside stands this fraction of the band's contrast above the lower of its flanks (a
#: bone's step inside the band is allowed).
BAND_INSIDE = 0.3
#: A pedestal (:func:`_background_reading`) from which bone lies under the vessels: unsubtracted
#: bench frames 0.17-0.53, subtracted ones with a shutter in view up to 0.22 (development seeds
#: 231-250), whose masks a band between edges would only change.
BONE_PEDESTAL = 0.25
#: Where bands between edges are looked for: within this many projected radii (+
#: BAND_LUMEN_PAD_PX) of the projected aorta (the vessel a vertebral body lies under).
BAND_LUMEN_RADII = 1.5
BAND_LUMEN_PAD_PX = 2.0


def _with_bands_between_edges(flattened: np.ndarray, oriented: np.ndarray, across: LinesAcross,
                              over_bone: np.ndarray) -> np.ndarray:
    """``flattened`` (:func:`_flatten_across` of ``oriented``, vessels bright), raised where
    ``over_bone`` (bool, the grid's shape: the projected aorta's lumen on a frame with bone under
    the vessels) to the contrast of a band between two matching edges read along the same lines
    across (:func:`_bands_between_edges`), which a bone's step inside the lumen leaves whole.

    Only the vessel's extent is read from this map: the vesselness and the hysteresis tree stay
    those of ``flattened`` (their thresholds are fractions of the whole frame's responses).
    """
    extent = flattened.copy()
    for (k, length), chosen in across.where.items():
        here = chosen & over_bone
        if not here.any():
            continue
        step, radius = LINE_STEPS[k], (length - LINE_PAD_PX) / LINE_RADII
        reach, _, longest = _band_extents(step, radius)
        box, inner = _box_around(here, (longest + reach + 1) * np.abs(step))     # all its bands read
        band = _bands_between_edges(oriented[box], step, radius, here[box])
        target = extent[box][inner]
        np.maximum(target, np.where(here[box][inner], band[inner], 0.0), out=target)
    return extent


def _projected_aorta_lumen(prior: FluoroPrior, where) -> np.ndarray:
    """Pixels of the band's box nearest to the projected aorta and within
    :data:`BAND_LUMEN_RADII` of its projected radius (+ :data:`BAND_LUMEN_PAD_PX`); not those
    nearest to the aorta's free end (beyond it a vertebral body as wide as the aorta is a band
    too, and its skeleton grew spurs off the aorta's end: bench seed 231)."""
    degree = np.bincount(np.asarray(prior.edges, dtype=np.intp).ravel(), minlength=len(prior.uv))
    inner_aorta = (np.asarray(prior.labels) == "aorta") & (degree != 1)
    return inner_aorta[where.nearest] & (where.distance <= BAND_LUMEN_RADII * where.radius + BAND_LUMEN_PAD_PX)


def _shifted(image: np.ndarray, step: tuple, n: int, fill) -> np.ndarray:
    """``out[p] = image[p + n step]`` (``fill`` beyond the grid)."""
    out = np.full(image.shape, fill, dtype=image.dtype)
    rows, cols = image.shape
    dr, dc = step[0] * n, step[1] * n
    if abs(dr) >= rows or abs(dc) >= cols:
        return out
    out[max(-dr, 0):rows - max(dr, 0), max(-dc, 0):cols - max(dc, 0)] = \
        image[max(dr, 0):rows + min(dr, 0), max(dc, 0):cols + min(dc, 0)]
    return out


def _steepest(jump: np.ndarray, step: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(rise, fall): ``jump`` where it is positive and a maximum along ``step`` (against its two
    neighbours, 0 beyond the grid), else 0; ``-jump`` where it is positive and a minimum, else 0."""
    ahead, behind = _shifted(jump, step, 1, 0.0), _shifted(jump, step, -1, 0.0)
    rise = np.where((jump > 0) & (jump >= ahead) & (jump >= behind), jump, 0.0).astype(jump.dtype)
    fall = np.where((jump < 0) & (jump <= ahead) & (jump <= behind), -jump, 0.0).astype(jump.dtype)
    return rise, fall


def _bands_between_edges(part: np.ndarray, step: tuple, radius: float,
                         needed: np.ndarray | None = None) -> np.ndarray:
    """Per pixel of ``part`` (vessels bright), the contrast of a band of the vessel's width that
    holds it, read along ``step``: a rise and a fall (each where the change over 2 x about a
    third of ``radius`` is steepest) :data:`BAND_WIDTH_DIAMETERS` apart, of matching size
    (:data:`BAND_EDGE_BALANCE`), the inside above the lower flank (:data:`BAND_INSIDE`). Each rise
    is paired with its nearest such fall and each fall with its nearest rise (the narrowest pairs
    first), so that a vertebral body's edge just beyond the aorta's does not widen it. The value is
    the pixel's height above the lowest flank of the bands that hold it, at most their contrast
    (the weaker edge's): a lumen's chord keeps its shape, and its edge falls where it does.

    A vertebral body under part of the aorta is a step inside its lumen: the line opening fits in
    the aorta and the body together and flattens the aorta's part off the body away; the aorta's
    own two edges are still there, of equal size, however the body's step lies between them.

    Edges are few (peaks along the line), so the pairs are sought from the rises only
    (:func:`_paired_edges`) and the bands written over the pixels they hold (:func:`_held_by_bands`).
    With ``needed`` (bool, ``part``'s shape) only those pixels get their value (the others 0), and
    only the rises within the widest band of them along the line are paired: whether a band from
    ``s`` to ``s + width`` is taken depends only on the edges between the two (the narrower bands
    that took either edge lie between them), so the value there is the same.
    """
    reach, shortest, longest = _band_extents(step, radius)
    with np.errstate(invalid="ignore"):         # inf - inf beyond the grid: no edge there
        jump = _shifted(part, step, reach, np.inf) - _shifted(part, step, -reach, np.inf)
    jump[~np.isfinite(jump)] = 0.0
    rise, fall = _steepest(jump, step)
    if needed is not None:
        rise = np.where(_along_line_within(needed, step, longest), rise, 0.0).astype(rise.dtype)
    pairs = _paired_edges(part, step, reach, rise, fall, range(shortest, longest + 1))
    best, lowest_flank = _held_by_bands(part, step, pairs)
    if needed is not None:
        best[~needed] = 0.0
    with np.errstate(invalid="ignore"):
        return np.where(best > 0, np.clip(part - lowest_flank, 0.0, best), 0.0).astype(part.dtype)


def _band_extents(step: tuple, radius: float) -> tuple[int, int, int]:
    """(reach, shortest, longest) in steps along ``step`` of :func:`_bands_between_edges` for a
    vessel of projected ``radius``: how far to either side an edge is read, the narrowest and the
    widest band. A band's value at a pixel reads ``part`` at most ``longest + reach`` steps off it."""
    norm = math.hypot(*step)
    reach = max(1, int(round(radius / 3.0 / norm)))
    shortest = max(2, int(math.floor(BAND_WIDTH_DIAMETERS[0] * 2.0 * radius / norm)))
    longest = int(math.ceil((BAND_WIDTH_DIAMETERS[1] * 2.0 * radius + 1.0) / norm))
    return reach, shortest, longest


def _along_line_within(region: np.ndarray, step: tuple, n: int) -> np.ndarray:
    """Pixels at most ``n`` steps along ``step`` (either way) from a pixel of ``region`` (bool)."""
    ahead = _line_extreme(region, step, n + 1, np.logical_or, False)
    return _line_extreme(ahead, (-step[0], -step[1]), n + 1, np.logical_or, False)


def _paired_edges(part: np.ndarray, step: tuple, reach: int, rise: np.ndarray, fall: np.ndarray,
                  widths: range) -> tuple:
    """The bands of :func:`_bands_between_edges`: per width (narrowest first), each still unpaired
    rise at ``s`` whose fall at ``s + width`` along ``step`` is still unpaired, of matching size
    and with its inside above its flanks (:func:`_inside_above_flanks`). Returns (rise's flat
    index in ``part``, width, contrast, flank) per band: the weaker edge and the lower flank. A
    rise or fall with an edge has its ``part`` ``reach`` px off it on the grid, so every pixel a
    band reads is on the grid, and flat indices step along the line by ``step``'s flat stride."""
    rows, cols = np.nonzero(rise > 0)
    span = np.asarray(widths)
    to_row, to_col = rows[None, :] + span[:, None] * step[0], cols[None, :] + span[:, None] * step[1]
    on_grid = (to_row >= 0) & (to_row < part.shape[0]) & (to_col >= 0) & (to_col < part.shape[1])
    up = rise[rows, cols]
    partner = np.where(on_grid, fall[np.clip(to_row, 0, part.shape[0] - 1), np.clip(to_col, 0, part.shape[1] - 1)],
                       0.0)
    contrast = np.minimum(up, partner)                                  # (width, rise)
    width_at, rise_at = np.nonzero((contrast > 0) & (contrast >= BAND_EDGE_BALANCE * np.maximum(up, partner)))
    stride = step[0] * part.shape[1] + step[1]
    start = rows[rise_at] * part.shape[1] + cols[rise_at]
    width, contrast = span[width_at], contrast[width_at, rise_at]
    above, flank = _inside_above_flanks(part.reshape(-1), stride, start, width, reach, contrast)
    width_at, rise_at, start, width, contrast, flank = (
        a[above] for a in (width_at, rise_at, start, width, contrast, flank))
    taken = _narrowest_first(rise_at, start + width * stride, np.searchsorted(width_at, np.arange(len(span) + 1)),
                             len(rows), part.size)
    return start[taken], width[taken], contrast[taken], flank[taken]


def _narrowest_first(rise_at: np.ndarray, fall_at: np.ndarray, bounds: np.ndarray, n_rises: int,
                     n_falls: int) -> np.ndarray:
    """Which candidate bands (their rise and fall indices, sorted by width: those of the j-th width
    at ``bounds[j]:bounds[j + 1]``) are taken, width by width, each rise and fall at most once."""
    taken = np.zeros(len(rise_at), dtype=bool)
    rise_free, fall_free = np.ones(n_rises, dtype=bool), np.ones(n_falls, dtype=bool)
    for first, last in zip(bounds[:-1], bounds[1:]):
        free = first + np.flatnonzero(rise_free[rise_at[first:last]] & fall_free[fall_at[first:last]])
        taken[free] = True
        rise_free[rise_at[free]] = False
        fall_free[fall_at[free]] = False
    return taken


def _inside_above_flanks(flat: np.ndarray, stride: int, start: np.ndarray, width: np.ndarray, reach: int,
                         contrast: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For a band from each pixel ``start`` (flat index of the grid ``flat``) to ``start + width``
    along the line of flat ``stride`` (edges read ``reach`` px to either side), whether the least
    of its inside stands :data:`BAND_INSIDE` times ``contrast`` above the lower of its two flanks
    (``flat`` at ``start - reach`` and at ``start + width + reach``), and that flank: a bone's step
    inside the band leaves it above the flank on the step's low side, a gap to a device beside the
    vessel falls to the background."""
    last = np.maximum(width - 2 * reach, 1) - 1                        # the inside: reach .. reach + last
    offsets = np.minimum(np.arange(int(last.max(initial=0)) + 1)[None, :], last[:, None]) + reach
    least = flat[start[:, None] + offsets * stride].min(axis=1, initial=np.inf)
    flank = np.minimum(flat[start - reach * stride], flat[start + (width + reach) * stride])
    return least - flank >= BAND_INSIDE * contrast, flank


def _held_by_bands(part: np.ndarray, step: tuple, bands: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``part``, the largest contrast and the lowest flank of the ``bands``
    (:func:`_paired_edges`) that hold it (the pixels strictly between a band's edges, ``s + 1`` ..
    ``s + width - 1``); 0 and inf where none does."""
    start, width, contrast, flank = bands
    best = np.zeros(part.shape, dtype=part.dtype)
    lowest_flank = np.full(part.shape, np.inf, dtype=part.dtype)
    k = np.arange(1, int(width.max(initial=1)))[None, :]
    holds = k < width[:, None]
    held = (start[:, None] + k * (step[0] * part.shape[1] + step[1]))[holds]
    np.maximum.at(best.reshape(-1), held, np.broadcast_to(contrast[:, None], holds.shape)[holds])
    np.minimum.at(lowest_flank.reshape(-1), held, np.broadcast_to(flank[:, None], holds.shape)[holds])
    return best, lowest_flank


def _square_opening(image: np.ndarray, side: float) -> np.ndarray:
    """Grey opening of ``image`` by a square of ``side`` px (rows and columns separably)."""
    n = max(2, int(round(side)))
    eroded = _line_extreme(_line_extreme(image, (0, 1), n, np.minimum, np.inf), (1, 0), n, np.minimum, np.inf)
    return _line_extreme(_line_extreme(eroded, (0, -1), n, np.maximum, -np.inf), (-1, 0), n, np.maximum, -np.inf)


def _diagonal_squares(oriented: np.ndarray, across: LinesAcross) -> dict:
    """Per diagonal line ``(step index, length)`` of ``across``, the square opening
    (:func:`_square_opening`, side ``length``) of ``oriented`` on the bounding box of the pixels
    it serves; computed once per length, on the union of those boxes widened by the side (all
    a square through them can reach)."""
    squares = {}
    diagonal = {key: chosen for key, chosen in across.where.items() if all(LINE_STEPS[key[0]])}
    for length in {key[1] for key in diagonal}:
        reach = int(math.ceil(length))
        boxes = {key: _box_around(chosen, (reach, reach)) for key, chosen in diagonal.items() if key[1] == length}
        r0 = min(box[0].start for box, _ in boxes.values())
        r1 = max(box[0].stop for box, _ in boxes.values())
        c0 = min(box[1].start for box, _ in boxes.values())
        c1 = max(box[1].stop for box, _ in boxes.values())
        opened = _square_opening(oriented[r0:r1, c0:c1], length)
        for key, (box, inner) in boxes.items():
            rows = slice(box[0].start + inner[0].start - r0, box[0].start + inner[0].stop - r0)
            cols = slice(box[1].start + inner[1].start - c0, box[1].start + inner[1].stop - c0)
            squares[key] = opened[rows, cols]
    return squares


def _background_reading(oriented: np.ndarray, where) -> tuple[float, float, float]:
    """(pedestal, bright share, level) of the frame's background, read on every other pixel of
    ``oriented`` (vessels bright) and of the prior's band ``where``, against the vessels'
    contrast (the band's 99th percentile above the level, the median outside the band):

    - the pedestal, how far the band more than :data:`FLAT_RING_GAP_PX` px off the projected
      lumen (its :data:`FLAT_RING_PERCENTILE` percentile) stands above the level, as a fraction
      of the contrast: vertebral bodies, the pelvis or a box wall under the vessels raise it
      (>= 0.2 on the unsubtracted bench frames, < 0.12 on subtracted ones);
    - the share of pixels outside the band brighter than the vessels: a collimator shutter (or
      burned-in text) in view, whose step only the ratio residue of :func:`_flatten_across`
      keeps out of the mask (bench DSA frames, shutter across the iliacs: Dice 0.84-0.88 when
      not flattened, 0.97-0.98 flattened); an exposure fall-off (heel effect, vignetting)
      gives none.

    The background is flat (a subtracted frame, no shutter in view) when the pedestal is under
    :data:`FLAT_PEDESTAL` and the bright share at most :data:`FLAT_BRIGHT_SHARE`; with too few
    pixels to read, (0, 1, 0): not flat, no bone.
    """
    o, band, distance, radius = (a[::2, ::2] for a in (oriented, where.band, where.distance, where.radius))
    ring, far = band & (distance > radius + FLAT_RING_GAP_PX), o[~band]
    if ring.sum() < 10 or far.size < 10:
        return 0.0, 1.0, 0.0
    level = float(np.median(far))
    peak = float(np.percentile(o[band], 99))
    pedestal = (float(np.percentile(o[ring], FLAT_RING_PERCENTILE)) - level) / max(peak - level, 1e-6)
    return pedestal, float(np.mean(far > peak)), level


def _box_around(region: np.ndarray, reach) -> tuple:
    """The bounding box of ``region`` widened by ``reach`` (rows, cols) px, clipped to the grid, and
    within it the slices of the unwidened box."""
    rows, cols = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
    r0, r1 = max(rows[0] - reach[0], 0), min(rows[-1] + 1 + reach[0], region.shape[0])
    c0, c1 = max(cols[0] - reach[1], 0), min(cols[-1] + 1 + reach[1], region.shape[1])
    return ((slice(r0, r1), slice(c0, c1)),
            (slice(rows[0] - r0, rows[-1] + 1 - r0), slice(cols[0] - c0, cols[-1] + 1 - c0)))


# ----------------------------------------------------------------------------------------
# A faint renal's outer part: tracked along its projected course from the part already found
# ----------------------------------------------------------------------------------------

#: Where a renal is tracked: pixels nearest a projected renal, at most this many projected
#: radii (+ 1 px) off it. Development (``bench_realbench.py`` seeds 481, 494, 495, 497, whose
#: frames' masks lost a renal beyond its first millimetres; 19 mg/ml of iodine, a steel ECG clip
#: across one): the renal's recall 0.49 / 0.46 / 0.38 / 0.40 -> 0.89 / 1.0 / 0.92 / 0.97, frame
#: Dice 0.932 / 0.910 / 0.953 / 0.958 -> 0.937 / 0.911 / 0.968 / 0.973 (the rest of the renal
#: sat 4-7 px of the reduced grid off its projection); ``bench_frame_masks.py`` seeds 231-250
#: (every / every_dsa, both polarities, 80 frames): mean Dice 0.9334 -> 0.9354, 24 frames up by
#: 0.001-0.037, 2 down by 0.003. A wrong frame whose refusal rested on a lost renal may now be
#: answered: development bench 242's swap (another bench phantom's frame, whose faint renal lies
#: along this case's projected renal) was refused "renal_right not found in the frame" and is
#: answered 12.1 mm off with only a pose warning (``bench_wrong_frames.py``, branch renalend).
RENAL_TRACK_RADII = 2.5
#: The vesselness is averaged over this many pixels either side along the projected renal
#: (the :data:`LINE_STEPS` direction nearest to it), so that an air bubble or a wire across the
#: renal does not cut it and a speck of noise does not pass for it.
RENAL_TRACK_SPAN_PX = 2
#: ... and kept above this fraction of the hysteresis' ``low`` threshold.
RENAL_TRACK_LOW = 0.5
#: Before it is averaged, gaps in the response shorter than this (px of the reduced grid) along
#: the renal are closed: just outside the aorta's edge, where the wide vessel's edge dominates
#: the Hessian, a renal's vesselness is 0 over a few pixels.
RENAL_TRACK_GAP_PX = 6.0


def _renals_tracked(tree: np.ndarray, response: np.ndarray, prior: FluoroPrior, where, grid_key: tuple,
                    low: float) -> np.ndarray:
    """Pixels that continue the hysteresis ``tree`` along a projected renal: a faint renal's
    outer part whose vesselness (relative to the renal's own, :func:`_per_vessel_reference`)
    dips below ``low`` somewhere, at a bubble, a crossing wire or where the renal thins out.

    Within :data:`RENAL_TRACK_RADII` of a projected renal the response, closed over gaps
    (:data:`RENAL_TRACK_GAP_PX`) and averaged (:data:`RENAL_TRACK_SPAN_PX`) along the renal's
    projected direction (:func:`_mean_along`), is thresholded at
    :data:`RENAL_TRACK_LOW` times ``low``; the pieces of it that touch the tree are returned
    (the later steps set their width and drop what is no vessel).
    """
    from .off_tree import _node_angle, renal_frames

    frames = prior.derived(("renal_frames",) + tuple(grid_key), lambda: renal_frames(prior, where, grid_key[1]))
    zone = (frames.vessel >= 0) & (frames.off <= RENAL_TRACK_RADII * frames.radius + 1.0)
    if not (zone & tree).any():
        return np.zeros(tree.shape, dtype=bool)
    box, _ = _box_around(zone, (RENAL_TRACK_SPAN_PX, RENAL_TRACK_SPAN_PX))
    angle = _node_angle(prior, where, grid_key)[box]
    along = _mean_along(response[box], np.round(angle / (0.25 * np.pi)).astype(int) % len(LINE_STEPS),
                        RENAL_TRACK_SPAN_PX, RENAL_TRACK_GAP_PX)
    candidate = (zone[box] & (along > RENAL_TRACK_LOW * low)) | tree[box]
    labels, _ = ndi.label(candidate)
    touching = np.zeros(labels.max() + 1, dtype=bool)
    touching[labels[tree[box]]] = True
    touching[0] = False
    out = np.zeros(tree.shape, dtype=bool)
    out[box] = touching[labels] & ~tree[box]
    return out


def _mean_along(image: np.ndarray, step_index: np.ndarray, span: int, gap: float) -> np.ndarray:
    """Per pixel, ``image`` closed over ``gap`` px then averaged over ``span`` pixels either side,
    both along the :data:`LINE_STEPS` direction ``step_index`` (0 beyond the grid)."""
    out = np.zeros(image.shape, dtype=np.float32)
    for k, step in enumerate(LINE_STEPS):
        own = step_index == k
        if own.any():
            closed = _line_opening(image, step, gap, closing=True)
            total = sum(_shifted(closed, step, n, 0.0) for n in range(-span, span + 1))
            out[own] = total[own] / (2 * span + 1)
    return out

"""CT by HU window and seeded region growing, and the clean-up shared by every CT route (largest
component, small objects, holes); Dice.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage as ndi
from skimage import measure

from .. import io
from ..files import InputError
from ..io import Volume


def _lps_flips(ct: Volume) -> tuple[int, ...]:
    """Axes of a (k, j, i) slice stack to flip so that columns run to +x (patient left) and
    rows to +y (posterior), as in the LPS-aligned training CTs."""
    return tuple(axis for axis, column in ((2, 0), (1, 1)) if ct.direction[column, column] < 0)


def _check_ct(ct: Volume) -> None:
    if not isinstance(ct, Volume):
        raise TypeError(f"expected an io.Volume, got {type(ct).__name__}")
    if ct.array.ndim != 3 or min(ct.shape) < 1:
        raise InputError(f"CT has an unusable shape {ct.shape}")
    if np.issubdtype(ct.array.dtype, np.floating) and not np.isfinite(ct.array).all():
        raise InputError("CT contains NaN or infinite values")


def find_aorta_seed(ct: Volume, hu_window=(150, 600), *, top_fraction: float = 0.2,
                    area_mm2=(50.0, 2500.0), n_slices: int = 8) -> np.ndarray:
    """LPS position inside the upper aorta, found automatically.

    In evenly spaced axial slices of the superior ``top_fraction`` of the CT, the connected
    blobs inside ``hu_window`` of plausible area are scored by roundness (minor/major axis
    ratio times solidity) times mean HU; the centroid of the best blob is returned.
    """
    lo, hi = hu_window
    superior_last = ct.direction[2, 2] >= 0     # k axis pointing to +z (superior in LPS)
    n = ct.shape[0]
    span = max(1, int(math.ceil(n * top_fraction)))
    ks = np.arange(n - span, n) if superior_last else np.arange(0, span)
    ks = np.unique(np.linspace(ks[0], ks[-1], min(n_slices, len(ks))).round().astype(int))
    pixel_area = ct.spacing[0] * ct.spacing[1]
    best, best_score = None, -np.inf
    for k in ks:
        slice_hu = ct.array[k].astype(np.float32)
        inside = ndi.binary_opening((slice_hu >= lo) & (slice_hu <= hi), iterations=1)
        for region in measure.regionprops(measure.label(inside), intensity_image=slice_hu):
            area = region.area * pixel_area
            if not area_mm2[0] <= area <= area_mm2[1] or region.axis_major_length == 0:
                continue
            roundness = region.axis_minor_length / region.axis_major_length * region.solidity
            score = roundness ** 2 * region.intensity_mean
            if score > best_score:
                best_score, best = score, (k, *region.centroid)
    if best is None:
        raise InputError(f"no aorta-like blob in HU window {tuple(hu_window)} near the top of the CT; "
                         f"give a seed point")
    return ct.index_to_lps(np.array(best, dtype=float))


def segment_ct_threshold(ct: Volume, *, hu_window=(150, 600), seed_lps=None, separation_vox: int = 1,
                         postprocess: bool = True) -> Volume:
    """Lumen mask without learning: HU window plus seeded region growing.

    The window mask is eroded ``separation_vox`` times (cutting thin bridges to bone), the
    component holding the seed is kept and grown back inside the window by geodesic
    dilation (``separation_vox + 2`` steps).

    Parameters
    ----------
    ct : Volume
        CT in HU.
    hu_window : (float, float)
        Contrast-enhanced lumen intensities.
    seed_lps : array_like, optional
        A point in the lumen (LPS mm); default :func:`find_aorta_seed`.

    Returns
    -------
    Volume
        Boolean lumen mask.
    """
    _check_ct(ct)
    lo, hi = hu_window
    window = (ct.array >= lo) & (ct.array <= hi)
    seed_lps = find_aorta_seed(ct, hu_window) if seed_lps is None else np.asarray(seed_lps, dtype=float)
    seed = np.round(ct.lps_to_index(seed_lps)).astype(int)
    if np.any(seed < 0) or np.any(seed >= np.array(ct.shape)):
        raise InputError(f"seed {np.round(seed_lps, 1).tolist()} lies outside the CT")
    core = ndi.binary_erosion(window, iterations=separation_vox) if separation_vox else window
    seed = _nearest_true(core, seed)
    labels, _ = ndi.label(core)
    region = labels == labels[tuple(seed)]
    if separation_vox:
        region = ndi.binary_dilation(region, iterations=separation_vox + 2, mask=window)
    result = ct.with_array(region)
    return postprocess_mask(result) if postprocess else result


def _nearest_true(mask: np.ndarray, index: np.ndarray, radius: int = 6) -> np.ndarray:
    """``index`` if ``mask`` is set there, else the nearest set voxel within ``radius``."""
    if mask[tuple(index)]:
        return index
    lo = np.maximum(index - radius, 0)
    hi = np.minimum(index + radius + 1, mask.shape)
    local = np.argwhere(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]) + lo
    if len(local) == 0:
        raise InputError(f"seed voxel {index.tolist()} is not inside the HU window (nor near it)")
    return local[np.argmin(((local - index) ** 2).sum(axis=1))]


#: The CT segmenters :func:`segment_ct` knows.
CT_SEGMENTERS = ("classical", "unet", "threshold")


def postprocess_mask(mask, *, min_size_mm3: float = 50.0, keep_largest: bool = True,
                     fill_holes: bool = True):
    """Clean a lumen mask (the paper's ``regionprops`` / ``bwareaopen`` step, plus hole filling).

    Removes connected objects smaller than ``min_size_mm3``, keeps the largest component and
    fills holes (enclosed in 3D, and in each axial slice).

    Parameters
    ----------
    mask : Volume or numpy.ndarray
        Binary mask; an array is taken to have 1 mm voxels.

    Returns
    -------
    Volume or numpy.ndarray
        Boolean mask, of the same kind as the input.
    """
    array = np.asarray(mask.array if isinstance(mask, Volume) else mask) > 0
    if array.ndim != 3:
        raise ValueError(f"postprocess_mask expects a 3D mask, got shape {array.shape}")
    voxel_mm3 = float(np.prod(mask.spacing)) if isinstance(mask, Volume) else 1.0
    cleaned = np.zeros_like(array)
    if array.any():
        box = _bounding_box(array)        # nothing outside it changes, and it is much faster
        crop = _remove_small_objects(array[box], min_size_mm3 / voxel_mm3)
        if keep_largest:
            crop = _largest_component(crop)
        if fill_holes and crop.any():
            crop = ndi.binary_fill_holes(crop)
            crop = np.stack([ndi.binary_fill_holes(s) if s.any() else s for s in crop])
        cleaned[box] = crop
    return mask.with_array(cleaned) if isinstance(mask, Volume) else cleaned


def _bounding_box(array: np.ndarray) -> tuple[slice, ...]:
    """Index box of the non-zero voxels of a non-empty array."""
    box = []
    for axis in range(array.ndim):
        hit = np.nonzero(array.any(axis=tuple(a for a in range(array.ndim) if a != axis)))[0]
        box.append(slice(hit[0], hit[-1] + 1))
    return tuple(box)


def _component_sizes(array: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face-connected component labels and the size of each label (label 0 gets size 0)."""
    labels, _ = ndi.label(array)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels, sizes


def _remove_small_objects(array: np.ndarray, min_voxels: float) -> np.ndarray:
    """``array`` without the connected objects of fewer than ``min_voxels`` voxels (bwareaopen)."""
    labels, sizes = _component_sizes(array)
    return (sizes >= max(min_voxels, 1))[labels] if array.any() else array


def _largest_component(array: np.ndarray) -> np.ndarray:
    """The largest connected object of ``array`` (regionprops' largest area)."""
    if not array.any():
        return array
    labels, sizes = _component_sizes(array)
    return labels == np.argmax(sizes)


def dice(a, b) -> float:
    """Dice overlap ``2 |A & B| / (|A| + |B|)`` of two binary masks (1.0 when both are empty)."""
    a = np.asarray(a.array if isinstance(a, Volume) else a) > 0
    b = np.asarray(b.array if isinstance(b, Volume) else b) > 0
    if a.shape != b.shape:
        raise ValueError(f"mask shapes differ: {a.shape} vs {b.shape}")
    total = a.sum() + b.sum()
    return 1.0 if total == 0 else float(2.0 * np.logical_and(a, b).sum() / total)

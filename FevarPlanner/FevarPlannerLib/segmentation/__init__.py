"""Segmentation stage: CT -> aorta lumen mask -> surface, and fluoroscopy frame -> vessel mask.

CT side (paper Section II-A): a 6-block UNet (convolution, max-pooling, transposed
convolution) segments the lumen slice by slice; it is trained with cross-entropy, SGD with
momentum 0.9, learning rate 1e-3 and batch size 1, with "linear mapping" (random linear
intensity maps) and "window slicing" (random crop windows, i.e. varying aorta position) as
augmentation. The result is cleaned like MATLAB's ``regionprops`` / ``bwareaopen`` (largest
component, small objects removed) plus hole filling, and turned into a surface by marching
cubes. A learning-free alternative (HU window + seeded region growing) serves for
comparison and as a fallback.

Fluoroscopy side: multi-scale Hessian vesselness (Frangi) on a reduced-resolution copy of the
frame, hysteresis thresholding and a local-contrast refinement, upsampled back to the frame
grid.

Volumes are :class:`io.Volume` objects, arrays indexed ``(k, j, i)``; world coordinates are
LPS millimetres.

The stage is a package split along its seams: :mod:`.unet` (network, training, inference),
:mod:`.classical` (the learning-free CT route), :mod:`.threshold` (HU window, clean-up, Dice),
:mod:`.surface` (marching cubes) and :mod:`.fluoro` (the frame). Every name is re-exported here.
"""

from __future__ import annotations

from ..io import Volume
from ..quality import FluoroPrior
from .unet import (DEFAULT_NET_HU_WINDOW, DEFAULT_PIXEL_MM, MODEL_RELATIVE_PATHS, UNet, default_model_path,
    load_unet, read_case, segment_ct_unet, train_unet)
from .threshold import (CT_SEGMENTERS, dice, find_aorta_seed, postprocess_mask, segment_ct_threshold)
from .surface import (mask_surface, write_surface_vtp)
from .fluoro import (_downsample, _percentile_among_zeros, _upsample, frame_contrast_in_prior, segment_fluoro,
    select_frame, vesselness)
from .classical import (AORTA_RADIUS_MM, BONE_HU, BRANCH_REACH_MM, BRANCH_SIGMAS_MM, CONTRAST_HU,
    ILIAC_MIN_RADIUS_MM, SOFT_TISSUE_HU, find_aorta_in_slices, grow_branches,
    segment_ct_classical, trace_aorta)

__all__ = [
    "UNet", "train_unet", "load_unet", "default_model_path", "segment_ct_unet", "segment_ct_threshold",
    "find_aorta_seed", "segment_ct", "postprocess_mask", "mask_surface", "write_surface_vtp",
    "segment_fluoro", "FluoroPrior", "select_frame", "frame_contrast_in_prior", "vesselness",
    "segment_ct_classical", "find_aorta_in_slices", "trace_aorta", "grow_branches", "dice", "read_case",
]


def segment_ct(ct: Volume, method: str = "classical", **kwargs) -> Volume:
    """Lumen mask by ``method``: ``'classical'`` (:func:`segment_ct_classical`, the default:
    no training, validated on a real CT), ``'unet'`` (:func:`segment_ct_unet`, trained on
    phantoms only) or ``'threshold'`` (:func:`segment_ct_threshold`)."""
    if method == "classical":
        return segment_ct_classical(ct, **kwargs)
    if method == "unet":
        return segment_ct_unet(ct, **kwargs)
    if method == "threshold":
        return segment_ct_threshold(ct, **kwargs)
    raise ValueError(f"unknown segmenter {method!r}; use one of {', '.join(CT_SEGMENTERS)}")

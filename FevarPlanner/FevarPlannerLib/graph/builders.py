"""Conveniences: the skeleton graph of a mask (thinned here) or of a given skeleton."""

from __future__ import annotations

import numpy as np

from .. import skeleton as _skeleton
from ..io import Volume
from .skeleton_graph import SkeletonGraph

def skeleton_graph_3d(mask_or_skeleton: Volume, is_skeleton: bool = False, *,
                      smooth_sigma: float = 0.0) -> SkeletonGraph:
    """3D skeleton graph of a lumen mask (thinned here) or of a given skeleton volume."""
    skeleton = mask_or_skeleton if is_skeleton else _skeleton.skeletonize_3d(mask_or_skeleton,
                                                                              smooth_sigma=smooth_sigma)
    return SkeletonGraph.from_volume(skeleton)


def skeleton_graph_2d(mask: np.ndarray, *, pixel_size: float = 1.0, smooth_sigma: float = 1.0,
                      downsample: int | None = None, is_skeleton: bool = False, radii: bool = False) -> SkeletonGraph:
    """2D skeleton graph of a vessel mask (thinned here) or of a given 2D skeleton.

    With ``radii`` every node gets its local vessel radius in the mask (``SkeletonGraph.radii``).
    """
    vessels = np.asarray(mask) if radii else None
    if is_skeleton:
        return SkeletonGraph.from_image(mask, pixel_size, mask=vessels)
    box, thin = _skeleton.skeleton_2d_box(mask, smooth_sigma=smooth_sigma, downsample=downsample)
    return SkeletonGraph.from_image_box(box, thin, np.shape(mask), pixel_size, mask=vessels)

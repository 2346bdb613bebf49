"""Rigid pre-alignment (paper eq. 1) and an optional in-plane pose refinement.

The paper pre-aligns the 3D skeleton with the projection matrix ``P`` alone. When the
frame and ``P`` disagree (a moved table, a mis-calibrated C-arm: the misaligned cases of
the paper's Fig. 5), the projected 3D skeleton lands beside the 2D one and the graph
matching sees wrong tangents. ``refine_in_plane_pose`` finds the similarity transform of
the image plane (translation, rotation, scale) that lays the projected 3D skeleton onto
the 2D skeleton's distance map, and folds it into ``P`` (``A @ P``) so that everything
downstream keeps working with one matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import minimize

from .projection import in_plane_transform, project

__all__ = ["PoseRefinement", "refine_in_plane_pose", "chamfer_distance_map"]

#: Distances beyond this (pixels) count as this much: outliers of either skeleton do not
#: dominate the fit.
TRUNCATION_PX = 25.0


@dataclass
class PoseRefinement:
    """The in-plane correction found, and the corrected projection matrix."""

    P: np.ndarray
    translation: tuple
    rotation_deg: float
    scale: float
    cost_before: float
    cost_after: float


def chamfer_distance_map(skeleton_uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Euclidean distance (px) from every pixel to the nearest 2D skeleton node."""
    image = np.ones(shape, dtype=bool)
    rc = np.round(skeleton_uv[:, ::-1]).astype(int)
    keep = np.all((rc >= 0) & (rc < shape), axis=1)
    image[rc[keep, 0], rc[keep, 1]] = False
    return ndimage.distance_transform_edt(image)


def _chamfer_cost(uv: np.ndarray, distance_map: np.ndarray) -> float:
    values = ndimage.map_coordinates(distance_map, [uv[:, 1], uv[:, 0]], order=1, mode="nearest")
    outside = (uv[:, 0] < 0) | (uv[:, 1] < 0) | (uv[:, 0] > distance_map.shape[1] - 1) | \
              (uv[:, 1] > distance_map.shape[0] - 1)
    values = np.where(outside, TRUNCATION_PX, values)
    return float(np.mean(np.minimum(values, TRUNCATION_PX) ** 2))


def _apply(uv: np.ndarray, params: np.ndarray, center: np.ndarray) -> np.ndarray:
    tx, ty, theta, log_scale = params
    c, s = np.cos(theta), np.sin(theta)
    R = np.exp(log_scale) * np.array([[c, -s], [s, c]])
    return (uv - center) @ R.T + center + [tx, ty]


def refine_in_plane_pose(points3d: np.ndarray, skeleton_uv: np.ndarray, P: np.ndarray,
                         shape: tuple[int, int], *, max_rotation_deg: float = 30.0,
                         allow_scale: bool = False) -> PoseRefinement:
    """Similarity transform of the image plane that best overlays projected 3D on 2D.

    Parameters
    ----------
    points3d : (n, 3) LPS mm
        3D skeleton nodes.
    skeleton_uv : (k, 2)
        2D skeleton nodes (u, v).
    P : (3, 4)
        The given projection matrix.
    shape : (rows, cols)
        Frame size.
    max_rotation_deg : float
        Half-width of the coarse rotation search.
    allow_scale : bool
        Fit an isotropic scale as well (a table height error).

    Returns
    -------
    PoseRefinement
        With ``P`` replaced by ``A @ P``; ``cost_*`` are mean truncated squared chamfer
        distances (px^2) before and after.
    """
    distance_map = chamfer_distance_map(skeleton_uv, shape)
    uv = project(P, points3d)
    center = uv.mean(axis=0)
    shift = skeleton_uv.mean(axis=0) - center

    def cost(params):
        return _chamfer_cost(_apply(uv, params, center), distance_map)

    before = cost(np.zeros(4))
    starts = [np.zeros(4)] + [np.array([shift[0], shift[1], np.deg2rad(a), 0.0])
                              for a in np.arange(-max_rotation_deg, max_rotation_deg + 1e-9, 5.0)]
    best = min(starts, key=cost)
    bounds_scale = (np.log(0.8), np.log(1.25)) if allow_scale else (0.0, 0.0)
    result = minimize(cost, best, method="Powell",
                      bounds=[(None, None), (None, None), (-np.pi / 2, np.pi / 2), bounds_scale],
                      options={"xtol": 1e-3, "ftol": 1e-4})
    params = result.x if result.fun < before else np.zeros(4)
    tx, ty, theta, log_scale = params
    refined = in_plane_transform(P, translation=(tx, ty), rotation_deg=np.rad2deg(theta),
                                 scale=float(np.exp(log_scale)), center=center)
    return PoseRefinement(refined, (float(tx), float(ty)), float(np.rad2deg(theta)), float(np.exp(log_scale)),
                          before, min(before, float(result.fun)))

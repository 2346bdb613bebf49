"""Rigid pre-alignment (paper eq. 1) and an optional in-plane pose correction.

The paper pre-aligns the 3D skeleton with the projection matrix ``P`` alone. When the
frame and ``P`` disagree (a moved table, a mis-calibrated C-arm: the misaligned cases of
the paper's Fig. 5), the deformation explains the offset as a 3D shift. ``fit_in_plane_rigid``
finds the rotation and translation of the image plane between corresponding points and
folds it into ``P`` (``A @ P``), so that everything downstream keeps working with one matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .projection import in_plane_transform

__all__ = ["PoseRefinement", "fit_in_plane_rigid"]


@dataclass
class PoseRefinement:
    """The in-plane correction found, and the corrected projection matrix."""

    P: np.ndarray
    translation: tuple
    rotation_deg: float
    scale: float
    cost_before: float
    cost_after: float


def fit_in_plane_rigid(source_uv: np.ndarray, target_uv: np.ndarray, P: np.ndarray) -> PoseRefinement:
    """Least-squares rotation and translation of the image plane taking ``source`` to ``target``.

    The closed-form 2D Procrustes (Kabsch) solution for corresponding points, e.g. the
    projected 3D nodes of the stable vessels and their soft-assigned 2D targets. ``cost_*``
    are the mean squared distances (px^2) before and after.
    """
    source_uv, target_uv = np.asarray(source_uv, float), np.asarray(target_uv, float)
    if len(source_uv) < 3 or source_uv.shape != target_uv.shape:
        raise ValueError(f"need three or more corresponding points, got {source_uv.shape} and {target_uv.shape}")
    centre_s, centre_t = source_uv.mean(axis=0), target_uv.mean(axis=0)
    covariance = (source_uv - centre_s).T @ (target_uv - centre_t)
    theta = np.arctan2(covariance[0, 1] - covariance[1, 0], covariance[0, 0] + covariance[1, 1])
    c, s = np.cos(theta), np.sin(theta)
    moved = (source_uv - centre_s) @ np.array([[c, -s], [s, c]]).T + centre_t
    translation = centre_t - centre_s
    refined = in_plane_transform(P, translation=translation, rotation_deg=np.rad2deg(theta), center=centre_s)
    before = float(np.mean(np.sum((source_uv - target_uv) ** 2, axis=1)))
    after = float(np.mean(np.sum((moved - target_uv) ** 2, axis=1)))
    return PoseRefinement(refined, (float(translation[0]), float(translation[1])), float(np.rad2deg(theta)), 1.0,
                          before, after)

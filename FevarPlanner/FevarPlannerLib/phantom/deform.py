"""The intra-operative deformation: segment rotations that keep every vessel length.

See the package docstring ("Intra-operative deformation").
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .anatomy import BASE_STEP_MM, Anatomy, Vessel, _axis_towards, _unit, build_preop_anatomy
from .params import PhantomParams


def _bend_from_anchor(points: np.ndarray, anchor: int, rotvecs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turn segment ``i`` by the composed rotations between ``anchor`` and it (lengths kept).

    ``rotvecs[i]`` is the incremental rotation (world axes) at segment ``i``. Returns the
    new points and each point's total rotation.
    """
    increments = Rotation.from_rotvec(rotvecs).as_matrix()
    segments = np.diff(points, axis=0)
    new = points.copy()
    rotations = np.repeat(np.eye(3)[None], len(points), axis=0)
    current = np.eye(3)
    for i in range(anchor, len(points) - 1):
        current = increments[i] @ current
        new[i + 1] = new[i] + current @ segments[i]
        rotations[i + 1] = current
    current = np.eye(3)
    for i in range(anchor - 1, -1, -1):
        current = increments[i] @ current
        new[i] = new[i + 1] - current @ segments[i]
        rotations[i] = current
    return new, rotations


def _window(n: int, centre: float, width: float) -> np.ndarray:
    """Gaussian weights over ``n`` segments, summing to 1 (0 when ``n`` is 0)."""
    if n == 0:
        return np.zeros(0)
    w = np.exp(-0.5 * ((np.arange(n) - centre) / max(width, 1.0)) ** 2)
    return w / w.sum()


def _deform_aorta(aorta: Vessel, params: PhantomParams, anchor: int) -> tuple[np.ndarray, np.ndarray]:
    """Bend the aorta about the renal level: the sac region below, the upper aorta above."""
    p, scale = params, params.deformation_scale
    segments = len(aorta.points) - 1
    below = segments - anchor
    sac_middle = (p.neck_length_mm + 0.5 * p.sac_length_mm) / BASE_STEP_MM
    lower = _window(below, sac_middle, 0.35 * p.sac_length_mm / BASE_STEP_MM)
    upper = _window(anchor, anchor / 2.0, anchor / 3.0)
    # +angle about +y turns a downward tangent towards -x; about +x towards +y (posterior)
    lower_axis = (-np.deg2rad(p.bend_lateral_deg) * np.array([0.0, 1.0, 0.0])
                  - np.deg2rad(p.bend_anterior_deg) * np.array([1.0, 0.0, 0.0]))
    upper_axis = np.deg2rad(p.upper_bend_deg) * np.array([0.0, 1.0, 0.0])
    rotvecs = np.zeros((segments, 3))
    rotvecs[anchor:] = scale * lower[:, None] * lower_axis
    rotvecs[:anchor] = scale * upper[:, None] * upper_axis
    return _bend_from_anchor(aorta.points, anchor, rotvecs)


def _rigid_about_origin(points: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    new = points[0] + (points - points[0]) @ rotation.T
    return new, np.repeat(rotation[None], len(points), axis=0)


def _straighten(points: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Turn every segment ``fraction`` of the way towards the chord direction (lengths kept)."""
    segments = np.diff(points, axis=0)
    chord = _unit(points[-1] - points[0])
    unit = _unit(segments)
    axes = np.cross(unit, chord)
    sin = np.linalg.norm(axes, axis=1)
    angles = np.arctan2(sin, unit @ chord)
    axes = np.where(sin[:, None] > 1e-12, axes / np.maximum(sin, 1e-12)[:, None], 0.0)
    seg_rot = Rotation.from_rotvec(axes * (fraction * angles)[:, None]).as_matrix()
    new = points[0] + np.vstack([np.zeros(3), np.cumsum(np.einsum("kab,kb->ka", seg_rot, segments), axis=0)])
    rotations = np.concatenate([seg_rot[:1], seg_rot], axis=0)
    return new, rotations


def _local_deformation(name: str, vessel: Vessel, params: PhantomParams, anchor: int):
    """The deformation of ``vessel`` in its own frame: new points, per-point rotations."""
    scale = params.deformation_scale
    side = 0 if name.endswith("left") else 1
    sign = 1.0 if side == 0 else -1.0
    if name == "aorta":
        return _deform_aorta(vessel, params, anchor)
    if name in ("iliac_left", "iliac_right"):
        straight, rotations = _straighten(vessel.points, float(np.clip(scale * params.iliac_straighten[side], 0, 1)))
        # + swing turns the iliac laterally in the frontal plane (about the AP axis)
        swing = Rotation.from_rotvec(-sign * np.deg2rad(scale * params.iliac_swing_deg[side]) * np.array(
            [0.0, 1.0, 0.0])).as_matrix()
        swung, _ = _rigid_about_origin(straight, swing)
        return swung, np.einsum("ab,kbc->kac", swing, rotations)
    if name in ("renal_left", "renal_right"):
        initial = _unit(vessel.points[1] - vessel.points[0])
        axis = _axis_towards(initial, [0.0, 0.0, 1.0])
        tilt = Rotation.from_rotvec(np.deg2rad(scale * params.renal_tilt_deg[side]) * axis).as_matrix()
        return _rigid_about_origin(vessel.points, tilt)
    return vessel.points.copy(), np.repeat(np.eye(3)[None], len(vessel.points), axis=0)


def _renal_anchor(anatomy: Anatomy) -> int:
    renals = [v.parent_index for v in anatomy.by_label("renal_right")]
    return renals[0] if renals else 0


def deform_anatomy(anatomy: Anatomy, params: PhantomParams) -> Anatomy:
    """Apply the intra-operative deformation of ``params`` to ``anatomy``.

    Each vessel is deformed in its own frame (segment rotations, so every segment keeps its
    length), then carried by the rotation and displacement of its parent at the ostium.
    The aorta stays fixed at the right renal ostium. ``deformation_scale`` scales every
    angle; 0 returns an identical copy.

    Parameters
    ----------
    anatomy : Anatomy
    params : PhantomParams

    Returns
    -------
    Anatomy
    """
    anchor = _renal_anchor(anatomy)
    moved, rotations = {}, {}
    for name, vessel in anatomy.vessels.items():
        local, local_rot = _local_deformation(name, vessel, params, anchor)
        if vessel.parent is not None:
            j = vessel.parent_index
            parent_rot = rotations[vessel.parent][j]
            local = moved[vessel.parent].points[j] + (local - vessel.points[0]) @ parent_rot.T
            local_rot = np.einsum("ab,kbc->kac", parent_rot, local_rot)
        moved[name] = vessel.moved(local, local_rot)
        rotations[name] = local_rot
    return Anatomy(moved)


def state_anatomy(params: PhantomParams) -> Anatomy:
    """The rest anatomy of ``params`` deformed by its deformation parameters."""
    return deform_anatomy(build_preop_anatomy(params), params)


"""The DSA-like fluoroscopic frame, its lumen mask, the fitted detector and the misaligned pose."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from ..projection import CArmGeometry, in_plane_transform, project, projection_matrix_from_carm, source_position
from .anatomy import Anatomy, Vessel, _unit
from .params import PhantomParams
from .raster import _chunks, _segment_nearest

_FLUORO_FULL_SCALE = 4095   # 12-bit detector


def _projected_radii(P: np.ndarray, points: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Radius in pixels of each lumen cross-section as the frame sees it (perspective)."""
    rays = _unit(points - source_position(P))
    tangents = _unit(np.gradient(points, axis=0))
    side = np.cross(tangents, rays)
    degenerate = np.linalg.norm(side, axis=1) < 1e-6
    side[degenerate] = np.cross(rays[degenerate], [1.0, 0.0, 0.0])
    side = _unit(side)
    return np.linalg.norm(project(P, points + radii[:, None] * side) - project(P, points), axis=1)


def _outside_parent(anatomy: Anatomy, vessel: Vessel) -> slice:
    """The part of a branch beyond its parent's lumen (its first points lie inside it)."""
    if vessel.parent is None:
        return slice(0, len(vessel.points))
    parent = anatomy.vessels[vessel.parent]
    limit = parent.radius[vessel.parent_index]
    start = int(np.searchsorted(vessel.arc_length(), limit))
    return slice(max(0, min(start, len(vessel.points) - 2)), len(vessel.points))


def _project_tubes(anatomy: Anatomy, P: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Projected lumen mask and contrast path length (mm, summed over vessels) per pixel."""
    mask = np.zeros(shape, dtype=bool)
    path = np.zeros(shape, dtype=np.float32)
    rows, cols = shape
    for vessel in anatomy.vessels.values():
        part = _outside_parent(anatomy, vessel)
        pts, radii = vessel.points[part], vessel.radius[part]
        uv = project(P, pts)
        r_px = _projected_radii(P, pts, radii)
        mm_per_px = radii / r_px
        chord = np.zeros(shape, dtype=np.float32)
        for sl in _chunks(len(uv) - 1):
            a, b = uv[sl], uv[sl.start + 1:sl.stop + 1]
            ra, rb = r_px[sl], r_px[sl.start + 1:sl.stop + 1]
            reach = max(ra.max(), rb.max()) + 1.0
            lo = np.floor(np.minimum(a.min(0), b.min(0)) - reach).astype(int)
            hi = np.ceil(np.maximum(a.max(0), b.max(0)) + reach).astype(int) + 1
            (u0, v0), (u1, v1) = np.maximum(lo, 0), np.minimum(hi, [cols, rows])
            if u1 <= u0 or v1 <= v0:
                continue
            vv, uu = np.mgrid[v0:v1, u0:u1]
            coords = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
            dist, radius = (x.reshape(uu.shape) for x in _segment_nearest(coords, a, b, ra, rb))
            inside = dist <= radius
            half_px = np.sqrt(np.clip(radius ** 2 - dist ** 2, 0.0, None))
            scale = float(np.mean(mm_per_px[sl]))
            block = chord[v0:v1, u0:u1]
            np.maximum(block, (2.0 * scale * half_px).astype(np.float32), out=block)
            mask[v0:v1, u0:u1] |= inside
        path += chord
    return mask, path


def render_fluoro(anatomy: Anatomy, P: np.ndarray, carm: CArmGeometry, params: PhantomParams,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A DSA-like frame of ``anatomy`` seen through ``P`` and its vessel mask.

    The background is a smooth grey field (vignetting and slow variation); contrast in the
    lumen attenuates it as ``exp(-mu * path length)`` (``fluoro_attenuation_per_mm``), so the
    vessels are dark (MONOCHROME2); signal-dependent Gaussian noise from ``rng``.

    Returns
    -------
    frame : numpy.ndarray of uint16, shape (rows, cols)
        12-bit values.
    mask : numpy.ndarray of bool, shape (rows, cols)
        Pixels whose ray meets a lumen (the projected intra-operative lumen).
    """
    shape = (carm.rows, carm.cols)
    mask, path = _project_tubes(anatomy, P, shape)
    path = ndimage.gaussian_filter(path, 0.7)
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
    centre = np.array([(shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0])
    radial2 = ((vv - centre[0]) ** 2 + (uu - centre[1]) ** 2) / (0.5 * max(shape)) ** 2
    coarse = rng.normal(size=(6, 6))
    slow = ndimage.zoom(coarse, (shape[0] / 6.0, shape[1] / 6.0), order=3, mode="nearest")[:shape[0], :shape[1]]
    slow /= max(float(np.abs(slow).max()), 1e-12)
    background = 0.62 * _FLUORO_FULL_SCALE * (1.0 - 0.12 * radial2 + 0.04 * slow)
    signal = background * np.exp(-params.fluoro_attenuation_per_mm * path)
    noise = rng.normal(size=shape) * params.fluoro_noise * np.sqrt(signal * background.mean())
    frame = np.clip(np.rint(signal + noise), 0, _FLUORO_FULL_SCALE).astype(np.uint16)
    return frame, mask


def fit_detector(anatomy: Anatomy, params: PhantomParams, isocenter) -> CArmGeometry:
    """The C-arm of ``params``; a detector size left as None is fitted to the anatomy.

    The fitted detector is square, keeps every projected lumen ``detector_margin_px``
    inside the frame and is a multiple of 32 pixels.
    """
    pixel = params.detector_pixel_mm
    probe = CArmGeometry(params.sid_mm, params.sod_mm, (pixel, pixel), params.primary_angle_deg,
                         params.secondary_angle_deg, 1, 1)
    P = projection_matrix_from_carm(probe, isocenter)
    extent = np.zeros(2)
    for vessel in anatomy.vessels.values():
        uv = project(P, vessel.points)
        r_px = _projected_radii(P, vessel.points, vessel.radius)
        extent = np.maximum(extent, (np.abs(uv) + r_px[:, None]).max(axis=0))
    size = int(32 * np.ceil((2.0 * (extent.max() + params.detector_margin_px) + 1.0) / 32.0))
    rows = int(params.detector_rows) if params.detector_rows is not None else size
    cols = int(params.detector_cols) if params.detector_cols is not None else size
    return CArmGeometry(params.sid_mm, params.sod_mm, (pixel, pixel), params.primary_angle_deg,
                        params.secondary_angle_deg, rows, cols)


def _misaligned(P_true: np.ndarray, params: PhantomParams, isocenter: np.ndarray, carm: CArmGeometry) -> np.ndarray:
    """P_given: P_true after a small 3D rotation about the isocentre and an in-plane motion."""
    R = Rotation.from_euler("xyz", params.misalign_rotation3d_deg, degrees=True).as_matrix()
    world = np.eye(4)
    world[:3, :3] = R
    world[:3, 3] = isocenter - R @ isocenter
    centre = ((carm.cols - 1) / 2.0, (carm.rows - 1) / 2.0)
    return in_plane_transform(P_true @ world, params.misalign_shift_px, params.misalign_rotation_deg, 1.0, centre)


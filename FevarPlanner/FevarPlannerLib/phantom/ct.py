"""The contrast CT: body, spine, kidneys, wall, thrombus and lumen in HU, blur and noise."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .. import io
from .anatomy import Anatomy, _unit
from .params import PhantomParams
from .raster import Grid, _lumen_field, _spine, _tube_field, _wall_tubes, ct_grid


_AIR_HU, _FAT_HU, _SOFT_HU = -1000.0, -100.0, 40.0
_CORTICAL_HU, _CANCELLOUS_HU, _DISC_HU, _KIDNEY_HU = 700.0, 250.0, 90.0, 160.0
_PERIVASCULAR_FAT_MM = 6.0


def _fraction_inside(signed_mm: np.ndarray, voxel_mm: float) -> np.ndarray:
    """Partial-volume fraction from a signed distance (linear over one voxel)."""
    return np.clip(0.5 - signed_mm / voxel_mm, 0.0, 1.0)


def _body_and_spine(volume: io.Volume, anatomy: Anatomy) -> np.ndarray:
    """Background HU: air, subcutaneous fat, soft tissue, vertebral bodies and discs, kidneys."""
    x = volume.origin[0] + np.arange(volume.shape[2]) * volume.spacing[0]
    y = volume.origin[1] + np.arange(volume.shape[1]) * volume.spacing[1]
    z = volume.origin[2] + np.arange(volume.shape[0]) * volume.spacing[2]
    spine_x, spine_y, spine_r = _spine(anatomy)
    aorta_y = float(anatomy.vessels["aorta"].points[:, 1].min())
    front, back = aorta_y - 90.0, spine_y + 70.0
    body_y, body_b, body_a = 0.5 * (front + back), 0.5 * (back - front), 160.0
    X, Y = np.meshgrid(x, y, indexing="xy")
    ellipse = ((X - spine_x) / body_a) ** 2 + ((Y - body_y) / body_b) ** 2
    axial = np.where(ellipse <= 1.0, _FAT_HU, _AIR_HU)
    axial = np.where(ellipse <= (1.0 - 15.0 / body_b) ** 2, _SOFT_HU, axial).astype(np.float32)
    hu = np.broadcast_to(axial, volume.shape).copy()
    radial = np.hypot(X - spine_x, Y - spine_y)
    cortex = np.where(radial <= spine_r - 3.0, _CANCELLOUS_HU, _CORTICAL_HU)
    in_disc = (np.mod(z, 35.0) < 8.0)[:, None, None]
    hu = np.where(radial[None] <= spine_r, np.where(in_disc, _DISC_HU, cortex[None]), hu)
    process = (np.abs(X - spine_x) <= 4.0) & (Y > spine_y + spine_r) & (Y < spine_y + spine_r + 35.0)
    hu = np.where(process[None] & ~in_disc, _CORTICAL_HU, hu)
    return _add_kidneys(hu, anatomy, x, y, z)


def _add_kidneys(hu: np.ndarray, anatomy: Anatomy, x, y, z) -> np.ndarray:
    """Enhancing kidneys: ellipsoids around the end of each renal artery (at the hilum)."""
    for renal in anatomy.by_label("renal_left") + anatomy.by_label("renal_right"):
        end, tangent = renal.points[-1], _unit(renal.points[-1] - renal.points[-4])
        centre = end + 14.0 * tangent
        semi = np.array([22.0, 25.0, 50.0])
        dx = ((x - centre[0]) / semi[0]) ** 2
        dy = ((y - centre[1]) / semi[1]) ** 2
        dz = ((z - centre[2]) / semi[2]) ** 2
        inside = (dz[:, None, None] + dy[None, :, None] + dx[None, None, :]) <= 1.0
        hu[inside] = _KIDNEY_HU
    return hu


def _coarse_tube_field(volume: io.Volume, tubes, pad_mm: float) -> np.ndarray:
    """:func:`_tube_field` on a grid twice as coarse, linearly interpolated back (smooth wall)."""
    coarse_shape = tuple((np.array(volume.shape) + 1) // 2)
    coarse = io.Volume(np.zeros(coarse_shape, dtype=np.uint8), 2.0 * volume.spacing, volume.origin, volume.direction)
    field_ = _tube_field(coarse, tubes, pad_mm)
    return ndimage.affine_transform(field_, np.full(3, 0.5), output_shape=volume.shape, order=1, mode="nearest")


def render_ct(anatomy: Anatomy, params: PhantomParams, rng: np.random.Generator,
              grid: Grid | None = None) -> io.Volume:
    """A contrast CT of ``anatomy``: int16 HU on ``grid`` (default :func:`ct_grid`).

    Enhancing lumen (``params.lumen_hu``), non-enhancing thrombus and wall, a rim of
    peri-aortic fat, soft tissue and subcutaneous fat in a body ellipse, air outside,
    vertebral bodies with discs behind the aorta and enhancing kidneys; then partial-volume
    blur (``ct_blur_mm``) and Gaussian noise (``ct_noise_hu``) from ``rng``.
    """
    grid = grid or ct_grid(anatomy, params.ct_spacing_mm, params.ct_margin_mm)
    volume = grid.volume(dtype=np.int16)
    return _ct_from_lumen_field(anatomy, params, rng, volume, _lumen_field(anatomy, volume))


def _ct_from_lumen_field(anatomy: Anatomy, params: PhantomParams, rng: np.random.Generator, volume: io.Volume,
                         lumen: np.ndarray, stressors=None) -> io.Volume:
    """The CT from the lumen's signed distance; ``stressors`` (:class:`.stressors._Painter`) paints
    what lies around the vessels before them and what lies on them after them."""
    voxel = float(min(volume.spacing))
    hu = _body_and_spine(volume, anatomy)
    if stressors is not None:
        stressors.before_vessels(hu, volume, anatomy, lumen)
    wall = _coarse_tube_field(volume, _wall_tubes(anatomy), pad_mm=_PERIVASCULAR_FAT_MM + 2.0 * voxel)
    fat = _fraction_inside(wall - _PERIVASCULAR_FAT_MM, voxel)
    hu += fat * (_FAT_HU - hu)
    hu += _fraction_inside(wall, voxel) * (params.thrombus_hu - hu)
    hu += _fraction_inside(lumen, voxel) * (params.lumen_hu - hu)
    if stressors is not None:
        stressors.after_vessels(hu, volume, anatomy, lumen)
    sigma = params.ct_blur_mm / np.asarray(volume.spacing)[::-1]
    hu = ndimage.gaussian_filter(hu, sigma=sigma, mode="nearest")
    hu += rng.normal(0.0, params.ct_noise_hu, size=hu.shape).astype(np.float32)
    return volume.with_array(np.clip(np.rint(hu), -1024, 3071).astype(np.int16))


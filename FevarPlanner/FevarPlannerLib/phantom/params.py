"""Phantom parameters: every number that defines a case, and the ranges a random case is drawn from."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np


@dataclass
class PhantomParams:
    """Every number that defines a phantom case: shape, deformation, C-arm, noise.

    Lengths in mm, angles in degrees. Pairs are ``(left, right)``. ``to_dict`` /
    ``from_dict`` round-trip through JSON.
    """

    # aorta
    aorta_radius_mm: float = 11.0            # lumen radius at the top
    aorta_distal_radius_mm: float = 9.0      # lumen radius at the bifurcation
    wall_thickness_mm: float = 1.5
    upper_aorta_length_mm: float = 75.0      # above the (right) renal ostium
    neck_length_mm: float = 20.0             # renals to the sac
    sac_length_mm: float = 90.0
    sac_outer_radius_mm: float = 23.0        # outer wall of the sac (thrombus included)
    sac_lumen_radius_mm: float = 13.0        # flow lumen in the sac
    thrombus_eccentricity_mm: float = 3.0    # outer wall centre lies this far anterior of the lumen
    distal_aorta_length_mm: float = 20.0     # sac to bifurcation
    aorta_lateral_shift_mm: float = 8.0      # leftward drift of the sac
    aorta_anterior_bulge_mm: float = 12.0    # anterior bowing of the lower aorta (lordosis)
    # renal arteries
    renal_left_above_mm: float = 5.0         # left ostium this much higher than the right
    renal_length_mm: tuple = (55.0, 55.0)
    renal_radius_mm: float = 3.0
    renal_descent_deg: float = 15.0          # initial downward angle from horizontal
    renal_posterior_deg: float = 15.0        # initial posterior angle from the frontal plane
    renal_curve_deg: float = 20.0            # further downward turn along the artery
    # common iliacs
    iliac_length_mm: tuple = (80.0, 80.0)
    iliac_radius_mm: float = 5.0
    iliac_half_angle_deg: float = 30.0       # each iliac's angle from the vertical at the bifurcation
    iliac_curve_deg: float = 15.0            # turn back towards the vertical along the iliac
    # optional branches (label "other")
    sma: bool = False
    coeliac: bool = False
    internal_iliacs: bool = False
    # intra-operative deformation (all scaled by deformation_scale; 0 = none)
    deformation_scale: float = 1.0
    bend_lateral_deg: float = 6.0            # lower aorta turns this much towards the patient's left
    bend_anterior_deg: float = 3.0           # lower aorta turns this much anteriorly
    upper_bend_deg: float = 2.0              # upper aorta turns this much towards the left
    iliac_straighten: tuple = (0.5, 0.5)     # fraction of each iliac's curvature removed
    iliac_swing_deg: tuple = (-4.0, -4.0)    # iliac rotation in the frontal plane, + = lateral
    renal_tilt_deg: tuple = (6.0, 4.0)       # renal rotation, + = cranial
    # C-arm
    sid_mm: float = 1100.0
    sod_mm: float = 760.0
    detector_pixel_mm: float = 0.6
    primary_angle_deg: float = 0.0           # LAO +
    secondary_angle_deg: float = 0.0         # cranial +
    detector_rows: int | None = None         # None: fitted to the anatomy
    detector_cols: int | None = None
    detector_margin_px: int = 24
    # misalignment of the given pose (geometry.json) against the true one
    misalign_shift_px: tuple = (0.0, 0.0)
    misalign_rotation_deg: float = 0.0       # in-plane, about the image centre
    misalign_rotation3d_deg: tuple = (0.0, 0.0, 0.0)  # about x, y, z through the isocentre
    # imaging
    ct_spacing_mm: float = 1.0
    ct_margin_mm: float = 25.0
    lumen_hu: float = 350.0
    thrombus_hu: float = 40.0
    ct_noise_hu: float = 12.0
    ct_blur_mm: float = 0.6
    fluoro_attenuation_per_mm: float = 0.03
    fluoro_noise: float = 0.015              # relative noise at the background level
    seed: int = 0                            # image noise

    def to_dict(self) -> dict:
        """A JSON-serialisable dict (tuples become lists)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> "PhantomParams":
        """Inverse of :meth:`to_dict`; ``ValueError`` on unknown keys or bad values."""
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ValueError(f"unknown phantom parameters: {unknown}")
        defaults = cls()
        values = {}
        for name, value in data.items():
            default = getattr(defaults, name)
            if isinstance(default, tuple):
                value = tuple(float(v) for v in value)
                if len(value) != len(default):
                    raise ValueError(f"phantom parameter {name}: expected {len(default)} values, got {len(value)}")
            values[name] = value
        params = cls(**values)
        params.validate()
        return params

    def shape_dict(self) -> dict:
        """The parameters that define the rest anatomy (not deformation or imaging)."""
        return {k: v for k, v in self.to_dict().items() if k in _SHAPE_FIELDS}

    def validate(self) -> "PhantomParams":
        """Return self, or raise ``ValueError`` naming the first inconsistent parameter."""
        positive = ["aorta_radius_mm", "aorta_distal_radius_mm", "upper_aorta_length_mm", "neck_length_mm",
                    "sac_length_mm", "distal_aorta_length_mm", "renal_radius_mm", "iliac_radius_mm",
                    "sid_mm", "sod_mm", "detector_pixel_mm", "ct_spacing_mm"]
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"phantom parameter {name} must be positive, got {value}")
        for name in ("renal_length_mm", "iliac_length_mm"):
            if min(getattr(self, name)) <= 0:
                raise ValueError(f"phantom parameter {name} must be positive, got {getattr(self, name)}")
        if self.sod_mm >= self.sid_mm:
            raise ValueError(f"phantom parameter sod_mm ({self.sod_mm}) must be smaller than sid_mm ({self.sid_mm})")
        if self.sac_outer_radius_mm < self.sac_lumen_radius_mm + self.thrombus_eccentricity_mm:
            raise ValueError("phantom parameter sac_outer_radius_mm must be at least sac_lumen_radius_mm + "
                             "thrombus_eccentricity_mm")
        if self.deformation_scale < 0 or self.ct_margin_mm < 0:
            raise ValueError("phantom parameters deformation_scale and ct_margin_mm must not be negative")
        for name in ("detector_rows", "detector_cols"):
            value = getattr(self, name)
            if value is not None and int(value) < 16:
                raise ValueError(f"phantom parameter {name} must be None or at least 16, got {value}")
        return self


_SHAPE_FIELDS = ("aorta_radius_mm", "aorta_distal_radius_mm", "wall_thickness_mm", "upper_aorta_length_mm",
                 "neck_length_mm", "sac_length_mm", "sac_outer_radius_mm", "sac_lumen_radius_mm",
                 "thrombus_eccentricity_mm", "distal_aorta_length_mm", "aorta_lateral_shift_mm",
                 "aorta_anterior_bulge_mm", "renal_left_above_mm", "renal_length_mm", "renal_radius_mm",
                 "renal_descent_deg", "renal_posterior_deg", "renal_curve_deg", "iliac_length_mm",
                 "iliac_radius_mm", "iliac_half_angle_deg", "iliac_curve_deg", "sma", "coeliac", "internal_iliacs")

_DEFORMATION_FIELDS = ("deformation_scale", "bend_lateral_deg", "bend_anterior_deg", "upper_bend_deg",
                       "iliac_straighten", "iliac_swing_deg", "renal_tilt_deg")

#: Uniform ranges that :func:`random_params` draws from (pairs are drawn per side).
PARAM_RANGES = {
    "aorta_radius_mm": (9.5, 12.0),
    "aorta_distal_radius_mm": (8.0, 9.5),
    "upper_aorta_length_mm": (60.0, 90.0),
    "neck_length_mm": (15.0, 30.0),
    "sac_length_mm": (70.0, 110.0),
    "sac_outer_radius_mm": (19.0, 25.0),
    "sac_lumen_radius_mm": (10.0, 14.0),
    "thrombus_eccentricity_mm": (0.0, 4.0),
    "distal_aorta_length_mm": (10.0, 25.0),
    "aorta_lateral_shift_mm": (-4.0, 14.0),
    "aorta_anterior_bulge_mm": (0.0, 20.0),
    "renal_left_above_mm": (-2.0, 10.0),
    "renal_length_mm": (40.0, 70.0),
    "renal_radius_mm": (2.6, 3.4),
    "renal_descent_deg": (0.0, 30.0),
    "renal_posterior_deg": (5.0, 30.0),
    "renal_curve_deg": (0.0, 35.0),
    "iliac_length_mm": (60.0, 100.0),
    "iliac_radius_mm": (4.5, 6.0),
    "iliac_half_angle_deg": (25.0, 40.0),
    "iliac_curve_deg": (0.0, 25.0),
    "deformation_scale": (0.5, 1.2),
    "bend_lateral_deg": (-8.0, 8.0),
    "bend_anterior_deg": (-4.0, 6.0),
    "upper_bend_deg": (-4.0, 4.0),
    "iliac_straighten": (0.2, 0.8),
    "iliac_swing_deg": (-6.0, 4.0),
    "renal_tilt_deg": (-4.0, 12.0),
    "sid_mm": (1000.0, 1200.0),
    "sod_mm": (700.0, 800.0),
    "detector_pixel_mm": (0.5, 0.65),
    "primary_angle_deg": (-20.0, 20.0),
    "secondary_angle_deg": (-10.0, 10.0),
    "misalign_shift_px": (-8.0, 8.0),
    "misalign_rotation_deg": (-3.0, 3.0),
    "lumen_hu": (300.0, 400.0),
    "ct_noise_hu": (8.0, 18.0),
}
_BRANCH_PROBABILITY = 0.5


def _draw(rng: np.random.Generator, default, bounds):
    low, high = bounds
    if isinstance(default, tuple):
        return tuple(float(v) for v in rng.uniform(low, high, size=len(default)))
    return float(rng.uniform(low, high))


def random_params(rng: np.random.Generator, **overrides) -> PhantomParams:
    """Draw a plausible phantom from :data:`PARAM_RANGES`; ``overrides`` win.

    Parameters
    ----------
    rng : numpy.random.Generator
    **overrides
        Any :class:`PhantomParams` field.

    Returns
    -------
    PhantomParams
    """
    defaults = PhantomParams()
    unknown = sorted(set(overrides) - {f.name for f in fields(PhantomParams)})
    if unknown:
        raise ValueError(f"unknown phantom parameters: {unknown}")
    values = {name: _draw(rng, getattr(defaults, name), bounds) for name, bounds in PARAM_RANGES.items()}
    for branch in ("sma", "coeliac", "internal_iliacs"):
        values[branch] = bool(rng.random() < _BRANCH_PROBABILITY)
    values["seed"] = int(rng.integers(0, 2**31 - 1))
    values.update(overrides)
    return replace(defaults, **values).validate()


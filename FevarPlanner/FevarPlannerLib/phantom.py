"""Synthetic AAA phantoms with ground truth, for the paper's simulation experiment (Sec. III).

A phantom is a set of vessel centrelines (LPS mm) with a lumen radius per point: the aorta
(upper aorta, neck, fusiform aneurysm sac with non-enhancing thrombus, distal aorta), the
left and right renal arteries, the common iliacs and, by parameter, the SMA, the coeliac
trunk and the internal iliacs (label ``other``). From it we render

* a contrast CT (int16 HU, DICOM series) and the pre-operative lumen mask on its grid;
* a DSA-like fluoroscopic frame of the intra-operative shape (DICOM XA with the C-arm
  tags) and its projected lumen mask;
* the ground truth: the dense pre- and intra-operative centrelines (node ``n`` of one is
  node ``n`` of the other) and the true projection matrix.

Intra-operative deformation
---------------------------
The intra-operative shape comes from rotating the segments of each centreline (aortic
bending about the renal level, iliac straightening and swing as a stiff wire causes, a
change of the renal take-off angle). Rotating segments keeps every segment length, so the
vessel lengths are preserved exactly and both shapes resample to the same graph.

Paper protocol
--------------
Sec. III-A/B: five deformed states of one phantom; each state's pre-operative 3D skeleton
is paired with the intra-operative 2D skeleton of each of the other four states, giving
20 cases. :func:`paper_protocol` builds one rest anatomy and five deformation states of it
(same shape parameters, different deformations) and returns the 20 ordered pairs
``(state i, state j)``, ``i != j``. Pairing states of the SAME phantom is what makes the
pairs geometrically meaningful: the true intra-operative shape is a smooth, length
preserving deformation of the pre-operative one, as for the physical phantom bent by a
string in the paper. The paper's simulated frames are projected without misalignment; the
in-plane misalignment of its robustness test is a parameter here (``misalign_*``).

Coordinates: LPS (+x patient left, +y posterior, +z superior), mm. The CT grid is axis
aligned (identity direction), the C-arm isocentre is the CT grid centre, so the P built
from the DICOM tags with :func:`projection.projection_matrix_from_carm` equals ``P_true``.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from . import io
from .centerline import ANATOMY_LABELS, Centerline
from .projection import (CArmGeometry, in_plane_transform, project, projection_matrix_from_carm,
                         source_position, write_geometry_json)

__all__ = [
    "PhantomParams",
    "random_params",
    "Vessel",
    "Anatomy",
    "build_preop_anatomy",
    "deform_anatomy",
    "state_anatomy",
    "Grid",
    "ct_grid",
    "PhantomCase",
    "generate_case",
    "rasterize_lumen",
    "render_ct",
    "render_fluoro",
    "fit_detector",
    "write_case",
    "write_phantom_set",
    "paper_protocol",
]

BASE_STEP_MM = 1.0          # spacing of the dense anatomy polylines
_CHUNK = 8                  # segments per block in the distance computations
_AORTA_X0 = 5.0             # the abdominal aorta lies slightly left of the midline
_FLUORO_FULL_SCALE = 4095   # 12-bit detector


# --------------------------------------------------------------------------- parameters

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


# --------------------------------------------------------------------------- anatomy

@dataclass
class Vessel:
    """One vessel: a dense centreline with lumen and outer-wall radii.

    Attributes
    ----------
    label : str
        One of :data:`centerline.ANATOMY_LABELS`.
    points : numpy.ndarray, shape (k, 3)
        Lumen centreline, LPS mm, ordered from the parent (or the top of the aorta).
    radius : numpy.ndarray, shape (k,)
        Lumen radius, mm.
    outer_radius : numpy.ndarray, shape (k,)
        Outer wall radius (thrombus included), mm.
    outer_offset : numpy.ndarray, shape (k, 3)
        Centre of the outer wall minus the lumen centre (eccentric thrombus).
    parent : str or None
        Name of the vessel it leaves from; its first point lies on the parent's centreline.
    parent_index : int
        Index of that point in the parent's ``points``.
    """

    label: str
    points: np.ndarray
    radius: np.ndarray
    outer_radius: np.ndarray
    outer_offset: np.ndarray
    parent: str | None = None
    parent_index: int = 0

    def __post_init__(self):
        if self.label not in ANATOMY_LABELS:
            raise ValueError(f"unknown anatomy label {self.label!r}")
        self.points = np.asarray(self.points, dtype=float).reshape(-1, 3)
        k = len(self.points)
        self.radius = np.broadcast_to(np.asarray(self.radius, dtype=float), (k,)).copy()
        self.outer_radius = np.broadcast_to(np.asarray(self.outer_radius, dtype=float), (k,)).copy()
        self.outer_offset = np.broadcast_to(np.asarray(self.outer_offset, dtype=float), (k, 3)).copy()

    def arc_length(self) -> np.ndarray:
        """Cumulative arc length at each point, mm."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))])

    @property
    def length(self) -> float:
        return float(self.arc_length()[-1])

    def moved(self, points: np.ndarray, rotations: np.ndarray) -> "Vessel":
        """The same vessel at new points, its wall offsets turned by per-point ``rotations``."""
        offsets = np.einsum("kab,kb->ka", rotations, self.outer_offset)
        return replace(self, points=points, outer_offset=offsets)


@dataclass
class Anatomy:
    """Vessels by name, parents listed before their branches.

    The five main vessels are named after their labels (``aorta``, ``renal_left``,
    ``renal_right``, ``iliac_left``, ``iliac_right``); optional branches are ``sma``,
    ``coeliac``, ``internal_iliac_left``, ``internal_iliac_right`` (label ``other``).
    """

    vessels: dict = field(default_factory=dict)

    def by_label(self, label: str) -> list:
        """The vessels carrying ``label``."""
        return [v for v in self.vessels.values() if v.label == label]

    def lengths(self) -> dict:
        """Centreline length of each vessel, mm."""
        return {name: v.length for name, v in self.vessels.items()}

    def wall_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """LPS bounding box (low, high) of all outer walls."""
        lows, highs = [], []
        for v in self.vessels.values():
            centres = v.points + v.outer_offset
            lows.append((centres - v.outer_radius[:, None]).min(axis=0))
            highs.append((centres + v.outer_radius[:, None]).max(axis=0))
        return np.min(lows, axis=0), np.max(highs, axis=0)

    def to_centerline(self, step_mm: float = 1.0) -> Centerline:
        """One connected centreline graph, resampled every ``step_mm`` along each vessel.

        A branch's first node is one step from its ostium and is joined to the parent node
        nearest (in arc length) to where it leaves. Deformed copies of an anatomy resample
        to the same nodes in the same order (lengths are preserved), so node ``n`` of the
        pre-operative centreline corresponds to node ``n`` of the intra-operative one.
        """
        if step_mm <= 0:
            raise ValueError(f"centreline step must be positive, got {step_mm}")
        points, labels, edges = [], [], []
        positions, first_node = {}, {}
        count = 0
        for name, vessel in self.vessels.items():
            s = vessel.arc_length()
            steps = max(1, int(round(s[-1] / step_mm)))
            at = np.linspace(0.0, s[-1], steps + 1)
            if vessel.parent is not None:
                at = at[1:]
            pts = np.column_stack([np.interp(at, s, vessel.points[:, d]) for d in range(3)])
            nodes = count + np.arange(len(at))
            edges.extend(zip(nodes[:-1], nodes[1:]))
            if vessel.parent is not None:
                parent_s = self.vessels[vessel.parent].arc_length()[vessel.parent_index]
                parent_at = positions[vessel.parent]
                edges.append((first_node[vessel.parent] + int(np.argmin(np.abs(parent_at - parent_s))), nodes[0]))
            positions[name], first_node[name] = at, count
            points.append(pts)
            labels.extend([vessel.label] * len(at))
            count += len(at)
        return Centerline(np.vstack(points), np.asarray(edges, dtype=np.int64), labels)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _axis_towards(direction, target) -> np.ndarray:
    """Unit rotation axis that turns ``direction`` towards ``target`` (positive angle)."""
    axis = np.cross(direction, target)
    norm = np.linalg.norm(axis)
    if norm < 1e-9:
        axis = np.cross(direction, [1.0, 0.0, 0.0] if abs(direction[0]) < 0.9 else [0.0, 1.0, 0.0])
        norm = np.linalg.norm(axis)
    return axis / norm


def _arc_polyline(origin, direction, bend_target, bend_deg: float, length: float,
                  step: float = BASE_STEP_MM) -> np.ndarray:
    """A constant-curvature arc of ``length`` mm leaving ``origin`` along ``direction``.

    The direction turns by ``bend_deg`` in total towards ``bend_target``; every segment is
    ``length / n`` long.
    """
    direction = _unit(direction)
    n = max(2, int(round(length / step)))
    mid = (np.arange(n) + 0.5) / n * np.deg2rad(bend_deg)
    axis = _axis_towards(direction, _unit(bend_target))
    dirs = Rotation.from_rotvec(mid[:, None] * axis).apply(direction)
    steps = dirs * (length / n)
    return np.asarray(origin, dtype=float) + np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])


def _smoothstep(u) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _sac_bump(t, start: float, length: float) -> np.ndarray:
    """0 outside the sac, rising as sin^2 to 1 at its middle (fusiform aneurysm)."""
    u = np.clip((np.asarray(t) - start) / length, 0.0, 1.0)
    return np.sin(np.pi * u) ** 2


def _resample_by_arc_length(points: np.ndarray, *values, step: float = BASE_STEP_MM):
    """Resample a finely sampled curve (and per-point values) at equal arc-length steps."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    at = np.linspace(0.0, s[-1], max(2, int(round(s[-1] / step))) + 1)
    out = [np.column_stack([np.interp(at, s, points[:, d]) for d in range(points.shape[1])])]
    for value in values:
        value = np.asarray(value, dtype=float)
        if value.ndim == 1:
            out.append(np.interp(at, s, value))
        else:
            out.append(np.column_stack([np.interp(at, s, value[:, d]) for d in range(value.shape[1])]))
    return out


def _aorta_profile(params: PhantomParams) -> tuple[np.ndarray, ...]:
    """Fine samples of the aorta: depth ``t`` below the right renal, points, radii, offsets."""
    p = params
    total = p.neck_length_mm + p.sac_length_mm + p.distal_aorta_length_mm
    t = np.arange(-p.upper_aorta_length_mm, total + 1e-9, 0.1)
    sac = _sac_bump(t, p.neck_length_mm, p.sac_length_mm)
    below = _smoothstep(t / total)
    x = _AORTA_X0 + p.aorta_lateral_shift_mm * (sac + 0.4 * below) / 1.4
    y = -p.aorta_anterior_bulge_mm * below
    points = np.column_stack([x, y, -t])
    taper = p.aorta_radius_mm + (p.aorta_distal_radius_mm - p.aorta_radius_mm) * _smoothstep(
        (t + p.upper_aorta_length_mm) / (total + p.upper_aorta_length_mm))
    lumen = taper + (p.sac_lumen_radius_mm - taper) * sac
    outer = taper + p.wall_thickness_mm + (p.sac_outer_radius_mm - taper - p.wall_thickness_mm) * sac
    offset = np.outer(sac * p.thrombus_eccentricity_mm, [0.0, -1.0, 0.0])
    return t, points, lumen, outer, offset


def _branch(label: str, parent: str, parent_vessel: Vessel, index: int, direction, bend_target, bend_deg: float,
            length: float, radius: float, wall: float) -> Vessel:
    points = _arc_polyline(parent_vessel.points[index], direction, bend_target, bend_deg, length)
    r = radius * np.linspace(1.0, 0.8, len(points))
    return Vessel(label, points, r, r + wall, np.zeros(3), parent=parent, parent_index=index)


def build_preop_anatomy(params: PhantomParams) -> Anatomy:
    """The rest (undeformed) anatomy of ``params``: the pre-operative shape of a random case.

    Parameters
    ----------
    params : PhantomParams

    Returns
    -------
    Anatomy
        Aorta, renal and common iliac arteries, and the optional branches.
    """
    p = params.validate()
    t_fine, pts_fine, lumen_fine, outer_fine, offset_fine = _aorta_profile(p)
    pts, lumen, outer, offset, t = _resample_by_arc_length(pts_fine, lumen_fine, outer_fine, offset_fine, t_fine)
    aorta = Vessel("aorta", pts, lumen, outer, offset)
    vessels = {"aorta": aorta}
    wall = p.wall_thickness_mm * 0.5
    down = np.array([0.0, 0.0, -1.0])
    sides = {"left": 1.0, "right": -1.0}

    def aorta_index(depth_below_renal: float) -> int:
        return int(np.argmin(np.abs(t - depth_below_renal)))

    for k, (side, sign) in enumerate(sides.items()):
        a, b = np.deg2rad(p.renal_descent_deg), np.deg2rad(p.renal_posterior_deg)
        direction = [sign * np.cos(a) * np.cos(b), np.cos(a) * np.sin(b), -np.sin(a)]
        depth_renal = -p.renal_left_above_mm if side == "left" else 0.0
        vessels[f"renal_{side}"] = _branch(f"renal_{side}", "aorta", aorta, aorta_index(depth_renal), direction, down,
                                           p.renal_curve_deg, p.renal_length_mm[k], p.renal_radius_mm, wall)
    bifurcation = len(pts) - 1
    for k, (side, sign) in enumerate(sides.items()):
        h = np.deg2rad(p.iliac_half_angle_deg)
        direction = _unit([sign * np.sin(h), 0.15, -np.cos(h)])
        vessels[f"iliac_{side}"] = _branch(f"iliac_{side}", "aorta", aorta, bifurcation, direction, down,
                                           p.iliac_curve_deg, p.iliac_length_mm[k], p.iliac_radius_mm, wall)
    top_renal = min(0.0, -p.renal_left_above_mm)
    if p.sma:
        vessels["sma"] = _branch("other", "aorta", aorta, aorta_index(top_renal - 12.0), [0.1, -0.85, -0.5], down,
                                 50.0, 60.0, 3.5, wall)
    if p.coeliac:
        vessels["coeliac"] = _branch("other", "aorta", aorta, aorta_index(top_renal - 26.0), [0.05, -0.95, 0.3],
                                     down, 0.0, 25.0, 3.5, wall)
    if p.internal_iliacs:
        for side, sign in sides.items():
            iliac = vessels[f"iliac_{side}"]
            index = int(round(0.75 * (len(iliac.points) - 1)))
            vessels[f"internal_iliac_{side}"] = _branch("other", f"iliac_{side}", iliac, index,
                                                        [-sign * 0.35, 0.75, -0.55], down, 30.0, 35.0, 2.5, wall)
    return Anatomy(vessels)


# --------------------------------------------------------------------------- deformation

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


# --------------------------------------------------------------------------- grids and distance fields

@dataclass(frozen=True)
class Grid:
    """An axis-aligned CT grid: ``shape`` (k, j, i), ``spacing`` (i, j, k) mm, ``origin`` LPS."""

    shape: tuple
    spacing: tuple
    origin: tuple

    def volume(self, array: np.ndarray | None = None, dtype=np.int16) -> io.Volume:
        """A :class:`io.Volume` on this grid holding ``array`` (zeros of ``dtype`` if None)."""
        if array is None:
            array = np.zeros(self.shape, dtype=dtype)
        return io.Volume(array, self.spacing, self.origin, np.eye(3))

    def center_lps(self) -> np.ndarray:
        """LPS of the grid centre (the C-arm isocentre of the phantoms)."""
        ijk = (np.array(self.shape[::-1]) - 1) / 2.0
        return np.asarray(self.origin) + ijk * np.asarray(self.spacing)


def _spine(anatomy: Anatomy) -> tuple[float, float, float]:
    """Vertebral body (x, y centre, radius): on the midline, just behind the aortic wall."""
    aorta = anatomy.vessels["aorta"]
    back = float(np.max(aorta.points[:, 1] + aorta.outer_offset[:, 1] + aorta.outer_radius))
    radius = 20.0
    return 0.0, back + 3.0 + radius, radius


def ct_grid(anatomy: Anatomy, spacing_mm: float = 1.0, margin_mm: float = 25.0) -> Grid:
    """The CT grid: the anatomy's wall bounding box plus ``margin_mm``, and the spine behind."""
    if spacing_mm <= 0:
        raise ValueError(f"CT spacing must be positive, got {spacing_mm}")
    low, high = anatomy.wall_bounds()
    low, high = low - margin_mm, high + margin_mm
    _, spine_y, spine_r = _spine(anatomy)
    high[1] = max(high[1], spine_y + spine_r + 10.0)
    counts = np.ceil((high - low) / spacing_mm).astype(int) + 1
    return Grid(tuple(int(c) for c in counts[::-1]), (float(spacing_mm),) * 3, tuple(round(float(v), 3) for v in low))


def _as_volume(grid) -> io.Volume:
    return grid.volume(dtype=np.uint8) if isinstance(grid, Grid) else grid


def _segment_nearest(coords: np.ndarray, a: np.ndarray, b: np.ndarray, ra: np.ndarray,
                     rb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance and radius of the segment minimising (distance - interpolated radius).

    ``coords`` (N, d); ``a``, ``b`` (G, d) segment ends; ``ra``, ``rb`` (G,) radii at the ends.
    Everything is expanded into (N, G) dot products so no (N, G, d) array is formed.
    """
    origin = a[0]
    coords, a, b = coords - origin, a - origin, b - origin
    ab = b - a
    length2 = np.maximum(np.einsum("gd,gd->g", ab, ab), 1e-12)
    along = coords @ ab.T - np.einsum("gd,gd->g", a, ab)          # (X - A) . AB
    t = np.clip(along / length2, 0.0, 1.0)
    rel2 = np.einsum("nd,nd->n", coords, coords)[:, None] - 2.0 * coords @ a.T + np.einsum("gd,gd->g", a, a)
    dist = np.sqrt(np.maximum(rel2 - 2.0 * t * along + t * t * length2, 0.0))
    radius = ra + t * (rb - ra)
    best = np.argmin(dist - radius, axis=1)[:, None]
    return np.take_along_axis(dist, best, 1)[:, 0], np.take_along_axis(radius, best, 1)[:, 0]


def _chunks(n_segments: int):
    for start in range(0, n_segments, _CHUNK):
        yield slice(start, min(start + _CHUNK, n_segments))


def _chunk_boxes(volume: io.Volume, centres: np.ndarray, reach: np.ndarray):
    """Index boxes ``(lo, hi)`` (k, j, i) covering each run of segments dilated by ``reach``."""
    shape = np.array(volume.shape)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    for sl in _chunks(len(centres) - 1):
        pts = centres[sl.start:sl.stop + 1]
        r = reach[sl.start:sl.stop + 1].max()
        low, high = pts.min(0) - r, pts.max(0) + r
        kji = volume.lps_to_index(low + corners * (high - low))
        lo = np.clip(np.floor(kji.min(0)).astype(int), 0, shape)
        hi = np.clip(np.ceil(kji.max(0)).astype(int) + 1, 0, shape)
        if np.all(hi > lo):
            yield lo, hi


def _window_half_width(centres: np.ndarray, radii: np.ndarray, reach: float) -> int:
    """Segments either side of the nearest vertex that can hold the minimum of (distance - radius).

    Where the radius changes by ``dr/ds`` along the axis, that minimum lies up to
    ``reach * dr/ds`` away from the nearest point.
    """
    lengths = np.maximum(np.linalg.norm(np.diff(centres, axis=0), axis=1), 1e-9)
    slope = float(np.max(np.abs(np.diff(radii)) / lengths)) if len(lengths) else 0.0
    return int(np.ceil(reach * slope / max(float(lengths.min()), 1e-3))) + 2


def _tube_field(volume: io.Volume, centres_radii, pad_mm: float) -> np.ndarray:
    """Signed distance (mm, negative inside) to a union of tapered tubes, exact within ``pad_mm``.

    ``centres_radii`` yields (points (k, 3), radii (k,)); elsewhere the value is ``pad_mm``.
    Each candidate voxel is tested against the few segments around its nearest centreline
    vertex (k-d tree), not against the whole vessel.
    """
    out = np.full(volume.shape, pad_mm, dtype=np.float32)
    for centres, radii in centres_radii:
        reach = radii + pad_mm
        boxes = list(_chunk_boxes(volume, centres, reach))
        if not boxes:
            continue
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        candidate = np.zeros(tuple(hi - lo), dtype=bool)
        for blo, bhi in boxes:
            candidate[tuple(slice(a, b) for a, b in zip(blo - lo, bhi - lo))] = True
        kji = np.column_stack(np.nonzero(candidate)) + lo
        coords = volume.index_to_lps(kji.astype(float))
        _, nearest = cKDTree(centres).query(coords, distance_upper_bound=float(reach.max()) + 1.0)
        near = nearest < len(centres)
        kji, coords, nearest = kji[near], coords[near], nearest[near]
        half = _window_half_width(centres, radii, float(reach.max()))
        segments = np.clip(nearest[:, None] + np.arange(-half, half)[None], 0, len(centres) - 2)
        values = _windowed_field(coords, centres, radii, segments)
        index = tuple(kji.T)
        out[index] = np.minimum(out[index], values)
    return out


def _windowed_field(coords: np.ndarray, centres: np.ndarray, radii: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """min over the listed segments (N, W) of (distance - interpolated radius), per coordinate."""
    a, b = centres[segments], centres[segments + 1]
    ab = b - a
    rel = coords[:, None, :] - a
    t = np.clip(np.einsum("nwd,nwd->nw", rel, ab) / np.maximum(np.einsum("nwd,nwd->nw", ab, ab), 1e-12), 0.0, 1.0)
    dist = np.linalg.norm(rel - t[..., None] * ab, axis=-1)
    radius = radii[segments] + t * (radii[segments + 1] - radii[segments])
    return (dist - radius).min(axis=1)


def _lumen_tubes(anatomy: Anatomy):
    return ((v.points, v.radius) for v in anatomy.vessels.values())


def _wall_tubes(anatomy: Anatomy):
    return ((v.points + v.outer_offset, v.outer_radius) for v in anatomy.vessels.values())


def rasterize_lumen(anatomy: Anatomy, grid: io.Volume | Grid | None = None, *, spacing_mm: float = 1.0,
                    margin_mm: float = 25.0) -> io.Volume:
    """Binary lumen mask of ``anatomy`` (voxel centres inside a vessel), LPS.

    Parameters
    ----------
    anatomy : Anatomy
    grid : io.Volume or Grid, optional
        Target grid (any direction). Default: :func:`ct_grid` with ``spacing_mm`` and
        ``margin_mm``.

    Returns
    -------
    io.Volume
        Boolean array on the grid.
    """
    volume = _as_volume(grid if grid is not None else ct_grid(anatomy, spacing_mm, margin_mm))
    return volume.with_array(_lumen_field(anatomy, volume) <= 0.0)


def _lumen_field(anatomy: Anatomy, volume: io.Volume) -> np.ndarray:
    """Signed distance to the lumen, exact within one voxel (enough for mask and partial volume)."""
    return _tube_field(volume, _lumen_tubes(anatomy), pad_mm=max(1.0, float(min(volume.spacing))))


# --------------------------------------------------------------------------- CT

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
                         lumen: np.ndarray) -> io.Volume:
    voxel = float(min(volume.spacing))
    hu = _body_and_spine(volume, anatomy)
    wall = _coarse_tube_field(volume, _wall_tubes(anatomy), pad_mm=_PERIVASCULAR_FAT_MM + 2.0 * voxel)
    fat = _fraction_inside(wall - _PERIVASCULAR_FAT_MM, voxel)
    hu += fat * (_FAT_HU - hu)
    hu += _fraction_inside(wall, voxel) * (params.thrombus_hu - hu)
    hu += _fraction_inside(lumen, voxel) * (params.lumen_hu - hu)
    sigma = params.ct_blur_mm / np.asarray(volume.spacing)[::-1]
    hu = ndimage.gaussian_filter(hu, sigma=sigma, mode="nearest")
    hu += rng.normal(0.0, params.ct_noise_hu, size=hu.shape).astype(np.float32)
    return volume.with_array(np.clip(np.rint(hu), -1024, 3071).astype(np.int16))


# --------------------------------------------------------------------------- fluoroscopy

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


# --------------------------------------------------------------------------- cases

@dataclass
class PhantomCase:
    """A generated case: both shapes, the C-arm, the poses and the CT grid.

    Attributes
    ----------
    name : str
    params : PhantomParams
        Intra-operative state (deformation, C-arm, fluoroscopy noise).
    preop_params : PhantomParams
        Pre-operative state (CT noise); for a random case the same object as ``params``,
        whose pre-operative shape is the rest anatomy.
    preop, intraop : Anatomy
    carm : CArmGeometry
        The true C-arm; its tags give ``P_true`` with the isocentre at the CT centre.
    P_true, P_given : numpy.ndarray, shape (3, 4)
        The projection that made the frame and the one written to geometry.json.
    grid : Grid
        The CT grid.
    info : dict
        Extra JSON-serialisable facts (protocol, pairing).
    """

    name: str
    params: PhantomParams
    preop_params: PhantomParams
    preop: Anatomy
    intraop: Anatomy
    carm: CArmGeometry
    P_true: np.ndarray
    P_given: np.ndarray
    grid: Grid
    info: dict = field(default_factory=dict)


def _same_phantom(pre: PhantomParams, intra: PhantomParams) -> None:
    if pre.shape_dict() != intra.shape_dict():
        differing = sorted(k for k, v in pre.shape_dict().items() if intra.shape_dict()[k] != v)
        raise ValueError(f"pre- and intra-operative states describe different phantoms (differ in {differing})")


def generate_case(params: PhantomParams, intraop_params: PhantomParams | None = None, *,
                  name: str = "phantom", info: dict | None = None) -> PhantomCase:
    """Build a case.

    Parameters
    ----------
    params : PhantomParams
        With ``intraop_params`` None: the pre-operative shape is the rest anatomy and the
        intra-operative one is it deformed by ``params``. Otherwise ``params`` is the
        pre-operative state (rest anatomy deformed by its own deformation parameters).
    intraop_params : PhantomParams, optional
        The intra-operative state of the same phantom (paper protocol); its C-arm,
        misalignment and fluoroscopy parameters are used.
    name : str
    info : dict, optional

    Returns
    -------
    PhantomCase
    """
    params.validate()
    if intraop_params is None:
        pre_params, intra_params = params, params
        preop = build_preop_anatomy(params)
        intraop = deform_anatomy(preop, params)
    else:
        intraop_params.validate()
        _same_phantom(params, intraop_params)
        pre_params, intra_params = params, intraop_params
        preop, intraop = state_anatomy(params), state_anatomy(intraop_params)
    grid = ct_grid(preop, pre_params.ct_spacing_mm, pre_params.ct_margin_mm)
    isocenter = grid.center_lps()
    carm = fit_detector(intraop, intra_params, isocenter)
    P_true = projection_matrix_from_carm(carm, isocenter)
    P_given = _misaligned(P_true, intra_params, isocenter, carm)
    return PhantomCase(name, intra_params, pre_params, preop, intraop, carm, P_true, P_given, grid, dict(info or {}))


def _ground_truth(case: PhantomCase) -> dict:
    pre, intra = case.preop.to_centerline(), case.intraop.to_centerline()
    return {
        "version": 1,
        "preop_centerline": pre.to_dict(),
        "intraop_centerline": intra.to_dict(),
        "correspondence": "node n of intraop_centerline is node n of preop_centerline",
        "projection_matrix_true": case.P_true.tolist(),
        "projection_matrix_given": case.P_given.tolist(),
        "vessel_lengths_mm": {"preop": case.preop.lengths(), "intraop": case.intraop.lengths()},
    }


def _case_json(case: PhantomCase) -> dict:
    return {
        "version": 1,
        "name": case.name,
        "seed": case.params.seed,
        "params": case.params.to_dict(),
        "preop_params": case.preop_params.to_dict(),
        "carm": {"sid": case.carm.sid, "sod": case.carm.sod, "pixel_spacing": list(case.carm.pixel_spacing),
                 "primary_angle": case.carm.primary_angle, "secondary_angle": case.carm.secondary_angle,
                 "rows": case.carm.rows, "cols": case.carm.cols},
        "ct_grid": {"shape_kji": list(case.grid.shape), "spacing_ijk": list(case.grid.spacing),
                    "origin": list(case.grid.origin)},
        **case.info,
    }


def write_case(case: PhantomCase, folder, *, mask_only: bool = False) -> Path:
    """Write a case folder (docs/DESIGN.md section 4) atomically and return its path.

    Files: ``ct/`` (DICOM series, skipped with ``mask_only``), ``aorta_mask.nrrd``,
    ``fluoro.dcm`` (skipped with ``mask_only``), ``fluoro_mask.png``, ``geometry.json``
    (``P_given``, and ``true_projection_matrix``), ``gt.json``, ``case.json``.
    """
    folder = Path(folder)
    pre_rng = np.random.default_rng([case.preop_params.seed, 1])
    intra_rng = np.random.default_rng([case.params.seed, 2])
    with io.atomic_folder(folder) as tmp:
        volume = case.grid.volume(dtype=np.uint8)
        lumen = _lumen_field(case.preop, volume)
        io.write_volume(tmp / "aorta_mask.nrrd", volume.with_array((lumen <= 0.0).astype(np.uint8)))
        frame, fluoro_mask = render_fluoro(case.intraop, case.P_true, case.carm, case.params, intra_rng)
        io.write_mask_png(tmp / "fluoro_mask.png", fluoro_mask)
        if not mask_only:
            ct = _ct_from_lumen_field(case.preop, case.preop_params, pre_rng, volume, lumen)
            io.write_ct_dicom_series(ct, tmp / "ct", series_description=f"FevarPlanner phantom CT {case.name}",
                                     patient_name=f"Phantom^{case.name}", patient_id=case.name)
            io.write_fluoro_dicom(tmp / "fluoro.dcm", frame, case.carm, patient_name=f"Phantom^{case.name}",
                                  patient_id=case.name)
        write_geometry_json(tmp / "geometry.json", case.P_given, true_projection_matrix=case.P_true.tolist(),
                            isocenter=case.grid.center_lps().tolist())
        io.write_text_atomic(tmp / "gt.json", json.dumps(_ground_truth(case)))
        io.write_text_atomic(tmp / "case.json", json.dumps(_case_json(case), indent=2))
    return folder


# --------------------------------------------------------------------------- sets and the paper protocol

PAPER_STATES = 5
#: Out-of-plane bend of the sac between the paper protocol's states, degrees (see
#: :func:`paper_protocol`).
PAPER_OUT_OF_PLANE_DEG = 0.0


def paper_protocol(seed: int = 0, out_of_plane_deg: float = PAPER_OUT_OF_PLANE_DEG) -> list:
    """The paper's simulation protocol (Sec. III-A/B): 20 ``(pre_params, intra_params)`` pairs.

    One phantom (shape drawn from ``seed``) with the five main vessels only (like the
    paper's endovascular evaluator), in five deformed states, AP view, no misalignment;
    every ordered pair of different states ``(i, j)`` is one case, in the order
    ``(0, 1), (0, 2), ..., (4, 3)``.

    The paper's phantom lay on a table and was bent by a string (paper Sec. III), so its states
    differ by bending in the frontal (coronal) plane, which an AP frame sees: the sac's
    anterior bend is drawn from ``+-out_of_plane_deg`` (0 by default). The vessels' own 3D
    curvature still moves in depth as the iliacs straighten and the renals tilt. A non-zero
    ``out_of_plane_deg`` adds a bend that one view cannot see (the benchmark reports it as
    a separate set); the other parameters are drawn identically whatever its value.
    """
    rng = np.random.default_rng(seed)
    shape = random_params(rng, primary_angle_deg=0.0, secondary_angle_deg=0.0, misalign_shift_px=(0.0, 0.0),
                          misalign_rotation_deg=0.0, sma=False, coeliac=False, internal_iliacs=False)
    defaults = PhantomParams()
    ranges = {**PARAM_RANGES, "bend_anterior_deg": (-out_of_plane_deg, out_of_plane_deg)}
    states = []
    for _ in range(PAPER_STATES):
        deformation = {name: _draw(rng, getattr(defaults, name), ranges[name]) for name in _DEFORMATION_FIELDS}
        states.append(replace(shape, seed=int(rng.integers(0, 2**31 - 1)), **deformation).validate())
    return [(states[i], states[j]) for i in range(PAPER_STATES) for j in range(PAPER_STATES) if i != j]


def _planned_cases(n: int, seed: int, preset: str) -> list:
    """(name, pre_params, intra_params or None, info) for each case of a set."""
    if preset == "paper":
        planned, batch = [], 0
        while len(planned) < n:
            pairs = paper_protocol(seed + batch)
            order = [(i, j) for i in range(PAPER_STATES) for j in range(PAPER_STATES) if i != j]
            for (pre, intra), (i, j) in zip(pairs, order):
                info = {"protocol": "paper", "protocol_seed": seed + batch, "preop_state": i, "intraop_state": j}
                planned.append((f"paper{batch:02d}_pre{i}_intra{j}", pre, intra, info))
            batch += 1
        return planned[:n]
    if preset == "random":
        children = np.random.SeedSequence(seed).spawn(n)
        return [(f"case_{i:03d}", random_params(np.random.default_rng(child)), None,
                 {"protocol": "random", "set_seed": seed, "index": i}) for i, child in enumerate(children)]
    raise ValueError(f"unknown phantom preset {preset!r} (expected 'paper' or 'random')")


def write_phantom_set(out_dir, n: int = 20, seed: int = 0, preset: str = "paper", mask_only: bool = False,
                      progress=None) -> list:
    """Write ``n`` phantom cases under ``out_dir`` and return their folders.

    Parameters
    ----------
    out_dir : path
    n : int
        Number of cases; the paper preset has 20 per phantom and draws a further phantom
        (seed + 1, ...) for more.
    seed : int
    preset : {"paper", "random"}
        ``paper``: :func:`paper_protocol` pairs; ``random``: independent random cases.
    mask_only : bool
        Skip the CT series and the DICOM frame (masks, geometry and ground truth only).
    progress : callable, optional
        Called as ``progress(i, n, name)`` before case ``i`` is written.
    """
    if n < 1:
        raise ValueError(f"number of phantom cases must be positive, got {n}")
    out_dir = Path(out_dir)
    folders = []
    planned = _planned_cases(n, seed, preset)
    for i, (name, pre, intra, info) in enumerate(planned):
        if progress is not None:
            progress(i, len(planned), name)
        case = generate_case(pre, intra, name=name, info=info)
        folders.append(write_case(case, out_dir / name, mask_only=mask_only))
    return folders

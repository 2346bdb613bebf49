"""The rest anatomy: vessels (dense centrelines with lumen and wall radii) and how they are built."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..centerline import ANATOMY_LABELS, Centerline
from .params import PhantomParams

BASE_STEP_MM = 1.0          # spacing of the dense anatomy polylines
_AORTA_X0 = 5.0             # the abdominal aorta lies slightly left of the midline


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


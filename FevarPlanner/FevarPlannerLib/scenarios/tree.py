"""The scenario family's own vessel tree (:func:`build_tree`): an aorta with a fusiform sac
(narrow or wide), both renals, common iliacs that can fork distally into an internal (label
``other``) and an external iliac (which keeps the common iliac's label), optional SMA, coeliac
trunk, an accessory renal artery and lumbar stubs (``other``), and tortuous iliacs. Every
tube is a dense polyline (1 mm steps) with a lumen radius.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..centerline import Centerline
from ..conventions import BRANCH_LABELS

__all__ = [
    "Tube",
    "VesselTree",
    "TreeShape",
    "random_shape",
    "build_tree",
    "MAIN_VESSELS",
    "STEP_MM",
    "SIDES",
]

#: The five vessels that every tree holds and every benchmark compares.
MAIN_VESSELS = BRANCH_LABELS
STEP_MM = 1.0
SIDES = ("left", "right")
#: Depth swing of a looping iliac per mm of its along-chord swing (:func:`_loops`): enough
#: that the passes of a loop stay apart in 3D (their lumens do not merge in the CT).
LOOP_DEPTH = 2.0
_LEFT = {"left": 1.0, "right": -1.0}


@dataclass
class Tube:
    """One vessel: a dense polyline (LPS mm) with a lumen radius per point.

    ``parent`` / ``parent_index`` say where it leaves its parent tube (its first point is that
    parent point); ``in_ct`` False marks a tube that the frames show but the CT tree lacks.
    """

    label: str
    points: np.ndarray
    radius: np.ndarray
    parent: str | None = None
    parent_index: int = 0
    in_ct: bool = True

    def copy(self) -> "Tube":
        return replace(self, points=self.points.copy(), radius=self.radius.copy())


@dataclass
class VesselTree:
    """Named tubes in a fixed order (the order of the centreline nodes)."""

    tubes: dict

    def copy(self) -> "VesselTree":
        return VesselTree({name: tube.copy() for name, tube in self.tubes.items()})

    def distal_part(self, name: str, index: int) -> list[tuple[str, int]]:
        """``(tube, first point)`` of everything beyond point ``index`` of ``name``, inclusive.

        The tube itself from ``index`` on, and every tube (with its own descendants) that
        leaves it at or beyond ``index``.
        """
        part = [(name, index)]
        for child, tube in self.tubes.items():
            if tube.parent == name and tube.parent_index >= index:
                part.extend(self.distal_part(child, 0))
        return part

    def centerline(self, in_ct_only: bool = True) -> Centerline:
        """The tree as one centreline graph: each tube a chain, joined to its parent point."""
        offsets, points, labels, edges, start = {}, [], [], [], 0
        chosen = [name for name, tube in self.tubes.items() if tube.in_ct or not in_ct_only]
        for name in chosen:
            tube = self.tubes[name]
            offsets[name] = start
            points.append(tube.points)
            labels.extend([tube.label] * len(tube.points))
            n = len(tube.points)
            edges.append(np.column_stack([np.arange(start, start + n - 1), np.arange(start + 1, start + n)]))
            start += n
        for name in chosen:
            tube = self.tubes[name]
            if tube.parent is not None and tube.parent in offsets:
                # the branch starts at (or, after an ostium shift, next to) its parent point
                edges.append(np.array([[offsets[tube.parent] + tube.parent_index, offsets[name]]]))
        return Centerline(np.concatenate(points), np.concatenate(edges), labels)


@dataclass
class TreeShape:
    """Every number of a rest vessel tree (mm, degrees). ``to_dict`` is JSON-ready."""

    aorta_top_radius: float = 11.0
    aorta_distal_radius: float = 8.5
    upper_aorta: float = 75.0        # aorta top to the right renal ostium
    neck: float = 20.0               # right renal ostium to the sac
    sac_length: float = 90.0
    sac_radius: float = 16.0         # lumen radius at the widest point of the sac
    distal_aorta: float = 18.0       # sac to the bifurcation
    sac_drift: float = 8.0           # leftward drift of the sac (+x)
    sac_bulge: float = 10.0          # anterior bowing of the sac (-y)
    renal_offset: float = 4.0        # left ostium this much above the right
    renal_length: tuple = (55.0, 55.0)
    renal_radius: float = 3.0
    renal_descent_deg: float = 15.0
    renal_posterior_deg: float = 15.0
    renal_turn_deg: float = 20.0
    iliac_length: tuple = (85.0, 85.0)
    iliac_radius: float = 5.2
    iliac_spread_deg: tuple = (30.0, 30.0)   # from the vertical at the bifurcation
    iliac_turn_deg: tuple = (15.0, 15.0)     # back towards the vertical along the iliac
    iliac_posterior_deg: float = 8.0
    tortuosity_mm: tuple = (2.0, 2.0)        # amplitude of the iliacs' sinuous offset
    tortuosity_waves: tuple = (1.5, 1.5)
    tortuosity_phase: tuple = (0.0, 0.0)
    tortuosity_plane_deg: tuple = (0.0, 0.0)  # direction of the offset about the iliac's axis
    internal_iliacs: str = "none"            # "none", "ct" (in the CT tree) or "frame" (frames only)
    internal_at: tuple = (0.65, 0.65)        # fraction of the iliac where the internal iliac leaves
    internal_length: tuple = (38.0, 38.0)
    sma: bool = False
    coeliac: bool = False
    accessory_renal: str = "none"            # "none", "left", "right" or "both" (in the CT tree)
    lumbars: str = "none"                    # "none", "ct" or "frame"
    # patient-like anatomy (the ``patient_like`` kind); at these defaults the tree is as before
    ima: bool = False                        # inferior mesenteric artery off the sac (in the CT tree)
    sma_above: float = 18.0                  # SMA ostium this far above the right renal's
    coeliac_above: float = 34.0
    accessory_below: float = 16.0            # accessory renal ostium this far below the right renal's
    accessory_descent_deg: float = 10.0      # steeper than the main renal by this much
    accessory_length: float = 40.0
    accessory_radius: float = 2.0
    accessory_turn_deg: float = 10.0
    iliac_loop_mm: tuple = (0.0, 0.0)        # along-axis swing of the tortuous iliacs: loops in projection
    neck_kink_mm: float = 0.0                # S-shaped offset of the upper aorta and neck (tortuous neck)
    neck_kink_dir_deg: float = 0.0           # its direction in the axial plane (0: patient left)
    internal_direction: tuple = (-0.45, 0.55, -0.7)   # internal iliacs leave along this (x: towards their side)

    def to_dict(self) -> dict:
        """JSON-ready; the patient-like fields only where they differ from their defaults."""
        default = asdict(TreeShape())
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()
                if k not in _PATIENT_LIKE_FIELDS or v != default[k]}


#: Fields that only the ``patient_like`` kind sets (left out of ``to_dict`` at their defaults).
_PATIENT_LIKE_FIELDS = ("ima", "sma_above", "coeliac_above", "accessory_below", "accessory_descent_deg",
                        "accessory_length", "accessory_radius", "accessory_turn_deg", "iliac_loop_mm", "neck_kink_mm",
                        "neck_kink_dir_deg", "internal_direction")


_SHAPE_RANGES = {
    "aorta_top_radius": (9.5, 12.0), "aorta_distal_radius": (7.5, 9.5), "upper_aorta": (60.0, 90.0),
    "neck": (15.0, 30.0), "sac_length": (70.0, 110.0), "sac_radius": (13.0, 18.0), "distal_aorta": (10.0, 25.0),
    "sac_drift": (-5.0, 14.0), "sac_bulge": (0.0, 18.0), "renal_offset": (-3.0, 10.0),
    "renal_length": (42.0, 68.0), "renal_radius": (2.6, 3.4), "renal_descent_deg": (0.0, 30.0),
    "renal_posterior_deg": (5.0, 30.0), "renal_turn_deg": (0.0, 35.0), "iliac_length": (70.0, 100.0),
    "iliac_radius": (4.5, 6.0), "iliac_spread_deg": (22.0, 40.0), "iliac_turn_deg": (0.0, 25.0),
    "iliac_posterior_deg": (0.0, 15.0), "tortuosity_mm": (0.0, 3.0), "tortuosity_waves": (1.0, 2.5),
    "tortuosity_phase": (0.0, 2 * np.pi), "tortuosity_plane_deg": (0.0, 360.0), "internal_at": (0.55, 0.75),
    "internal_length": (30.0, 45.0),
}


def _draw(rng: np.random.Generator, default, low: float, high: float):
    if isinstance(default, tuple):
        return tuple(float(v) for v in rng.uniform(low, high, size=len(default)))
    return float(rng.uniform(low, high))


def random_shape(rng: np.random.Generator, **overrides) -> TreeShape:
    """A plausible rest tree drawn from uniform ranges; ``overrides`` win."""
    default = TreeShape()
    values = {name: _draw(rng, getattr(default, name), *bounds) for name, bounds in _SHAPE_RANGES.items()}
    values.update(overrides)
    return replace(default, **values)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _resample(points: np.ndarray, step: float = STEP_MM) -> np.ndarray:
    """The polyline at even arc-length steps (the last point kept)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    n = max(2, int(round(s[-1] / step)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, points[:, d]) for d in range(points.shape[1])])


def _perpendicular(direction: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to ``direction``."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    return _unit(np.cross(direction, helper))


def _curved(start, direction, towards, turn_deg: float, length: float, *, wiggle_mm: float = 0.0,
            waves: float = 1.0, phase: float = 0.0, plane_deg: float = 0.0, loop_mm: float = 0.0) -> np.ndarray:
    """A tube path: starts along ``direction``, turns uniformly by ``turn_deg`` towards ``towards``.

    A sinuous offset of amplitude ``wiggle_mm`` (zero at the start, ``waves`` periods)
    perpendicular to the chord makes it tortuous; the result is resampled at 1 mm.
    ``loop_mm`` adds a swing along the chord and one across both (a quarter period apart,
    see :func:`_loops`): the path loops in projection without meeting itself in 3D.
    """
    direction = _unit(direction)
    axis = np.cross(direction, _unit(towards))
    axis = _unit(axis) if np.linalg.norm(axis) > 1e-9 else _perpendicular(direction)
    n = max(3, int(np.ceil(length / 0.25)))
    s = np.linspace(0.0, length, n)
    turns = Rotation.from_rotvec(np.outer(np.deg2rad(turn_deg) * s / length, axis))
    steps = turns.apply(direction) * (length / (n - 1))
    points = np.asarray(start, dtype=float) + np.concatenate([[np.zeros(3)], np.cumsum(steps[:-1], axis=0)])
    if wiggle_mm:
        chord = _unit(points[-1] - points[0])
        side = Rotation.from_rotvec(np.deg2rad(plane_deg) * chord).apply(_perpendicular(chord))
        envelope = np.sqrt(np.clip(np.sin(np.pi * s / length), 0.0, None))
        points = points + np.outer(wiggle_mm * envelope * np.sin(2 * np.pi * waves * s / length + phase), side)
        if loop_mm:
            points = points + _loops(chord, side, envelope, 2 * np.pi * waves * s / length + phase, loop_mm)
    return _resample(points)


def _loops(chord: np.ndarray, side: np.ndarray, envelope: np.ndarray, angle: np.ndarray, loop_mm: float) -> np.ndarray:
    """Offsets that turn a sinuous path into loops: ``loop_mm cos(angle)`` along the chord
    (a prolate trochoid with the sideways sine: the path doubles back and crosses itself
    where ``loop_mm * 2 pi waves / length > 1``) and as much across chord and side, so that
    the two passes of a crossing lie ``2 LOOP_DEPTH loop_mm sin(delta)`` apart in depth."""
    across = np.cross(chord, side)
    swing = loop_mm * envelope * np.cos(angle)
    return np.outer(swing, chord) + np.outer(LOOP_DEPTH * swing, across)


def _aorta(shape: TreeShape) -> Tube:
    total = shape.upper_aorta + shape.neck + shape.sac_length + shape.distal_aorta
    s = np.linspace(0.0, total, int(np.ceil(total / 0.25)) + 1)
    sac_start = shape.upper_aorta + shape.neck
    in_sac = np.clip((s - sac_start) / shape.sac_length, 0.0, 1.0)
    below_neck = np.clip((s - shape.upper_aorta) / (total - shape.upper_aorta), 0.0, 1.0)
    x = shape.sac_drift * (3 * below_neck ** 2 - 2 * below_neck ** 3)
    y = -shape.sac_bulge * np.sin(np.pi * in_sac)
    if shape.neck_kink_mm:
        x, y = _kinked_neck(shape, s, x, y)
    points = _resample(np.column_stack([x, y, -s]))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    base = np.interp(arc, [0.0, arc[-1]], [shape.aorta_top_radius, shape.aorta_distal_radius])
    bump = np.sin(np.pi * np.clip((arc - sac_start) / shape.sac_length, 0.0, 1.0)) ** 2
    radius = base + bump * max(shape.sac_radius - base.mean(), 0.0)
    return Tube("aorta", points, radius)


def _kinked_neck(shape: TreeShape, s: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tortuous neck: an S-shaped offset (one full sine period under a sine window) of
    ``neck_kink_mm`` in direction ``neck_kink_dir_deg`` from a third of the upper aorta down
    to the sac, so the renal ostia sit on a bend."""
    start, end = shape.upper_aorta / 3.0, shape.upper_aorta + shape.neck
    t = np.clip((s - start) / (end - start), 0.0, 1.0)
    offset = shape.neck_kink_mm * np.sin(np.pi * t) * np.sin(2 * np.pi * t)
    a = np.deg2rad(shape.neck_kink_dir_deg)
    return x + offset * np.cos(a), y + offset * np.sin(a)


def _index_at(tube: Tube, depth_mm: float) -> int:
    """The point of ``tube`` nearest ``depth_mm`` of arc length from its start."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(tube.points, axis=0), axis=1))])
    return int(np.clip(np.searchsorted(arc, depth_mm), 0, len(arc) - 1))


def _branch(tree: dict, name: str, label: str, parent: str, index: int, direction, towards, turn_deg, length,
            radius, in_ct: bool = True, **wiggle) -> None:
    start = tree[parent].points[index]
    points = _curved(start, direction, towards, turn_deg, length, **wiggle)
    tree[name] = Tube(label, points, np.full(len(points), float(radius)), parent, index, in_ct)


def _renal_direction(side: str, shape: TreeShape, descent_deg: float) -> np.ndarray:
    d, p = np.deg2rad(descent_deg), np.deg2rad(shape.renal_posterior_deg)
    return _unit([_LEFT[side] * np.cos(d) * np.cos(p), np.cos(d) * np.sin(p), -np.sin(d)])


def build_tree(shape: TreeShape) -> VesselTree:
    """The rest vessel tree of ``shape`` (the pre-operative anatomy before any deformation)."""
    tubes = {"aorta": _aorta(shape)}
    aorta = tubes["aorta"]
    down = np.array([0.0, 0.0, -1.0])
    for k, side in enumerate(SIDES):
        ostium = _index_at(aorta, shape.upper_aorta - (shape.renal_offset if side == "left" else 0.0))
        _branch(tubes, f"renal_{side}", f"renal_{side}", "aorta", ostium, _renal_direction(side, shape,
                shape.renal_descent_deg), down, shape.renal_turn_deg, shape.renal_length[k], shape.renal_radius)
    accessory_sides = SIDES if shape.accessory_renal == "both" else (shape.accessory_renal,)
    for side in (s for s in accessory_sides if s in SIDES):
        name = "accessory_renal" if len(accessory_sides) == 1 else f"accessory_renal_{side}"
        _branch(tubes, name, "other", "aorta", _index_at(aorta, shape.upper_aorta + shape.accessory_below),
                _renal_direction(side, shape, shape.renal_descent_deg + shape.accessory_descent_deg), down,
                shape.accessory_turn_deg, shape.accessory_length, shape.accessory_radius)
    if shape.sma:
        _branch(tubes, "sma", "other", "aorta", _index_at(aorta, shape.upper_aorta - shape.sma_above),
                [0.0, -0.9, -0.35], down, 45.0, 50.0, 3.5)
    if shape.coeliac:
        _branch(tubes, "coeliac", "other", "aorta", _index_at(aorta, shape.upper_aorta - shape.coeliac_above),
                [0.0, -1.0, 0.1], [0.0, -1.0, 0.5], 10.0, 26.0, 3.5)
    if shape.ima:
        _branch(tubes, "ima", "other", "aorta", _index_at(aorta, shape.upper_aorta + shape.neck + 0.7 *
                                                          shape.sac_length), [0.35, -0.85, -0.4], down, 30.0, 45.0, 2.0)
    if shape.lumbars != "none":
        for k, depth in enumerate((0.3, 0.65)):
            index = _index_at(aorta, shape.upper_aorta + shape.neck + depth * shape.sac_length)
            for side in SIDES:
                _branch(tubes, f"lumbar_{side}_{k}", "other", "aorta", index, [0.55 * _LEFT[side], 0.8, -0.1],
                        [_LEFT[side], 0.0, 0.0], 10.0, aorta.radius[index] + 16.0, 1.8, shape.lumbars == "ct")
    last = len(aorta.points) - 1
    for k, side in enumerate(SIDES):
        spread, back = np.deg2rad(shape.iliac_spread_deg[k]), np.deg2rad(shape.iliac_posterior_deg)
        direction = [_LEFT[side] * np.sin(spread), np.sin(back), -np.cos(spread)]
        _branch(tubes, f"iliac_{side}", f"iliac_{side}", "aorta", last, direction, down, shape.iliac_turn_deg[k],
                shape.iliac_length[k], shape.iliac_radius, wiggle_mm=shape.tortuosity_mm[k],
                waves=shape.tortuosity_waves[k], phase=shape.tortuosity_phase[k],
                plane_deg=shape.tortuosity_plane_deg[k], loop_mm=shape.iliac_loop_mm[k])
        if shape.internal_iliacs != "none":
            iliac = tubes[f"iliac_{side}"]
            _branch(tubes, f"internal_iliac_{side}", "other", f"iliac_{side}",
                    _index_at(iliac, shape.internal_at[k] * shape.iliac_length[k]),
                    np.multiply(shape.internal_direction, [_LEFT[side], 1.0, 1.0]), down, 15.0,
                    shape.internal_length[k], 3.0,
                    shape.internal_iliacs == "ct")
    return VesselTree(tubes)

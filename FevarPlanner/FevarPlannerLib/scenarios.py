"""An independent phantom family for the benchmark (issue 10): data the method was not tuned on.

Nothing here shares geometry or deformation code with :mod:`phantom`; only the file
writers (:mod:`io`) and the projection (:mod:`projection`) are common. A scenario is

* a **vessel tree** of its own generator (:func:`build_tree`): an aorta with a fusiform sac
  (narrow or wide), both renals, common iliacs that can fork distally into an internal
  (label ``other``) and an external iliac (which keeps the common iliac's label),
  optional SMA, coeliac trunk, an accessory renal artery and lumbar stubs (``other``), and
  tortuous iliacs. Every tube is a dense polyline (1 mm steps) with a lumen radius;
* its **deformations** (:func:`deform_tree`), each a length-preserving move of part of the
  tree: a 3D bend of the lower aorta, a 3D bend at the aortic bifurcation and one along
  each iliac, in any direction (not only the frontal plane), wire straightening of the
  iliacs towards the chord between their ends (directions blended towards the chord,
  segment lengths kept), and a shift and tilt of the renal ostia;
* its **frames**: one or more C-arm views with their true and given projections, masks
  drawn from the intra-operative tree by a capsule rasteriser of its own: clipped frames
  (the upper aorta leaves the image at the top border), tubes the frame shows but the CT
  tree lacks (distal iliac forks, lumbar stubs), misaligned given poses, angulated views
  and two-view cases.

Case folders follow docs/DESIGN.md section 4: ``aorta_mask.nrrd`` (the pre-operative lumen on a
1 mm CT grid), ``fluoro_mask.png`` + ``geometry.json`` (the main view, given ``P``),
``views/<name>/fluoro_mask.png`` + ``geometry.json`` for a second view, ``gt.json`` (the
intra- and pre-operative centrelines of the CT's tubes, node ``n`` of one is node ``n`` of
the other, and every view's true projection) and ``scenario.json`` (everything drawn).

Coordinates are LPS mm (+x left, +y posterior, +z superior). Every random number comes
from the scenario's seed: the same seed writes the same files.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from . import files, io
from .centerline import Centerline
from .conventions import BRANCH_LABELS
from .projection import CArmGeometry, in_plane_transform, project, projection_matrix_from_carm, source_position, \
    write_geometry_json

__all__ = [
    "KINDS",
    "MAIN_VESSELS",
    "Tube",
    "VesselTree",
    "TreeShape",
    "random_shape",
    "build_tree",
    "Deformation",
    "bend_subtree",
    "straighten_tube",
    "deform_tree",
    "View",
    "Scenario",
    "plan_scenarios",
    "RenderedView",
    "ScenarioCase",
    "generate",
    "paint_capsules",
    "mask_end_points",
    "render_ct",
    "render_dsa",
    "write_scenario",
    "write_scenario_set",
]

#: The five vessels that every tree holds and every benchmark compares.
MAIN_VESSELS = BRANCH_LABELS
#: The scenario kinds, one benchmark set each.
KINDS = ("out_of_plane", "straightening", "clipped", "distal_forks", "wide_sac", "extra_branches", "misaligned",
         "angulated", "two_views", "image_only")
#: Severities of the out-of-plane set, degrees (bend at the bifurcation and along each iliac).
OUT_OF_PLANE_SEVERITIES_DEG = (0.0, 5.0, 10.0, 20.0)
#: Angulated views of the angulated set: (primary, LAO +; secondary, cranial +), degrees.
ANGULATED_VIEWS_DEG = ((30.0, 15.0), (-30.0, -15.0), (30.0, -15.0), (-30.0, 15.0))
#: Angle of the second view from the main (AP) one in the two-view set, degrees.
SECOND_VIEW_DEG = (30.0, 50.0, 70.0, 90.0)
STEP_MM = 1.0
CT_SPACING_MM = 1.0
CT_MARGIN_MM = 15.0
#: Image-only cases: a wider CT grid (a body around the vessels), its HU, and the DSA frame.
IMAGE_CT_MARGIN_MM = 40.0
CT_HU = {"air": -1000.0, "tissue": 45.0, "lumen": 330.0, "cortical": 750.0, "cancellous": 230.0, "disc": 90.0}
#: Vertebral bodies behind the aorta: radius, cortical shell, body height and disc height (mm).
SPINE_MM = {"radius": 17.0, "shell": 3.0, "body": 24.0, "disc": 9.0}
CT_NOISE_HU = 14.0
DSA_ATTENUATION_PER_MM = 0.035
DSA_NOISE = 0.012
_DSA_FULL_SCALE = 65535
DETECTOR_MARGIN_PX = 24
SIDES = ("left", "right")
_LEFT = {"left": 1.0, "right": -1.0}


# --------------------------------------------------------------------------- the tree

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
    accessory_renal: str = "none"            # "none", "left" or "right" (in the CT tree)
    lumbars: str = "none"                    # "none", "ct" or "frame"

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


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
            waves: float = 1.0, phase: float = 0.0, plane_deg: float = 0.0) -> np.ndarray:
    """A tube path: starts along ``direction``, turns uniformly by ``turn_deg`` towards ``towards``.

    A sinuous offset of amplitude ``wiggle_mm`` (zero at the start, ``waves`` periods)
    perpendicular to the chord makes it tortuous; the result is resampled at 1 mm.
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
    return _resample(points)


def _aorta(shape: TreeShape) -> Tube:
    total = shape.upper_aorta + shape.neck + shape.sac_length + shape.distal_aorta
    s = np.linspace(0.0, total, int(np.ceil(total / 0.25)) + 1)
    sac_start = shape.upper_aorta + shape.neck
    in_sac = np.clip((s - sac_start) / shape.sac_length, 0.0, 1.0)
    below_neck = np.clip((s - shape.upper_aorta) / (total - shape.upper_aorta), 0.0, 1.0)
    x = shape.sac_drift * (3 * below_neck ** 2 - 2 * below_neck ** 3)
    y = -shape.sac_bulge * np.sin(np.pi * in_sac)
    points = _resample(np.column_stack([x, y, -s]))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    base = np.interp(arc, [0.0, arc[-1]], [shape.aorta_top_radius, shape.aorta_distal_radius])
    bump = np.sin(np.pi * np.clip((arc - sac_start) / shape.sac_length, 0.0, 1.0)) ** 2
    radius = base + bump * max(shape.sac_radius - base.mean(), 0.0)
    return Tube("aorta", points, radius)


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
    if shape.accessory_renal in SIDES:
        side = shape.accessory_renal
        _branch(tubes, "accessory_renal", "other", "aorta", _index_at(aorta, shape.upper_aorta + 16.0),
                _renal_direction(side, shape, shape.renal_descent_deg + 10.0), down, 10.0, 40.0, 2.0)
    if shape.sma:
        _branch(tubes, "sma", "other", "aorta", _index_at(aorta, shape.upper_aorta - 18.0), [0.0, -0.9, -0.35],
                down, 45.0, 50.0, 3.5)
    if shape.coeliac:
        _branch(tubes, "coeliac", "other", "aorta", _index_at(aorta, shape.upper_aorta - 34.0), [0.0, -1.0, 0.1],
                [0.0, -1.0, 0.5], 10.0, 26.0, 3.5)
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
                plane_deg=shape.tortuosity_plane_deg[k])
        if shape.internal_iliacs != "none":
            iliac = tubes[f"iliac_{side}"]
            _branch(tubes, f"internal_iliac_{side}", "other", f"iliac_{side}",
                    _index_at(iliac, shape.internal_at[k] * shape.iliac_length[k]),
                    [-0.45 * _LEFT[side], 0.55, -0.7], down, 15.0, shape.internal_length[k], 3.0,
                    shape.internal_iliacs == "ct")
    return VesselTree(tubes)


# --------------------------------------------------------------------------- deformations

def _axis_about(tangent: np.ndarray, direction_deg: float) -> np.ndarray:
    """A unit axis perpendicular to ``tangent``, at ``direction_deg`` about it.

    0 degrees is the axis closest to patient x (left): about it, a vertical vessel bends
    antero-posteriorly, out of an AP frame's plane; 90 degrees bends it in the frontal plane.
    """
    tangent = _unit(tangent)
    first = np.array([1.0, 0.0, 0.0]) - tangent[0] * tangent
    first = _unit(first) if np.linalg.norm(first) > 1e-6 else _perpendicular(tangent)
    second = np.cross(tangent, first)
    a = np.deg2rad(direction_deg)
    return np.cos(a) * first + np.sin(a) * second


def bend_subtree(tree: VesselTree, name: str, index: int, axis, angle_deg: float, spread_mm: float = 0.0) -> None:
    """Bend ``tree`` in place: everything beyond point ``index`` of tube ``name`` turns by ``angle_deg``.

    The turn about the unit ``axis`` is shared out over the points from ``index`` over
    ``spread_mm`` of arc (a smooth bend, not a kink); each share is a rotation about its own
    point, so every segment keeps its length.
    """
    tube = tree.tubes[name]
    count = max(1, min(int(round(spread_mm / STEP_MM)), len(tube.points) - 1 - index))
    pivots = range(index, index + count)
    share = Rotation.from_rotvec(np.deg2rad(angle_deg) / count * _unit(axis))
    for pivot_index in pivots:
        pivot = tree.tubes[name].points[pivot_index].copy()
        for part, first in tree.distal_part(name, pivot_index):
            moved = tree.tubes[part].points[first:]
            tree.tubes[part].points[first:] = share.apply(moved - pivot) + pivot


def _translate_distal(tree: VesselTree, name: str, index: int, shift: np.ndarray) -> None:
    for part, first in tree.distal_part(name, index):
        tree.tubes[part].points[first:] += shift


def straighten_tube(tree: VesselTree, name: str, fraction: float) -> None:
    """Pull tube ``name`` towards the chord between its ends, as a stiff wire does (in place).

    Each segment's direction is blended towards the chord's by ``fraction`` (0: unchanged,
    1: straight) and the tube is rebuilt from its first point with the same segment
    lengths, so the vessel keeps its length and its end moves on. Tubes that leave it ride
    along (translated with their take-off point).
    """
    tube = tree.tubes[name]
    steps = np.diff(tube.points, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    chord = _unit(tube.points[-1] - tube.points[0])
    blended = _unit((1.0 - fraction) * steps / lengths[:, None] + fraction * chord)
    rebuilt = tube.points[0] + np.concatenate([[np.zeros(3)], np.cumsum(blended * lengths[:, None], axis=0)])
    shifts = rebuilt - tube.points
    for child, other in tree.tubes.items():
        if other.parent == name:
            _translate_distal(tree, child, 0, shifts[other.parent_index])
    tube.points = rebuilt


@dataclass
class Deformation:
    """The intra-operative deformation of a tree (degrees, mm); pairs are (left, right).

    Directions (``*_dir_deg``) are angles about the local vessel axis, see
    :func:`_axis_about` (0 = out of an AP frame's plane, 90 = in it).
    """

    aorta_bend_deg: float = 0.0
    aorta_dir_deg: float = 0.0
    bifurcation_bend_deg: float = 0.0
    bifurcation_dir_deg: float = 0.0
    iliac_bend_deg: tuple = (0.0, 0.0)
    iliac_dir_deg: tuple = (0.0, 0.0)
    straighten: tuple = (0.0, 0.0)
    renal_shift_mm: tuple = (0.0, 0.0)
    renal_tilt_deg: tuple = (0.0, 0.0)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


def _tangent(tube: Tube, index: int) -> np.ndarray:
    a, b = max(index - 3, 0), min(index + 3, len(tube.points) - 1)
    return _unit(tube.points[b] - tube.points[a])


def deform_tree(tree: VesselTree, deformation: Deformation) -> VesselTree:
    """The intra-operative tree: ``tree`` (unchanged) deformed; every tube keeps its length.

    Order: renal ostia shift along the aorta and tilt; the lower aorta bends below the
    neck; the distal aorta bends at the bifurcation (the iliacs swing with it); each iliac
    is straightened, then bent halfway along its length.
    """
    out = tree.copy()
    d = deformation
    aorta = out.tubes["aorta"]
    for k, side in enumerate(SIDES):
        renal = out.tubes[f"renal_{side}"]
        ostium = renal.parent_index
        _translate_distal(out, f"renal_{side}", 0, d.renal_shift_mm[k] * _tangent(aorta, ostium))
        tilt_axis = _unit(np.cross(_tangent(renal, 0), [0.0, 0.0, 1.0]))
        bend_subtree(out, f"renal_{side}", 0, tilt_axis, d.renal_tilt_deg[k], spread_mm=6.0)
    neck = max(out.tubes[f"renal_{side}"].parent_index for side in SIDES) + 12
    bend_subtree(out, "aorta", neck, _axis_about(_tangent(aorta, neck), d.aorta_dir_deg), d.aorta_bend_deg,
                 spread_mm=40.0)
    last = len(aorta.points) - 1
    distal = max(last - 12, 0)
    bend_subtree(out, "aorta", distal, _axis_about(_tangent(aorta, distal), d.bifurcation_dir_deg),
                 d.bifurcation_bend_deg, spread_mm=12.0)
    for k, side in enumerate(SIDES):
        name = f"iliac_{side}"
        straighten_tube(out, name, d.straighten[k])
        iliac = out.tubes[name]
        middle = len(iliac.points) // 2
        bend_subtree(out, name, middle, _axis_about(_tangent(iliac, middle), d.iliac_dir_deg[k]),
                     d.iliac_bend_deg[k], spread_mm=15.0)
    return out


# --------------------------------------------------------------------------- scenarios

@dataclass
class View:
    """One C-arm view: angles (degrees), optional top clipping and a misaligned given pose."""

    name: str = "main"
    primary_deg: float = 0.0
    secondary_deg: float = 0.0
    clip_top_mm: float | None = None      # the top border cuts the aorta this far below its top
    misalign_shift_px: tuple = (0.0, 0.0)
    misalign_rotation_deg: float = 0.0


@dataclass
class Scenario:
    """Everything one case is made of (JSON-ready through :meth:`to_dict`)."""

    name: str
    kind: str
    seed: int
    shape: TreeShape
    deformation: Deformation
    views: list = field(default_factory=lambda: [View()])
    sid_mm: float = 1150.0
    sod_mm: float = 760.0
    detector_pixel_mm: float = 0.6
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"version": 1, "family": "scenarios", "name": self.name, "kind": self.kind, "seed": self.seed,
                "shape": self.shape.to_dict(), "deformation": self.deformation.to_dict(),
                "views": [asdict(v) for v in self.views], "sid_mm": self.sid_mm, "sod_mm": self.sod_mm,
                "detector_pixel_mm": self.detector_pixel_mm, **self.info}


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def _base_deformation(rng: np.random.Generator, out_of_plane_deg: tuple = (3.0, 8.0)) -> Deformation:
    """A moderate deformation in any direction: what a stiff wire does on every kind of case."""
    return Deformation(
        aorta_bend_deg=float(rng.uniform(2.0, 6.0)), aorta_dir_deg=float(rng.uniform(0.0, 360.0)),
        bifurcation_bend_deg=float(rng.uniform(*out_of_plane_deg)), bifurcation_dir_deg=float(rng.uniform(0, 360)),
        iliac_bend_deg=tuple(float(v) for v in rng.uniform(*out_of_plane_deg, size=2)),
        iliac_dir_deg=tuple(float(v) for v in rng.uniform(0.0, 360.0, size=2)),
        straighten=tuple(float(v) for v in rng.uniform(0.2, 0.5, size=2)),
        renal_shift_mm=tuple(_signed(rng, 0.5, 3.0) for _ in SIDES),
        renal_tilt_deg=tuple(_signed(rng, 1.0, 8.0) for _ in SIDES))


def _out_of_plane_direction(rng: np.random.Generator) -> float:
    """A bend direction at least half out of an AP frame's plane: within 45 degrees of 0 or 180."""
    return float(rng.choice([0.0, 180.0]) + rng.uniform(-45.0, 45.0))


def _out_of_plane(rng: np.random.Generator, severity: float) -> Deformation:
    """Bends of ``severity`` degrees at the bifurcation and along each iliac, forwards or
    backwards and obliquely (:func:`_out_of_plane_direction`), so that severity means depth.

    The aorta bends only in the frontal plane (90 degrees), so at severity 0 nothing moves in depth.
    """
    return Deformation(aorta_bend_deg=float(rng.uniform(1.0, 4.0)), aorta_dir_deg=90.0,
                       bifurcation_bend_deg=severity, bifurcation_dir_deg=_out_of_plane_direction(rng),
                       iliac_bend_deg=(severity, severity),
                       iliac_dir_deg=(_out_of_plane_direction(rng), _out_of_plane_direction(rng)))


def _kind_plan(kind: str, index: int, rng: np.random.Generator) -> tuple[dict, Deformation, list, dict]:
    """Shape overrides, deformation, views and info of case ``index`` of ``kind``."""
    shape, views, info = {}, [View()], {}
    deformation = _base_deformation(rng)
    if kind == "out_of_plane":
        severity = OUT_OF_PLANE_SEVERITIES_DEG[index % len(OUT_OF_PLANE_SEVERITIES_DEG)]
        deformation, info = _out_of_plane(rng, severity), {"severity_deg": severity}
    elif kind == "straightening":
        shape = {"tortuosity_mm": tuple(float(v) for v in rng.uniform(5.0, 9.0, size=2)),
                 "tortuosity_waves": tuple(float(v) for v in rng.uniform(1.5, 2.5, size=2))}
        deformation = replace(deformation, straighten=tuple(float(v) for v in rng.uniform(0.6, 0.9, size=2)))
    elif kind == "clipped":
        views = [View(clip_top_mm=float(rng.uniform(25.0, 45.0)))]
    elif kind == "distal_forks":
        shape = {"internal_iliacs": "frame"}
    elif kind == "wide_sac":
        shape = {"sac_radius": float(rng.uniform(28.0, 36.0)), "sac_length": float(rng.uniform(95.0, 120.0))}
    elif kind == "extra_branches":
        shape = {"sma": True, "coeliac": True, "accessory_renal": str(rng.choice(SIDES)), "lumbars": "frame",
                 "internal_iliacs": "ct"}
    elif kind == "misaligned":
        views = [View(misalign_shift_px=(_signed(rng, 3.0, 8.0), _signed(rng, 3.0, 8.0)),
                      misalign_rotation_deg=_signed(rng, 2.0, 4.0))]
    elif kind == "angulated":
        primary, secondary = ANGULATED_VIEWS_DEG[index % len(ANGULATED_VIEWS_DEG)]
        views = [View(primary_deg=primary, secondary_deg=secondary)]
    elif kind == "image_only":
        info = {"images": True}
    elif kind == "two_views":
        angle = SECOND_VIEW_DEG[index % len(SECOND_VIEW_DEG)] * (1.0 if index % 2 == 0 else -1.0)
        name = f"{'lao' if angle > 0 else 'rao'}{abs(angle):g}"
        views = [View(), View(name=name, primary_deg=angle)]
        info = {"second_view_deg": abs(angle)}
    else:
        raise ValueError(f"unknown scenario kind {kind!r}; choose one of {', '.join(KINDS)}")
    return shape, deformation, views, info


def plan_scenarios(kind: str, n: int, seed: int = 0) -> list[Scenario]:
    """``n`` scenarios of ``kind``, drawn from ``seed`` (the kind's own stream of it)."""
    if n < 1:
        raise ValueError(f"number of scenarios must be positive, got {n}")
    stream = np.random.SeedSequence([seed, KINDS.index(kind) if kind in KINDS else len(KINDS)])
    scenarios = []
    for index, child in enumerate(stream.spawn(n)):
        rng = np.random.default_rng(child)
        case_seed = int(rng.integers(0, 2**31 - 1))
        overrides, deformation, views, info = _kind_plan(kind, index, rng)
        shape = random_shape(rng, **overrides)
        scenarios.append(Scenario(f"{kind}_{index:02d}", kind, case_seed, shape, deformation, views,
                                  sid_mm=float(rng.uniform(1050.0, 1200.0)), sod_mm=float(rng.uniform(720.0, 800.0)),
                                  info=info))
    return scenarios


# --------------------------------------------------------------------------- rendering

def _capsule_blocks(shape, centres: np.ndarray, radii: np.ndarray, chunk: int = 8):
    """Yield ``(box, headroom)`` over a polyline's tube: for each cell of the box (a tuple of
    slices into an array of ``shape``) the largest ``r**2 - d**2`` over the chunk's segments,
    ``d`` the distance to a segment and ``r`` its radius there (>= 0: inside the tube)."""
    centres = np.asarray(centres, dtype=float)
    radii = np.asarray(radii, dtype=float)
    shape = np.array(shape)
    for start in range(0, len(centres) - 1, chunk):
        b, rb = centres[start + 1:start + chunk + 1], radii[start + 1:start + chunk + 1]
        a, ra = centres[start:start + len(b)], radii[start:start + len(b)]
        reach = max(ra.max(), rb.max()) + 1.0
        low = np.maximum(np.floor(np.minimum(a.min(0), b.min(0)) - reach).astype(int), 0)
        high = np.minimum(np.ceil(np.maximum(a.max(0), b.max(0)) + reach).astype(int) + 1, shape)
        if np.any(high <= low):
            continue
        cells = np.stack(np.meshgrid(*[np.arange(lo, hi) for lo, hi in zip(low, high)], indexing="ij"), axis=-1)
        cells = cells.reshape(-1, len(shape)).astype(float)
        ab = b - a
        length2 = np.maximum(np.einsum("sd,sd->s", ab, ab), 1e-12)
        t = np.clip(np.einsum("csd,sd->cs", cells[:, None, :] - a[None], ab) / length2, 0.0, 1.0)
        distance2 = np.square(cells[:, None, :] - (a[None] + t[..., None] * ab[None])).sum(axis=-1)
        headroom = (np.square(ra[None] + t * (rb - ra)[None]) - distance2).max(axis=1)
        yield tuple(slice(lo, hi) for lo, hi in zip(low, high)), headroom.reshape(high - low)


def paint_capsules(mask: np.ndarray, centres: np.ndarray, radii: np.ndarray, chunk: int = 8) -> None:
    """Set every cell of ``mask`` (2D or 3D) inside the tube along a polyline, in place.

    ``centres`` (n, d) are in index units of ``mask`` (row/column, or k/j/i), ``radii``
    (n,) too; between two points the radius varies linearly (a rounded cone per segment).
    """
    for box, headroom in _capsule_blocks(mask.shape, centres, radii, chunk):
        mask[box] |= headroom >= 0.0


def _projected_radius(P: np.ndarray, points: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Lumen radius in pixels at each point: a radius across the ray, projected (perspective)."""
    rays = _unit(points - source_position(P))
    across = np.array([_perpendicular(r) for r in rays])
    return np.linalg.norm(project(P, points + radius[:, None] * across) - project(P, points), axis=1)


def _draw_frame(tree: VesselTree, P: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    mask = np.zeros(shape, dtype=bool)
    for tube in tree.tubes.values():
        uv = project(P, tube.points)
        paint_capsules(mask, uv[:, ::-1], _projected_radius(P, tube.points, tube.radius))
    return mask


def _draw_lumen(tree: VesselTree, volume: io.Volume) -> np.ndarray:
    lumen = np.zeros(volume.shape, dtype=bool)
    for tube in tree.tubes.values():
        if tube.in_ct:
            paint_capsules(lumen, volume.lps_to_index(tube.points), tube.radius / volume.spacing[0])
    return lumen


def _ct_volume(tree: VesselTree, margin_mm: float = CT_MARGIN_MM) -> io.Volume:
    """An axis-aligned 1 mm grid around the CT's tubes."""
    points = np.concatenate([t.points for t in tree.tubes.values() if t.in_ct])
    reach = max(float(t.radius.max()) for t in tree.tubes.values() if t.in_ct) + margin_mm
    low, high = points.min(axis=0) - reach, points.max(axis=0) + reach
    counts = np.ceil((high - low) / CT_SPACING_MM).astype(int) + 1
    return io.Volume(np.zeros(tuple(counts[::-1]), dtype=np.uint8), (CT_SPACING_MM,) * 3, np.round(low, 3),
                     np.eye(3))


def _fitted_carm(tree: VesselTree, scenario: Scenario, view: View, isocenter: np.ndarray) -> tuple[CArmGeometry,
                                                                                                       np.ndarray]:
    """The view's C-arm with a detector just big enough for the whole frame tree, and its ``P``."""
    pixel = (scenario.detector_pixel_mm, scenario.detector_pixel_mm)
    probe = CArmGeometry(scenario.sid_mm, scenario.sod_mm, pixel, view.primary_deg, view.secondary_deg, 1, 1)
    P = projection_matrix_from_carm(probe, isocenter)
    extent = np.zeros(2)
    for tube in tree.tubes.values():
        uv = project(P, tube.points)
        extent = np.maximum(extent, (np.abs(uv) + _projected_radius(P, tube.points, tube.radius)[:, None]).max(0))
    cols, rows = (32 * np.ceil((2 * (extent + DETECTOR_MARGIN_PX) + 1) / 32)).astype(int)
    carm = CArmGeometry(scenario.sid_mm, scenario.sod_mm, pixel, view.primary_deg, view.secondary_deg, int(rows),
                        int(cols))
    return carm, projection_matrix_from_carm(carm, isocenter)


def _clipped(P: np.ndarray, rows: int, tree: VesselTree, clip_top_mm: float) -> tuple[np.ndarray, int, int]:
    """``P`` and row count of a frame whose top border runs ``clip_top_mm`` below the aorta's top."""
    aorta = tree.tubes["aorta"]
    v = project(P, aorta.points[_index_at(aorta, clip_top_mm)])[1]
    first_row = int(np.floor(v))
    shift = np.eye(3)
    shift[1, 2] = -first_row
    return shift @ P, rows - first_row, first_row


@dataclass
class RenderedView:
    """One rendered view: its mask, true and given projections and C-arm."""

    name: str
    mask: np.ndarray
    P_true: np.ndarray
    P_given: np.ndarray
    carm: CArmGeometry
    clipped_rows: int = 0


@dataclass
class ScenarioCase:
    """A generated scenario: both trees, the CT lumen and every view."""

    scenario: Scenario
    preop: VesselTree
    intraop: VesselTree
    lumen: io.Volume
    views: list

    def ground_truth(self) -> dict:
        pre, intra = self.preop.centerline(), self.intraop.centerline()
        return {
            "version": 1,
            "family": "scenarios",
            "preop_centerline": pre.to_dict(),
            "intraop_centerline": intra.to_dict(),
            "correspondence": "node n of intraop_centerline is node n of preop_centerline",
            "projection_matrix_true": self.views[0].P_true.tolist(),
            "projection_matrix_given": self.views[0].P_given.tolist(),
            "views": {v.name: {"projection_matrix_true": v.P_true.tolist(), "projection_matrix_given":
                               v.P_given.tolist(), "clipped_rows": v.clipped_rows} for v in self.views},
            "frame_only_tubes": [name for name, t in self.intraop.tubes.items() if not t.in_ct],
            "vessel_lengths_mm": {name: float(np.linalg.norm(np.diff(t.points, axis=0), axis=1).sum())
                                  for name, t in self.intraop.tubes.items()},
        }


def _render_view(tree: VesselTree, scenario: Scenario, view: View, isocenter: np.ndarray) -> RenderedView:
    carm, P = _fitted_carm(tree, scenario, view, isocenter)
    rows, clipped_rows = carm.rows, 0
    if view.clip_top_mm is not None:
        P, rows, clipped_rows = _clipped(P, rows, tree, view.clip_top_mm)
        carm = replace(carm, rows=rows)
    mask = _draw_frame(tree, P, (rows, carm.cols))
    centre = ((carm.cols - 1) / 2.0, (rows - 1) / 2.0)
    P_given = in_plane_transform(P, view.misalign_shift_px, view.misalign_rotation_deg, 1.0, centre)
    return RenderedView(view.name, mask, P, P_given, carm, clipped_rows)


def generate(scenario: Scenario) -> ScenarioCase:
    """Build both trees, the CT lumen and every view's mask of ``scenario``."""
    preop = build_tree(scenario.shape)
    intraop = deform_tree(preop, scenario.deformation)
    volume = _ct_volume(preop, IMAGE_CT_MARGIN_MM if scenario.info.get("images") else CT_MARGIN_MM)
    lumen = volume.with_array(_draw_lumen(preop, volume).astype(np.uint8))
    isocenter = volume.center_lps()
    views = [_render_view(intraop, scenario, view, isocenter) for view in scenario.views]
    return ScenarioCase(scenario, preop, intraop, lumen, views)


def _chord_image(tree: VesselTree, P: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Millimetres of contrast-filled lumen along each pixel's ray (each tube once, tubes summed;
    a branch from where it leaves its parent's lumen, so that no lumen counts twice)."""
    path = np.zeros(shape)
    for tube in tree.tubes.values():
        first = 0
        if tube.parent is not None:
            parent = tree.tubes[tube.parent]
            outside = np.linalg.norm(tube.points - parent.points[tube.parent_index], axis=1) > \
                parent.radius[tube.parent_index]
            first = min(int(np.argmax(outside)), len(tube.points) - 2)
        points, radius = tube.points[first:], tube.radius[first:]
        uv = project(P, points)
        radius_px = _projected_radius(P, points, radius)
        mm_per_px = float(np.mean(radius / radius_px))
        chord = np.zeros(shape)
        for box, headroom in _capsule_blocks(shape, uv[:, ::-1], radius_px):
            block = chord[box]
            np.maximum(block, 2.0 * mm_per_px * np.sqrt(np.clip(headroom, 0.0, None)), out=block)
        path += chord
    return path


def render_dsa(tree: VesselTree, P: np.ndarray, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A DSA-like frame (uint16, dark vessels): a smooth uneven background attenuated as
    ``exp(-mu * lumen path)``, slightly blurred, with signal-dependent noise from ``rng``."""
    from scipy import ndimage

    rows, cols = shape
    vv, uu = np.mgrid[0:rows, 0:cols]
    radial2 = ((vv - rows / 2) ** 2 + (uu - cols / 2) ** 2) / (0.5 * max(shape)) ** 2
    slow = ndimage.gaussian_filter(rng.normal(size=shape), sigma=max(shape) / 10.0)
    slow /= max(float(np.abs(slow).max()), 1e-12)
    background = 0.6 * _DSA_FULL_SCALE * (1.0 - 0.1 * radial2 + 0.05 * slow)
    path = ndimage.gaussian_filter(_chord_image(tree, P, shape), 0.8)
    signal = background * np.exp(-DSA_ATTENUATION_PER_MM * path)
    noisy = signal + rng.normal(size=shape) * DSA_NOISE * np.sqrt(signal * background.mean())
    return np.clip(np.rint(noisy), 0, _DSA_FULL_SCALE).astype(np.uint16)


def render_ct(tree: VesselTree, lumen: io.Volume, rng: np.random.Generator) -> io.Volume:
    """A contrast CT (int16 HU) on the lumen's grid: an elliptic body of soft tissue in air,
    vertebral bodies (cortical shell, cancellous core) and discs behind the aorta, the lumen
    (partial volume at its border) and noise."""
    from scipy import ndimage

    k, j, i = np.indices(lumen.shape, sparse=True)
    x = lumen.origin[0] + i * lumen.spacing[0]
    y = lumen.origin[1] + j * lumen.spacing[1]
    z = lumen.origin[2] + k * lumen.spacing[2]
    centre_x, centre_y = (lumen.origin[:2] + (np.array(lumen.shape[::-1][:2]) - 1) * lumen.spacing[:2] / 2.0)
    half = (np.array(lumen.shape[::-1][:2]) - 1) * lumen.spacing[:2] / 2.0 - 3.0
    body = ((x - centre_x) / half[0]) ** 2 + ((y - centre_y) / half[1]) ** 2 <= 1.0
    aorta = tree.tubes["aorta"]
    spine_y = float(aorta.points[:, 1].max() + aorta.radius.max() + SPINE_MM["radius"] + 4.0)
    radial = np.hypot(x - float(np.median(aorta.points[:, 0])), y - spine_y)
    in_disc = np.mod(z, SPINE_MM["body"] + SPINE_MM["disc"]) < SPINE_MM["disc"]
    bone = np.where(radial <= SPINE_MM["radius"] - SPINE_MM["shell"], CT_HU["cancellous"], CT_HU["cortical"])
    hu = np.where(body, CT_HU["tissue"], CT_HU["air"]) + np.zeros(lumen.shape)
    hu = np.where((radial <= SPINE_MM["radius"]) & body, np.where(in_disc, CT_HU["disc"], bone), hu)
    filled = ndimage.gaussian_filter(lumen.array.astype(float), 0.6 / lumen.spacing[0])
    hu += filled * (CT_HU["lumen"] - hu) * body
    hu += rng.normal(scale=CT_NOISE_HU, size=lumen.shape)
    return lumen.with_array(np.clip(np.rint(hu), -1024, 3071).astype(np.int16))


def mask_end_points(mask: np.ndarray) -> np.ndarray:
    """``(row, col)`` of the end points (one 8-neighbour) of the 2D skeleton of ``mask``."""
    from scipy import ndimage
    from skimage.morphology import skeletonize

    thin = skeletonize(np.asarray(mask, dtype=bool))
    neighbours = ndimage.convolve(thin.astype(int), np.ones((3, 3), dtype=int), mode="constant") - thin
    return np.argwhere(thin & (neighbours == 1))


def write_scenario(case: ScenarioCase | Scenario, folder, *, images: bool | None = None) -> Path:
    """Write a scenario as a case folder (docs/DESIGN.md section 4), atomically; returns the folder.

    Mask level: ``aorta_mask.nrrd`` and ``fluoro_mask.png``; with ``images`` (default: the
    scenario's ``info["images"]``, the image-only kind) ``ct.nrrd`` (HU, :func:`render_ct`)
    and ``fluoro.png`` (16-bit DSA-like, :func:`render_dsa`) instead, so that the pipeline
    segments both. Beside them ``geometry.json`` (the first view's given ``P``;
    ``true_projection_matrix`` too), ``views/<name>/`` for any further view, ``gt.json``
    and ``scenario.json``.
    """
    if isinstance(case, Scenario):
        case = generate(case)
    images = bool(case.scenario.info.get("images")) if images is None else images
    rng = np.random.default_rng([case.scenario.seed, 7])
    folder = Path(folder)
    with files.atomic_folder(folder) as tmp:
        if images:
            io.write_volume(tmp / "ct.nrrd", render_ct(case.preop, case.lumen, rng))
        else:
            io.write_volume(tmp / "aorta_mask.nrrd", case.lumen)
        for k, view in enumerate(case.views):
            where = tmp if k == 0 else tmp / "views" / view.name
            where.mkdir(parents=True, exist_ok=True)
            if images:
                io.write_png(where / "fluoro.png", render_dsa(case.intraop, view.P_true, view.mask.shape, rng))
            else:
                io.write_mask_png(where / "fluoro_mask.png", view.mask)
            write_geometry_json(where / "geometry.json", view.P_given, true_projection_matrix=view.P_true.tolist(),
                                view=view.name, primary_angle=view.carm.primary_angle,
                                secondary_angle=view.carm.secondary_angle)
        files.write_text_atomic(tmp / "gt.json", json.dumps(case.ground_truth()))
        files.write_text_atomic(tmp / "scenario.json", json.dumps(case.scenario.to_dict(), indent=1))
    return folder


def write_scenario_set(out_dir, kinds=KINDS, n_per_kind: int = 4, seed: int = 0, progress=None) -> list:
    """Write ``n_per_kind`` cases of each kind under ``out_dir``; returns ``[(kind, folder), ...]``."""
    out_dir = Path(out_dir)
    written = []
    for kind in kinds:
        for scenario in plan_scenarios(kind, n_per_kind, seed):
            if progress is not None:
                progress(scenario.name)
            written.append((kind, write_scenario(scenario, out_dir / scenario.name)))
    return written

"""Deformations of a scenario tree (:func:`deform_tree`), each a length-preserving move of part
of the tree: a 3D bend of the lower aorta, a 3D bend at the aortic bifurcation and one along
each iliac, in any direction (not only the frontal plane), wire straightening of the iliacs
towards the chord between their ends (directions blended towards the chord, segment lengths
kept), and a shift and tilt of the renal ostia.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .tree import SIDES, STEP_MM, Tube, VesselTree, _perpendicular, _unit

__all__ = [
    "bend_subtree",
    "straighten_tube",
    "Deformation",
    "deform_tree",
]


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

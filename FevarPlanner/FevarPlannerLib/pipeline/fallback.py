"""Never worse than SV: a vessel whose deformation changes its length more than the
vessels do, or fits the frames worse than the undeformed pre-operative shape (SV), is
replaced by the best alternative, and by SV's own shape at the last.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..centerline import Centerline
from ..preop import Preoperative
from ..projection import project


#: Largest relative change of a vessel's length that a deformation may make: vessels barely
#: stretch, and the length term (eq. 6) holds a right match to about 1 %.
LENGTH_TOLERANCE = 0.05
#: A vessel's 2D fit may be this much worse than the undeformed (SV) one before the result
#: counts as worse than SV: one pixel, the 2D skeleton's own resolution.
FIT_TOLERANCE_PX = 1.0


@dataclass
class _Vessel:
    label: str
    nodes: np.ndarray          # kept-node indices
    edges: np.ndarray          # kept-node edges inside the vessel
    attachments: np.ndarray    # (k, 2) edges (vessel node, other node)


def _vessels(centerline: Centerline) -> list:
    labels = np.asarray(centerline.labels)
    edges = centerline.edges
    vessels = []
    for label in dict.fromkeys(centerline.labels):
        member = labels == label
        inner = edges[member[edges[:, 0]] & member[edges[:, 1]]]
        cut = edges[member[edges[:, 0]] != member[edges[:, 1]]]
        cut = np.where(member[cut[:, :1]], cut, cut[:, ::-1])
        vessels.append(_Vessel(str(label), np.flatnonzero(member), inner, cut))
    return vessels


def _length(points: np.ndarray, edges: np.ndarray) -> float:
    return float(np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1).sum()) if len(edges) else 0.0


def _fit_px(points: np.ndarray, nodes: np.ndarray, views: list, kept: np.ndarray) -> float:
    """Mean over the views of the mean 2D distance (px) of the shown projected ``nodes`` to the skeleton."""
    return _fits_px(points, [nodes], views, kept)[0]


def _fits_px(points: np.ndarray, node_sets: list, views: list, kept: np.ndarray) -> list:
    """:func:`_fit_px` of each of several node sets, with one skeleton query per view."""
    return _fits_of([(points, nodes) for nodes in node_sets], views, kept)


def _fits_of(sets: list, views: list, kept: np.ndarray) -> list:
    """:func:`_fit_px` of each ``(points, nodes)`` of ``sets``, with one skeleton query per view."""
    fits = [[] for _ in sets]
    for v in views:
        shown = [(points, nodes[v.visible[kept[nodes]]]) for points, nodes in sets]
        uv = [project(v.P, points[nodes]) for points, nodes in shown if len(nodes)]
        if not uv:
            continue
        distances = iter(np.split(v.skeleton_index.distances(np.concatenate(uv)), np.cumsum([len(u) for u in uv])[:-1]))
        for fit, (_, nodes) in zip(fits, shown):
            if len(nodes):
                fit.append(next(distances).mean())
    return [float(np.mean(fit)) if fit else 0.0 for fit in fits]


def _judge(points, vessel: _Vessel, preop_points, sv_fit: float, views, kept,
           fit: float | None = None) -> tuple[str | None, float]:
    """Why ``points`` are implausible for ``vessel`` (None if plausible), and its 2D fit
    (``fit``, when already measured on these ``points``)."""
    fit = _fit_px(points, vessel.nodes, views, kept) if fit is None else fit
    rest = _length(preop_points, vessel.edges)
    change = _length(points, vessel.edges) / rest - 1.0 if rest > 0 else 0.0
    if abs(change) > LENGTH_TOLERANCE:
        return f"length changed by {100 * change:+.1f}% (limit {100 * LENGTH_TOLERANCE:g}%)", fit
    if fit > sv_fit + FIT_TOLERANCE_PX:
        return f"2D fit {fit:.1f} px, worse than the undeformed {sv_fit:.1f} px", fit
    return None, fit


def _attached(option: np.ndarray, base: np.ndarray, vessel: _Vessel) -> np.ndarray:
    """``option``'s positions of ``vessel`` moved rigidly so that it stays joined to ``base``."""
    if not len(vessel.attachments):
        return option[vessel.nodes]
    outer = vessel.attachments[:, 1]
    return option[vessel.nodes] + (base[outer] - option[outer]).mean(axis=0)


SV_NAME = "the undeformed pre-operative shape (SV)"


def _replaced(result: np.ndarray, option: np.ndarray, vessel: _Vessel) -> np.ndarray:
    """``result`` with ``vessel`` taken from ``option``: the aorta as a whole tree, any other
    vessel moved rigidly so that it stays joined to ``result``."""
    if vessel.label == "aorta":
        return option.copy()
    moved = result.copy()
    moved[vessel.nodes] = _attached(option, result, vessel)
    return moved


def _never_worse_than_sv(result: np.ndarray, alternatives, preop: Preoperative, views: list) -> tuple:
    """Check each vessel of ``result`` against the undeformed (SV) start; replace implausible ones.

    A matched vessel (every label but "other") is implausible when its length changed by
    more than :data:`LENGTH_TOLERANCE` or its 2D fit (all views) is worse than SV's by more
    than :data:`FIT_TOLERANCE_PX`. It is replaced by the plausible alternative with the best
    2D fit: the same vessel from another registration (``alternatives()`` returns
    ``[(positions, name), ...]``: other candidate correspondences, each view alone), or SV,
    moved rigidly with its junction; the aorta by a whole alternative or SV. Returns
    (positions, warnings).
    """
    alternatives = functools.cache(alternatives)
    sv = preop.centerline.points
    # "other" vessels (SMA, coeliac, internal iliacs) have no 2D partner: the TPS moves them
    vessels = [v for v in _vessels(preop.centerline) if v.label != "other"]
    vessels.sort(key=lambda v: v.label != "aorta")
    result, warnings = result.copy(), []
    # SV's fits and those of the vessels still to judge on ``result``: one query per view while it stays
    both = _fits_of([(sv, vessel.nodes) for vessel in vessels] + [(result, vessel.nodes) for vessel in vessels],
                    views, preop.kept)
    sv_fits, fits = both[:len(vessels)], both[len(vessels):]
    for k, (vessel, sv_fit) in enumerate(zip(vessels, sv_fits)):
        if fits is None:
            fits = [None] * k + _fits_px(result, [v.nodes for v in vessels[k:]], views, preop.kept)
        reason, _ = _judge(result, vessel, sv, sv_fit, views, preop.kept, fits[k])
        if reason is None:
            continue
        options = list(alternatives()) + [(sv, SV_NAME)]
        best, best_fit, best_name = None, np.inf, None
        for points, name in options:
            moved = _replaced(result, points, vessel)
            why, fit = _judge(moved, vessel, sv, sv_fit, views, preop.kept)
            if why is None and fit < best_fit:
                best, best_fit, best_name = moved, fit, name
        if best is None:            # SV moved with its junction may fit worse than SV in place
            best, best_name = _replaced(result, sv, vessel), SV_NAME
        result, fits = best, None
        warnings.append(f"{vessel.label}: {reason}; replaced by {best_name}")
    return result, warnings

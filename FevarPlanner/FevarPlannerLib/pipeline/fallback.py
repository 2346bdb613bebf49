"""Never worse than SV: a vessel whose deformation changes its length more than the
vessels do, or fits the frames worse than the undeformed pre-operative shape (SV), is
replaced by the best alternative, and by SV's own shape at the last. Each vessel is also
judged in pieces of about 25 mm of arc: a stretched or ill-fitting piece is repaired alone
(the best alternative over that piece, bent to meet the result at its ends), so that one bad
level does not throw away the rest of a good vessel, nor hide under a small overall change.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

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
        projected = {}
        for points, nodes in shown:
            if len(nodes) and id(points) not in projected:
                projected[id(points)] = project(v.P, points)       # eq. 1, once a shape
        uv = [projected[id(points)][nodes] for points, nodes in shown if len(nodes)]
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


#: Arc length (mm) of the pieces a vessel is judged in besides as a whole: about the distance
#: between the aorta's ostia, so that a stretch at one level is seen where it is.
PIECE_MM = 25.0
#: Largest relative length change of one piece: a stretch the whole vessel's 5 % hides (a piece
#: is a fifth of the aorta), above what a right match of a short bent piece changes (up to
#: +16 % measured on a bench-phantom aorta registered to 1.8 mm).
LOCAL_LENGTH_TOLERANCE = 0.20
#: A piece's 2D fit may be this much worse than SV's over the same piece: twice the vessel's
#: margin, since a short piece averages fewer pixels.
LOCAL_FIT_TOLERANCE_PX = 2.0 * FIT_TOLERANCE_PX
#: Pieces (by arc length) that may fail before the vessel is replaced whole rather than repaired.
MOST_OF_A_VESSEL = 0.5


@dataclass
class _Piece:
    nodes: np.ndarray          # kept-node indices of this stretch of arc
    edges: np.ndarray          # the vessel's edges with an end in the piece
    start_mm: float
    end_mm: float


def _arc_from_root(vessel: _Vessel, points: np.ndarray) -> np.ndarray | None:
    """Arc length (mm, on ``points``, along the tree) of each of ``vessel.nodes`` from its root
    (the junction of a branch, an end of the aorta); the parts of a vessel broken in the CT
    skeleton follow one another, each from one of its ends. None for a vessel without edges."""
    if len(vessel.nodes) < 2 or not len(vessel.edges):
        return None
    local = np.searchsorted(vessel.nodes, vessel.edges)
    lengths = np.linalg.norm(points[vessel.edges[:, 0]] - points[vessel.edges[:, 1]], axis=1)
    neighbours = [[] for _ in vessel.nodes]
    for (a, b), length in zip(local.tolist(), lengths.tolist()):
        neighbours[a].append((b, length))
        neighbours[b].append((a, length))
    ends = [i for i, n in enumerate(neighbours) if len(n) <= 1]
    roots = np.searchsorted(vessel.nodes, vessel.attachments[:, 0]).tolist() if vessel.label != "aorta" else []
    arc = [None] * len(vessel.nodes)
    for root in roots[:1] + ends + list(range(len(arc))):
        if arc[root] is None:
            arc[root], stack = max((a for a in arc if a is not None), default=0.0), [root]
            while stack:
                a = stack.pop()
                for b, length in neighbours[a]:
                    if arc[b] is None:
                        arc[b] = arc[a] + length
                        stack.append(b)
    return np.array(arc)


def _pieces(vessel: _Vessel, points: np.ndarray) -> list:
    """``vessel`` cut into stretches of about :data:`PIECE_MM` of arc (on ``points``), root first."""
    arc = _arc_from_root(vessel, points)
    if arc is None or not arc.max() > 0:
        return []
    total = float(arc.max())
    count = max(1, int(round(total / PIECE_MM)))
    index = np.minimum((arc / total * count).astype(int), count - 1)
    pieces = []
    for k in range(count):
        member = np.zeros(len(points), bool)
        member[vessel.nodes[index == k]] = True
        edges = vessel.edges[member[vessel.edges[:, 0]] | member[vessel.edges[:, 1]]]
        pieces.append(_Piece(vessel.nodes[index == k], edges, k * total / count, (k + 1) * total / count))
    return pieces


def _piece_reason(points, piece: _Piece, preop_points, fit: float, sv_fit: float) -> str | None:
    """Why ``points`` are implausible over ``piece`` (None if plausible), from its fit and SV's."""
    rest = _length(preop_points, piece.edges)
    change = _length(points, piece.edges) / rest - 1.0 if rest > 0 else 0.0
    if abs(change) > LOCAL_LENGTH_TOLERANCE:
        return f"length changed by {100 * change:+.1f}%"
    if fit > sv_fit + LOCAL_FIT_TOLERANCE_PX:
        return f"2D fit {fit:.1f} px against the undeformed {sv_fit:.1f} px"
    return None


def _boundary(result_len: int, edges: np.ndarray, run: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """Edges (inside node, outside node) leaving ``run`` towards a node of ``allowed``."""
    inside = np.zeros(result_len, bool)
    inside[run] = True
    ok = np.zeros(result_len, bool)
    ok[allowed] = True
    leaving = edges[inside[edges[:, 0]] != inside[edges[:, 1]]]
    leaving = np.where(inside[leaving[:, :1]], leaving, leaving[:, ::-1])
    return leaving[ok[leaving[:, 1]]]


def _blended(result: np.ndarray, option: np.ndarray, run: np.ndarray, arc: dict, leaving: np.ndarray,
             sv: np.ndarray) -> np.ndarray:
    """``option``'s shape over the nodes ``run`` put in ``result``, bent so that it meets ``result``
    at the run's ends: the offsets at the ends interpolated along the arc (inverse arc
    distance, which is linear between two ends)."""
    offsets = result[leaving[:, 1]] - option[leaving[:, 1]]
    step = np.linalg.norm(sv[leaving[:, 0]] - sv[leaving[:, 1]], axis=1)
    along = np.array([[abs(arc[n] - arc[a]) for a in leaving[:, 0]] for n in run]) + step + 1e-6
    weights = 1.0 / along
    weights /= weights.sum(axis=1, keepdims=True)
    repaired = result.copy()
    repaired[run] = option[run] + weights @ offsets
    return repaired


def _carried(repaired: np.ndarray, result: np.ndarray, centerline: Centerline, vessel: _Vessel,
             fixed: np.ndarray) -> np.ndarray:
    """``repaired`` with every subtree hanging off ``vessel`` (branches of the aorta, say) moved
    rigidly with the node it hangs from, except those holding a node of ``fixed``."""
    outside = np.ones(len(result), bool)
    outside[vessel.nodes] = False
    edges = centerline.edges[outside[centerline.edges[:, 0]] & outside[centerline.edges[:, 1]]]
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(result),) * 2)
    _, component = csgraph.connected_components(graph, directed=False)
    moved = repaired.copy()
    pinned = set(component[fixed].tolist())
    for inner, outer in vessel.attachments:
        shift = repaired[inner] - result[inner]
        if component[outer] not in pinned and np.any(shift):
            members = (component == component[outer]) & outside
            moved[members] = repaired[members] + shift
            pinned.add(component[outer])
    return moved


SV_NAME = "the undeformed pre-operative shape (SV)"


def _runs(indices: list) -> list:
    """Consecutive ``indices`` grouped as [first, last] runs."""
    runs = []
    for i in indices:
        if runs and runs[-1][1] == i - 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return runs


def _best_blend(result, options, vessel, pieces, lo, hi, arc, sv, views, kept, centerline):
    """The plausible option (best 2D fit over the run) blended into pieces ``lo``..``hi``, as
    (positions, name), or None."""
    nodes = np.concatenate([p.nodes for p in pieces[lo:hi + 1]])
    allowed = vessel.nodes if vessel.label == "aorta" else np.concatenate([vessel.nodes, vessel.attachments[:, 1]])
    leaving = _boundary(len(result), centerline.edges, nodes, allowed)
    if not len(leaving):
        return None
    judged = pieces[max(lo - 1, 0):hi + 2]          # the run and its neighbours, whose joining edges move
    sv_fits = _fits_of([(sv, p.nodes) for p in judged], views, kept)
    best, best_fit = None, np.inf
    for points, name in options:
        candidate = _carried(_blended(result, points, nodes, arc, leaving, sv), result, centerline, vessel,
                             leaving[:, 1])
        fits = _fits_of([(candidate, p.nodes) for p in judged], views, kept)
        if all(_piece_reason(candidate, p, sv, f, s) is None for p, f, s in zip(judged, fits, sv_fits)):
            if np.mean(fits) < best_fit:
                best, best_fit = (candidate, name), float(np.mean(fits))
    return best


def _repaired_locally(result, vessel, pieces, bad, options, sv, views, kept, centerline):
    """``result`` with each run of ``bad`` pieces of ``vessel`` replaced by the best plausible option
    over that run only, bent to stay continuous with its ends (a run that no option repairs
    grows by a piece on each side). Returns (positions, notes), or None when the runs grow
    over :data:`MOST_OF_A_VESSEL` of the vessel."""
    arc = dict(zip(vessel.nodes.tolist(), _arc_from_root(vessel, sv)))
    total = pieces[-1].end_mm
    notes = []
    for lo, hi in _runs(bad):
        while True:
            if pieces[hi].end_mm - pieces[lo].start_mm > MOST_OF_A_VESSEL * total:
                return None
            found = _best_blend(result, options, vessel, pieces, lo, hi, arc, sv, views, kept, centerline)
            if found is not None:
                result = found[0]
                notes.append(f"{pieces[lo].start_mm:.0f}-{pieces[hi].end_mm:.0f} mm from its root "
                             f"taken from {found[1]}")
                break
            lo, hi = max(lo - 1, 0), min(hi + 1, len(pieces) - 1)
    return result, notes


def _bad_pieces(result, pieces, sv, fits, sv_fits) -> list:
    """(index, reason) of each piece over which ``result`` (whose pieces fit by ``fits``) is implausible."""
    if len(pieces) < 2:
        return []
    reasons = [_piece_reason(result, p, sv, f, s) for p, f, s in zip(pieces, fits, sv_fits)]
    return [(i, why) for i, why in enumerate(reasons) if why is not None]


def _fits_by_vessel(positions: list, vessels: list, pieces: list, views: list, kept: np.ndarray) -> list:
    """For each of ``positions``, per vessel: (its fit, its pieces' fits), in one skeleton query per view."""
    node_sets = [v.nodes for v in vessels] + [p.nodes for cut in pieces for p in cut]
    fits = iter(_fits_of([(points, nodes) for points in positions for nodes in node_sets], views, kept))
    measured = []
    for _ in positions:
        whole = [next(fits) for _ in vessels]
        measured.append([(fit, [next(fits) for _ in cut]) for fit, cut in zip(whole, pieces)])
    return measured


def _replaced(result: np.ndarray, option: np.ndarray, vessel: _Vessel) -> np.ndarray:
    """``result`` with ``vessel`` taken from ``option``: the aorta as a whole tree, any other
    vessel moved rigidly so that it stays joined to ``result``."""
    if vessel.label == "aorta":
        return option.copy()
    moved = result.copy()
    moved[vessel.nodes] = _attached(option, result, vessel)
    return moved


def _judged_vessels(centerline: Centerline) -> tuple[list, list]:
    """The matched vessels of ``centerline`` (the aorta first) and their pieces on its own points
    (:func:`_pieces`); kept for the last centerline asked about, whose frames follow one another."""
    key = (centerline.points.tobytes(), centerline.edges.tobytes(), tuple(centerline.labels))
    if _JUDGED[0] is not centerline or _JUDGED[1] != key:
        # "other" vessels (SMA, coeliac, internal iliacs) have no 2D partner: the TPS moves them
        vessels = [v for v in _vessels(centerline) if v.label != "other"]
        vessels.sort(key=lambda v: v.label != "aorta")
        _JUDGED[:] = [centerline, key, (vessels, [_pieces(vessel, centerline.points) for vessel in vessels])]
    return _JUDGED[2]


_JUDGED = [None, None, None]


def _never_worse_than_sv(result: np.ndarray, alternatives, preop: Preoperative, views: list) -> tuple:
    """Check each vessel of ``result`` against the undeformed (SV) start; replace implausible ones.

    A matched vessel (every label but "other") is implausible when its length changed by
    more than :data:`LENGTH_TOLERANCE` or its 2D fit (all views) is worse than SV's by more
    than :data:`FIT_TOLERANCE_PX`. It is replaced by the plausible alternative with the best
    2D fit: the same vessel from another registration (``alternatives()`` returns
    ``[(positions, name), ...]``: other candidate correspondences, each view alone), or SV,
    moved rigidly with its junction; the aorta by a whole alternative or SV.

    Each vessel is also cut into pieces (:func:`_pieces`); a piece whose length changed by more
    than :data:`LOCAL_LENGTH_TOLERANCE` or whose fit is worse than SV's there by more than
    :data:`LOCAL_FIT_TOLERANCE_PX` is repaired alone (:func:`_repaired_locally`) when the bad
    pieces cover less than :data:`MOST_OF_A_VESSEL` of it and the repaired vessel passes the
    whole-vessel checks; otherwise a vessel failing those checks is replaced whole as above, and
    one passing them is kept. When no option passes, SV moved with its junction is the last
    resort, unless it fits the frame worse than both the vessel as registered and SV in place
    (plus the margin): a junction moved far in the image would carry SV off its vessel (issue 10,
    a right iliac 9.9 mm from the truth against 4.7 mm as registered), so the vessel is kept.
    Every change and every kept doubt is a warning. Returns (positions, warnings).
    """
    alternatives = functools.cache(alternatives)
    sv = preop.centerline.points
    vessels, pieces = _judged_vessels(preop.centerline)
    result, warnings = result.copy(), []
    # SV's fits and those of the vessels (and pieces) still to judge on ``result``: one query per view while it stays
    sv_fits, fits = _fits_by_vessel([sv, result], vessels, pieces, views, preop.kept)
    for k, (vessel, cut, (sv_fit, sv_piece_fits)) in enumerate(zip(vessels, pieces, sv_fits)):
        if fits is None:
            fits = [None] * k + _fits_by_vessel([result], vessels[k:], pieces[k:], views, preop.kept)[0]
        reason, _ = _judge(result, vessel, sv, sv_fit, views, preop.kept, fits[k][0])
        bad = _bad_pieces(result, cut, sv, fits[k][1], sv_piece_fits)
        if reason is None and not bad:
            continue
        local_reasons = "; ".join(f"{cut[i].start_mm:.0f}-{cut[i].end_mm:.0f} mm from its root: {why}"
                                  for i, why in bad)
        if bad:
            local = _repaired_locally(result, vessel, cut, [i for i, _ in bad],
                                      list(alternatives()) + [(sv, SV_NAME)], sv, views, preop.kept,
                                      preop.centerline)
            if local is not None and _judge(local[0], vessel, sv, sv_fit, views, preop.kept)[0] is None:
                result, fits = local[0], None
                whole = f"{reason}; " if reason else ""
                warnings.append(f"{vessel.label}: {whole}{local_reasons}; repaired there only: "
                                f"{'; '.join(local[1])} (continuous at its ends)")
                continue
            if reason is None:      # plausible as a whole: keep it rather than lose the rest of it
                warnings.append(f"{vessel.label}: {local_reasons}; no alternative repairs it there, kept")
                continue
        options = list(alternatives()) + [(sv, SV_NAME)]
        best, best_fit, best_name = None, np.inf, None
        for points, name in options:
            moved = _replaced(result, points, vessel)
            why, fit = _judge(moved, vessel, sv, sv_fit, views, preop.kept)
            if why is None and fit < best_fit:
                best, best_fit, best_name = moved, fit, name
        if best is None:            # SV moved with its junction may fit worse than SV in place
            moved = _replaced(result, sv, vessel)
            if _fit_px(moved, vessel.nodes, views, preop.kept) > max(fits[k][0], sv_fit + FIT_TOLERANCE_PX):
                warnings.append(f"{vessel.label}: {reason}; kept: {SV_NAME} moved with its junction fits the "
                                f"frame worse still")
                continue
            best, best_name = moved, SV_NAME
        result, fits = best, None
        warnings.append(f"{vessel.label}: {reason}; replaced by {best_name}")
    return result, warnings

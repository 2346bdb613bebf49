"""All the correspondences worth deforming with, and which deformed candidate to keep.

The paper's match (tangent similarity), the anatomical-label match where it differs
(:mod:`.paper`), and the matches against the projected pre-operative tree
(:mod:`.projected`) are deformed one by one; the caller keeps the one of least
:func:`candidate_score` (the energy after the deformation plus the 3D implausibility of
the result).
"""

from __future__ import annotations

import numpy as np

from ..graph import Classification, SkeletonGraph
from .paper import Correspondence, _with_chains, match_branches, match_trunks
from .projected import match_by_projection

__all__ = ["candidate_correspondences", "candidate_score", "UNASSIGNED_PX2"]

#: Weight (px^2) per share of the 3D nodes left unassigned, in :func:`candidate_score`:
#: a candidate that leaves a branch without partner wins over one that pairs it only when
#: the pairing fits worse than this many px (RMS) after the deformation.
UNASSIGNED_PX2 = 25.0


def _pairs_by_label(c3: Classification, c2: Classification) -> list[tuple[int, int]]:
    index2 = {b.label: i for i, b in enumerate(c2.branches) if b.label != "other"}
    return [(i, index2[b.label]) for i, b in enumerate(c3.branches) if b.label in index2]


def candidate_correspondences(g3: SkeletonGraph, c3: Classification, g2: SkeletonGraph,
                              c2: Classification, P: np.ndarray) -> list[Correspondence]:
    """Every consistent correspondence worth deforming with (duplicates removed).

    For each trunk candidate, the tangent-similarity branch match (the paper's) and the
    anatomical-label match where it differs; then the matches against the projected 3D tree
    (:func:`match_by_projection`) that pair some 3D branch with another 2D end (a 2D branch
    the 3D tree lacks taken for a main one, or a 3D branch the frame does not show). The
    paper's match stays first (the pose refinement fits on the first).
    """
    found = {}
    try:
        trunk_candidates = match_trunks(g3, c3, g2, c2, P)
    except ValueError:
        trunk_candidates = []
    for trunk_pairs, junction_pairs in trunk_candidates:
        for source, branch_pairs in (("tangent", match_branches(g3, c3, g2, c2, P, junction_pairs)),
                                     ("labels", _pairs_by_label(c3, c2))):
            if len(branch_pairs) < len(c3.branches):
                continue
            candidate = _with_chains(Correspondence(branch_pairs, trunk_pairs, junction_pairs, source), c2)
            found.setdefault(candidate.key(), candidate)
    for projected in match_by_projection(g3, c3, g2, c2, P):
        found.setdefault(projected.key(), projected)
    if not found:
        if not trunk_candidates:
            match_trunks(g3, c3, g2, c2, P)  # raises, saying what is missing
        raise ValueError("no consistent branch correspondence between the 3D and 2D skeletons")
    return list(found.values())


def candidate_score(energy: float, assigned_fraction: float, preop_points: np.ndarray, deformed_points: np.ndarray,
                    edges: np.ndarray, alpha: float) -> float:
    """Which deformed candidate to keep: the registration energy plus its 3D implausibility.

    ``energy`` is eq. (6) after the deformation (on the assigned nodes). Added: the length
    term of eq. (6) over every kept edge, TPS-filled nodes included (a vessel stretched or
    compressed where no data held it), weighted by ``alpha`` as in eq. (6); and
    :data:`UNASSIGNED_PX2` times the share of 3D nodes the candidate leaves unassigned, so
    that leaving a branch without partner does not win by fitting less.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    rest = np.linalg.norm(preop_points[edges[:, 0]] - preop_points[edges[:, 1]], axis=1)
    now = np.linalg.norm(deformed_points[edges[:, 0]] - deformed_points[edges[:, 1]], axis=1)
    stretch = float(np.mean(((now - rest) / np.maximum(rest, 1e-9)) ** 2)) if len(edges) else 0.0
    return float(energy) + alpha * stretch + UNASSIGNED_PX2 * (1.0 - float(assigned_fraction))

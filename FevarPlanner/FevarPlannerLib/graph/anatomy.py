"""Anatomical roles and labels of the preserved branches and the trunks."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from ..conventions import BRANCH_LABELS
from .skeleton_graph import Classification, SkeletonGraph, _path_length, _walk_back

def _unit(vector, dim: int, name: str) -> np.ndarray:
    vector = np.asarray(vector, dtype=float).reshape(-1)
    flat = vector.ravel(order="K")
    length = np.sqrt(flat.dot(flat)) if vector.shape == (dim,) else 0.0      # np.linalg.norm's own steps
    if vector.shape != (dim,) or not np.all(np.isfinite(vector)) or length == 0:
        raise ValueError(f"{name} must be a finite non-zero {dim}-vector, got {vector}")
    return vector / length


#: Weights of the role scores in :func:`anatomical_roles` (dimensionless: lengths in the
#: graph's unit). Renals: lateral counts twice as much as height; a 3D end anterior of the
#: top end (coeliac, SMA) or posterior of it (internal iliac) is penalised twice its offset.
ROLE_LATERAL_WEIGHT = 2.0
DEPTH_PENALTY = 2.0
#: With branch calibres (``sizes``), the renal role of a side goes to the widest of the ends
#: whose renal score is within this share of the aorta's length (top end to the iliacs) of
#: the best: an accessory renal artery runs beside the main one (its end as lateral and
#: high, or more so) but is narrower, while a lumbar stub or a visceral branch scores lower
#: by more than this.
RENAL_TIE_SHARE = 0.25


def anatomical_roles(end_positions, *, left, superior, anterior=None, sizes=None) -> dict:
    """Which end node plays which of the five roles: label -> row of ``end_positions``.

    With ``p`` an end's offset from the most superior end (the upper aorta's):

    * the iliacs are the pair of other ends with the largest
      ``-(p_a + p_b).superior + |p_a - p_b|.left - 2 max(0, p.posterior)`` summed: low and
      far apart, so that an internal iliac beside its common iliac is not taken for the
      other side; the one further to the patient's left is ``iliac_left``;
    * ``renal_{side}`` is the end on its side of the top end (``s p.left > 0``, ``s = +1``
      for left) with the largest ``2 s p.left + p.superior - 2 max(0, p.anterior)``: lateral
      and high, not an anterior visceral branch.

    ``sizes`` (optional, one per end: the calibre of the end's branch, e.g. its median lumen
    radius) break near-ties of the renal score: of the ends on a side scoring within
    :data:`RENAL_TIE_SHARE` of the aorta's length of the best and reaching at least half as
    far to the side, the widest is the renal (the main renal artery, not an accessory one
    beside it).

    ``anterior`` (3D only) enables the depth terms; in a 2D view depth is not seen. Lateral
    offsets are measured across the cranio-caudal direction (in an angulated view the
    image directions of left and superior are not orthogonal).

    Raises
    ------
    ValueError
        With fewer than five ends.
    """
    points = np.asarray(end_positions, dtype=float)
    if len(points) < len(BRANCH_LABELS):
        raise ValueError(f"need {len(BRANCH_LABELS)} end nodes for the anatomy, got {len(points)}")
    dim = points.shape[1]
    superior = _unit(superior, dim, "superior")
    left = _unit(left, dim, "left")
    left = _unit(left - (left @ superior) * superior, dim, "left")
    top = int(np.argmax(points @ superior))
    offset = points - points[top]
    height, lateral = offset @ superior, offset @ left
    forward = offset @ _unit(anterior, dim, "anterior") if anterior is not None else np.zeros(len(points))
    others = np.array([i for i in range(len(points)) if i != top])
    low = -height[others] - DEPTH_PENALTY * np.maximum(0.0, -forward[others])
    pair_score = low[:, None] + low[None, :] + np.abs(lateral[others][:, None] - lateral[others][None, :])
    np.fill_diagonal(pair_score, -np.inf)
    a, b = np.unravel_index(np.argmax(pair_score), pair_score.shape)
    right_iliac, left_iliac = sorted((int(others[a]), int(others[b])), key=lambda i: lateral[i])
    roles = {"aorta": top, "iliac_left": left_iliac, "iliac_right": right_iliac}
    aorta_length = float(np.linalg.norm(0.5 * (offset[left_iliac] + offset[right_iliac])))
    for side, s in (("left", 1.0), ("right", -1.0)):
        score = ROLE_LATERAL_WEIGHT * s * lateral + height - DEPTH_PENALTY * np.maximum(0.0, forward)
        order = [int(i) for i in np.argsort(-score, kind="stable") if int(i) not in roles.values()]
        on_side = [i for i in order if s * lateral[i] > 0] or order
        roles[f"renal_{side}"] = _widest_of_the_best(on_side, score, s * lateral, sizes,
                                                     RENAL_TIE_SHARE * aorta_length)
    return roles


def _widest_of_the_best(order: list, score: np.ndarray, lateral: np.ndarray, sizes, margin: float) -> int:
    """The first of ``order`` (best score first), or with ``sizes`` the widest of those
    scoring within ``margin`` of it and reaching at least half as far to the side (an
    accessory renal beside it, not a visceral branch near the midline). The first always
    stands, even when no end lies on that side and ``lateral`` is negative."""
    if sizes is None:
        return order[0]
    best = order[0]
    tied = [i for i in order
            if i == best or (score[i] >= score[best] - margin and lateral[i] >= 0.5 * lateral[best])]
    return max(tied, key=lambda i: (float(sizes[i]), -tied.index(i)))


#: Smallest radius (graph units) in the flow resistance of :func:`_flow_adjacency`, so that a
#: node whose lumen radius came out 0 does not make its edges impassable.
MIN_FLOW_RADIUS = 0.5


def _flow_adjacency(graph: SkeletonGraph) -> sp.csr_matrix:
    """Edge weights of the route blood takes: Poiseuille resistance ``length / r^4``, ``r``
    the mean lumen radius of the edge's two nodes; the plain length without radii.

    On a tree every route is the only one; where the skeleton closes a cycle (an internal
    iliac whose tip touches the external iliac in the mask) the wide vessel is the route and
    the narrow one a side branch.
    """
    if graph.radii is None:
        return graph.adjacency
    coo = graph.adjacency.tocoo()
    radius = np.maximum(0.5 * (graph.radii[coo.row] + graph.radii[coo.col]), MIN_FLOW_RADIUS)
    return sp.csr_matrix((coo.data / radius ** 4, (coo.row, coo.col)), shape=coo.shape)


def _main_routes(graph: SkeletonGraph, source: int, targets) -> list:
    """The least-resistance route (:func:`_flow_adjacency`) from ``source`` to each target, source first."""
    dist, pred = csgraph.dijkstra(_flow_adjacency(graph), directed=True, indices=int(source),
                                  return_predecessors=True)
    routes = []
    for target in targets:
        if not np.isfinite(dist[target]):
            raise ValueError(f"labelling: the upper aorta's end {source} and the iliac end {target} "
                             "are not connected in the skeleton graph")
        routes.append(_walk_back(pred, int(target))[::-1])
    return routes


def _parting_index(first: np.ndarray, second: np.ndarray) -> int:
    """Index of the last node two routes from the same source share (where they part)."""
    common = min(len(first), len(second))
    differs = np.flatnonzero(first[:common] != second[:common])
    return int(differs[0] - 1) if len(differs) else common - 1


def aortic_bifurcation(classification: Classification) -> int | None:
    """The aortic bifurcation of a labelled classification: the junction both iliac branches
    leave (:func:`label_anatomy` makes it so), or None before labelling or when they differ."""
    try:
        left, right = classification.branch("iliac_left"), classification.branch("iliac_right")
    except KeyError:
        return None
    return int(left.junction) if left.junction == right.junction else None


def _on_route(trunk, route_nodes: set) -> bool:
    return all(int(node) in route_nodes for node in trunk.nodes)


def _hang_iliacs_from_the_bifurcation(graph: SkeletonGraph, classification: Classification) -> np.ndarray:
    """Make the iliac branches leave the aortic bifurcation; return the aorta's route (top end first).

    The bifurcation is where the routes from the upper aorta's end to the two iliac ends
    part (:func:`_main_routes`), not the lowest junction Algorithm 1 left on the way: a
    common iliac that forks into internal and external iliac (or an internal iliac whose tip
    touches the external one in the mask) keeps a junction of its own, and a trunk from the
    bifurcation to it is common iliac, not aorta. Each iliac branch becomes its whole route
    below the bifurcation; trunks off the aorta's route are dropped (their nodes below the
    bifurcation are iliac, the others side vessels), and so are junctions that no longer
    join a trunk or a preserved branch.
    """
    aorta = classification.branch("aorta")
    iliacs = [classification.branch("iliac_left"), classification.branch("iliac_right")]
    # the repaired graph (gaps bridged, loops broken), whatever positions ``graph`` gives its nodes
    repaired = graph if classification.graph is None else classification.graph
    routes = _main_routes(repaired, aorta.end, [b.end for b in iliacs])
    parting = _parting_index(*routes)
    bifurcation = int(routes[0][parting])
    for branch, route in zip(iliacs, routes):
        nodes = route[parting:]
        if not np.array_equal(nodes, branch.nodes):
            branch.nodes, branch.junction = nodes, bifurcation
            branch.length = _path_length(graph.positions, nodes)
    aorta_route = routes[0][:parting + 1]
    on_route = set(aorta_route.tolist())
    kept_junctions = {int(b.junction) for b in classification.branches}
    trunks = [t for t in classification.trunks
              if _on_route(t, on_route) or kept_junctions & {int(t.nodes[0]), int(t.nodes[-1])} - on_route]
    classification.trunks = trunks
    kept_junctions |= {int(j) for t in trunks for j in (t.nodes[0], t.nodes[-1])}
    classification.junction_nodes = np.array(
        sorted(j for j in np.asarray(classification.junction_nodes).tolist() if j in kept_junctions), dtype=np.int64)
    return aorta_route


def label_anatomy(graph: SkeletonGraph, classification: Classification, *, left, superior,
                  anterior=None) -> Classification:
    """Name the five preserved branches and the trunks; fill ``node_labels`` (in place).

    Parameters
    ----------
    graph : SkeletonGraph
    classification : Classification
        From :func:`classify` with ``tau=5``.
    left, superior : array_like, shape (d,)
        The patient's left and superior directions in the graph's frame: in 3D LPS
        ``(1, 0, 0)`` and ``(0, 0, 1)``; in 2D from ``projection.image_directions(P, at)``
        (a mirrored view flips ``left``).

    anterior : array_like, shape (3,), optional
        The patient's anterior direction (3D only: ``(0, -1, 0)`` in LPS).

    Rule: :func:`anatomical_roles` on the five branch ends (the most superior end is the
    upper aorta; iliacs low and on their side; renals lateral and high). The aortic
    bifurcation is where the routes from the upper aorta's end to the two iliac ends part
    (:func:`_hang_iliacs_from_the_bifurcation`, which also makes each iliac branch its
    whole route from there, so :func:`aortic_bifurcation` reads it off the branches). The
    aorta is its route from its end to the bifurcation (with any trunk that leads to a
    preserved branch off that route); nodes elsewhere are 'other'.

    Returns
    -------
    Classification
        The same object, labelled (its iliac branches, trunks and junctions as above).
    """
    branches = classification.branches
    if len(branches) != len(BRANCH_LABELS):
        raise ValueError(f"labelling needs exactly {len(BRANCH_LABELS)} preserved branches, got {len(branches)}")
    _unit(left, graph.dim, "left")
    _unit(superior, graph.dim, "superior")
    roles = anatomical_roles(graph.positions[[b.end for b in branches]], left=left, superior=superior,
                             anterior=anterior)
    for label, index in roles.items():
        branches[index].label = label
    aorta_route = _hang_iliacs_from_the_bifurcation(graph, classification)
    labels = ["other"] * len(graph)
    for branch in branches:
        for node in branch.nodes[1:]:
            labels[node] = branch.label
    for trunk in classification.trunks:
        trunk.label = "aorta"
        for node in trunk.nodes:
            labels[node] = "aorta"
    for node in aorta_route:
        labels[node] = "aorta"
    for branch in branches:
        labels[branch.junction] = "aorta"
    for node in classification.deleted_nodes:
        labels[node] = "other"
    classification.node_labels = labels
    return classification

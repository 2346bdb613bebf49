"""The 2D skeleton's nodes centred across their vessel's outline in the frame (issue 10).

Eqs. (4)-(5) put every 3D node's target on a 2D skeleton node (``t_j = X M[:, j]``), and the
deformation fits the projection to it: whatever separates the 2D skeleton from the projected
centre line across the vessel stays in the result as in-plane error. Thinning a binary frame
mask leaves its nodes on whole pixels (up to about a pixel off the outline's midline where a
vessel is an even number of pixels wide) and, where the outline widens along the vessel (a
sac), the medial axis bends away from the midline between the two walls by 1-2.5 px.
On the out-of-plane 0 degree case (depth floor 0.01 mm) the targets lay 0.37 mm across from
the projected aorta and the result's in-plane error was 0.27 mm; with the targets moved
across onto the truth it was 0.09 mm.

:func:`centre_in_outline` moves each connection node of the 2D skeleton along its normal to
the midpoint of the vessel's walls on that normal, each wall at sub-pixel precision where the
bilinearly interpolated mask crosses one half. Nodes whose normal does not meet both walls
within :data:`WALL_SEARCH_RADII` radii, and those within :data:`JUNCTION_RADII` radii of a
junction (where it runs into a branch's mouth), keep their place.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..graph import SkeletonGraph, smoothed_positions
from ..projection import pixels_per_mm, project
from .paper import targets_of

__all__ = ["WALL_SEARCH_RADII", "COARSE_SAMPLES", "centre_in_outline", "targets_at", "render_lumen",
           "route_offsets", "offset_targets", "RouteOffsets"]

#: How far along its normal a node looks for each wall: this many times its 2D radius (the
#: distance to the nearest background pixel), plus 2 px.
WALL_SEARCH_RADII = 1.6
#: Samples per side of the coarse search for each wall; the wall is then refined between the
#: last sample inside and the first outside (:data:`FINE_SAMPLES`).
COARSE_SAMPLES = 12
FINE_SAMPLES = 6
#: Laplacian smoothing iterations (graph.smooth_positions) of the positions the tangents are
#: taken from, and of the centred positions (the walls' pixel steps).
TANGENT_SMOOTHING = 40
SHIFT_SMOOTHING = 10
#: Nodes within this many of their 2D radii of a junction keep their place: there a wall is
#: missing over the branch's mouth, and the normal meets the branch's far wall or the mouth's
#: corner (shifts of 3-5 px beside the renal ostia).
JUNCTION_RADII = 1.5


def _bilinear(mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The boolean ``mask`` (as 0 / 1) bilinearly interpolated at (..., 2) points ``(u, v)``; the
    frame's border pixels stand for what lies beyond it."""
    h, w = mask.shape
    u = np.clip(points[..., 0], 0.0, w - 1.001)
    v = np.clip(points[..., 1], 0.0, h - 1.001)
    u0, v0 = u.astype(np.int64), v.astype(np.int64)
    fu, fv = u - u0, v - v0
    flat = mask.ravel().view(np.uint8)
    at = v0 * w + u0
    top = flat[at] + fu * (flat[at + 1].astype(np.int8) - flat[at])
    bottom = flat[at + w] + fu * (flat[at + w + 1].astype(np.int8) - flat[at + w])
    return top + fv * (bottom - top)


def _wall_offsets(mask: np.ndarray, centres: np.ndarray, normals: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Signed distance along ``normals`` from each centre to the first half-crossing of the mask,
    searched up to ``reach``; NaN where there is none (or the centre is not inside)."""
    steps = np.linspace(0.0, 1.0, COARSE_SAMPLES + 1)[None, :] * reach[:, None]            # (n, k)
    values = _bilinear(mask, centres[:, None, :] + steps[..., None] * normals[:, None, :])
    outside = values < 0.5
    found = outside.any(axis=1) & ~outside[:, 0]
    first = np.argmax(outside, axis=1)
    rows = np.arange(len(centres))
    last_in = steps[rows, np.maximum(first - 1, 0)]
    # refine between the last coarse sample inside and the first outside
    fine = last_in[:, None] + np.linspace(0.0, 1.0, FINE_SAMPLES + 1)[None, :] * (steps[rows, first] - last_in)[:, None]
    values = _bilinear(mask, centres[:, None, :] + fine[..., None] * normals[:, None, :])
    k = np.clip(np.argmax(values < 0.5, axis=1), 1, FINE_SAMPLES)
    before, after = values[rows, k - 1], values[rows, k]
    fraction = np.clip((before - 0.5) / np.maximum(before - after, 1e-9), 0.0, 1.0)
    wall = fine[rows, k - 1] + fraction * (fine[rows, k] - fine[rows, k - 1])
    return np.where(found, wall, np.nan)


def _chain_tangents(g: SkeletonGraph, along: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """For degree-2 ``nodes`` of ``g``: ``along`` at the second neighbour minus at the first (not normalised)."""
    slot = g.adjacency.indptr[nodes]
    return along[g.adjacency.indices[slot + 1]] - along[g.adjacency.indices[slot]]


def centre_in_outline(g2: SkeletonGraph, mask: np.ndarray) -> SkeletonGraph:
    """``g2`` with each connection node moved across its vessel to the midpoint of the walls.

    Parameters
    ----------
    g2 : SkeletonGraph
        The frame's 2D skeleton graph (positions ``(u, v)`` in pixels), with its radii.
    mask : numpy.ndarray, shape (rows, cols)
        The vessel mask it was thinned from (non-zero: vessel).

    Returns
    -------
    SkeletonGraph
        Same nodes and edges; nodes of degree 2 whose normal meets both walls within
        :data:`WALL_SEARCH_RADII` radii moved along the normal to the walls' midpoint (the
        tangent from their two neighbours); the others where they were. Unchanged without radii.
    """
    if g2.radii is None or g2.dim != 2:
        return g2
    radii = np.asarray(g2.radii, dtype=float)
    movable = np.flatnonzero(g2.degrees == 2)
    junctions = np.flatnonzero(g2.degrees >= 3)
    if len(junctions):
        near, _ = cKDTree(g2.positions[junctions]).query(g2.positions[movable])
        movable = movable[near > JUNCTION_RADII * radii[movable]]
    if len(movable) == 0:
        return g2
    # the tangent over a few px of the chain: from neighbour to neighbour it turns by whole
    # pixel steps, and a tilted normal meets a sac's walls far from where the midline is
    tangent = _chain_tangents(g2, smoothed_positions(g2, TANGENT_SMOOTHING), movable)
    length = np.linalg.norm(tangent, axis=1)
    keep = length > 0
    movable, tangent = movable[keep], tangent[keep] / length[keep, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    centres = g2.positions[movable]
    reach = WALL_SEARCH_RADII * radii[movable] + 2.0
    mask = np.asarray(mask)
    binary = mask if mask.dtype == bool and mask.flags.c_contiguous else np.ascontiguousarray(mask > 0)
    # both walls in one search: the rows are independent
    both = _wall_offsets(binary, np.concatenate([centres, centres]), np.concatenate([normal, -normal]),
                         np.concatenate([reach, reach]))
    plus, minus = both[:len(centres)], both[len(centres):]
    shift = 0.5 * (plus - minus)
    moved = np.isfinite(shift)
    positions = np.array(g2.positions, dtype=float)
    positions[movable[moved]] += shift[moved, None] * normal[moved]
    return g2.with_positions(smoothed_positions(g2, SHIFT_SMOOTHING, positions=positions))


def targets_at(assignment, positions: np.ndarray):
    """``assignment`` (a :class:`paper.SoftAssignment`) with its targets ``t_j = X M[:, j]`` taken at
    ``positions`` (the 2D nodes' positions, e.g. :func:`centre_in_outline`'s) instead of those it
    was computed on; ``M`` and which nodes are assigned unchanged."""
    return dataclasses.replace(assignment, targets=targets_of(assignment.M, positions, assignment.assigned))


#: Spacing of the spheres :func:`render_lumen` sweeps along each 3D edge: this share of the smaller
#: projected radius at the edge's ends (the union's scallops are then under 1 % of the radius
#: deep), at least :data:`MIN_DISC_SPACING_PX`.
DISC_SPACING_RADII = 0.25
MIN_DISC_SPACING_PX = 1.0


def _lumen_discs(g3: SkeletonGraph, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The projected 3D lumen as a union of discs ``(centres (k, 2) px, radii (k,) px)``: every edge of
    ``g3`` sampled every :data:`DISC_SPACING_RADII` of its projected radius, each sample's sphere
    (its radius interpolated between the edge's nodes) projected to a disc of its radius times
    the magnification at its depth (eq. 1)."""
    edges = g3.edges()
    ends = project(P, g3.positions)
    radii = np.asarray(g3.radii, dtype=float) * pixels_per_mm(P, g3.positions)
    span = np.linalg.norm(ends[edges[:, 0]] - ends[edges[:, 1]], axis=1)
    spacing = np.maximum(DISC_SPACING_RADII * radii[edges].min(axis=1), MIN_DISC_SPACING_PX)
    counts = np.maximum(np.ceil(span / spacing).astype(np.int64), 1)
    edge_of = np.repeat(np.arange(len(edges)), counts)
    step = np.arange(len(edge_of)) - np.repeat(np.cumsum(counts) - counts, counts)
    t = step / counts[edge_of]
    a, b = edges[edge_of, 0], edges[edge_of, 1]
    centres = ends[a] * (1.0 - t)[:, None] + ends[b] * t[:, None]
    return (np.concatenate([centres, ends]),
            np.concatenate([radii[a] * (1.0 - t) + radii[b] * t, radii]))


def render_lumen(g3: SkeletonGraph, P: np.ndarray, shape: tuple) -> np.ndarray:
    """The pre-operative lumen projected through ``P`` onto a frame of ``shape`` (rows, cols), boolean:
    the union of the projected spheres swept along the 3D skeleton (:func:`_lumen_discs`).

    A pixel is inside when its centre lies in a disc; each disc is drawn as its runs along
    the rows it crosses, all runs at once (a +1 / -1 pair per run, summed along each row).
    """
    rows, cols = shape
    centres, radii = _lumen_discs(g3, P)
    first = np.maximum(np.ceil(centres[:, 1] - radii), 0).astype(np.int64)
    last = np.minimum(np.floor(centres[:, 1] + radii), rows - 1).astype(np.int64)
    counts = np.maximum(last - first + 1, 0)
    disc = np.repeat(np.arange(len(radii)), counts)
    row = first[disc] + np.arange(len(disc)) - np.repeat(np.cumsum(counts) - counts, counts)
    half = np.sqrt(np.maximum(radii[disc] ** 2 - (row - centres[disc, 1]) ** 2, 0.0))
    begin = np.clip(np.ceil(centres[disc, 0] - half), 0, cols).astype(np.int64)
    end = np.clip(np.floor(centres[disc, 0] + half) + 1, 0, cols).astype(np.int64)
    run = begin < end
    width = cols + 1
    steps = (np.bincount(row[run] * width + begin[run], minlength=rows * width)
             - np.bincount(row[run] * width + end[run], minlength=rows * width))
    return np.cumsum(steps.reshape(rows, width), axis=1)[:, :cols] > 0


#: A node whose 2D route on its own projected lumen (:func:`route_offsets`) misses its projection by
#: more than this many of its projected radii (plus 1 px) takes no offset: the route did not place
#: it there, and its error says nothing of the frame's. (Leaving such nodes without target was
#: measured too: a patient-like renal then slid onto its accessory, +0.27 mm on that case.)
ROUTE_CAP_RADII = 2.0
#: An offset whose part across the vessel is larger than this many of its projected radii is no
#: bias of the route but a target on another vessel (an internal iliac beside the external one, a
#: leg crossing, an accessory renal): it is not applied (on a patient-like case the iliacs' took
#: 16-25 px and stretched both legs past the length check).
ACROSS_CAP_RADII = 0.5
#: The vessels of the trunk's own course: their offsets are taken across them only (a slide along
#: them is eq. (4)-(5)'s own business and changes with the deformation); a side branch (a renal)
#: takes the whole offset (where thinning's bridge inside the aorta's outline meets it).
MAIN_COURSE = ("aorta", "iliac_left", "iliac_right")


def _across(g3: SkeletonGraph, P: np.ndarray, nodes: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``vectors`` (len(nodes), 2) less their part along the projected tangent of each of ``nodes``
    (degree-2 nodes; the tangent over a few nodes of the smoothed chain, as in :func:`centre_in_outline`)."""
    tangent = _chain_tangents(g3, project(P, smoothed_positions(g3, TANGENT_SMOOTHING)), nodes)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    return vectors - np.sum(vectors * tangent, axis=1)[:, None] * tangent


def route_offsets(g3: SkeletonGraph, P: np.ndarray, assignments, labels, radii2=None) -> "RouteOffsets":
    """What the single-view 2D route gets wrong on the pre-operative lumen's own projection, per 3D node.

    The frame's targets come from a route (thinning, Algorithm 1, the matching, eqs. (4)-(5),
    the centring) that does not return the projected centre line exactly: where a wide aorta
    bends within its own radius (a tortuous neck, a sac's drift) the walls follow the outer
    spheres; beside a junction a branch's mouth pulls the thinned skeleton; inside the
    aorta's outline thinning draws a renal's own bridge. On the patient-like scenario sets
    the aorta's targets lay 2-6 px across from it beside the renal ostia. Run on the
    pre-operative lumen projected through ``P`` (:func:`render_lumen`), whose centre line is
    known, the same route shows the same errors node by node; the frame, the same lumen
    deformed, repeats them, so they are added to its targets (:func:`offset_targets`).

    Parameters
    ----------
    g3 : SkeletonGraph
        The pre-operative 3D graph (LPS mm) with its lumen radii (mm).
    P : numpy.ndarray, shape (3, 4)
    assignments : list of SoftAssignment
        The route's assignments of ``g3`` to the 2D graph of its own rendered lumen, one per
        candidate correspondence, their targets taken as the frame's are (centred, held). The
        one that places the projected nodes best (among those assigning at least 90 % as
        many nodes as the most) is the route's.
    labels : sequence of str
        Each 3D node's anatomical label: the nodes of :data:`MAIN_COURSE` keep only the part of
        their offset across their vessel. Ends and junctions take none (the route's 2D ends
        lie a radius or so short of the 3D ones: moving them along would stretch the vessel).
    radii2 : numpy.ndarray, optional
        The 2D radii (px) of the rendered route's graph nodes: the route's vessel width at
        each target (:class:`RouteOffsets`), which the frame's must match.

    Returns
    -------
    RouteOffsets
    """
    n3 = len(g3.positions)
    offsets, widths = np.zeros((n3, 2)), np.full(n3, np.nan)
    usable = [a for a in assignments if a.assigned.any()]
    if g3.radii is None or not usable:
        return RouteOffsets(offsets, widths)
    at = project(P, g3.positions)
    most = max(int(a.assigned.sum()) for a in usable)
    usable = [a for a in usable if a.assigned.sum() >= 0.9 * most]
    best = min(usable, key=lambda a: float(np.mean(np.linalg.norm(at[a.assigned] - a.targets[a.assigned], axis=1))))
    offsets[best.assigned] = at[best.assigned] - best.targets[best.assigned]
    own = np.asarray(g3.radii, dtype=float) * pixels_per_mm(P, g3.positions)
    missed = np.linalg.norm(offsets, axis=1) > ROUTE_CAP_RADII * own + 1.0
    offsets[missed | (g3.degrees != 2)] = 0.0             # ends and junctions: a move along would stretch
    inner = np.flatnonzero(g3.degrees == 2)
    across = _across(g3, P, inner, offsets[inner])
    main = np.isin(np.asarray(labels)[inner], MAIN_COURSE)
    offsets[inner[main]] = across[main]
    offsets[inner[np.linalg.norm(across, axis=1) > ACROSS_CAP_RADII * own[inner]]] = 0.0
    if radii2 is not None:
        widths[best.assigned] = (best.M.T @ np.asarray(radii2, dtype=float))[best.assigned]
    return RouteOffsets(offsets, widths)


#: The frame's 2D radius at a target must lie within this range of the route's on the rendered
#: lumen for the route's offset to apply (:func:`offset_targets`): a frame that shows its vessels
#: otherwise (the paper's simulation protocol draws them as 3 px lines) has other route errors.
WIDTH_RATIO_RANGE = (0.6, 1.6)


@dataclasses.dataclass(frozen=True)
class RouteOffsets:
    """:func:`route_offsets`' answer, per 3D node.

    Attributes
    ----------
    offsets : numpy.ndarray, shape (n3, 2)
        Projected node minus the route's target, px; zero where not assigned, where the route
        missed the node by more than :data:`ROUTE_CAP_RADII` of its projected radius (+ 1 px)
        or across it by more than :data:`ACROSS_CAP_RADII`, and at ends and junctions.
    widths : numpy.ndarray, shape (n3,)
        The route's 2D radius (px) at each node's target; NaN where unknown.
    """

    offsets: np.ndarray
    widths: np.ndarray


def offset_targets(assignment, route: RouteOffsets, frame_radii: np.ndarray | None = None):
    """``assignment`` (a :class:`paper.SoftAssignment`) with the ``route``'s offsets (from the 2D route's
    targets to the centre line) added to its targets where the frame shows the vessel as wide
    as the route did: its 2D radius at the target (from ``frame_radii``, the 2D nodes' radii,
    through ``M``) within :data:`WIDTH_RATIO_RANGE` of :attr:`RouteOffsets.widths`. Without
    ``frame_radii``, everywhere."""
    applies = np.ones(len(route.offsets), dtype=bool)
    if frame_radii is not None:
        frame_widths = np.full(len(route.offsets), np.nan)
        frame_widths[assignment.assigned] = (assignment.M.T @ np.asarray(frame_radii, dtype=float))[assignment.assigned]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = frame_widths / route.widths
        low, high = WIDTH_RATIO_RANGE
        applies = (ratio >= low) & (ratio <= high)
    return dataclasses.replace(assignment, targets=assignment.targets + np.where(applies[:, None], route.offsets, 0.0))

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

from ..graph import SkeletonGraph, smooth_positions
from ..projection import pixels_per_mm, project
from .paper import targets_of

__all__ = ["WALL_SEARCH_RADII", "COARSE_SAMPLES", "centre_in_outline", "targets_at", "render_lumen",
           "skeleton_offsets", "offset_targets", "off_the_route"]

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
    slot = g2.adjacency.indptr[movable]
    # the tangent over a few px of the chain: from neighbour to neighbour it turns by whole
    # pixel steps, and a tilted normal meets a sac's walls far from where the midline is
    along = smooth_positions(g2, TANGENT_SMOOTHING).positions
    tangent = along[g2.adjacency.indices[slot + 1]] - along[g2.adjacency.indices[slot]]
    length = np.linalg.norm(tangent, axis=1)
    keep = length > 0
    movable, tangent = movable[keep], tangent[keep] / length[keep, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    centres = g2.positions[movable]
    reach = WALL_SEARCH_RADII * radii[movable] + 2.0
    binary = np.ascontiguousarray(np.asarray(mask) > 0)
    plus = _wall_offsets(binary, centres, normal, reach)
    minus = _wall_offsets(binary, centres, -normal, reach)
    shift = 0.5 * (plus - minus)
    moved = np.isfinite(shift)
    positions = np.array(g2.positions, dtype=float)
    positions[movable[moved]] += shift[moved, None] * normal[moved]
    return smooth_positions(g2.with_positions(positions), SHIFT_SMOOTHING)


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
#: A node's offset (:func:`skeleton_offsets`) is taken only from a centred 2D skeleton point within
#: this share of the node's projected radius (plus 1 px); farther, it is another vessel's.
OFFSET_REACH_RADII = 0.5
#: Samples per px along the centred 2D skeleton's edges for the nearest-point search.
CURVE_SAMPLES_PER_PX = 4.0


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


def _sampled_curve(curve: SkeletonGraph) -> np.ndarray:
    """Points along every edge of a 2D graph, :data:`CURVE_SAMPLES_PER_PX` per px."""
    edges = curve.edges()
    a, b = curve.positions[edges[:, 0]], curve.positions[edges[:, 1]]
    counts = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) * CURVE_SAMPLES_PER_PX).astype(np.int64), 1)
    edge_of = np.repeat(np.arange(len(edges)), counts)
    t = (np.arange(len(edge_of)) - np.repeat(np.cumsum(counts) - counts, counts)) / counts[edge_of]
    return np.concatenate([a[edge_of] * (1.0 - t)[:, None] + b[edge_of] * t[:, None], curve.positions])


def skeleton_offsets(g3: SkeletonGraph, P: np.ndarray, rendered: SkeletonGraph) -> np.ndarray:
    """How far each 3D node's projection lies across from where the 2D route puts its vessel, (n3, 2) px.

    ``rendered`` is the centred 2D skeleton graph (:func:`centre_in_outline`) of the
    pre-operative lumen's own projection (:func:`render_lumen`), built as the frame's is.
    Where a wide vessel bends within its own radius (a tortuous neck, a sac's drift), or a
    side branch's mouth pulls the thinned skeleton beside a junction, the 2D skeleton is
    not the projected centre line (on the patient-like sets the targets lay 2-6 px across
    from the true aorta beside the renal ostia); the frame, showing the same lumen
    deformed, does the same. The offset is from the nearest point of ``rendered`` to the
    projected node, across the node's projected tangent only (a slide along the vessel is
    eq. (4)-(5)'s business); zero where that point lies more than
    :data:`OFFSET_REACH_RADII` of the node's projected radius + 1 px away, and without radii.
    """
    offsets = np.zeros((len(g3.positions), 2))
    if g3.radii is None or len(rendered.positions) == 0:
        return offsets
    at = project(P, g3.positions)
    own = g3.radii * pixels_per_mm(P, g3.positions)
    nodes = np.flatnonzero(g3.degrees == 2)
    curve = _sampled_curve(rendered)
    distance, index = cKDTree(curve).query(at[nodes], distance_upper_bound=OFFSET_REACH_RADII * own[nodes].max() + 1.0)
    close = np.isfinite(distance)
    close[close] &= distance[close] <= OFFSET_REACH_RADII * own[nodes[close]] + 1.0
    nodes, nearest = nodes[close], curve[index[close]]
    along = project(P, smooth_positions(g3, TANGENT_SMOOTHING).positions)
    slot = g3.adjacency.indptr
    tangent = along[g3.adjacency.indices[slot[nodes] + 1]] - along[g3.adjacency.indices[slot[nodes]]]
    length = np.linalg.norm(tangent, axis=1)
    keep = length > 0
    nodes, nearest, tangent = nodes[keep], nearest[keep], tangent[keep] / length[keep, None]
    offset = at[nodes] - nearest
    offsets[nodes] = offset - np.sum(offset * tangent, axis=1)[:, None] * tangent
    return offsets


#: A node whose projection lies farther than this many of its projected radii (plus 1 px) from the
#: 2D route's skeleton of the pre-operative lumen (:func:`off_the_route`) gets no target.
OFF_ROUTE_RADII = 1.0


def off_the_route(g3: SkeletonGraph, P: np.ndarray, rendered: SkeletonGraph) -> np.ndarray:
    """Which 3D nodes the 2D route cannot place, (n3,) bool: on the pre-operative lumen's own
    projection (``rendered``, as in :func:`skeleton_offsets`) their vessel's 2D skeleton runs
    more than :data:`OFF_ROUTE_RADII` of their projected radius (+ 1 px) from their projection.

    There the frame's skeleton, the same lumen deformed, does not follow the vessel either: a
    renal's hidden part inside the aorta's outline, where thinning draws its own bridge from the
    aorta's centre line (on a patient-like case the right renal's ostium took targets 12 px
    down the aorta), or the 2D skeleton of a sac crossing from lumbar to lumbar. None without radii.
    """
    if g3.radii is None or len(rendered.positions) == 0:
        return np.zeros(len(g3.positions), dtype=bool)
    at = project(P, g3.positions)
    limit = OFF_ROUTE_RADII * g3.radii * pixels_per_mm(P, g3.positions) + 1.0
    distance, _ = cKDTree(_sampled_curve(rendered)).query(at, distance_upper_bound=float(limit.max()))
    return distance > limit


def offset_targets(assignment, offsets: np.ndarray, untrusted: np.ndarray | None = None):
    """``assignment`` (a :class:`paper.SoftAssignment`) with ``offsets`` (n3, 2) px added to its targets
    (:func:`skeleton_offsets`: from the 2D route's skeleton to the centre line); the nodes
    ``untrusted`` (:func:`off_the_route`) left without target."""
    targets = assignment.targets + offsets
    if untrusted is None or not np.any(untrusted & assignment.assigned):
        return dataclasses.replace(assignment, targets=targets)
    assigned = assignment.assigned & ~untrusted
    targets[~assigned] = np.nan
    return dataclasses.replace(assignment, targets=targets, assigned=assigned)

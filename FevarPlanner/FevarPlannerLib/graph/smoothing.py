"""Positions of the skeleton nodes: Laplacian smoothing and centring in the lumen's cross-sections."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .. import skeleton as _skeleton
from ..io import Volume
from .skeleton_graph import SkeletonGraph, _MIN_WEIGHT

def smooth_positions(graph: SkeletonGraph, iterations: int = 10, weight: float = 0.5) -> SkeletonGraph:
    """Laplacian smoothing of the connection nodes' positions (topology unchanged).

    Thinning leaves a voxel staircase around the true centreline; moving every degree-2
    node ``weight`` of the way to the mean of its neighbours, ``iterations`` times, takes
    most of it out. End and junction nodes stay where they are, so branch lengths shrink
    only by the staircase they lose.

    Returns
    -------
    SkeletonGraph
        Same nodes, edges and grid indices; new positions and edge lengths.
    """
    return graph.with_positions(smoothed_positions(graph, iterations, weight))


def smoothed_positions(graph: SkeletonGraph, iterations: int = 10, weight: float = 0.5,
                       positions: np.ndarray | None = None) -> np.ndarray:
    """The positions :func:`smooth_positions` gives, without the graph around them (its edge
    lengths not computed); ``positions``: start from these instead of the graph's (the
    graph's edges, same shape)."""
    positions = graph.positions if positions is None else positions
    movable = np.flatnonzero(graph.degrees == 2)
    first_slot = graph.adjacency.indptr[movable]
    first, second = graph.adjacency.indices[first_slot], graph.adjacency.indices[first_slot + 1]
    n, dim = positions.shape
    # component-major and flat: every step is a 1D gather or scatter (4x faster than on rows)
    flat = np.array(positions, dtype=float).T.ravel()
    component = np.arange(dim)[:, None] * n
    first, second, movable = ((component + nodes).ravel() for nodes in (first, second, movable))
    for _ in range(iterations):
        mean_of_neighbours = 0.5 * flat[first] + 0.5 * flat[second]
        here = flat[movable]
        flat[movable] = here + weight * (mean_of_neighbours - here)
    return np.ascontiguousarray(flat.reshape(dim, n).T)


def _lumen_distance_map(lumen: Volume) -> tuple[np.ndarray, np.ndarray]:
    """Inside distance to the wall (mm) on the lumen's bounding box, and the box's first index."""
    array = _skeleton.as_binary(lumen.array, "lumen mask")
    if not array.any():
        raise ValueError("lumen mask is empty: nothing to centre the skeleton in")
    box = _skeleton.bounding_box(array, pad=1)
    spacing_kji = lumen.spacing[::-1]
    return ndimage.distance_transform_edt(array[box], sampling=spacing_kji), np.array([b.start for b in box])


def _cross_section_offset(position, tangent, radius, inside_lps, slab_mm, margin_mm) -> np.ndarray | None:
    """Mean in-plane offset of the lumen voxels in a thin slab across the vessel at ``position``."""
    offset = inside_lps - position
    along = offset @ tangent
    across = offset - along[:, None] * tangent
    section = (np.abs(along) <= slab_mm) & (np.linalg.norm(across, axis=1) <= radius + margin_mm)
    if section.sum() < 4:
        return None
    return across[section].mean(axis=0)


def centre_in_lumen(graph: SkeletonGraph, lumen: Volume, *, slab_mm: float = 0.75,
                    margin_mm: float = 1.5) -> SkeletonGraph:
    """Move the connection nodes of a 3D skeleton to the centroid of the lumen's cross-section.

    Thinning puts the skeleton on voxel centres, up to half a voxel from the true axis, and
    :func:`smooth_positions` only averages that staircase along the vessel. Here every
    degree-2 node moves, within the plane normal to its tangent, to the mean of the lumen
    voxels in a slab ``2 slab_mm`` thick across the vessel and within the local radius (the
    inside distance to the wall) plus ``margin_mm``: for a round lumen that is its axis, to
    a small fraction of a voxel, because it averages the whole wall. The margin keeps
    neighbouring vessels out of the section except right at an ostium. End and junction
    nodes stay where they are; a node whose correction would exceed one voxel diagonal
    (a section that is not one vessel) is left alone. On the 1 mm phantom CT this takes the
    mean distance to the true centreline from 0.39 to 0.16 mm (after smoothing).

    Parameters
    ----------
    graph : SkeletonGraph
        A 3D skeleton graph, positions in LPS mm (after :func:`smooth_positions`, so that
        the tangents are not staircase directions).
    lumen : Volume
        The binary lumen mask the skeleton was thinned from.
    slab_mm, margin_mm : float
        Half thickness of the cross-section and how far beyond the local radius it reaches.

    Returns
    -------
    SkeletonGraph
        Same nodes and edges; new positions and edge lengths.
    """
    if graph.dim != 3:
        raise ValueError(f"centre_in_lumen needs a 3D skeleton graph, got dim={graph.dim}")
    distance, box_start = _lumen_distance_map(lumen)
    inside = distance > 0
    spacing_kji = lumen.spacing[::-1]
    max_shift = float(np.linalg.norm(lumen.spacing))
    positions = np.array(graph.positions, dtype=float)
    grid = np.round(lumen.lps_to_index(graph.positions)).astype(int) - box_start
    adjacency = graph.adjacency
    for node in np.flatnonzero(graph.degrees == 2):
        voxel = grid[node]
        if np.any(voxel < 0) or np.any(voxel >= distance.shape) or not inside[tuple(voxel)]:
            continue
        radius = float(distance[tuple(voxel)])
        reach = np.ceil((radius + margin_mm) / spacing_kji).astype(int) + 1
        low, high = np.maximum(voxel - reach, 0), np.minimum(voxel + reach + 1, distance.shape)
        window = tuple(slice(a, b) for a, b in zip(low, high))
        inside_lps = lumen.index_to_lps(np.argwhere(inside[window]) + low + box_start)
        first, second = graph.positions[adjacency.indices[adjacency.indptr[node]:adjacency.indptr[node + 1]]]
        tangent = (first - second) / max(float(np.linalg.norm(first - second)), _MIN_WEIGHT)
        shift = _cross_section_offset(graph.positions[node], tangent, radius, inside_lps, slab_mm, margin_mm)
        if shift is not None and np.linalg.norm(shift) <= max_shift:
            positions[node] += shift
    return graph.with_positions(positions)

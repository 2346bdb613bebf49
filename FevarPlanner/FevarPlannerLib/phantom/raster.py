"""CT grids and signed distance fields of tapered tubes; the lumen mask."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .. import io
from .anatomy import Anatomy

_CHUNK = 8                  # segments per block in the distance computations


@dataclass(frozen=True)
class Grid:
    """An axis-aligned CT grid: ``shape`` (k, j, i), ``spacing`` (i, j, k) mm, ``origin`` LPS."""

    shape: tuple
    spacing: tuple
    origin: tuple

    def volume(self, array: np.ndarray | None = None, dtype=np.int16) -> io.Volume:
        """A :class:`io.Volume` on this grid holding ``array`` (zeros of ``dtype`` if None)."""
        if array is None:
            array = np.zeros(self.shape, dtype=dtype)
        return io.Volume(array, self.spacing, self.origin, np.eye(3))

    def center_lps(self) -> np.ndarray:
        """LPS of the grid centre (the C-arm isocentre of the phantoms)."""
        ijk = (np.array(self.shape[::-1]) - 1) / 2.0
        return np.asarray(self.origin) + ijk * np.asarray(self.spacing)


def _spine(anatomy: Anatomy) -> tuple[float, float, float]:
    """Vertebral body (x, y centre, radius): on the midline, just behind the aortic wall."""
    aorta = anatomy.vessels["aorta"]
    back = float(np.max(aorta.points[:, 1] + aorta.outer_offset[:, 1] + aorta.outer_radius))
    radius = 20.0
    return 0.0, back + 3.0 + radius, radius


def ct_grid(anatomy: Anatomy, spacing_mm: float = 1.0, margin_mm: float = 25.0) -> Grid:
    """The CT grid: the anatomy's wall bounding box plus ``margin_mm``, and the spine behind."""
    if spacing_mm <= 0:
        raise ValueError(f"CT spacing must be positive, got {spacing_mm}")
    low, high = anatomy.wall_bounds()
    low, high = low - margin_mm, high + margin_mm
    _, spine_y, spine_r = _spine(anatomy)
    high[1] = max(high[1], spine_y + spine_r + 10.0)
    counts = np.ceil((high - low) / spacing_mm).astype(int) + 1
    return Grid(tuple(int(c) for c in counts[::-1]), (float(spacing_mm),) * 3, tuple(round(float(v), 3) for v in low))


def _as_volume(grid) -> io.Volume:
    return grid.volume(dtype=np.uint8) if isinstance(grid, Grid) else grid


def _segment_nearest(coords: np.ndarray, a: np.ndarray, b: np.ndarray, ra: np.ndarray,
                     rb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance and radius of the segment minimising (distance - interpolated radius).

    ``coords`` (N, d); ``a``, ``b`` (G, d) segment ends; ``ra``, ``rb`` (G,) radii at the ends.
    Everything is expanded into (N, G) dot products so no (N, G, d) array is formed.
    """
    origin = a[0]
    coords, a, b = coords - origin, a - origin, b - origin
    ab = b - a
    length2 = np.maximum(np.einsum("gd,gd->g", ab, ab), 1e-12)
    along = coords @ ab.T - np.einsum("gd,gd->g", a, ab)          # (X - A) . AB
    t = np.clip(along / length2, 0.0, 1.0)
    rel2 = np.einsum("nd,nd->n", coords, coords)[:, None] - 2.0 * coords @ a.T + np.einsum("gd,gd->g", a, a)
    dist = np.sqrt(np.maximum(rel2 - 2.0 * t * along + t * t * length2, 0.0))
    radius = ra + t * (rb - ra)
    best = np.argmin(dist - radius, axis=1)[:, None]
    return np.take_along_axis(dist, best, 1)[:, 0], np.take_along_axis(radius, best, 1)[:, 0]


def _chunks(n_segments: int):
    for start in range(0, n_segments, _CHUNK):
        yield slice(start, min(start + _CHUNK, n_segments))


def _chunk_boxes(volume: io.Volume, centres: np.ndarray, reach: np.ndarray):
    """Index boxes ``(lo, hi)`` (k, j, i) covering each run of segments dilated by ``reach``."""
    shape = np.array(volume.shape)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    for sl in _chunks(len(centres) - 1):
        pts = centres[sl.start:sl.stop + 1]
        r = reach[sl.start:sl.stop + 1].max()
        low, high = pts.min(0) - r, pts.max(0) + r
        kji = volume.lps_to_index(low + corners * (high - low))
        lo = np.clip(np.floor(kji.min(0)).astype(int), 0, shape)
        hi = np.clip(np.ceil(kji.max(0)).astype(int) + 1, 0, shape)
        if np.all(hi > lo):
            yield lo, hi


def _window_half_width(centres: np.ndarray, radii: np.ndarray, reach: float) -> int:
    """Segments either side of the nearest vertex that can hold the minimum of (distance - radius).

    Where the radius changes by ``dr/ds`` along the axis, that minimum lies up to
    ``reach * dr/ds`` away from the nearest point.
    """
    lengths = np.maximum(np.linalg.norm(np.diff(centres, axis=0), axis=1), 1e-9)
    slope = float(np.max(np.abs(np.diff(radii)) / lengths)) if len(lengths) else 0.0
    return int(np.ceil(reach * slope / max(float(lengths.min()), 1e-3))) + 2


def _tube_field(volume: io.Volume, centres_radii, pad_mm: float) -> np.ndarray:
    """Signed distance (mm, negative inside) to a union of tapered tubes, exact within ``pad_mm``.

    ``centres_radii`` yields (points (k, 3), radii (k,)); elsewhere the value is ``pad_mm``.
    Each candidate voxel is tested against the few segments around its nearest centreline
    vertex (k-d tree), not against the whole vessel.
    """
    out = np.full(volume.shape, pad_mm, dtype=np.float32)
    for centres, radii in centres_radii:
        reach = radii + pad_mm
        boxes = list(_chunk_boxes(volume, centres, reach))
        if not boxes:
            continue
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        candidate = np.zeros(tuple(hi - lo), dtype=bool)
        for blo, bhi in boxes:
            candidate[tuple(slice(a, b) for a, b in zip(blo - lo, bhi - lo))] = True
        kji = np.column_stack(np.nonzero(candidate)) + lo
        coords = volume.index_to_lps(kji.astype(float))
        _, nearest = cKDTree(centres).query(coords, distance_upper_bound=float(reach.max()) + 1.0)
        near = nearest < len(centres)
        kji, coords, nearest = kji[near], coords[near], nearest[near]
        half = _window_half_width(centres, radii, float(reach.max()))
        segments = np.clip(nearest[:, None] + np.arange(-half, half)[None], 0, len(centres) - 2)
        values = _windowed_field(coords, centres, radii, segments)
        index = tuple(kji.T)
        out[index] = np.minimum(out[index], values)
    return out


def _windowed_field(coords: np.ndarray, centres: np.ndarray, radii: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """min over the listed segments (N, W) of (distance - interpolated radius), per coordinate."""
    a, b = centres[segments], centres[segments + 1]
    ab = b - a
    rel = coords[:, None, :] - a
    t = np.clip(np.einsum("nwd,nwd->nw", rel, ab) / np.maximum(np.einsum("nwd,nwd->nw", ab, ab), 1e-12), 0.0, 1.0)
    dist = np.linalg.norm(rel - t[..., None] * ab, axis=-1)
    radius = radii[segments] + t * (radii[segments + 1] - radii[segments])
    return (dist - radius).min(axis=1)


def _lumen_tubes(anatomy: Anatomy):
    return ((v.points, v.radius) for v in anatomy.vessels.values())


def _wall_tubes(anatomy: Anatomy):
    return ((v.points + v.outer_offset, v.outer_radius) for v in anatomy.vessels.values())


def rasterize_lumen(anatomy: Anatomy, grid: io.Volume | Grid | None = None, *, spacing_mm: float = 1.0,
                    margin_mm: float = 25.0) -> io.Volume:
    """Binary lumen mask of ``anatomy`` (voxel centres inside a vessel), LPS.

    Parameters
    ----------
    anatomy : Anatomy
    grid : io.Volume or Grid, optional
        Target grid (any direction). Default: :func:`ct_grid` with ``spacing_mm`` and
        ``margin_mm``.

    Returns
    -------
    io.Volume
        Boolean array on the grid.
    """
    volume = _as_volume(grid if grid is not None else ct_grid(anatomy, spacing_mm, margin_mm))
    return volume.with_array(_lumen_field(anatomy, volume) <= 0.0)


def _lumen_field(anatomy: Anatomy, volume: io.Volume) -> np.ndarray:
    """Signed distance to the lumen, exact within one voxel (enough for mask and partial volume)."""
    return _tube_field(volume, _lumen_tubes(anatomy), pad_mm=max(1.0, float(min(volume.spacing))))


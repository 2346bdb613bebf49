"""A scenario's frames and images: C-arm views with their true and given projections, masks
drawn from the intra-operative tree by a capsule rasteriser of its own (clipped frames,
tubes the CT tree lacks, misaligned poses, angulated and second views), and for the
image-only cases a CT volume and a DSA frame (:func:`generate`, :func:`render_ct`,
:func:`render_dsa`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import io
from ..projection import CArmGeometry, in_plane_transform, project, projection_matrix_from_carm, source_position

from .tree import VesselTree, build_tree, _index_at, _perpendicular, _unit
from .deformations import deform_tree
from .plans import Scenario, View
from .bench import GRID_MARGIN_MM, fixed_carm

__all__ = [
    "paint_capsules",
    "RenderedView",
    "ScenarioCase",
    "generate",
    "render_dsa",
    "render_ct",
    "mask_end_points",
    "CT_SPACING_MM",
    "CT_MARGIN_MM",
    "IMAGE_CT_MARGIN_MM",
    "CT_HU",
    "SPINE_MM",
    "CT_NOISE_HU",
    "DSA_ATTENUATION_PER_MM",
    "DSA_NOISE",
    "DETECTOR_MARGIN_PX",
]

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


def _ct_volume(tree: VesselTree, margin_mm: float = CT_MARGIN_MM, spacing_mm: float = CT_SPACING_MM) -> io.Volume:
    """An axis-aligned grid (1 mm unless ``spacing_mm``) around the CT's tubes."""
    points = np.concatenate([t.points for t in tree.tubes.values() if t.in_ct])
    reach = max(float(t.radius.max()) for t in tree.tubes.values() if t.in_ct) + margin_mm
    low, high = points.min(axis=0) - reach, points.max(axis=0) + reach
    counts = np.ceil((high - low) / spacing_mm).astype(int) + 1
    return io.Volume(np.zeros(tuple(counts[::-1]), dtype=np.uint8), (spacing_mm,) * 3, np.round(low, 3),
                     np.eye(3))


def _grid_of(tree: VesselTree, scenario: Scenario) -> io.Volume:
    """The pre-operative grid: a bench skeleton's fine voxels (``info["voxel_mm"]``), the
    image-only kind's wide CT, else the 1 mm lumen grid."""
    if "voxel_mm" in scenario.info:
        return _ct_volume(tree, GRID_MARGIN_MM, scenario.info["voxel_mm"])
    return _ct_volume(tree, IMAGE_CT_MARGIN_MM if scenario.info.get("images") else CT_MARGIN_MM)


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
    fixed = "frame_px" in scenario.info       # a bench frame of fixed size (scenarios.bench)
    carm, P = fixed_carm(scenario, view, isocenter) if fixed else _fitted_carm(tree, scenario, view, isocenter)
    rows, clipped_rows = carm.rows, 0
    if view.clip_top_mm is not None:
        P, rows, clipped_rows = _clipped(P, rows, tree, view.clip_top_mm)
        carm = replace(carm, rows=rows)
    mask = _draw_frame(tree, P, (rows, carm.cols))
    shift, turn, centre = view.misalign_shift_px, view.misalign_rotation_deg, ((carm.cols - 1) / 2.0, (rows - 1) / 2.0)
    along = scenario.info.get("misalign_along_aorta")
    if along is not None and view is scenario.views[0]:
        shift, turn, centre = _along_aorta_pose_error(tree, P, along)
    P_given = in_plane_transform(P, shift, turn, 1.0, centre)
    return RenderedView(view.name, mask, P, P_given, carm, clipped_rows)


def _along_aorta_pose_error(tree: VesselTree, P: np.ndarray, error: dict) -> tuple:
    """(shift px, turn degrees, centre) of a given pose off along the upper aorta (plans, kind
    ``misaligned_along``): the turn about the projected upper aorta's centre, the shift
    ``along_px`` along its projected course (top to bottom) and ``across_px`` across it (that
    course turned by +90 degrees). The upper aorta: the aorta above the higher renal ostium."""
    aorta = tree.tubes["aorta"]
    ostium = min(tree.tubes[f"renal_{side}"].parent_index for side in ("left", "right"))
    uv = project(P, aorta.points[:ostium])
    centred = uv - uv.mean(axis=0)
    course = np.linalg.eigh(centred.T @ centred)[1][:, -1]
    if (uv[-1] - uv[0]) @ course < 0:
        course = -course
    shift = error["along_px"] * course + error["across_px"] * np.array([-course[1], course[0]])
    return (float(shift[0]), float(shift[1])), float(error["rotation_deg"]), tuple(float(c) for c in uv.mean(axis=0))


def generate(scenario: Scenario) -> ScenarioCase:
    """Build both trees, the CT lumen and every view's mask of ``scenario``."""
    preop = build_tree(scenario.shape)
    intraop = deform_tree(preop, scenario.deformation)
    volume = _grid_of(preop, scenario)
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

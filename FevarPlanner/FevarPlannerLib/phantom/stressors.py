"""Stressors for the phantom CT: what makes a real aorta unusual for a segmenter.

The plain phantom CT (:mod:`.ct`) is a clean contrast lumen in soft tissue with a spine a few
millimetres behind it. Real pre- and post-operative scans add what the classical route has to
survive, each an option here (:data:`STRESSORS`):

``stent``
    A stent graft from below the lowest renal down into both common iliacs: zig-zag metal
    rings (:data:`METAL_HU`) on the lumen wall every :data:`STENT_RING_PITCH_MM` and four
    marker balls at its top. Walled by metal, the aorta looks like bone to a naive test.
``dissection``
    A flap (thin, :data:`FLAP_HU`) splitting the aorta from its top to just above the
    bifurcation, off centre (a compressed true lumen), the false lumen less opacified
    (``false_lumen_fraction`` of the true lumen's enhancement). The label keeps both channels.
``calcium``
    Calcified plaques (:data:`CALCIUM_HU`) on the outer side of the wall, arcs of 25-70 degrees.
``spine_contact``
    A vertebral body (cortex and cancellous bone) touching the aortic wall from behind.
``venous_contrast``
    An enhancing IVC beside the aorta, the left renal vein crossing just in front of it, and
    bowel loops with positive oral contrast near its anterior wall.
``fading``
    Late-arterial or slow-flow timing: the lumen's enhancement falls linearly along the aorta
    from ``fade_top_hu`` at its top to ``fade_bottom_hu`` at the bifurcation; each branch keeps
    its parent's level at its ostium (the iliacs the bifurcation's). A dissection's false lumen,
    drawn first, fades with it.
``thorax``
    The field of view continues 110 mm above the abdominal aorta (the descending thoracic
    aorta, added to the label) with the heart's enhancing chambers touching it from the front,
    and the lungs.
``arch``
    A chest-abdomen-pelvis field of view as FEVAR planning CTAs have: the descending thoracic
    aorta (:data:`DESCENDING_MM`), the arch turning forwards and to the right and the ascending
    aorta coming down in front to the aortic root (all added to the label: in the upper chest
    each axial slice crosses the aorta twice), the heart's chambers around the root and the left
    atrium in front of the descending aorta, the pulmonary trunk and arteries (one passing under
    the arch, between the ascending and descending aorta) as bright as the aorta, and the
    lungs. With ``fading`` and ``fade_start`` the lumen is bright in the chest and fades only
    below the diaphragm; with ``dissection`` the flap runs the whole length. Not with ``thorax``.

:func:`stressed_phantom_ct` draws a phantom case with any of them and returns the CT and the
lumen label on its grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from .. import io
from .anatomy import Anatomy, Vessel, _unit
from .ct import _CANCELLOUS_HU, _CORTICAL_HU, _ct_from_lumen_field
from .params import PhantomParams
from .raster import Grid, _lumen_field, _tube_field, ct_grid, rasterize_lumen

STRESSORS = ("stent", "dissection", "calcium", "spine_contact", "venous_contrast", "thorax", "fading", "arch")

METAL_HU, CALCIUM_HU, FLAP_HU, LUNG_HU, MYOCARDIUM_HU = 3000.0, 1200.0, 60.0, -850.0, 110.0
STENT_RING_PITCH_MM, STENT_AMPLITUDE_MM, STENT_PEAKS = 15.0, 4.0, 6
THORAX_EXTENSION_MM = 110.0
#: ``arch``: height (mm) of the descending thoracic aorta above the abdominal one, the arch's
#: radius of curvature (mm: the ascending aorta lies twice that in front of the descending one),
#: its shift to the right (mm) and the ascending aorta's height (mm) from the root to the arch.
DESCENDING_MM, ARCH_RADIUS_MM, ARCH_RIGHTWARD_MM, ASCENDING_MM = 140.0, 32.0, 20.0, 55.0
#: Voxels this far (mm) outside a lumen get a local frame (nearest centreline point, angle, arc length).
_FRAME_REACH_MM = 4.0
#: Soft tissue HU: enhancement is measured above it.
_SOFT_HU = 40.0


@dataclass
class StressorOptions:
    """Which stressors to draw and their strengths.

    Attributes
    ----------
    names : tuple of str
        A subset of :data:`STRESSORS`.
    false_lumen_fraction : float
        Enhancement of a dissection's false lumen above soft tissue, relative to the true lumen's.
    flap_offset : float
        Flap position from the aortic centre, as a fraction of the radius (true lumen on the
        negative side, the smaller one when positive).
    venous_fraction : float
        Enhancement of the IVC and renal veins relative to the arterial lumen.
    oral_contrast_hu : float
        HU of the bowel contents.
    fade_top_hu, fade_bottom_hu : float
        Lumen HU at the top of the aorta and at its bifurcation with ``fading``.
    fade_start : float
        Fraction of the aorta's length (from its top) over which the lumen keeps ``fade_top_hu``
        before it fades (0: it fades from the top; with ``arch``, e.g. the chest's share).
    """

    names: tuple = ()
    false_lumen_fraction: float = 0.6
    flap_offset: float = 0.25
    venous_fraction: float = 0.85
    oral_contrast_hu: float = 600.0
    fade_top_hu: float = 400.0
    fade_bottom_hu: float = 150.0
    fade_start: float = 0.0

    def __post_init__(self):
        unknown = sorted(set(self.names) - set(STRESSORS))
        if unknown:
            raise ValueError(f"unknown CT stressor(s) {', '.join(unknown)}; use any of {', '.join(STRESSORS)}")
        if {"arch", "thorax"} <= set(self.names):
            raise ValueError("CT stressors arch and thorax both continue the aorta upwards; use one")
        if not 0.0 <= self.fade_start < 1.0:
            raise ValueError(f"fade_start must lie in [0, 1), got {self.fade_start}")
        self.names = tuple(self.names)


class _Painter:
    """The hooks :func:`.ct._ct_from_lumen_field` calls before and after it paints the vessels."""

    def __init__(self, options: StressorOptions, params: PhantomParams, rng: np.random.Generator):
        self.options, self.params, self.rng = options, params, rng

    def before_vessels(self, hu: np.ndarray, volume: io.Volume, anatomy: Anatomy, lumen: np.ndarray) -> None:
        names = self.options.names
        axes = _Axes(volume)
        if "thorax" in names:
            _paint_thorax(hu, axes, anatomy, self.params)
        if "arch" in names:
            _paint_chest(hu, volume, axes, anatomy, self.params)
        if "spine_contact" in names:
            _paint_vertebra_on_the_wall(hu, axes, anatomy)
        if "venous_contrast" in names:
            _paint_veins_and_bowel(hu, volume, axes, anatomy, self.params, self.options)

    def after_vessels(self, hu: np.ndarray, volume: io.Volume, anatomy: Anatomy, lumen: np.ndarray) -> None:
        names = self.options.names
        if not {"stent", "dissection", "calcium", "fading"} & set(names):
            return
        frame = _VesselFrame(volume, anatomy)
        if "dissection" in names:
            _paint_dissection(hu, frame, anatomy, self.params, self.options)
        if "fading" in names:
            _fade_enhancement(hu, volume, anatomy, lumen, self.params, self.options)
        if "calcium" in names:
            _paint_calcium(hu, frame, self.rng)
        if "stent" in names:
            _paint_stent(hu, volume, frame, anatomy)


class _Axes:
    """The LPS coordinate of each index along i (x), j (y), k (z) of an axis-aligned volume."""

    def __init__(self, volume: io.Volume):
        self.x = volume.origin[0] + np.arange(volume.shape[2]) * volume.spacing[0]
        self.y = volume.origin[1] + np.arange(volume.shape[1]) * volume.spacing[1]
        self.z = volume.origin[2] + np.arange(volume.shape[0]) * volume.spacing[2]


def _aorta_at(anatomy: Anatomy, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Aortic lumen centre (x, y) and lumen / outer radius at heights ``z`` (clamped to its ends)."""
    aorta = anatomy.vessels["aorta"]
    order = np.argsort(aorta.points[:, 2])
    zs = aorta.points[order, 2]
    centre = np.column_stack([np.interp(z, zs, aorta.points[order, d]) for d in (0, 1)])
    return centre, np.interp(z, zs, aorta.radius[order]), np.interp(z, zs, aorta.outer_radius[order])


# ----------------------------------------------------------------------------------------
# Around the aorta: heart and lungs, a vertebra on the wall, veins and bowel
# ----------------------------------------------------------------------------------------

def _ellipsoid(axes: _Axes, centre, semi) -> np.ndarray:
    dz = ((axes.z - centre[2]) / semi[2]) ** 2
    dy = ((axes.y - centre[1]) / semi[1]) ** 2
    dx = ((axes.x - centre[0]) / semi[0]) ** 2
    return (dz[:, None, None] + dy[None, :, None] + dx[None, None, :]) <= 1.0


def _paint_thorax(hu: np.ndarray, axes: _Axes, anatomy: Anatomy, params: PhantomParams) -> None:
    """Lungs beside the mediastinum and the heart's chambers touching the aorta from the front,
    in the slices above the abdomen (the top ``THORAX_EXTENSION_MM`` of the aorta)."""
    aorta = anatomy.vessels["aorta"]
    z_top = float(aorta.points[:, 2].max())
    chest = axes.z >= z_top - THORAX_EXTENSION_MM + 10.0
    (cx, cy), r, outer = (v[0] for v in _aorta_at(anatomy, np.array([z_top - 50.0])))
    soft = hu > -200.0
    lateral = np.abs(axes.x - cx + 15.0) > 45.0
    lung = chest[:, None, None] & lateral[None, None, :] & soft & (hu < 200.0)
    hu[lung] = LUNG_HU
    semi = np.array([50.0, 40.0, 45.0])
    centre = np.array([cx - 20.0, cy - outer - 2.0 - semi[1], z_top - 55.0])
    hu[_ellipsoid(axes, centre, semi + 6.0)] = MYOCARDIUM_HU
    hu[_ellipsoid(axes, centre, semi)] = params.lumen_hu * 0.95
    atrium = centre + np.array([20.0, semi[1] - 8.0, 0.0])      # left atrium, just in front of the aorta
    hu[_ellipsoid(axes, atrium, np.array([25.0, 12.0, 25.0]))] = params.lumen_hu * 0.95


def _paint_chest(hu: np.ndarray, volume: io.Volume, axes: _Axes, anatomy: Anatomy, params: PhantomParams) -> None:
    """``arch``: lungs above the diaphragm (10 mm above the abdominal aorta's top, 45-95 mm to
    either side of the mediastinum, inside the chest wall), the heart's
    chambers around the aortic root with the left atrium against the descending aorta, and the
    pulmonary trunk rising left of the ascending aorta into a left and a right pulmonary artery
    (the right one under the arch, between the ascending and descending aorta), the superior
    vena cava right of the ascending aorta (brighter than it: the contrast arrives through it)."""
    aorta = anatomy.vessels["aorta"]
    root = aorta.points[0]
    apex = int(np.argmax(aorta.points[:, 2]))                   # the top of the arch
    descending = aorta.points[apex]
    z_diaphragm = float(aorta.points[apex, 2]) - ARCH_RADIUS_MM - DESCENDING_MM + 10.0
    soft = (hu > -50.0) & (hu < 200.0)                         # inside the subcutaneous fat: the chest wall
    chest = axes.z >= z_diaphragm
    lateral = np.abs(np.abs(axes.x - 0.5 * (root[0] + descending[0])) - 70.0) < 25.0
    ribs = axes.y <= axes.y[-1] - 15.0                           # the back's wall stays in the field of view
    hu[chest[:, None, None] & ribs[None, :, None] & lateral[None, None, :] & soft] = LUNG_HU
    chambers = params.lumen_hu * 0.95
    heart = root + np.array([25.0, -30.0, -40.0])
    semi = np.array([50.0, 45.0, 45.0])
    hu[_ellipsoid(axes, heart, semi + 6.0)] = MYOCARDIUM_HU
    hu[_ellipsoid(axes, heart, semi)] = chambers
    (dx, dy), _, outer = (v[0] for v in _aorta_at_height(aorta, apex, np.array([z_diaphragm + 30.0])))
    atrium = np.array([dx - 5.0, dy - outer - 1.0 - 12.0, z_diaphragm + 30.0])   # 1 mm in front of the wall
    hu[_ellipsoid(axes, atrium, np.array([28.0, 12.0, 25.0]))] = chambers
    trunk = np.array([root + [30.0, -20.0, -5.0], root + [30.0, -10.0, 35.0], root + [25.0, 10.0, 50.0]])
    fork = trunk[-1]
    left_pa = np.array([fork, fork + [35.0, 20.0, 0.0], fork + [70.0, 30.0, -10.0]])
    right_pa = np.array([fork, fork + [-45.0, 15.0, -5.0], fork + [-95.0, 20.0, -15.0]])
    for tube, radius in ((trunk, 13.0), (left_pa, 9.0), (right_pa, 9.0)):
        hu[_tube(volume, tube, radius)] = params.lumen_hu * 0.9
    apex_point = aorta.points[apex]
    svc = np.array([root + [-35.0, 0.0, -20.0], root + [-35.0, 5.0, 60.0], apex_point + [-50.0, -10.0, 60.0]])
    hu[_tube(volume, svc, 9.0)] = params.lumen_hu * 1.5                 # the injected contrast arriving


def _aorta_at_height(aorta: Vessel, first: int, z: np.ndarray):
    """:func:`_aorta_at` restricted to the aorta's points from ``first`` on (from the top of the
    arch: the descending aorta has one centre per height)."""
    return _aorta_at(Anatomy({"aorta": replace(aorta, points=aorta.points[first:], radius=aorta.radius[first:],
                                               outer_radius=aorta.outer_radius[first:],
                                               outer_offset=aorta.outer_offset[first:])}), z)


def _paint_vertebra_on_the_wall(hu: np.ndarray, axes: _Axes, anatomy: Anatomy, radius: float = 18.0,
                                cortex: float = 1.5) -> None:
    """A vertebral body (right of and behind the aorta) whose cortex touches the aortic outer
    wall, in every slice; a disc (soft tissue) every 35 mm as in :mod:`.ct`."""
    centre, _, outer = _aorta_at(anatomy, axes.z)
    towards = _unit([-0.2, 1.0, 0.0])[:2]
    in_disc = np.mod(axes.z, 35.0) < 8.0
    for k in range(len(axes.z)):
        body_centre = centre[k] + (outer[k] + radius - 0.5) * towards
        distance = np.hypot(axes.x[None, :] - body_centre[0], axes.y[:, None] - body_centre[1])
        if in_disc[k]:
            hu[k][distance <= radius] = 90.0
            continue
        hu[k][distance <= radius] = _CORTICAL_HU
        hu[k][distance <= radius - cortex] = _CANCELLOUS_HU


def _tube(volume: io.Volume, points: np.ndarray, radius: float) -> np.ndarray:
    """Voxels within ``radius`` of the polyline ``points`` (LPS)."""
    return _tube_field(volume, [(np.asarray(points, float), np.full(len(points), radius))], pad_mm=radius) <= 0.0


def _paint_veins_and_bowel(hu: np.ndarray, volume: io.Volume, axes: _Axes, anatomy: Anatomy, params: PhantomParams,
                           options: StressorOptions) -> None:
    """IVC right of the aorta, left renal vein in front of it, two bowel loops with oral contrast."""
    vein_hu = 40.0 + options.venous_fraction * (params.lumen_hu - 40.0)
    zs = np.linspace(axes.z[0], axes.z[-1], 40)
    centre, r, outer = _aorta_at(anatomy, zs)
    ivc = np.column_stack([centre[:, 0] - outer - 3.0 - 11.0, centre[:, 1] + 2.0, zs])
    hu[_tube(volume, ivc, 11.0)] = vein_hu
    renal = anatomy.vessels["renal_left"].points
    z_vein = float(renal[0, 2]) - 8.0
    (cx, cy), r0, o0 = (v[0] for v in _aorta_at(anatomy, np.array([z_vein])))
    front = cy - o0 - 1.0 - 5.0                          # 1 mm of fat between vein and aortic wall
    left_vein = np.array([[cx + 75.0, cy + 5.0, z_vein - 5.0], [cx + 25.0, front, z_vein],
                          [cx - 10.0, front, z_vein], [ivc[0, 0] + 10.0, cy + 2.0, z_vein]])
    hu[_tube(volume, left_vein, 5.0)] = vein_hu
    for dz, gap in ((-25.0, 1.5), (20.0, 4.0)):
        z = z_vein + dz
        (bx, by), _, bo = (v[0] for v in _aorta_at(anatomy, np.array([z])))
        y = by - bo - gap - 10.0
        loop = np.array([[bx - 60.0, y - 15.0, z], [bx - 20.0, y, z - 5.0], [bx + 20.0, y, z + 5.0],
                         [bx + 60.0, y - 20.0, z]])
        hu[_tube(volume, loop, 10.0)] = options.oral_contrast_hu


# ----------------------------------------------------------------------------------------
# On the vessels: flap, plaques, stent
# ----------------------------------------------------------------------------------------

class _VesselFrame:
    """For voxels within :data:`_FRAME_REACH_MM` of the aorta or iliac lumens: the nearest
    centreline point's vessel, arc length ``s`` (mm, plus the axial offset), radial distance,
    angle about the tangent and the lumen radius there."""

    def __init__(self, volume: io.Volume, anatomy: Anatomy):
        names = [n for n in ("aorta", "iliac_left", "iliac_right") if n in anatomy.vessels]
        vessels = [anatomy.vessels[n] for n in names]
        field = _tube_field(volume, ((v.points, v.radius) for v in vessels), pad_mm=_FRAME_REACH_MM)
        self.index = np.argwhere(field < _FRAME_REACH_MM)
        coords = volume.index_to_lps(self.index.astype(float))
        points = np.vstack([v.points for v in vessels])
        owner = np.concatenate([np.full(len(v.points), i) for i, v in enumerate(vessels)])
        arc = np.concatenate([v.arc_length() for v in vessels])
        tangent = np.vstack([np.gradient(v.points, axis=0) for v in vessels])
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        radius = np.concatenate([v.radius for v in vessels])
        _, nearest = cKDTree(points).query(coords)
        rel = coords - points[nearest]
        t = tangent[nearest]
        along = np.einsum("nd,nd->n", rel, t)
        across = rel - along[:, None] * t
        u = _perpendicular(t, np.array([1.0, 0.0, 0.0]))
        w = np.cross(t, u)
        self.vessel = np.asarray(names)[owner[nearest]]
        self.s = arc[nearest] + along
        self.radial = np.linalg.norm(across, axis=1)
        self.angle = np.arctan2(np.einsum("nd,nd->n", across, w), np.einsum("nd,nd->n", across, u))
        self.lateral = np.einsum("nd,nd->n", across, u)        # towards the patient's left
        self.radius = radius[nearest]
        self.point_index = nearest - np.concatenate([[0], np.cumsum([len(v.points) for v in vessels])])[owner[nearest]]

    def paint(self, hu: np.ndarray, where: np.ndarray, value) -> None:
        hu[tuple(self.index[where].T)] = value


def _perpendicular(t: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Unit vectors perpendicular to each row of ``t``, as close as possible to ``reference``."""
    u = reference[None] - np.einsum("nd,d->n", t, reference)[:, None] * t
    return u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)


def _paint_dissection(hu: np.ndarray, frame: _VesselFrame, anatomy: Anatomy, params: PhantomParams,
                      options: StressorOptions, flap_mm: float = 1.0) -> None:
    """A flap splitting the aorta down to 15 mm above its end; the false lumen less opacified."""
    aorta = anatomy.vessels["aorta"]
    inside = (frame.vessel == "aorta") & (frame.radial <= frame.radius) & (frame.s <= aorta.length - 15.0)
    offset = frame.lateral - options.flap_offset * frame.radius     # the flap runs antero-posteriorly
    false_hu = 40.0 + options.false_lumen_fraction * (params.lumen_hu - 40.0)
    frame.paint(hu, inside & (offset > 0.5 * flap_mm), false_hu)
    frame.paint(hu, inside & (np.abs(offset) <= 0.5 * flap_mm), FLAP_HU)


def enhancement_levels(anatomy: Anatomy, top_hu: float, bottom_hu: float, start: float = 0.0) -> dict:
    """Lumen HU per centreline point of each vessel with a fade: ``top_hu`` over the first
    ``start`` of the aorta's arc length, then linear in arc length down to ``bottom_hu`` at its
    end; a branch at its parent's level at its ostium."""
    aorta = anatomy.vessels["aorta"]
    arc = aorta.arc_length()
    fraction = np.clip((arc / max(float(arc[-1]), 1e-9) - start) / (1.0 - start), 0.0, 1.0)
    levels = {"aorta": top_hu + (bottom_hu - top_hu) * fraction}
    pending = [n for n in anatomy.vessels if n != "aorta"]
    while pending:
        ready = [n for n in pending if anatomy.vessels[n].parent in levels]
        if not ready:
            raise ValueError(f"vessels {', '.join(pending)} do not connect to the aorta")
        for name in ready:
            vessel = anatomy.vessels[name]
            parent_level = levels[vessel.parent][min(vessel.parent_index, len(levels[vessel.parent]) - 1)]
            levels[name] = np.full(len(vessel.points), float(parent_level))
            pending.remove(name)
    return levels


def _fade_enhancement(hu: np.ndarray, volume: io.Volume, anatomy: Anatomy, lumen: np.ndarray, params: PhantomParams,
                      options: StressorOptions) -> None:
    """Bring every voxel in or at a lumen to the level of the nearest centreline point
    (:func:`enhancement_levels`): inside, its enhancement above soft tissue scaled (a false
    lumen or flap keeps its fraction); at the wall, its lumen share shifted by its partial volume."""
    voxel = float(min(volume.spacing))
    weight = np.clip(0.5 - lumen / voxel, 0.0, 1.0)
    index = np.argwhere(weight > 0)
    levels = enhancement_levels(anatomy, options.fade_top_hu, options.fade_bottom_hu, options.fade_start)
    points = np.vstack([anatomy.vessels[n].points for n in levels])
    level = np.concatenate([levels[n] for n in levels])
    _, nearest = cKDTree(points).query(volume.index_to_lps(index.astype(float)))
    gain = (level[nearest] - _SOFT_HU) / (params.lumen_hu - _SOFT_HU)
    where = tuple(index.T)
    w = weight[where]
    shifted = hu[where] + w * (level[nearest] - params.lumen_hu)
    hu[where] = np.where(w >= 1.0, _SOFT_HU + (hu[where] - _SOFT_HU) * gain, shifted)


def _paint_calcium(hu: np.ndarray, frame: _VesselFrame, rng: np.random.Generator, n_plaques: int = 40) -> None:
    """Plaques on the outer side of the wall: arcs 1.5 mm thick, 3-8 mm long, 25-70 degrees wide."""
    aorta = frame.vessel == "aorta"
    if not aorta.any():
        return
    s_max = float(frame.s[aorta].max())
    shell = aorta & (frame.radial > frame.radius) & (frame.radial <= frame.radius + 1.5)
    for _ in range(n_plaques):
        s0, a0 = rng.uniform(0.0, s_max), rng.uniform(-np.pi, np.pi)
        half_angle, half_length = np.deg2rad(rng.uniform(12.5, 35.0)), rng.uniform(1.5, 4.0)
        d_angle = np.angle(np.exp(1j * (frame.angle - a0)))
        frame.paint(hu, shell & (np.abs(d_angle) <= half_angle) & (np.abs(frame.s - s0) <= half_length), CALCIUM_HU)


def _paint_stent(hu: np.ndarray, volume: io.Volume, frame: _VesselFrame, anatomy: Anatomy) -> None:
    """Zig-zag rings on the lumen wall from 10 mm below the lowest renal to 60 mm down each iliac,
    and four marker balls at the graft's top."""
    aorta = anatomy.vessels["aorta"]
    renal_index = max(v.parent_index for v in anatomy.by_label("renal_left") + anatomy.by_label("renal_right"))
    start = float(aorta.arc_length()[renal_index]) + 10.0
    covered = np.where(frame.vessel == "aorta", frame.s >= start, frame.s <= 60.0)
    wire_mm = max(0.5, 0.5 * float(min(volume.spacing)))
    on_wall = covered & (np.abs(frame.radial - (frame.radius - 0.5)) <= wire_mm)
    phase = STENT_PEAKS * frame.angle / (2 * np.pi)
    zigzag = STENT_AMPLITUDE_MM * (2.0 * np.abs(phase - np.floor(phase) - 0.5) - 0.5)
    ring_s = np.mod(frame.s - start + zigzag, STENT_RING_PITCH_MM)
    frame.paint(hu, on_wall & (np.minimum(ring_s, STENT_RING_PITCH_MM - ring_s) <= wire_mm), METAL_HU)
    axes = _Axes(volume)
    index = int(np.argmin(np.abs(aorta.arc_length() - start)))
    centre, radius = aorta.points[index], aorta.radius[index]
    for angle in np.deg2rad([45.0, 135.0, 225.0, 315.0]):
        ball = centre + (radius - 1.0) * np.array([np.cos(angle), np.sin(angle), 0.0])
        hu[_ellipsoid(axes, ball, np.full(3, 1.5))] = METAL_HU


# ----------------------------------------------------------------------------------------
# The case
# ----------------------------------------------------------------------------------------

def stressed_anatomy(anatomy: Anatomy, names) -> Anatomy:
    """``anatomy`` with the aorta continued upwards: :data:`THORAX_EXTENSION_MM` (straight, the
    top radius) when ``thorax`` is among ``names``, the descending aorta, the arch and the
    ascending aorta down to the root (:func:`_arch_centreline`) with ``arch``; else unchanged."""
    if "thorax" not in names and "arch" not in names:
        return anatomy
    aorta = anatomy.vessels["aorta"]
    up = _unit(aorta.points[0] - aorta.points[3])
    if "arch" in names:
        extra, scale = _arch_centreline(aorta.points[0], up)
    else:
        steps = np.arange(int(THORAX_EXTENSION_MM), 0, -1)[:, None]
        extra, scale = aorta.points[0] + steps * up, np.ones(len(steps))
    n = len(extra)
    extended = Vessel("aorta", np.vstack([extra, aorta.points]), np.concatenate([scale * aorta.radius[0], aorta.radius]),
                      np.concatenate([scale * aorta.outer_radius[0], aorta.outer_radius]),
                      np.vstack([np.repeat(aorta.outer_offset[:1], n, 0), aorta.outer_offset]))
    vessels = {"aorta": extended}
    for name, vessel in anatomy.vessels.items():
        if name != "aorta":
            vessels[name] = replace(vessel, parent_index=vessel.parent_index + (n if vessel.parent == "aorta" else 0))
    if "arch" in names:
        vessels.update(_supra_aortic_branches(extended))
    return Anatomy(vessels)


def _supra_aortic_branches(aorta: Vessel, length_mm: float = 80.0) -> dict:
    """The brachiocephalic trunk, left common carotid and left subclavian artery: straight up
    (and outwards) from the top of the arch, front to back, ``length_mm`` long (label ``other``)."""
    apex_z = float(aorta.points[:, 2].max())
    on_top = np.nonzero(aorta.points[:, 2] >= apex_z - 6.0)[0]
    on_top = on_top[np.argsort(aorta.points[on_top, 1])]              # front to back
    branches = {}
    for name, fraction, radius, sideways in (("brachiocephalic", 0.15, 6.0, -15.0), ("carotid_left", 0.5, 4.0, 3.0),
                                             ("subclavian_left", 0.85, 5.0, 15.0)):
        index = int(on_top[int(fraction * (len(on_top) - 1))])
        base = aorta.points[index]
        points = base + np.linspace(0.0, 1.0, int(length_mm) + 1)[:, None] * np.array([sideways, 0.0, length_mm])
        branches[name] = Vessel("other", points, radius, radius + 1.0, np.zeros(3), parent="aorta", parent_index=index)
    return branches


def _arch_centreline(top: np.ndarray, up: np.ndarray, step_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The thoracic aorta above the abdominal aorta's ``top``, ordered from the aortic root:
    the ascending aorta (:data:`ASCENDING_MM`, rising), the arch (a half turn of radius
    :data:`ARCH_RADIUS_MM` from front to back, drifting :data:`ARCH_RIGHTWARD_MM` to the right
    on the way to the front) and the descending aorta (:data:`DESCENDING_MM` along ``up``);
    with each point's radius relative to the abdominal aorta's top (1.3 at the root, 1.1 at
    the arch's far end, 1 at ``top``).

    Returns
    -------
    points : numpy.ndarray, shape (n, 3)
        LPS mm, one every ``step_mm``; ``top`` itself is not among them.
    scale : numpy.ndarray, shape (n,)
    """
    arch_start = top + DESCENDING_MM * up                             # the descending aorta's top
    centre = arch_start + np.array([0.0, -ARCH_RADIUS_MM, 0.0])       # anterior is -y in LPS
    turn = np.linspace(np.pi, 0.0, int(np.pi * ARCH_RADIUS_MM / step_mm) + 1)      # front to back
    arch = np.column_stack([centre[0] - ARCH_RIGHTWARD_MM * turn / np.pi, centre[1] + ARCH_RADIUS_MM * np.cos(turn),
                            centre[2] + ARCH_RADIUS_MM * np.sin(turn)])
    rise = np.arange(int(ASCENDING_MM / step_mm), 0, -1)[:, None] * step_mm
    ascending = arch[0] + np.array([6.0, 0.0, 0.0]) * rise / ASCENDING_MM - np.array([0.0, 0.0, 1.0]) * rise
    fall = np.arange(int(DESCENDING_MM / step_mm), 0, -1)[:, None] * step_mm
    descending = top + fall * up
    points = np.vstack([ascending, arch[:-1], descending])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    arch_end = len(ascending) + len(arch) - 1
    scale = np.interp(arc, [0.0, arc[arch_end], arc[-1]], [1.3, 1.1, 1.0])
    return points, scale


def _grid_with_room_in_front(anatomy: Anatomy, params: PhantomParams, front_mm: float, side_mm: float = 0.0) -> Grid:
    """:func:`ct_grid`, extended ``front_mm`` anteriorly (for the heart and the bowel) and
    ``side_mm`` to either side (for the lungs and the pulmonary arteries)."""
    grid = ct_grid(anatomy, params.ct_spacing_mm, params.ct_margin_mm)
    extra = int(np.ceil(front_mm / params.ct_spacing_mm))
    side = int(np.ceil(side_mm / params.ct_spacing_mm))
    origin = (round(grid.origin[0] - side * params.ct_spacing_mm, 3), round(grid.origin[1] - extra * params.ct_spacing_mm, 3),
              grid.origin[2])
    return Grid((grid.shape[0], grid.shape[1] + extra, grid.shape[2] + 2 * side), grid.spacing, origin)


def stressed_phantom_ct(params: PhantomParams, options: StressorOptions, rng: np.random.Generator):
    """A phantom CT of the rest anatomy of ``params`` with the stressors of ``options``.

    Returns
    -------
    ct : io.Volume
        int16 HU.
    truth : io.Volume
        The lumen label on the CT grid (both channels of a dissection; the thoracic aorta too).
    anatomy : Anatomy
        The anatomy drawn (with the thoracic aorta when ``thorax`` is asked).
    """
    from .anatomy import build_preop_anatomy

    anatomy = stressed_anatomy(build_preop_anatomy(params), options.names)
    front = 60.0 if {"thorax", "venous_contrast", "arch"} & set(options.names) else 0.0
    side = 60.0 if "arch" in options.names else 0.0
    grid = _grid_with_room_in_front(anatomy, params, front, side)
    if "arch" in options.names:                                         # the neck's arteries leave the field at its top
        grid = Grid((grid.shape[0] + int(np.ceil(40.0 / params.ct_spacing_mm)),) + tuple(grid.shape[1:]), grid.spacing,
                    grid.origin)
    volume = grid.volume(dtype=np.int16)
    lumen = _lumen_field(anatomy, volume)
    ct = _ct_from_lumen_field(anatomy, params, rng, volume, lumen, stressors=_Painter(options, params, rng))
    return ct, rasterize_lumen(anatomy, ct), anatomy

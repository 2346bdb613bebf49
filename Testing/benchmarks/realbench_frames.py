"""Raw X-ray frames of a silicone aortic phantom on a bench, as a real C-arm records them.

An independent frame family: it shares no rendering or distractor code with
``phantom/distractors.py``, ``phantom/fluoro.py`` or ``scenarios/frames.py`` (the segmentation
was tuned on those). Only the case geometry (``phantom.generate_case``: the pre- and
intra-operative anatomy with lumen radii) and the CT of the existing image-only cases are
reused. Everything the frame shows is a 3D object traced ray by ray (Beer-Lambert, exact
chords through cylinders, spheres and boxes, LPS mm):

- the phantom: silicone tube walls around the lumen, the lumen filled with diluted iodine
  that mixes badly (a denser core jet, less contrast downstream and in the side branches)
  and holds air bubbles on its anterior side; connectors and tubing at the ends, the tubing
  sometimes filled with contrast too;
- devices inside the vessels: a guidewire and a catheter from a femoral end (sometimes into a
  renal), a sheath with its hub and valve at that femoral end;
- the bench: a PMMA box (walls, steel screws), optionally filled with water, on a carbon-fibre
  table with an edge and steel rails, a ruler with lead ticks, ECG electrodes, leads and clips;
- the imaging chain of an image intensifier: a round field with vignetting, a heel gradient,
  object scatter, pincushion distortion, veiling glare, quantum (Poisson) and electronic
  noise, blur, log display with edge enhancement, 8 bits, either polarity, burned-in text and
  a date; a rectangular collimator on some frames.

:func:`write_seed` writes one seed's case folders (DESIGN.md section 4; no masks in the
image-only folders):

- ``angio/``: DICOM CT + ``fluoro.png`` (or ``fluoro.dcm``) + ``geometry.json`` + ``gt.json``;
- ``angio_truemask/``: the same with the true vessel mask as ``fluoro_mask.png`` (reference);
- ``no_contrast/``, ``box_only/``, ``other_phantom/``: non-angiograms of the same style with this
  case's CT (the phantom filled with water or air; the box without phantom; another phantom's
  contrast frame), which ``plan`` must refuse;
- ``eval/``: the true vessel mask, the exposed field and what was drawn (``scene.json``).

    python Testing/benchmarks/realbench_frames.py --out /tmp/rb --seeds 480 481
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, replace
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy import ndimage

from FevarPlannerLib import files, io
from FevarPlannerLib import phantom as ph
from FevarPlannerLib.phantom.case import _ground_truth
from FevarPlannerLib.phantom.ct import _ct_from_lumen_field
from FevarPlannerLib.phantom.raster import _lumen_field
from FevarPlannerLib.projection import (CArmGeometry, project, projection_jacobian, projection_matrix_from_carm,
                                        write_geometry_json)

#: Linear attenuation (1/mm) at the effective energy of a 70 kVp fluoroscopy beam (about 50 keV).
MU = {"water": 0.022, "silicone": 0.026, "pmma": 0.024, "steel": 1.4, "lead": 6.0, "carbon": 0.007,
      "catheter": 0.07, "sheath": 0.045, "polypropylene": 0.019, "pvc": 0.035, "copper": 1.6,
      "platinum": 9.0}
#: Iodine: 1/mm per mg/ml of iodine at about 50 keV (12 cm^2/g).
MU_IODINE_PER_MG_ML = 0.0012
KINDS = ("angio", "no_contrast", "box_only", "other_phantom")
FONT = "/usr/share/fonts/truetype/dejavu/DejaVuSansMono.ttf"


# ----------------------------------------------------------------------------- ray tracing

@dataclass
class Rays:
    """The source and one unit direction per detector pixel (rows, cols, 3), LPS mm."""

    source: np.ndarray
    directions: np.ndarray
    P: np.ndarray

    @classmethod
    def of(cls, P: np.ndarray, shape: tuple[int, int]) -> "Rays":
        M, p4 = P[:, :3], P[:, 3]
        source = -np.linalg.solve(M, p4)
        vv, uu = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
        pixels = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
        directions = pixels @ np.linalg.inv(M).T
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        if np.mean(directions.reshape(-1, 3) @ (np.mean(directions.reshape(-1, 3), 0))) < 0:
            directions = -directions
        return cls(source, directions, P)

    @property
    def shape(self) -> tuple[int, int]:
        return self.directions.shape[:2]

    def window(self, points: np.ndarray, reach_mm: float):
        """The pixel window (row slice, column slice) holding the projection of ``points``
        widened by ``reach_mm`` at their depth; None when it misses the frame."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        uv = project(self.P, points)
        px_per_mm = np.abs(projection_jacobian(self.P, points)).sum(axis=-1).max()
        reach = reach_mm * px_per_mm + 3.0
        lo = np.floor(uv.min(0) - reach).astype(int)
        hi = np.ceil(uv.max(0) + reach).astype(int) + 1
        rows, cols = self.shape
        u0, v0 = max(lo[0], 0), max(lo[1], 0)
        u1, v1 = min(hi[0], cols), min(hi[1], rows)
        if u1 <= u0 or v1 <= v0:
            return None
        return slice(v0, v1), slice(u0, u1)


def cylinder_chord(source, directions, a, b, radius) -> np.ndarray:
    """Length (mm) of each ray inside the finite cylinder of axis ``a -> b`` and ``radius``."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    if length < 1e-9:
        return np.zeros(directions.shape[:-1])
    axis = axis / length
    w = source - a
    d_along = directions @ axis
    w_along = float(w @ axis)
    d_perp = directions - d_along[..., None] * axis
    w_perp = w - w_along * axis
    qa = np.einsum("...k,...k->...", d_perp, d_perp)
    qb = 2.0 * (d_perp @ w_perp)
    qc = float(w_perp @ w_perp) - radius * radius
    disc = qb * qb - 4.0 * qa * qc
    inside = (disc > 0) & (qa > 1e-12)
    root = np.sqrt(np.where(inside, disc, 0.0))
    safe_a = np.where(inside, qa, 1.0)
    t1, t2 = (-qb - root) / (2 * safe_a), (-qb + root) / (2 * safe_a)
    safe_d = np.where(np.abs(d_along) > 1e-12, d_along, 1e-12)
    s1, s2 = -w_along / safe_d, (length - w_along) / safe_d
    lo, hi = np.maximum(t1, np.minimum(s1, s2)), np.minimum(t2, np.maximum(s1, s2))
    return np.where(inside, np.clip(hi - lo, 0.0, None), 0.0)


def sphere_chord(source, directions, centre, radius) -> np.ndarray:
    """Length (mm) of each ray inside a sphere."""
    w = centre - source
    along = directions @ w
    miss = float(w @ w) - along * along
    return 2.0 * np.sqrt(np.clip(radius * radius - miss, 0.0, None))


def box_chord(source, directions, low, high) -> np.ndarray:
    """Length (mm) of each ray inside an axis-aligned box (slab method)."""
    safe = np.where(np.abs(directions) > 1e-12, directions, 1e-12)
    t_low, t_high = (low - source) / safe, (high - source) / safe
    enter = np.minimum(t_low, t_high).max(axis=-1)
    leave = np.maximum(t_low, t_high).min(axis=-1)
    return np.clip(leave - np.maximum(enter, 0.0), 0.0, None)


class Film:
    """Accumulates line integrals (nepers) of a scene on the detector, and the lumen mask."""

    def __init__(self, rays: Rays):
        self.rays = rays
        self.nepers = np.zeros(rays.shape)

    def tube(self, points, radii, mu, *, hollow_radii=None) -> np.ndarray:
        """Add a polyline tube of per-segment attenuation ``mu`` (scalar or per segment); a
        ``hollow_radii`` inner bore is left out. Returns the chord image (mm) of the tube."""
        points = np.asarray(points, dtype=float)
        radii = np.broadcast_to(np.asarray(radii, dtype=float), (len(points),))
        mu = np.broadcast_to(np.asarray(mu, dtype=float), (len(points) - 1,))
        inner = None if hollow_radii is None else np.broadcast_to(np.asarray(hollow_radii, dtype=float), (len(points),))
        chords = np.zeros(self.rays.shape)
        for k in range(len(points) - 1):
            a, b = points[k], points[k + 1]
            radius = 0.5 * (radii[k] + radii[k + 1])
            window = self.rays.window(np.vstack([a, b]), radius)
            if window is None:
                continue
            d = self.rays.directions[window]
            chord = cylinder_chord(self.rays.source, d, a, b, radius)
            if inner is not None:
                chord -= cylinder_chord(self.rays.source, d, a, b, 0.5 * (inner[k] + inner[k + 1]))
            chords[window] += chord
            self.nepers[window] += mu[k] * chord
        return chords

    def sphere(self, centre, radius, mu) -> None:
        window = self.rays.window(centre, radius)
        if window is not None:
            self.nepers[window] += mu * sphere_chord(self.rays.source, self.rays.directions[window], centre, radius)

    def box(self, low, high, mu) -> np.ndarray:
        corners = np.array([[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])])
        window = self.rays.window(corners, 0.0)
        chord = np.zeros(self.rays.shape)
        if window is not None:
            chord[window] = box_chord(self.rays.source, self.rays.directions[window], np.asarray(low, float),
                                      np.asarray(high, float))
            self.nepers += mu * chord
        return chord


# ----------------------------------------------------------------------------- the scene

def _smooth_noise(rng, n: int, scale: float, correlation: int) -> np.ndarray:
    noise = ndimage.gaussian_filter1d(rng.normal(size=n + 4 * correlation), correlation, mode="nearest")
    noise = noise[2 * correlation:2 * correlation + n]
    return scale * noise / max(np.std(noise), 1e-9)


def _resample(points: np.ndarray, step: float) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    at = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.column_stack([np.interp(at, s, points[:, d]) for d in range(3)])


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _outside_parent(anatomy, vessel) -> slice:
    """The branch beyond its parent's lumen (its first points lie on the parent's axis)."""
    if vessel.parent is None:
        return slice(0, len(vessel.points))
    parent = anatomy.vessels[vessel.parent]
    if vessel.parent_index >= len(parent.points) - 2:       # leaves from the parent's end: continues it
        return slice(0, len(vessel.points))
    start = int(np.searchsorted(vessel.arc_length(), 0.8 * parent.radius[vessel.parent_index]))
    return slice(min(start, len(vessel.points) - 3), len(vessel.points))


@dataclass
class Bench:
    """What is on the bench besides the phantom: drawn once per seed (LPS mm)."""

    box_low: np.ndarray
    box_high: np.ndarray
    wall_mm: float
    water: bool
    table_y: float
    table_edge_x: float
    table_side: int
    ruler_x: float
    ruler_z0: float
    electrodes: list
    leads: list


def draw_bench(rng, anatomy) -> Bench:
    low, high = anatomy.wall_bounds()
    centre = 0.5 * (low + high)
    half = np.array([rng.uniform(95, 150), rng.uniform(45, 70), rng.uniform(170, 230)])
    shift = np.array([rng.uniform(-25, 25), rng.uniform(-5, 5), rng.uniform(-30, 30)])
    box_low, box_high = centre + shift - half, centre + shift + half
    table_y = box_high[1] + rng.uniform(2, 10)
    side = int(rng.choice([-1, 1]))
    edge = centre[0] + side * rng.uniform(120, 230)
    electrodes, leads = [], []
    for _ in range(int(rng.integers(1, 4))):
        at = np.array([centre[0] + rng.uniform(-170, 170), box_low[1] - rng.uniform(0, 5), centre[2] + rng.uniform(-180, 180)])
        electrodes.append(at)
        leads.append(_lead_curve(rng, at))
    return Bench(box_low, box_high, rng.uniform(6, 12), bool(rng.random() < 0.5), table_y, edge, side,
                 centre[0] + rng.uniform(-140, 140), centre[2] - rng.uniform(150, 250), electrodes, leads)


def _lead_curve(rng, start) -> np.ndarray:
    heading, position, points = rng.uniform(0, 2 * np.pi), np.array(start, float), [np.array(start, float)]
    for _ in range(120):
        heading += rng.normal(0, 0.12)
        position = position + 5.0 * np.array([np.cos(heading), 0.0, np.sin(heading)])
        position[1] = start[1] - 2.0 + 1.5 * np.sin(len(points) / 9.0)
        points.append(position.copy())
    return np.array(points)


def render_bench(film: Film, bench: Bench, rng) -> None:
    """The PMMA box, its screws, the table with edge and rails, the ruler, ECG electrodes and leads."""
    t = bench.wall_mm
    film.box(bench.box_low, bench.box_high, MU["pmma"])
    inner_low, inner_high = bench.box_low + [t, 0.0, t], bench.box_high - [t, t, t]
    inner = film.box(inner_low, inner_high, -MU["pmma"])
    if bench.water:
        film.nepers += MU["water"] * inner * (rng.uniform(0.55, 0.8) if rng.random() < 0.3 else 1.0)
    for x in (bench.box_low[0] + t / 2, bench.box_high[0] - t / 2):
        for z in np.arange(bench.box_low[2] + 25.0, bench.box_high[2] - 10.0, rng.uniform(60, 90)):
            film.tube([[x, bench.box_low[1] - 2.0, z], [x, bench.box_low[1] + 14.0, z]], 1.9, MU["steel"])
            film.tube([[x, bench.box_low[1] - 4.0, z], [x, bench.box_low[1] - 1.5, z]], 3.6, MU["steel"])
    side, edge = bench.table_side, bench.table_edge_x
    far = edge - side * 600.0
    film.box([min(edge, far), bench.table_y, -2000.0], [max(edge, far), bench.table_y + 22.0, 2000.0], MU["carbon"])
    rail_x = edge + side * 12.0
    film.box([min(rail_x, rail_x + side * 10), bench.table_y - 5.0, -2000.0],
             [max(rail_x, rail_x + side * 10), bench.table_y + 25.0, 2000.0], MU["steel"] * 0.35)
    ruler_y = bench.table_y - 3.0
    film.box([bench.ruler_x - 15, ruler_y, bench.ruler_z0], [bench.ruler_x + 15, ruler_y + 2.5, bench.ruler_z0 + 400], MU["pmma"])
    for k in range(41):
        length = 12.0 if k % 10 == 0 else (8.0 if k % 5 == 0 else 5.0)
        z = bench.ruler_z0 + 10.0 * k
        film.box([bench.ruler_x - 15, ruler_y, z - 0.35], [bench.ruler_x - 15 + length, ruler_y + 0.15, z + 0.35], MU["lead"])
    for at, lead in zip(bench.electrodes, bench.leads):
        film.box(at - [18, 0.4, 18], at + [18, 0.4, 18], MU["pmma"] * 2.0)
        film.tube([at - [0, 1.5, 0], at + [0, 1.5, 0]], 2.2, MU["steel"])
        film.tube(lead[:2], 0.9, MU["pvc"])
        film.box(lead[1] - [4, 3, 9], lead[1] + [4, 3, 9], MU["steel"] * 0.25)
        film.tube(lead[1:], 1.2, MU["pvc"] * 1.5)
        film.tube(lead[1:], 0.28, MU["copper"])


@dataclass
class Fill:
    """How the phantom is filled: iodine (mg/ml) at the inflow, how it thins, bubbles."""

    iodine: float
    washout: float
    jet: float
    branch_fill: dict
    bubbles: int
    medium: str     # "water" or "air" inside the lumen when there is no iodine


def draw_fill(rng, contrast: bool) -> Fill:
    iodine = rng.uniform(18.0, 90.0) if contrast else 0.0
    return Fill(iodine, rng.uniform(0.0, 0.45), rng.uniform(0.0, 0.8),
                {"renal": rng.uniform(0.6, 1.0), "iliac": rng.uniform(0.75, 1.0), "other": rng.uniform(0.3, 1.0)},
                int(rng.integers(2, 12)), "water" if (contrast or rng.random() < 0.6) else "air")


def render_phantom(film: Film, anatomy, fill: Fill, rng, *, in_water: bool, wall_mm: float,
                   tubing_contrast: bool) -> np.ndarray:
    """The silicone phantom: walls, lumen (iodine, mixing, bubbles), connectors and tubing.

    Returns the chord image (mm) of the lumen: the true vessel mask is where it is positive.
    """
    medium = MU["water"] if in_water else 0.0
    solvent = MU["water"] if fill.medium == "water" else 0.0
    lumen_total = np.zeros(film.rays.shape)
    aorta_length = anatomy.vessels["aorta"].length
    for name, vessel in anatomy.vessels.items():
        part = _outside_parent(anatomy, vessel)
        pts, radii = vessel.points[part], vessel.radius[part]
        step = max(1, len(pts) // 120)
        pts, radii = pts[::step], radii[::step]
        if len(pts) < 2:
            continue
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        s_mid = 0.5 * (s[1:] + s[:-1])
        if vessel.parent is None:
            downstream = s_mid / aorta_length
            share = 1.0
        else:
            downstream = 0.5 + 0.3 * s_mid / max(s[-1], 1.0)
            share = fill.branch_fill["renal" if "renal" in vessel.label else ("iliac" if "iliac" in vessel.label else "other")]
        iodine = fill.iodine * share * (1.0 - fill.washout * downstream)
        iodine *= 1.0 + _smooth_noise(rng, len(s_mid), 0.08, 6)
        film.tube(pts, radii + wall_mm, MU["silicone"] - medium, hollow_radii=radii)
        lumen_mu = solvent + MU_IODINE_PER_MG_ML * np.clip(iodine, 0.0, None) - medium
        lumen_total += film.tube(pts, radii, lumen_mu)
        if fill.iodine > 0 and fill.jet > 0 and vessel.parent is None:
            jet = fill.jet * fill.iodine * MU_IODINE_PER_MG_ML * np.exp(-3.0 * s_mid / aorta_length)
            film.tube(pts + _jet_offset(rng, pts, radii), 0.45 * radii, jet)
        _bubbles(film, rng, pts, radii, solvent + MU_IODINE_PER_MG_ML * fill.iodine * share, fill.bubbles)
    _ends(film, anatomy, rng, fill, medium, solvent, tubing_contrast)
    return lumen_total


def _jet_offset(rng, pts, radii) -> np.ndarray:
    side = np.cross(_unit(np.gradient(pts, axis=0)), [0.3, 1.0, 0.2])
    side = _unit(side)
    return side * (0.3 * radii * np.sin(np.linspace(0, rng.uniform(2, 6), len(pts)) + rng.uniform(0, 6)))[:, None]


def _bubbles(film: Film, rng, pts, radii, lumen_mu: float, count: int) -> None:
    """Air bubbles on the anterior wall (supine phantom: air rises towards -y)."""
    if len(pts) < 8:
        return
    for _ in range(int(rng.binomial(count, min(1.0, len(pts) / 150.0)))):
        k = int(rng.integers(2, len(pts) - 2))
        radius = min(rng.uniform(0.6, 3.5), 0.6 * radii[k])
        centre = pts[k] + np.array([rng.normal(0, 0.3), -1.0, rng.normal(0, 0.2)]) * (radii[k] - radius)
        film.sphere(centre, radius, -lumen_mu)


def _ends(film: Film, anatomy, rng, fill: Fill, medium: float, solvent: float, tubing_contrast: bool) -> None:
    """Barbed connectors and tubing on the aorta's top and the iliacs' ends; caps on the renals."""
    for vessel in anatomy.vessels.values():
        end_index = 0 if vessel.parent is None else -1
        if vessel.label not in ("aorta", "iliac_left", "iliac_right", "renal_left", "renal_right"):
            continue
        tip = vessel.points[end_index]
        outward = _unit(vessel.points[0] - vessel.points[3]) if end_index == 0 else _unit(vessel.points[-1] - vessel.points[-4])
        radius = vessel.radius[end_index]
        if "renal" in vessel.label:
            film.tube([tip, tip + 3.0 * outward], radius + 1.5, MU["polypropylene"] - medium)
            continue
        film.tube([tip - 8.0 * outward, tip + 18.0 * outward], radius + 2.5, MU["polypropylene"] - medium, hollow_radii=radius * 0.8)
        bend = _unit(outward + rng.normal(0, 0.5, 3) * [1.0, 0.2, 1.0])
        path = np.array([tip + 18.0 * outward + bend * 12.0 * k + np.array([0, 0, 1.0]) * (0.05 * k * k) * rng.choice([-1, 1])
                         for k in range(25)])
        tube_radius = 0.7 * radius
        inside = solvent + (MU_IODINE_PER_MG_ML * fill.iodine * 0.9 if tubing_contrast else 0.0) - medium
        film.tube(path, tube_radius + 1.5, MU["pvc"] - medium, hollow_radii=tube_radius)
        film.tube(path, tube_radius, inside)


def _device_route(anatomy, rng, femoral: str, into_renal: str | None, height_mm: float) -> np.ndarray:
    """A path from outside the femoral end up the iliac into the aorta (and a renal)."""
    iliac, aorta = anatomy.vessels[femoral], anatomy.vessels["aorta"]
    outward = _unit(iliac.points[-1] - iliac.points[-5])
    outside = iliac.points[-1] + outward * np.linspace(80.0, 0.0, 9)[:, None]
    up_iliac = iliac.points[::-1]
    join = iliac.parent_index
    aorta_s = aorta.arc_length()
    stop = int(np.searchsorted(aorta_s, max(aorta_s[join] - height_mm, 5.0)))
    if into_renal is not None:
        renal = anatomy.vessels[into_renal]
        stop = renal.parent_index
    up_aorta = aorta.points[stop:join + 1][::-1]
    route = [outside, up_iliac, up_aorta]
    if into_renal is not None:
        renal = anatomy.vessels[into_renal]
        depth = int(np.searchsorted(renal.arc_length(), rng.uniform(15.0, 35.0)))
        route.append(renal.points[1:depth])
    path = _resample(np.vstack(route), 1.5)
    return path


def _offset_within(path, anatomy, rng, fraction: float) -> np.ndarray:
    """The device pushed off the centreline (it hugs a wall), at most ``fraction`` of the local lumen radius."""
    centres = np.vstack([v.points for v in anatomy.vessels.values()])
    radii = np.concatenate([v.radius for v in anatomy.vessels.values()])
    nearest = np.argmin(((path[:, None, :] - centres[None, ::3, :]) ** 2).sum(-1), axis=1) * 3
    local = np.where(np.linalg.norm(path - centres[nearest], axis=1) < radii[nearest] + 2.0, radii[nearest], 0.0)
    tangent = _unit(np.gradient(path, axis=0))
    side_a = _unit(np.cross(tangent, [0.0, 1.0, 0.0]) + 1e-6)
    side_b = _unit(np.cross(tangent, side_a))
    a = _smooth_noise(rng, len(path), 1.0, 12)
    b = _smooth_noise(rng, len(path), 1.0, 12)
    norm = np.maximum(1.0, np.hypot(a, b))
    return path + (fraction * local / norm)[:, None] * (a[:, None] * side_a + b[:, None] * side_b)


def render_devices(film: Film, anatomy, rng, *, in_water: bool) -> dict:
    """Guidewire, catheter (marker tip) and a femoral sheath with hub and valve."""
    medium = MU["water"] if in_water else 0.0
    femoral = str(rng.choice(["iliac_left", "iliac_right"]))
    renal = str(rng.choice(["renal_left", "renal_right"])) if rng.random() < 0.5 else None
    wire = _offset_within(_device_route(anatomy, rng, femoral, renal, rng.uniform(90, 200)), anatomy, rng, 0.6)
    film.tube(wire, 0.45, rng.uniform(0.6, 1.5) * MU["steel"] - medium)
    catheter_route = _device_route(anatomy, rng, femoral, renal, rng.uniform(40, 120))
    catheter = _offset_within(catheter_route[: max(10, int(len(catheter_route) * rng.uniform(0.85, 1.0)))], anatomy, rng, 0.4)
    film.tube(catheter, 0.85, MU["catheter"] - medium, hollow_radii=0.5)
    film.tube(catheter[-3:], 0.9, MU["platinum"] * 0.08, hollow_radii=0.5)
    iliac = anatomy.vessels[femoral]
    outward = _unit(iliac.points[-1] - iliac.points[-5])
    inner_end = iliac.points[-int(rng.integers(8, 20))]
    sheath = np.array([inner_end, iliac.points[-1], iliac.points[-1] + 70.0 * outward])
    film.tube(sheath, 1.45, MU["sheath"] - medium, hollow_radii=1.25)
    film.tube([inner_end - 1.5 * outward, inner_end + 1.5 * outward], 1.5, MU["platinum"] * 0.1, hollow_radii=1.25)
    hub = iliac.points[-1] + 70.0 * outward
    film.tube([hub, hub + 30.0 * outward], 5.5, MU["polypropylene"] * 1.5, hollow_radii=1.5)
    film.tube([hub + 8.0 * outward, hub + 12.0 * outward], 5.0, MU["steel"] * 0.1)
    second = None
    if rng.random() < 0.35:
        other = "iliac_right" if femoral == "iliac_left" else "iliac_left"
        second = _offset_within(_device_route(anatomy, rng, other, None, rng.uniform(30, 120)), anatomy, rng, 0.6)
        film.tube(second, 0.45, MU["steel"] - medium)
    return {"femoral": femoral, "renal": renal, "second_wire": second is not None}


# ----------------------------------------------------------------------------- the imaging chain

@dataclass
class Chain:
    """The image intensifier / camera chain of one seed."""

    field_radius: float
    field_centre: tuple
    vignetting: float
    heel: float
    heel_angle: float
    pincushion: float
    glare: float
    scatter: float
    photons: float
    electronic: float
    blur: float
    enhance: float
    collimator: tuple | None
    inverted: bool
    white_surround: bool
    dicom: bool
    gamma: float


def draw_chain(rng, shape) -> Chain:
    rows, cols = shape
    collimator = None
    if rng.random() < 0.5:
        collimator = (rng.uniform(0.0, 0.16) * cols, rng.uniform(0.0, 0.16) * cols,
                      rng.uniform(0.0, 0.12) * rows, rng.uniform(0.0, 0.12) * rows, rng.uniform(-4, 4))
    return Chain(rng.uniform(0.46, 0.52) * min(shape), (cols / 2 + rng.normal(0, 6), rows / 2 + rng.normal(0, 6)),
                 rng.uniform(0.2, 0.5), rng.uniform(0.0, 0.15), rng.uniform(0, 2 * np.pi), rng.uniform(0.02, 0.07),
                 rng.uniform(0.03, 0.12), rng.uniform(0.05, 0.25), rng.uniform(300, 2500), rng.uniform(0.5, 3.0),
                 rng.uniform(0.7, 1.4), rng.uniform(0.0, 0.8), collimator, bool(rng.random() < 0.35),
                 bool(rng.random() < 0.15), bool(rng.random() < 0.35), rng.uniform(0.8, 1.25))


def pincushion(image: np.ndarray, chain: Chain, order: int = 1) -> np.ndarray:
    """The image intensifier's pincushion distortion: a point at radius r appears at r (1 + k (r / R)^2)."""
    rows, cols = image.shape
    cu, cv = chain.field_centre
    vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    du, dv = uu - cu, vv - cv
    radius = np.hypot(du, dv) / chain.field_radius
    shrink = 1.0 / (1.0 + chain.pincushion * radius ** 2)
    return ndimage.map_coordinates(image, [cv + dv * shrink, cu + du * shrink], order=order, mode="nearest")


def exposed_field(shape, chain: Chain) -> np.ndarray:
    """Pixels inside the round field and the collimator's opening."""
    rows, cols = shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    cu, cv = chain.field_centre
    field = np.hypot(uu - cu, vv - cv) <= chain.field_radius
    return field & (_collimator_open(shape, chain) > 0.5)


def _collimator_open(shape, chain: Chain) -> np.ndarray:
    rows, cols = shape
    if chain.collimator is None:
        return np.ones(shape)
    left, right, top, bottom, angle = chain.collimator
    vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
    du, dv = uu - cols / 2, vv - rows / 2
    ru, rv = c * du + s * dv + cols / 2, -s * du + c * dv + rows / 2
    inside = (ru >= left) & (ru <= cols - right) & (rv >= top) & (rv <= rows - bottom)
    return ndimage.gaussian_filter(inside.astype(float), 2.5)


def expose(nepers: np.ndarray, chain: Chain, rng) -> np.ndarray:
    """Detected signal: heel gradient, collimator leaves, scatter, Poisson noise, veiling glare, blur."""
    rows, cols = nepers.shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    cu, cv = chain.field_centre
    along = ((uu - cols / 2) * np.cos(chain.heel_angle) + (vv - rows / 2) * np.sin(chain.heel_angle)) / cols
    radius = np.hypot(uu - cu, vv - cv) / chain.field_radius
    beam = (1.0 + chain.heel * along * 2.0)
    leaves = 0.04 + 0.96 * _collimator_open(nepers.shape, chain)
    primary = beam * leaves * np.exp(-nepers)
    scattered = chain.scatter * ndimage.gaussian_filter(primary, 40.0)
    counts = rng.poisson(chain.photons * (primary + scattered)).astype(float)
    light = counts * (1.0 - chain.vignetting * radius ** 2)
    light = (1.0 - chain.glare) * light + chain.glare * ndimage.gaussian_filter(light, 90.0)
    light = ndimage.gaussian_filter(light, chain.blur) + rng.normal(0.0, chain.electronic, light.shape)
    return np.clip(light, 0.5, None)


def display(signal: np.ndarray, field: np.ndarray, chain: Chain, rng) -> np.ndarray:
    """Log display, edge enhancement, window, gamma, polarity, the round field's surround: uint8."""
    logged = np.log(signal)
    logged = logged + chain.enhance * (logged - ndimage.gaussian_filter(logged, 4.0))
    inside = logged[field]
    low, high = np.percentile(inside, rng.uniform(0.2, 2.0)), np.percentile(inside, rng.uniform(98.5, 99.9))
    grey = np.clip((logged - low) / max(high - low, 1e-6), 0.0, 1.0) ** chain.gamma
    if chain.inverted:
        grey = 1.0 - grey
    grey = 8.0 + 235.0 * grey
    round_field = _round_field(signal.shape, chain)
    surround = 255.0 if chain.white_surround else rng.uniform(0.0, 6.0)
    grey = round_field * grey + (1.0 - round_field) * surround
    return np.clip(np.round(grey), 0, 255).astype(np.uint8)


def _round_field(shape, chain: Chain) -> np.ndarray:
    rows, cols = shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    cu, cv = chain.field_centre
    return np.clip(chain.field_radius - np.hypot(uu - cu, vv - cv) + 0.5, 0.0, 1.0)


def burn_text(grey: np.ndarray, rng, carm: CArmGeometry, when: datetime) -> np.ndarray:
    """Burned-in annotation: site, date and time, exposure, angles, frame counter and an R marker."""
    image = Image.fromarray(grey)
    draw = ImageDraw.Draw(image)
    size = max(12, grey.shape[0] // 48)
    font = ImageFont.truetype(FONT, size)
    big = ImageFont.truetype(FONT, 2 * size)
    colour = int(rng.choice([255, 235, 200]))
    rows, cols = grey.shape
    lines_left = ["BENCH LAB 2", "PHANTOM^AAA SIL-04", when.strftime("%d-%b-%Y %H:%M:%S").upper()]
    lines_right = [f"{rng.uniform(60, 85):.0f} kV  {rng.uniform(0.8, 4.0):.1f} mA",
                   f"{'LAO' if carm.primary_angle >= 0 else 'RAO'} {abs(carm.primary_angle):.0f}  "
                   f"{'CRA' if carm.secondary_angle >= 0 else 'CAU'} {abs(carm.secondary_angle):.0f}",
                   f"FL 15 p/s  MAG {int(rng.integers(0, 3))}"]
    for k, line in enumerate(lines_left):
        draw.text((8, 6 + k * (size + 4)), line, fill=colour, font=font)
    for k, line in enumerate(lines_right):
        width = draw.textlength(line, font=font)
        draw.text((cols - width - 8, 6 + k * (size + 4)), line, fill=colour, font=font)
    draw.text((8, rows - size - 10), f"F {int(rng.integers(1, 90)):03d}/120   {rng.uniform(0.1, 3.0):.1f} min",
              fill=colour, font=font)
    draw.text((cols - 3 * size, rows // 2 - size), "R", fill=colour, font=big)
    return np.asarray(image)


# ----------------------------------------------------------------------------- a seed's cases

def _carm(rng, anatomy) -> tuple[CArmGeometry, np.ndarray]:
    """A C-arm whose round field holds the renals, the bifurcation and most of the iliacs."""
    low, high = anatomy.wall_bounds()
    renal_z = np.mean([anatomy.vessels[n].points[0, 2] for n in ("renal_left", "renal_right")])
    iso = 0.5 * (low + high)
    iso[2] = renal_z - rng.uniform(55.0, 85.0)
    sid = rng.uniform(980.0, 1150.0)
    sod = sid / rng.uniform(1.2, 1.45)
    size = 1024
    pixel = rng.uniform(0.38, 0.46)
    carm = CArmGeometry(sid, sod, (pixel, pixel), rng.uniform(-18, 18), rng.uniform(-12, 12), size, size)
    return carm, iso + rng.normal(0, [8.0, 4.0, 8.0])


def render_frame(case, bench: Bench, chain: Chain, rng, *, contrast: bool, phantom: bool = True,
                 anatomy=None, fill: Fill | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """One raw frame (uint8 display, before the burned-in text), its true vessel mask and what
    was drawn; ``fill`` overrides the drawn filling (:func:`draw_fill`)."""
    rays = Rays.of(case.P_true, (case.carm.rows, case.carm.cols))
    film = Film(rays)
    render_bench(film, bench, rng)
    anatomy = case.intraop if anatomy is None else anatomy
    facts = {"water_bath": bench.water}
    lumen = np.zeros(rays.shape)
    if phantom:
        fill = draw_fill(rng, contrast) if fill is None else fill
        lumen = render_phantom(film, anatomy, fill, rng, in_water=bench.water, wall_mm=rng.uniform(1.2, 3.0),
                               tubing_contrast=bool(rng.random() < 0.5) and contrast)
        facts.update(iodine_mg_ml=fill.iodine, lumen_medium=fill.medium, devices=render_devices(film, anatomy, rng, in_water=bench.water))
    nepers = pincushion(film.nepers, chain)
    field = exposed_field(nepers.shape, chain)
    mask = (pincushion(lumen, chain, order=0) > 0.3) & field & phantom
    signal = expose(nepers, chain, rng)
    grey = display(signal, field, chain, rng)
    return grey, mask, facts


def _write_case_folder(folder: Path, ct_dir: Path, case, grey: np.ndarray, chain: Chain, rng, *, mask=None,
                       when: datetime) -> None:
    with files.atomic_folder(folder) as tmp:
        shutil.copytree(ct_dir, tmp / "ct")
        text = burn_text(grey, rng, case.carm, when)
        if chain.dicom:
            stored = text.astype(np.uint16) * 257
            photometric = "MONOCHROME2"
            if rng.random() < 0.5:
                stored, photometric = 65535 - stored, "MONOCHROME1"
            io.write_fluoro_dicom(tmp / "fluoro.dcm", stored, case.carm, photometric=photometric,
                                  patient_name="Phantom^Bench", patient_id=folder.parent.name)
        else:
            io.write_png(tmp / "fluoro.png", text)
        if mask is not None:
            io.write_mask_png(tmp / "fluoro_mask.png", mask)
        write_geometry_json(tmp / "geometry.json", case.P_true)
        files.write_text_atomic(tmp / "gt.json", json.dumps(_ground_truth(case)))


def make_case(seed: int):
    """The phantom case of a seed with this family's C-arm (the anatomy and CT of an image-only case)."""
    rng = np.random.default_rng([seed, 7])
    params = ph.random_params(rng)
    case = ph.generate_case(params, name=f"realbench_{seed}")
    carm, iso = _carm(rng, case.intraop)
    P = projection_matrix_from_carm(carm, iso)
    return replace(case, carm=carm, P_true=P, P_given=P)


def write_seed(out: Path, seed: int, kinds=KINDS) -> Path:
    """Write one seed's case folders (see the module docstring) under ``out/seed_<seed>``."""
    root = Path(out) / f"seed_{seed}"
    root.mkdir(parents=True, exist_ok=True)
    case = make_case(seed)
    rng = np.random.default_rng([seed, 11])
    bench = draw_bench(rng, case.intraop)
    chain = draw_chain(rng, (case.carm.rows, case.carm.cols))
    when = datetime(2026, 1, 1, 8) + timedelta(minutes=int(rng.integers(0, 300 * 24 * 60)))
    ct_dir = root / "eval" / "ct"
    (root / "eval").mkdir(exist_ok=True)
    if not ct_dir.exists():
        volume = case.grid.volume(dtype=np.uint8)
        lumen = _lumen_field(case.preop, volume)
        io.write_volume(root / "eval" / "aorta_mask_true.nrrd", volume.with_array((lumen <= 0.0).astype(np.uint8)))
        ct = _ct_from_lumen_field(case.preop, case.preop_params, np.random.default_rng([seed, 1]), volume, lumen)
        io.write_ct_dicom_series(ct, ct_dir, series_description=f"bench phantom CT {seed}",
                                 patient_name="Phantom^Bench", patient_id=f"RB{seed}")
    scene = {"seed": seed, "chain": {k: v for k, v in vars(chain).items()}, "bench_water": bench.water, "kinds": {}}
    for kind in kinds:
        frame_rng = np.random.default_rng([seed, 13, KINDS.index(kind)])
        other = None
        if kind == "other_phantom":
            other = ph.generate_case(ph.random_params(np.random.default_rng([seed, 99])), name="other").intraop
            other = _centred_like(other, case.intraop)
        grey, mask, facts = render_frame(case, bench, chain, frame_rng, contrast=kind != "no_contrast",
                                         phantom=kind != "box_only", anatomy=other)
        _write_case_folder(root / kind, ct_dir, case, grey, chain, frame_rng, when=when)
        mask &= kind != "no_contrast"
        if kind == "angio":
            io.write_mask_png(root / "eval" / "true_mask.png", mask)
            io.write_mask_png(root / "eval" / "exposed_field.png", exposed_field(mask.shape, chain))
            _write_case_folder(root / "angio_truemask", ct_dir, case, grey, chain, np.random.default_rng([seed, 13, 0]),
                               mask=mask, when=when)
        scene["kinds"][kind] = facts
    files.write_text_atomic(root / "eval" / "scene.json", json.dumps(scene, indent=1, default=_json_default))
    return root


def _centred_like(anatomy, reference):
    """``anatomy`` moved so that its renal level and midline sit where ``reference``'s do."""
    def anchor(a):
        return np.mean([a.vessels[n].points[0] for n in ("renal_left", "renal_right")], axis=0)
    shift = anchor(reference) - anchor(anatomy)
    vessels = {n: replace(v, points=v.points + shift) for n, v in anatomy.vessels.items()}
    return replace(anatomy, vessels=vessels)


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    args = parser.parse_args()
    for seed in args.seeds:
        print(write_seed(args.out, seed, args.kinds))


if __name__ == "__main__":
    main()

"""Bench frames: the phantom's vessels among what a real fluoroscopy frame also shows (issue 11).

A real frame of a contrast-filled aortic phantom on a bench is not a clean DSA: unless it is
subtracted it shows the spine and the pelvis (of an anthropomorphic phantom or a patient),
the walls and the support rail of the phantom's box, the table's edge, the collimator's
shutters, guide wires, catheters and a sheath, a radio-opaque ruler, burned-in text, and an
exposure that falls off across the field (heel effect, vignetting); the vessels may be dark
or bright. :func:`render_bench_frame` renders such a frame from a :class:`PhantomCase`, with
a mask per distractor so that a segmentation can be scored on what it wrongly takes.

The frame is built in attenuation (line integrals ``A = mu t``): each structure adds to
``A``; the detector sees ``I0 (u, v) exp(-A)`` with ``I0`` the exposure field (heel effect,
vignetting, the collimator's shutters with a blurred penumbra) and signal-dependent noise.
Iodine attenuates ``fluoro_attenuation_per_mm`` per mm of lumen (as :func:`render_fluoro`);
the bones are set relative to the aorta's centre-line attenuation (vertebral bodies 0.5-1.0
times it, their cortical rims more: in an unsubtracted abdominal angiogram the contrast-
filled aorta and the vertebral bodies are about as dark). A subtracted frame (DSA) keeps
only what differs between the fill and the mask run: the iodine, the devices that moved
(the wire and the catheter), the collimator and the text.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from ..projection import pixels_per_mm, project
from .fluoro import _FLUORO_FULL_SCALE, _project_tubes

#: Every distractor :func:`render_bench_frame` can draw.
DISTRACTORS = ("spine", "pelvis", "box", "rail", "table", "collimator", "wire", "catheter", "sheath", "ruler",
               "text", "exposure")
#: Those that a subtraction leaves in the frame (they differ between mask and fill, or are overlays).
SURVIVE_SUBTRACTION = ("collimator", "wire", "catheter", "text", "exposure")


@dataclass
class BenchFrame:
    """A rendered bench frame.

    Attributes
    ----------
    frame : numpy.ndarray of uint16
        12-bit frame (MONOCHROME2; vessels dark, or bright for ``polarity='bright'``).
    mask : numpy.ndarray of bool
        The projected lumen (empty without contrast).
    parts : dict
        ``distractor -> bool mask`` of the pixels each distractor draws (the exposure field has none).
    """

    frame: np.ndarray
    mask: np.ndarray
    parts: dict


def _polyline_coverage(shape, points: np.ndarray, width: float) -> np.ndarray:
    """Anti-aliased coverage (0..1) of a polyline (u, v) of ``width`` pixels."""
    from PIL import Image, ImageDraw

    canvas = Image.new("1", (shape[1], shape[0]), 0)
    ImageDraw.Draw(canvas).line([tuple(map(float, p)) for p in points], fill=1, width=1)
    drawn = np.asarray(canvas, dtype=bool)
    if not drawn.any():
        return np.zeros(shape, dtype=np.float32)
    distance = ndimage.distance_transform_edt(~drawn)
    return np.clip(width / 2.0 + 0.5 - distance, 0.0, 1.0).astype(np.float32)


def _tube_chord(shape, points: np.ndarray, radius: float) -> np.ndarray:
    """Chord length (px) through a tube of ``radius`` px along the polyline ``points``."""
    coverage = _polyline_coverage(shape, points, 1.0) > 0
    if not coverage.any():
        return np.zeros(shape, dtype=np.float32)
    distance = ndimage.distance_transform_edt(~coverage)
    return (2.0 * np.sqrt(np.clip(radius ** 2 - distance ** 2, 0.0, None))).astype(np.float32)


def _spine(shape, aorta_uv: np.ndarray, px_mm: float, level: float, rng,
           offset_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertebral bodies beside and under the aorta: rounded blocks with a cortical rim, discs between.

    The column's centre lies 8-20 mm to a random side of the aorta, or ``offset_mm`` (signed,
    along +u) when given (the random draws are made either way)."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float32)
    order = np.argsort(aorta_uv[:, 1])
    side = rng.choice([-1.0, 1.0])
    offset = side * rng.uniform(8, 20)
    offset = offset if offset_mm is None else float(offset_mm)
    centre_u = np.interp(v, aorta_uv[order, 1], aorta_uv[order, 0]) + offset * px_mm
    half_width = rng.uniform(20, 26) * px_mm
    height, disc = rng.uniform(26, 32) * px_mm, rng.uniform(5, 8) * px_mm
    phase = (v + rng.uniform(0, height + disc)) % (height + disc)
    across = np.abs(u - centre_u) / half_width
    along = np.abs(phase - height / 2.0) / (height / 2.0)
    body = np.clip(1.0 - np.maximum(across, along) ** 8, 0.0, 1.0) * (phase < height)
    rim = np.exp(-((np.maximum(across, along) - 0.93) / 0.05) ** 2) * (phase < height)
    attenuation = level * (body + 0.35 * rim)
    return ndimage.gaussian_filter(attenuation, 1.5).astype(np.float32), body > 0.2


def _pelvis(shape, iliac_ends: np.ndarray, px_mm: float, level: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Iliac wings: two broad plates below the bifurcation, each with a bright curved brim (a thin ridge)."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float32)
    attenuation = np.zeros(shape, dtype=np.float32)
    drawn = np.zeros(shape, dtype=bool)
    middle = float(np.mean(iliac_ends[:, 0]))
    for end in iliac_ends:
        outward = np.sign(end[0] - middle) or 1.0
        centre = end + np.array([outward * rng.uniform(25, 45), rng.uniform(-40, -10)]) * px_mm
        radii = np.array([rng.uniform(45, 60), rng.uniform(30, 45)]) * px_mm
        r = np.hypot((u - centre[0]) / radii[0], (v - centre[1]) / radii[1])
        plate = np.clip((1.0 - r) * 6.0, 0.0, 1.0)
        brim = np.exp(-((r - 1.0) * radii[1] / (1.2 * px_mm)) ** 2)
        attenuation += level * (plate + 0.6 * brim)
        drawn |= (plate > 0.2) | (brim > 0.3)
    return ndimage.gaussian_filter(attenuation, 1.0), drawn


def _box(shape, vessels_uv: np.ndarray, px_mm: float, level: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """The phantom's box: its side walls seen edge-on (strong straight lines) around the vessels."""
    lo, hi = vessels_uv.min(axis=0), vessels_uv.max(axis=0)
    margin = rng.uniform(15, 35, size=4) * px_mm
    u0, v0, u1, v1 = lo[0] - margin[0], lo[1] - margin[1], hi[0] + margin[2], hi[1] + margin[3]
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1], [u0, v0]])
    walls = _polyline_coverage(shape, corners, rng.uniform(3, 5) * px_mm / 2)
    return level * walls, walls > 0.5


def _rail(shape, vessels_uv: np.ndarray, px_mm: float, level: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """A support rail of the phantom's frame: a straight plastic bar across the vessels."""
    lo, hi = vessels_uv.min(axis=0), vessels_uv.max(axis=0)
    row = rng.uniform(lo[1] + 0.3 * (hi[1] - lo[1]), lo[1] + 0.8 * (hi[1] - lo[1]))
    tilt = np.tan(np.radians(rng.uniform(-20, 20)))
    ends = np.array([[0.0, row - tilt * shape[1] / 2], [shape[1] - 1.0, row + tilt * shape[1] / 2]])
    bar = _polyline_coverage(shape, ends, rng.uniform(6, 10) * px_mm)
    return level * bar, bar > 0.5


def _table(shape, px_mm: float, level: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """The table's edge: a step in attenuation with a metal rail along it, near one side of the frame."""
    rows, cols = shape
    vertical = rng.random() < 0.5
    n = cols if vertical else rows
    position = rng.uniform(0.8, 0.92) * n if rng.random() < 0.5 else rng.uniform(0.08, 0.2) * n
    coord = np.arange(n, dtype=np.float32)
    beyond = coord > position if position > n / 2 else coord < position
    profile = level * beyond + 2.0 * level * np.exp(-((coord - position) / (1.5 * px_mm)) ** 2)
    attenuation = np.broadcast_to(profile[None, :] if vertical else profile[:, None], shape).astype(np.float32)
    drawn = np.zeros(shape, dtype=bool)
    strip = slice(int(position) - 3, int(position) + 4)
    drawn[(slice(None), strip) if vertical else (strip, slice(None))] = True
    return attenuation, drawn


def _collimator(shape, rng) -> tuple[np.ndarray, np.ndarray]:
    """Exposure factor of the collimator's shutters (two sides, blurred penumbra) and the shutter edges."""
    rows, cols = shape
    exposure = np.ones(shape, dtype=np.float32)
    edges = np.zeros(shape, dtype=bool)
    for side in rng.choice(["top", "bottom", "left", "right"], size=2, replace=False):
        depth = int(rng.uniform(0.03, 0.08) * (rows if side in ("top", "bottom") else cols))
        band = np.zeros(shape, dtype=np.float32)
        index = {"top": (slice(0, depth), slice(None)), "bottom": (slice(rows - depth, rows), slice(None)),
                 "left": (slice(None), slice(0, depth)), "right": (slice(None), slice(cols - depth, cols))}[side]
        band[index] = 1.0
        exposure *= 1.0 - 0.92 * ndimage.gaussian_filter(band, 2.0)
        edge = ndimage.binary_dilation(band > 0, iterations=3) & ~ndimage.binary_erosion(band > 0, iterations=3)
        edges |= edge & (ndimage.binary_dilation(band == 0, iterations=4))
    return exposure, edges


def _exposure_field(shape, rng) -> np.ndarray:
    """Heel effect (a linear fall-off along a random direction) and vignetting."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float32)
    angle = rng.uniform(0, 2 * np.pi)
    along = ((u - cols / 2) * np.cos(angle) + (v - rows / 2) * np.sin(angle)) / max(shape)
    radial2 = ((u - cols / 2) ** 2 + (v - rows / 2) ** 2) / (0.5 * max(shape)) ** 2
    return (1.0 + rng.uniform(0.25, 0.4) * along) * (1.0 - 0.15 * radial2)


def _wire_path(case, px_mm: float) -> np.ndarray:
    """A guide wire from outside the frame up the right iliac into the aorta (u, v)."""
    aorta = project(case.P_true, case.intraop.vessels["aorta"].points)
    iliac = project(case.P_true, case.intraop.vessels["iliac_right"].points)
    out = (iliac[-1] - iliac[-8]) / max(np.linalg.norm(iliac[-1] - iliac[-8]), 1e-9)
    return np.vstack([iliac[-1] + 80 * px_mm * out, iliac[::-1][::4], aorta[::-1][::6][: len(aorta) // 12]])


def _catheter_path(case, px_mm: float, rng) -> np.ndarray:
    """A straight-ish catheter crossing the renal level at a slant, beside the aorta."""
    aorta = project(case.P_true, case.intraop.vessels["aorta"].points)
    renal = project(case.P_true, case.intraop.vessels["renal_left"].points)
    centre = renal[len(renal) // 2] + np.array([0.0, rng.uniform(15, 30) * px_mm])
    direction = np.array([np.sin(np.radians(rng.uniform(15, 40))), np.cos(np.radians(rng.uniform(15, 40)))])
    reach = 0.6 * float(np.ptp(aorta[:, 1]))
    bend = np.linspace(-1, 1, 30)
    return centre + reach * bend[:, None] * direction + (8 * px_mm * bend ** 2)[:, None] * direction[::-1]


def _ruler(shape, vessels_uv: np.ndarray, px_mm: float, level: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """A radio-opaque ruler under the phantom: a bar with a tick every 10 mm, across the iliacs."""
    rows, cols = shape
    row = float(np.clip(vessels_uv[:, 1].max() - rng.uniform(10, 40) * px_mm, 0, rows - 1))
    u0, u1 = 0.15 * cols, 0.85 * cols
    lines = [np.array([[u0, row], [u1, row]])]
    for k, u in enumerate(np.arange(u0, u1, 10 * px_mm)):
        lines.append(np.array([[u, row], [u, row - (8 if k % 5 == 0 else 4) * px_mm]]))
    coverage = np.max([_polyline_coverage(shape, line, 1.2 * px_mm) for line in lines], axis=0)
    return level * coverage, coverage > 0.5


def _text(shape, rng) -> np.ndarray:
    """Burned-in annotation (patient side, time, frame rate, a scale) in the corners."""
    from PIL import Image, ImageDraw

    rows, cols = shape
    canvas = Image.new("L", (cols, rows), 0)
    draw = ImageDraw.Draw(canvas)
    draw.text((0.06 * cols + 12, 0.06 * rows + 8), "L", fill=255)
    draw.text((cols - 170, 0.06 * rows + 8), f"{rng.integers(8, 18)}:{rng.integers(10, 59)}:21  15 fps", fill=255)
    draw.text((0.06 * cols + 12, rows - 0.1 * rows), "PHANTOM  AP  0/0  80 kV", fill=255)
    return np.asarray(canvas) > 0


def render_bench_frame(case, rng: np.random.Generator, *, subtracted: bool = False, polarity: str = "dark",
                       distractors=DISTRACTORS, contrast: bool = True, spine_offset_mm: float | None = None,
                       spine_gain: float | None = None) -> BenchFrame:
    """A fluoroscopy frame of ``case``'s intra-operative vessels seen through ``P_true``, with distractors.

    Parameters
    ----------
    case : PhantomCase
    rng : numpy.random.Generator
        Every random choice (placement, levels, noise).
    subtracted : bool
        DSA: only the iodine and the distractors of :data:`SURVIVE_SUBTRACTION`.
    polarity : {'dark', 'bright'}
        Vessels dark (MONOCHROME2 as displayed) or bright (the grey scale inverted).
    distractors : iterable of str
        Which of :data:`DISTRACTORS` to draw.
    contrast : bool
        False: the same frame without iodine (a frame before the bolus, or no angiogram).
    spine_offset_mm : float, optional
        The vertebral column's centre this far (signed, mm along +u) from the aorta's projection
        instead of 8-20 mm to a random side: near 0, the aorta lies over the vertebral bodies
        (an oblique view of a patient, RAO 30 on the real CT of ``bench_real_drr.py``).
    spine_gain : float, optional
        The vertebral bodies' attenuation as this multiple of the aorta's centre-line iodine
        instead of 0.5-1.0 (in a patient's radiograph about 3-6: the aorta's iodine is 6-7 mm
        of water-equivalent, a vertebral body some 20-40 mm).

    Neither option changes a random draw: the frame is the default one with only the spine moved
    or made denser.

    Returns
    -------
    BenchFrame
    """
    unknown = set(distractors) - set(DISTRACTORS)
    if unknown or polarity not in ("dark", "bright"):
        raise ValueError(f"unknown distractors {sorted(unknown)} or polarity {polarity!r}")
    drawn = [d for d in DISTRACTORS if d in distractors and (not subtracted or d in SURVIVE_SUBTRACTION)]
    shape = (case.carm.rows, case.carm.cols)
    lumen, path = _project_tubes(case.intraop, case.P_true, shape)
    mu = case.params.fluoro_attenuation_per_mm
    iodine = mu * ndimage.gaussian_filter(path, 0.7) if contrast else np.zeros(shape, np.float32)
    aorta_level = mu * 2.0 * float(np.median(case.intraop.vessels["aorta"].radius))
    px_mm = float(np.median(pixels_per_mm(case.P_true, case.intraop.vessels["aorta"].points)))
    vessels_uv = np.vstack([project(case.P_true, v.points) for v in case.intraop.vessels.values()])
    aorta_uv = project(case.P_true, case.intraop.vessels["aorta"].points)
    iliac_ends = np.array([project(case.P_true, case.intraop.vessels[name].points)[-1]
                           for name in ("iliac_left", "iliac_right")])
    attenuation = iodine.astype(np.float32)
    exposure = np.ones(shape, dtype=np.float32)
    parts = {}
    builders = {
        "spine": lambda: _spine(shape, aorta_uv, px_mm, _given_or(spine_gain, rng.uniform(0.5, 1.0)) * aorta_level,
                                rng, spine_offset_mm),
        "pelvis": lambda: _pelvis(shape, iliac_ends, px_mm, rng.uniform(0.3, 0.6) * aorta_level, rng),
        "box": lambda: _box(shape, vessels_uv, px_mm, rng.uniform(0.6, 1.2) * aorta_level, rng),
        "rail": lambda: _rail(shape, vessels_uv, px_mm, rng.uniform(0.15, 0.35) * aorta_level, rng),
        "table": lambda: _table(shape, px_mm, rng.uniform(0.15, 0.3) * aorta_level, rng),
        "ruler": lambda: _ruler(shape, vessels_uv, px_mm, rng.uniform(0.6, 1.0) * aorta_level, rng),
    }
    for name in drawn:
        if name in builders:
            added, parts[name] = builders[name]()
            attenuation += added
    for name, points, width, level in (("wire", lambda: _wire_path(case, px_mm), 0.9, 1.0),
                                       ("catheter", lambda: _catheter_path(case, px_mm, rng), 2.0, 0.5),
                                       ("sheath", lambda: _wire_path(case, px_mm)[:6], 3.0, 0.25)):
        if name in drawn:
            chord = _tube_chord(shape, points(), width * px_mm / 2.0)
            attenuation += level * aorta_level * chord / max(float(chord.max()), 1e-9)
            parts[name] = chord > 0.5
    if "exposure" in drawn:
        exposure *= _exposure_field(shape, rng)
    if "collimator" in drawn:
        shutters, parts["collimator"] = _collimator(shape, rng)
        exposure *= shutters
    background = 0.62 * _FLUORO_FULL_SCALE * exposure
    signal = background * np.exp(-attenuation)
    noise = rng.normal(size=shape) * case.params.fluoro_noise * np.sqrt(signal * float(background.mean()))
    frame = np.clip(signal + noise, 0, _FLUORO_FULL_SCALE)
    if polarity == "bright":
        frame = _FLUORO_FULL_SCALE - frame
    if "text" in drawn:
        parts["text"] = _text(shape, rng)
        frame[parts["text"]] = _FLUORO_FULL_SCALE
        parts["text"] = ndimage.binary_dilation(parts["text"], iterations=2)
    mask = lumen if contrast else np.zeros(shape, dtype=bool)
    return BenchFrame(np.rint(frame).astype(np.uint16), mask, parts)


def _given_or(given: float | None, drawn: float) -> float:
    """``given`` when not None, else the random ``drawn`` (drawn either way, so that the random
    stream is the same)."""
    return drawn if given is None else float(given)


def bench_case(seed: int, **case_kwargs):
    """A random phantom case (``random_params`` of ``seed``; ``case_kwargs`` replace its parameters)."""
    from .case import generate_case
    from .params import random_params

    params = random_params(np.random.default_rng(seed))
    return generate_case(replace(params, **case_kwargs) if case_kwargs else params)

"""Synthetic axial CT slices for training the lumen UNet to generalise (SynthSeg-style).

SynthSeg (Billot et al., 2023) trains on label maps whose tissues get random intensities,
resolutions and artefacts at every draw, so that the network cannot lean on any one scanner's
look. Here the label maps are drawn too: a body slice at one of five levels (chest,
upper abdomen, renal, infrarenal, iliac), with the structures that look like a contrast
lumen in a real scan: the heart and pulmonary vessels, ribs, vertebrae and pelvic bones,
kidneys with their arteries and veins, the IVC, liver and spleen, bowel with or without oral
contrast, calcified plaque, stent struts, mural thrombus of an aneurysm, a dissection flap.
Each class then gets a random mean HU from a wide range (contrast timing moves the veins
and organs from barely to fully enhanced), a smooth texture, and the slice a random blur
(slice thickness, kernel), pixel size, bias field and noise.

The label is the arterial lumen the pipeline wants: the aorta (both channels of a dissection,
the lumen inside a stent, not the thrombus), the common iliac arteries and the renal arteries.
Slices are in LPS orientation (rows to posterior, columns to the patient's left) at
:data:`~.unet.DEFAULT_PIXEL_MM`, in HU, as :class:`~.unet._SliceBank` hands them to training.

Train (the runs measured so far, none shipped, are in ``Resources/Models/README.md``)::

    python -m FevarPlannerLib.segmentation.synthetic --out synth_unet.pt --iterations 6000 --seed 0 \
        --crop 96 --init Resources/Models/aorta_unet.pt --cases CASE... --case-fraction 0.7
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch
from scipy import ndimage as ndi

from .unet import DEFAULT_NET_HU_WINDOW, DEFAULT_PIXEL_MM, _as_training_pairs, _SliceBank, _window, train_unet

#: Side (pixels = mm) of the square canvas a slice is drawn on before the crop.
CANVAS_MM = 224
#: Relative frequency of the body levels a slice is drawn at.
LEVELS = {"chest": 0.22, "upper_abdomen": 0.2, "renal": 0.24, "infrarenal": 0.18, "iliac": 0.16}
#: Range (low, high) of each tissue's mean HU; a draw picks one value per slice.
TISSUE_HU = {
    "air": (-1000.0, -950.0), "fat": (-130.0, -60.0), "muscle": (20.0, 75.0), "lung": (-920.0, -720.0),
    "liver": (40.0, 190.0), "spleen": (40.0, 220.0), "kidney_medulla": (30.0, 220.0),
    "cancellous": (100.0, 350.0), "cortical": (450.0, 1500.0), "thrombus": (15.0, 90.0),
    "calcium": (450.0, 1600.0), "strut": (1200.0, 3000.0), "bowel_wall": (20.0, 160.0), "flap": (30.0, 160.0),
    "disc": (50.0, 130.0),
}


class _Canvas:
    """A tissue label map (int codes) on a square mm grid, painted shape by shape."""

    def __init__(self, size: int):
        self.size = size
        half = size / 2.0
        self.y, self.x = np.mgrid[0:size, 0:size].astype(np.float32) - half
        self.tissue = np.zeros((size, size), dtype=np.int16)
        self.lumen = np.zeros((size, size), dtype=bool)
        self.names = ["air"]

    def code(self, name: str) -> int:
        """The integer code of tissue ``name`` (added on first use)."""
        if name not in self.names:
            self.names.append(name)
        return self.names.index(name)

    def _box(self, lo_x, hi_x, lo_y, hi_y) -> tuple[slice, slice]:
        """Index box (rows, cols) of the canvas holding the mm box, clipped."""
        half = self.size / 2.0

        def span(lo, hi) -> slice:
            return slice(int(min(max(math.floor(lo) + half, 0), self.size)),
                         int(min(max(math.ceil(hi) + 1 + half, 0), self.size)))

        return span(lo_y, hi_y), span(lo_x, hi_x)

    def ellipse(self, cx, cy, ax, ay, angle=0.0) -> np.ndarray:
        """Pixels inside the ellipse of centre (cx, cy), semi-axes (ax, ay), turned by ``angle``."""
        out = np.zeros((self.size, self.size), dtype=bool)
        reach = max(ax, ay)
        box = self._box(cx - reach, cx + reach, cy - reach, cy + reach)
        x, y = self.x[box] - cx, self.y[box] - cy
        c, s = math.cos(angle), math.sin(angle)
        out[box] = ((x * c + y * s) / ax) ** 2 + ((y * c - x * s) / ay) ** 2 <= 1.0
        return out

    def capsule(self, p0, p1, radius) -> np.ndarray:
        """Pixels within ``radius`` of the segment ``p0`` -> ``p1`` (an in-plane vessel)."""
        p0, p1 = np.asarray(p0, dtype=np.float32), np.asarray(p1, dtype=np.float32)
        out = np.zeros((self.size, self.size), dtype=bool)
        box = self._box(min(p0[0], p1[0]) - radius, max(p0[0], p1[0]) + radius,
                        min(p0[1], p1[1]) - radius, max(p0[1], p1[1]) + radius)
        x, y = self.x[box] - p0[0], self.y[box] - p0[1]
        d = p1 - p0
        t = np.clip((x * d[0] + y * d[1]) / max(float(d @ d), 1e-6), 0.0, 1.0)
        out[box] = np.hypot(x - t * d[0], y - t * d[1]) <= radius
        return out

    def paint(self, region: np.ndarray, name: str, lumen: bool | None = None) -> None:
        """Set ``region`` to tissue ``name``; ``lumen`` True / False sets / clears the label there."""
        self.tissue[region] = self.code(name)
        if lumen is not None:
            self.lumen[region] = lumen


class SyntheticSlices:
    """Random labelled axial slices; ``sample`` has the signature of the case slice bank.

    Parameters
    ----------
    canvas_mm : int
        Side of the drawing canvas (1 mm pixels).
    """

    def __init__(self, canvas_mm: int = CANVAS_MM):
        self.canvas_mm = canvas_mm

    def draw(self, rng: np.random.Generator, level: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One slice: (HU image float32, lumen label bool), both ``canvas_mm`` square."""
        level = level or rng.choice(list(LEVELS), p=np.array(list(LEVELS.values())) / sum(LEVELS.values()))
        canvas = _Canvas(self.canvas_mm)
        body = _draw_body(canvas, rng, level)
        _LEVEL_DRAWERS[level](canvas, rng, body)
        image = _intensities(canvas, rng)
        return _degrade(image, rng), canvas.lumen.copy()

    def sample(self, rng: np.random.Generator, crop: int, hu_window) -> tuple[torch.Tensor, torch.Tensor]:
        """One training pair: a random ``crop`` window of a fresh slice, HU-windowed (as the bank's)."""
        image, label = self.draw(rng)
        top, left = _crop_origin(rng, label, crop)
        image = image[top:top + crop, left:left + crop]
        label = label[top:top + crop, left:left + crop]
        x = _window(torch.from_numpy(np.ascontiguousarray(image)), hu_window)
        return x[None, None].float(), torch.from_numpy(np.ascontiguousarray(label))[None].long()


class MixedSlices:
    """Draws each training pair from one of several slice sources (``sample`` as the bank's).

    Parameters
    ----------
    sources : list
        Objects with ``sample(rng, crop, hu_window)``: :class:`SyntheticSlices`, a case bank.
    weights : list of float
        Relative frequency of each source.
    """

    def __init__(self, sources, weights):
        if len(sources) != len(weights) or not sources:
            raise ValueError(f"{len(sources)} sources for {len(weights)} weights")
        self.sources = list(sources)
        self.weights = np.asarray(weights, dtype=float) / float(np.sum(weights))

    def sample(self, rng: np.random.Generator, crop: int, hu_window):
        source = self.sources[int(rng.choice(len(self.sources), p=self.weights))]
        return source.sample(rng, crop, hu_window)


def _crop_origin(rng, label: np.ndarray, crop: int) -> tuple[int, int]:
    """A crop that holds lumen four times in five (at a random offset), else anywhere."""
    size = label.shape[0]
    if label.any() and rng.random() < 0.8:
        rows, cols = np.nonzero(label)
        pick = rng.integers(len(rows))
        centre = np.array([rows[pick], cols[pick]]) + rng.integers(-crop // 3, crop // 3 + 1, size=2)
    else:
        centre = rng.integers(0, size, size=2)
    return tuple(int(np.clip(c - crop // 2, 0, size - crop)) for c in centre)


# ----------------------------------------------------------------------------------------
# Anatomy: the body, then what each level holds
# ----------------------------------------------------------------------------------------

def _draw_body(canvas: _Canvas, rng, level: str) -> dict:
    """Body outline, fat, muscle wall, vertebra; returns the landmarks the levels build on."""
    ax, ay = rng.uniform(95, 165), rng.uniform(75, 120)
    cx, cy = rng.uniform(-15, 15), rng.uniform(-10, 10)
    fat = rng.uniform(4, 35)
    canvas.paint(canvas.ellipse(cx, cy, ax, ay), "fat")
    canvas.paint(canvas.ellipse(cx, cy, ax - fat, ay - fat), "muscle")
    canvas.paint(canvas.ellipse(cx, cy, ax - fat - rng.uniform(6, 15), ay - fat - rng.uniform(6, 15)), "visceral_fat")
    vr = rng.uniform(13, 22)
    spine = np.array([cx + rng.uniform(-4, 4), cy + ay - fat - rng.uniform(35, 55) - vr])
    _vertebra(canvas, rng, spine, vr, level)
    aorta_r = rng.uniform(7.0, 14.0)
    aneurysm = level in ("infrarenal", "renal") and rng.random() < 0.3
    outer_r = rng.uniform(18, 38) if aneurysm else aorta_r
    aorta = np.array([spine[0] + rng.uniform(0, 22), spine[1] - vr - outer_r - rng.uniform(1, 8)])
    return {"centre": (cx, cy), "axes": (ax, ay), "fat": fat, "spine": spine, "vr": vr, "aorta": aorta,
            "aorta_r": aorta_r, "outer_r": outer_r, "aneurysm": aneurysm}


def _vertebra(canvas: _Canvas, rng, centre, radius: float, level: str) -> None:
    """Vertebral body (cortex around cancellous bone) or, in about a quarter of the slices, an
    intervertebral disc (soft tissue, no cortex); posterior elements."""
    cortex = rng.uniform(1.0, 3.5)
    squash = rng.uniform(0.8, 1.0)
    if rng.random() < 0.25:
        canvas.paint(canvas.ellipse(*centre, radius * 1.1, radius * squash), "disc")
    else:
        canvas.paint(canvas.ellipse(*centre, radius * 1.1, radius * squash), "cortical")
        canvas.paint(canvas.ellipse(*centre, radius * 1.1 - cortex, radius * squash - cortex), "cancellous")
    back = centre + np.array([0.0, radius + rng.uniform(8, 14)])
    canvas.paint(canvas.ellipse(*back, 7, 6) & ~canvas.ellipse(*back, 4.5, 3.5), "cortical")    # canal ring
    canvas.paint(canvas.ellipse(*back, 4.5, 3.5), "muscle")
    canvas.paint(canvas.capsule(back + [0, 5], back + [rng.uniform(-3, 3), rng.uniform(18, 30)], rng.uniform(2, 4)),
                 "cortical")
    for side in (-1, 1):
        tip = back + np.array([side * rng.uniform(18, 35), rng.uniform(-6, 6)])
        canvas.paint(canvas.capsule(back, tip, rng.uniform(2, 4)), "cortical")
        if level not in ("chest", "iliac"):
            canvas.paint(canvas.ellipse(centre[0] + side * (radius + rng.uniform(12, 20)),
                                        centre[1] + rng.uniform(-4, 8), rng.uniform(8, 15), rng.uniform(10, 18)),
                         "muscle")                                                             # psoas


def _aorta(canvas: _Canvas, rng, body: dict) -> None:
    """The aortic lumen (label), with thrombus, calcified plaque, a stent or a dissection flap."""
    centre, r, outer = body["aorta"], body["aorta_r"], body["outer_r"]
    if rng.random() < 0.5:                                                       # periaortic fat
        fat = outer + rng.uniform(2, 9)
        canvas.paint(canvas.ellipse(*centre, fat, fat * rng.uniform(0.85, 1.0)), "fat", lumen=False)
    if body["aneurysm"]:
        canvas.paint(canvas.ellipse(*centre, outer, outer * rng.uniform(0.85, 1.0)), "thrombus", lumen=False)
        centre = centre + rng.uniform(-1, 1, size=2) * max(outer - r - 2, 0)      # eccentric lumen
    squash, angle = rng.uniform(0.75, 1.0), rng.uniform(0, math.pi)
    lumen = canvas.ellipse(*centre, r, r * squash, angle)
    canvas.paint(lumen, "lumen", lumen=True)
    if rng.random() < 0.1:                                                       # dissection: a flap, two channels
        direction = rng.normal(size=2)
        direction /= np.linalg.norm(direction)
        flap = canvas.capsule(centre - direction * r, centre + direction * r, rng.uniform(0.6, 1.2)) & lumen
        side = ((canvas.x - centre[0]) * direction[1] - (canvas.y - centre[1]) * direction[0]) > 0
        canvas.paint(lumen & side & ~flap, "false_lumen", lumen=True)
        canvas.paint(flap, "flap", lumen=True)
    if rng.random() < 0.4:                                                       # calcified plaque on the wall
        wall = body["outer_r"] if body["aneurysm"] else r
        for _ in range(rng.integers(1, 5)):
            a = rng.uniform(0, 2 * math.pi)
            spot = body["aorta"] + (wall + rng.uniform(0.0, 1.5)) * np.array([math.cos(a), math.sin(a)])
            canvas.paint(canvas.ellipse(*spot, rng.uniform(1, 3), rng.uniform(0.8, 2), a), "calcium", lumen=False)
    if rng.random() < 0.12:                                                      # stent struts inside the lumen
        n = rng.integers(8, 20)
        for a in np.linspace(0, 2 * math.pi, n, endpoint=False) + rng.uniform(0, 1):
            spot = centre + (r - 0.8) * np.array([math.cos(a), math.sin(a) * squash])
            canvas.paint(canvas.ellipse(*spot, 0.7, 0.7), "strut", lumen=True)


def _ivc(canvas: _Canvas, rng, body: dict) -> np.ndarray:
    spine = body["spine"]
    ivc = np.array([spine[0] - rng.uniform(18, 40), spine[1] - body["vr"] - rng.uniform(6, 20)])
    canvas.paint(canvas.ellipse(*ivc, rng.uniform(7, 16), rng.uniform(5, 12), rng.uniform(0, 1)), "vein",
                 lumen=False)
    return ivc


def _bowel(canvas: _Canvas, rng, body: dict, n_range=(3, 10), keep_out=()) -> None:
    """Bowel loops: a wall around air, fluid or positive oral contrast (as bright as the lumen)."""
    cx, cy = body["centre"]
    ax, ay = body["axes"]
    contents = ["bowel_air", "bowel_fluid", "bowel_contrast"]
    weights = [0.35, 0.35, 0.3]
    for _ in range(rng.integers(*n_range)):
        centre = np.array([cx + rng.uniform(-0.6, 0.6) * ax, cy + rng.uniform(-0.75, 0.1) * ay])
        if any(np.linalg.norm(centre - p) < r for p, r in keep_out):
            continue
        a, b = rng.uniform(6, 22), rng.uniform(5, 16)
        angle = rng.uniform(0, math.pi)
        canvas.paint(canvas.ellipse(*centre, a, b, angle) & (canvas.tissue == canvas.code("visceral_fat")),
                     "bowel_wall")
        inner = canvas.ellipse(*centre, a - 2, b - 2, angle) & (canvas.tissue == canvas.code("bowel_wall"))
        canvas.paint(inner, str(rng.choice(contents, p=weights)))


def _kidney(canvas: _Canvas, rng, body: dict, side: int, hilum_vessels: bool, ivc=None) -> None:
    """Kidney (cortex and medulla) beside the spine; at the hilum its artery (label) from the aorta and its vein."""
    spine, vr = body["spine"], body["vr"]
    centre = np.array([spine[0] + side * rng.uniform(55, 85), spine[1] + rng.uniform(-15, 10)])
    a, b, angle = rng.uniform(22, 35), rng.uniform(15, 25), side * rng.uniform(0.3, 1.0)
    canvas.paint(canvas.ellipse(*centre, a, b, angle), "kidney_cortex")
    canvas.paint(canvas.ellipse(*centre, a * 0.6, b * 0.5, angle), "kidney_medulla")
    if not hilum_vessels:
        return
    hilum = centre - side * np.array([a * 0.6, 0.0])
    aorta, r = body["aorta"], body["aorta_r"]
    origin = aorta + np.array([side * r * 0.8, rng.uniform(-0.5, 0.5) * r])
    vein_end = ivc if (side < 0 and ivc is not None) else None
    if vein_end is not None or side > 0:
        # the left renal vein crosses in front of the aorta to the IVC; the right one is short
        target = vein_end if vein_end is not None else aorta + np.array([-rng.uniform(20, 40), -r - rng.uniform(4, 9)])
        via = aorta + np.array([0.0, -r - rng.uniform(3, 8)]) if side > 0 else hilum
        vein_r = rng.uniform(3, 6)
        canvas.paint(canvas.capsule(hilum + [0, -4], via, vein_r), "renal_vein", lumen=False)
        canvas.paint(canvas.capsule(via, target, vein_r), "renal_vein", lumen=False)
    if rng.random() < 0.85:
        canvas.paint(canvas.capsule(origin, hilum + rng.uniform(-4, 4, size=2), rng.uniform(2.0, 3.8)), "lumen",
                     lumen=True)


def _level_chest(canvas: _Canvas, rng, body: dict) -> None:
    """Lungs with bright pulmonary vessels, the heart (chambers as bright as the aorta), ribs and
    sternum; ascending and descending aorta (label)."""
    cx, cy = body["centre"]
    ax, ay = body["axes"]
    inner_ax, inner_ay = ax - body["fat"] - 10, ay - body["fat"] - 10
    for side in (-1, 1):
        canvas.paint(canvas.ellipse(cx + side * inner_ax * 0.5, cy, inner_ax * 0.48, inner_ay * 0.9), "lung")
    spine, vr = body["spine"], body["vr"]
    front, back = cy - ay + body["fat"] + 8, spine[1] - vr - 4           # between the chest wall and the spine
    hr = min(rng.uniform(35, 60), 0.55 * (back - front))
    heart = np.array([cx + rng.uniform(0, 25), 0.5 * (front + back) + rng.uniform(-0.1, 0.1) * hr])
    canvas.paint(canvas.ellipse(*heart, hr, hr * rng.uniform(0.7, 0.95), rng.uniform(0, 1)), "myocardium")
    for name, shift in (("heart_left", 1), ("heart_right", -1)):
        chamber = heart + np.array([shift * hr * 0.3, rng.uniform(-8, 8)])
        canvas.paint(canvas.ellipse(*chamber, hr * 0.35, hr * 0.45, rng.uniform(0, 1)), name)
    descending = spine + np.array([0.6 * vr + body["aorta_r"] + rng.uniform(0, 6), -rng.uniform(0.5, 1.0) * vr])
    body["aorta"] = descending
    _aorta(canvas, rng, body)
    if rng.random() < 0.7:                       # ascending aorta above the heart's middle, with the pulmonary trunk
        ascending = heart + np.array([-rng.uniform(5, 25), -hr * rng.uniform(0.3, 0.8)])
        r = body["aorta_r"] * rng.uniform(1.1, 1.6)
        canvas.paint(canvas.ellipse(*ascending, r, r), "lumen", lumen=True)
        trunk = ascending + np.array([rng.uniform(20, 35), rng.uniform(-10, 5)])
        canvas.paint(canvas.ellipse(*trunk, r * 0.9, r * 0.8) & ~canvas.lumen, "pulmonary", lumen=False)
    lung = canvas.tissue == canvas.code("lung")
    rows, cols = np.nonzero(lung)
    for _ in range(rng.integers(10, 40)):        # pulmonary vessels: dots and short tubes
        pick = rng.integers(len(rows))
        p0 = np.array([cols[pick], rows[pick]], dtype=float) - canvas.size / 2
        p1 = p0 + rng.normal(0, 8, size=2) * (rng.random() < 0.5)
        canvas.paint(canvas.capsule(p0, p1, rng.uniform(1.0, 5.0)) & lung, "pulmonary", lumen=False)
    for a in np.linspace(0.15 * math.pi, 0.85 * math.pi, rng.integers(6, 10)):   # ribs at the body wall
        for side in (-1, 1):
            p = np.array([cx + side * (ax - body["fat"] - 5) * math.cos(a - math.pi / 2) * 0.98,
                          cy - (ay - body["fat"] - 5) * math.sin(a - math.pi / 2) * 0.9])
            canvas.paint(canvas.ellipse(*p, rng.uniform(3, 6), rng.uniform(2, 4), a), "cortical")
    canvas.paint(canvas.ellipse(cx, cy - ay + body["fat"] + 6, rng.uniform(10, 18), rng.uniform(4, 7)), "cortical")


def _level_upper_abdomen(canvas: _Canvas, rng, body: dict) -> None:
    """Liver with the portal vein, spleen, stomach, the coeliac trunk / SMA (arteries, not labelled)."""
    cx, cy = body["centre"]
    ax, ay = body["axes"]
    inner = ax - body["fat"] - 10
    canvas.paint(canvas.ellipse(cx - inner * 0.45, cy - 5, inner * 0.55, (ay - body["fat"]) * 0.75), "liver")
    canvas.paint(canvas.ellipse(cx + inner * 0.6, cy + rng.uniform(5, 30), inner * 0.25, 30), "spleen")
    for _ in range(rng.integers(2, 7)):          # portal and hepatic veins inside the liver
        p = np.array([cx - inner * rng.uniform(0.2, 0.7), cy + rng.uniform(-40, 30)])
        canvas.paint(canvas.capsule(p, p + rng.normal(0, 10, size=2), rng.uniform(2, 7)), "portal_vein")
    _ivc(canvas, rng, body)
    _aorta(canvas, rng, body)
    branch = body["aorta"] + np.array([rng.uniform(-5, 5), -body["aorta_r"] - rng.uniform(6, 25)])
    canvas.paint(canvas.ellipse(*branch, rng.uniform(3, 5), rng.uniform(3, 5)), "lumen", lumen=False)
    _bowel(canvas, rng, body, (1, 5), keep_out=[(body["aorta"], body["outer_r"] + 5)])
    if rng.random() < 0.5:
        _kidney(canvas, rng, body, 1, hilum_vessels=False)


def _level_renal(canvas: _Canvas, rng, body: dict) -> None:
    """Kidneys, renal arteries (label) and veins, IVC, SMA (not labelled), bowel."""
    ivc = _ivc(canvas, rng, body)
    for side in (-1, 1):
        _kidney(canvas, rng, body, side, hilum_vessels=rng.random() < 0.7, ivc=ivc)
    _aorta(canvas, rng, body)
    sma = body["aorta"] + np.array([rng.uniform(-3, 8), -body["outer_r"] - rng.uniform(8, 20)])
    canvas.paint(canvas.ellipse(*sma, rng.uniform(2.5, 4.5), rng.uniform(2.5, 4.5)), "lumen", lumen=False)
    _bowel(canvas, rng, body, (2, 8), keep_out=[(body["aorta"], body["outer_r"] + 6)])


def _level_infrarenal(canvas: _Canvas, rng, body: dict) -> None:
    """Aorta (often aneurysmal with thrombus), IVC, bowel loops, lower kidney poles."""
    _ivc(canvas, rng, body)
    for side in (-1, 1):
        if rng.random() < 0.4:
            _kidney(canvas, rng, body, side, hilum_vessels=False)
    _aorta(canvas, rng, body)
    _bowel(canvas, rng, body, (4, 12), keep_out=[(body["aorta"], body["outer_r"] + 6)])


def _level_iliac(canvas: _Canvas, rng, body: dict) -> None:
    """Two common iliac arteries (label) and veins, the iliac wings, bowel; just below the
    aortic bifurcation (a third of these slices) the two lumens still touch."""
    spine, vr = body["spine"], body["vr"]
    cx, cy = body["centre"]
    ax = body["axes"][0] - body["fat"]
    near_split = rng.random() < 0.35
    for side in (-1, 1):
        wing = np.array([cx + side * ax * rng.uniform(0.55, 0.75), spine[1] + rng.uniform(-10, 10)])
        wa, wb, angle = rng.uniform(25, 45), rng.uniform(8, 14), side * rng.uniform(0.3, 0.9)
        canvas.paint(canvas.ellipse(*wing, wa, wb, angle), "cortical")
        canvas.paint(canvas.ellipse(*wing, wa - 3, wb - 3, angle), "cancellous")
        r = rng.uniform(4.0, 8.0) if rng.random() > 0.1 else rng.uniform(10, 16)      # iliac aneurysm, rarely
        spread = r * rng.uniform(0.6, 1.0) if near_split else rng.uniform(12, 35)
        artery = np.array([spine[0] + rng.uniform(0, 10) + side * spread, spine[1] - vr - rng.uniform(2, 15)])
        vein = artery + np.array([-side * rng.uniform(0, 10), rng.uniform(6, 14)])
        canvas.paint(canvas.ellipse(*vein, rng.uniform(6, 11), rng.uniform(5, 9)), "vein", lumen=False)
        canvas.paint(canvas.ellipse(*artery, r, r * rng.uniform(0.8, 1.0)), "lumen", lumen=True)
        if rng.random() < 0.3:
            a = rng.uniform(0, 2 * math.pi)
            spot = artery + r * np.array([math.cos(a), math.sin(a)])
            canvas.paint(canvas.ellipse(*spot, 1.5, 1.2), "calcium", lumen=False)
    _bowel(canvas, rng, body, (3, 10))


_LEVEL_DRAWERS = {"chest": _level_chest, "upper_abdomen": _level_upper_abdomen, "renal": _level_renal,
                  "infrarenal": _level_infrarenal, "iliac": _level_iliac}


# ----------------------------------------------------------------------------------------
# Appearance: per-tissue intensities (contrast timing), texture, blur, pixel size, bias, noise
# ----------------------------------------------------------------------------------------

def _tissue_means(rng) -> dict:
    """One mean HU per tissue for this slice; the contrast phase ties lumen, veins and organs."""
    lumen = rng.uniform(150, 650)
    phase = rng.uniform(0, 1)                    # 0 early arterial .. 1 portal venous
    means = {name: rng.uniform(*TISSUE_HU[name]) for name in TISSUE_HU}
    means.update({
        "lumen": lumen, "false_lumen": lumen * rng.uniform(0.4, 1.0),
        "vein": 40 + phase * rng.uniform(0.4, 1.1) * (lumen - 40),
        "renal_vein": 40 + max(phase, rng.uniform(0.3, 1)) * (lumen - 40) * rng.uniform(0.6, 1.1),
        "portal_vein": 40 + phase * (lumen - 40) * rng.uniform(0.5, 1.1),
        "kidney_cortex": 40 + rng.uniform(0.4, 1.0) * (lumen - 40),
        "heart_left": lumen * rng.uniform(0.8, 1.15), "heart_right": lumen * rng.uniform(0.3, 1.4),
        "pulmonary": lumen * rng.uniform(0.5, 1.3), "myocardium": rng.uniform(60, 180),
        "visceral_fat": rng.uniform(-120, -40), "bowel_air": rng.uniform(-1000, -700),
        "bowel_fluid": rng.uniform(-10, 40), "bowel_contrast": rng.uniform(150, 900),
    })
    return means


def _smooth_noise(rng, shape, sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-variance Gaussian noise smoothed over ``sigma_px``."""
    field = ndi.gaussian_filter(rng.standard_normal(shape).astype(np.float32), sigma_px)
    return field / (field.std() + 1e-6)


def _low_frequency_field(rng, shape, cells: int = 4) -> np.ndarray:
    """A smooth zero-mean, unit-variance field varying over about a quarter of the image (bias)."""
    coarse = rng.standard_normal((cells, cells)).astype(np.float32)
    field = ndi.zoom(coarse, np.array(shape) / cells, order=3, mode="nearest")[:shape[0], :shape[1]]
    field = field - field.mean()
    return field / (field.std() + 1e-6)


def _intensities(canvas: _Canvas, rng) -> np.ndarray:
    """HU image of the tissue map: random means, per-tissue texture (a few HU to tens)."""
    means = _tissue_means(rng)
    lut = np.array([means.get(name, -1000.0) for name in canvas.names], dtype=np.float32)
    image = lut[canvas.tissue]
    texture = _smooth_noise(rng, image.shape, rng.uniform(0.8, 3.0))
    spread = np.array([0.0 if name == "air" else rng.uniform(3, 25) for name in canvas.names], dtype=np.float32)
    return image + texture * spread[canvas.tissue]


def _degrade(image: np.ndarray, rng) -> np.ndarray:
    """Blur (kernel and slice thickness), coarse pixels, bias field, noise."""
    image = ndi.gaussian_filter(image, rng.uniform(0.3, 1.4))
    factor = rng.uniform(1.0, 1.8)
    if factor > 1.1:                              # acquired at a coarser pixel, shown at 1 mm
        small = ndi.zoom(image, 1.0 / factor, order=1)
        image = ndi.zoom(small, np.array(image.shape) / np.array(small.shape), order=1)
    bias = 1.0 + rng.uniform(0.0, 0.12) * _low_frequency_field(rng, image.shape)
    image = (image + 1000.0) * bias - 1000.0
    noise = _smooth_noise(rng, image.shape, rng.uniform(0.5, 1.2)) if rng.random() < 0.6 else \
        rng.standard_normal(image.shape).astype(np.float32)
    return (image + noise * rng.uniform(4, 45)).astype(np.float32)


def main(argv=None) -> None:
    """Train the UNet on synthetic slices only (see the module docstring)."""
    parser = argparse.ArgumentParser(description="train the CT lumen UNet on SynthSeg-style synthetic slices")
    parser.add_argument("--out", required=True)
    parser.add_argument("--iterations", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--crop", type=int, default=128)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--resume")
    parser.add_argument("--init", help="checkpoint whose weights start the run (fine-tuning)")
    parser.add_argument("--cases", nargs="*", default=[],
                        help="case folders (ct + aorta_mask) whose slices are mixed in")
    parser.add_argument("--case-fraction", type=float, default=0.5, help="share of steps drawn from --cases")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    source = SyntheticSlices()
    if args.cases:
        bank = _SliceBank(_as_training_pairs(args.cases), DEFAULT_PIXEL_MM)
        source = MixedSlices([source, bank], [1.0 - args.case_fraction, args.case_fraction])

    def report(done, total, message):
        if done % 500 == 0 or done == total:
            print(f"{done}/{total} {message}", flush=True)

    train_unet(source, args.out, iterations=args.iterations, seed=args.seed, crop=args.crop, lr=args.lr,
               resume=args.resume, init=args.init, progress=report, hu_window=DEFAULT_NET_HU_WINDOW)


if __name__ == "__main__":
    main()

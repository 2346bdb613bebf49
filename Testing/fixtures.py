"""Shared test fixtures: tiny literal skeletons with their exact structure, and the generators.

Tests import from here (``from fixtures import ...``; pytest puts ``Testing/`` on the path)
and benchmarks through ``benchmarks/common.py``. Four groups:

* **Literal skeletons**: 2D pixel arrays small enough to read, each with the graph that
  Definition 1 must build from it (nodes in row-major order, edges, degrees, weights), in the
  manner of skan's test fixtures.
* **Synthetic AAA masks**: tubes with hemispherical caps drawn from their exact distance to
  each axis segment, in 3D (LPS) and projected to 2D.
* **Polyline skeletons**: voxel lines on a 1 mm grid whose LPS position equals its index,
  with exact branch tips and lengths.
* **Registration cases**: C-arm views, a labelled AAA-like centreline tree deformed in the
  image plane with its dense 2D projection, and an arc bent along the X-rays.
* **Phantom cases**: the pipeline tests' AP phantom (:data:`PHANTOM_PARAMS` with changes), its
  pre-operative model, and a centreline projected and drawn as a 2D skeleton mask.
"""

import numpy as np
import pytest

from FevarPlannerLib import benchmark, phantom, pipeline
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.io import Volume
from FevarPlannerLib.projection import (CArmGeometry, carm_axes, project, projection_matrix_from_carm,
                                        source_position)

# ---------------------------------------------------------------------------------------
# Literal skeletons (2D, row-major node order) and the graph each must give
# ---------------------------------------------------------------------------------------

_ROOT2 = float(np.sqrt(2.0))

#: A Y: two diagonal arms meet a vertical stem at one junction of degree 3.
TINY_Y = np.array([
    [0, 0, 0, 0, 0, 0, 0],
    [0, 1, 0, 0, 0, 1, 0],
    [0, 0, 1, 0, 1, 0, 0],
    [0, 0, 0, 1, 0, 0, 0],
    [0, 0, 0, 1, 0, 0, 0],
    [0, 0, 0, 1, 0, 0, 0],
    [0, 0, 0, 0, 0, 0, 0],
], dtype=bool)
TINY_Y_GRAPH = {
    "positions": [[1, 1], [5, 1], [2, 2], [4, 2], [3, 3], [3, 4], [3, 5]],        # (u, v)
    "edges": [[0, 2], [1, 3], [2, 4], [3, 4], [4, 5], [5, 6]],
    "weights": [_ROOT2, _ROOT2, _ROOT2, _ROOT2, 1.0, 1.0],
    "degrees": [1, 1, 2, 2, 3, 2, 1],
}

#: A diamond: four pixels joined diagonally into one cycle, no end and no junction.
TINY_CYCLE = np.array([
    [0, 1, 0],
    [1, 0, 1],
    [0, 1, 0],
], dtype=bool)
TINY_CYCLE_GRAPH = {
    "positions": [[1, 0], [0, 1], [2, 1], [1, 2]],
    "edges": [[0, 1], [0, 2], [1, 3], [2, 3]],
    "weights": [_ROOT2] * 4,
    "degrees": [2, 2, 2, 2],
}

#: A staircase: 8-connectivity makes two corner triangles; pruning keeps the 4-connected path.
TINY_STAIRCASE = np.array([
    [1, 1, 0],
    [0, 1, 1],
], dtype=bool)
TINY_STAIRCASE_GRAPH = {
    "positions": [[0, 0], [1, 0], [1, 1], [2, 1]],
    "edges": [[0, 1], [1, 2], [2, 3]],
    "weights": [1.0, 1.0, 1.0],
    "degrees": [1, 2, 2, 1],
}
#: The same staircase without triangle pruning: both diagonals stay.
TINY_STAIRCASE_UNPRUNED_EDGES = [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]

LITERAL_SKELETONS = {"y": (TINY_Y, TINY_Y_GRAPH), "cycle": (TINY_CYCLE, TINY_CYCLE_GRAPH),
                     "staircase": (TINY_STAIRCASE, TINY_STAIRCASE_GRAPH)}


# ---------------------------------------------------------------------------------------
# Synthetic AAA: axis segments (start, end, radius) in LPS mm. +x = patient left,
# -y = anterior, +z = superior. Renals run exactly along x and iliacs at exactly 45 degrees
# in the x-z plane, so their digital skeletons have no staircase error.
# ---------------------------------------------------------------------------------------

TOP = np.array([0.0, 0.0, 100.0])
RENAL_LEFT_ORIGIN = np.array([0.0, 0.0, 60.0])
RENAL_RIGHT_ORIGIN = np.array([0.0, 0.0, 51.0])
BIFURCATION = np.array([0.0, 0.0, -30.0])
TIPS = {
    "aorta": TOP,
    "renal_left": np.array([40.0, 0.0, 60.0]),
    "renal_right": np.array([-40.0, 0.0, 51.0]),
    "iliac_left": np.array([45.0, 0.0, -75.0]),
    "iliac_right": np.array([-45.0, 0.0, -75.0]),
}
ORIGINS = {"aorta": RENAL_LEFT_ORIGIN, "renal_left": RENAL_LEFT_ORIGIN, "renal_right": RENAL_RIGHT_ORIGIN,
           "iliac_left": BIFURCATION, "iliac_right": BIFURCATION}
TRUE_LENGTHS = {name: float(np.linalg.norm(TIPS[name] - ORIGINS[name])) for name in TIPS}
SAC_CENTRE, SAC_RADIUS = np.array([0.0, 0.0, 12.0]), 22.0


def aaa_segments(extra_branches=False):
    """(start, end, radius) of the AAA tubes; extras: SMA and two internal iliacs."""
    segments = [
        (TOP, BIFURCATION, 10.0),
        (RENAL_LEFT_ORIGIN, TIPS["renal_left"], 3.5),
        (RENAL_RIGHT_ORIGIN, TIPS["renal_right"], 3.5),
        (BIFURCATION, TIPS["iliac_left"], 5.0),
        (BIFURCATION, TIPS["iliac_right"], 5.0),
    ]
    if extra_branches:
        segments += [
            (np.array([0.0, 0.0, 78.0]), np.array([0.0, -24.0, 78.0]), 3.0),        # SMA, anterior
            (np.array([27.0, 0.0, -57.0]), np.array([27.0, 18.0, -57.0]), 2.5),     # internal iliac L
            (np.array([-27.0, 0.0, -57.0]), np.array([-27.0, 18.0, -57.0]), 2.5),   # internal iliac R
        ]
    return segments


def draw_tubes(points, segments, sphere=None):
    """Boolean membership of ``points`` (..., d) in the union of capsules (and a ball)."""
    inside = np.zeros(points.shape[:-1], dtype=bool)
    for start, end, radius in segments:
        axis = end - start
        t = np.clip(((points - start) @ axis) / (axis @ axis), 0.0, 1.0)
        inside |= np.linalg.norm(points - start - t[..., None] * axis, axis=-1) <= radius
    if sphere is not None:
        centre, radius = sphere
        inside |= np.linalg.norm(points - centre, axis=-1) <= radius
    return inside


def aaa_grid(spacing=1.5):
    """An LPS-aligned grid around the synthetic AAA."""
    lo, hi = np.array([-60.0, -36.0, -90.0]), np.array([60.0, 36.0, 116.0])
    shape_ijk = np.floor((hi - lo) / spacing).astype(int) + 1
    return Volume(np.zeros(shape_ijk[::-1], dtype=np.uint8), [spacing] * 3, lo, np.eye(3))


def aaa_mask_3d(spacing=1.5, extra_branches=False, sac=True, cut=None):
    """The AAA lumen as a uint8 Volume; ``cut=(z_lo, z_hi, side)`` empties a slab of one iliac."""
    grid = aaa_grid(spacing)
    kji = np.indices(grid.shape).reshape(3, -1).T
    points = grid.index_to_lps(kji)
    mask = draw_tubes(points, aaa_segments(extra_branches), (SAC_CENTRE, SAC_RADIUS) if sac else None)
    if cut is not None:
        z_lo, z_hi, side = cut
        mask &= ~((points[:, 2] >= z_lo) & (points[:, 2] <= z_hi) & (np.sign(points[:, 0]) == side))
    return grid.with_array(mask.reshape(grid.shape).astype(np.uint8))


def aaa_mask_2d(P, shape, extra_branches=False, sac=True):
    """The AAA projected through ``P`` and drawn as a 2D mask (radii scaled by magnification)."""
    rows, cols = shape
    uv = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).astype(float)
    scale = np.linalg.norm(project(P, [1.0, 0, 0]) - project(P, [0.0, 0, 0]))
    segments = [(project(P, a), project(P, b), r * scale) for a, b, r in aaa_segments(extra_branches)]
    sphere = (project(P, SAC_CENTRE), SAC_RADIUS * scale) if sac else None
    return draw_tubes(uv, segments, sphere)


def y_mask_2d(shape=(120, 120), width=4.0):
    """A 2D Y: stem from (60, 110) up to (60, 60), arms to (20, 15) and (100, 15) as (u, v)."""
    rows, cols = shape
    uv = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).astype(float)
    fork = np.array([60.0, 60.0])
    segments = [(np.array([60.0, 110.0]), fork, width), (fork, np.array([20.0, 15.0]), width),
                (fork, np.array([100.0, 15.0]), width)]
    return draw_tubes(uv, segments)


# ---------------------------------------------------------------------------------------
# Polyline skeletons on a 1 mm grid whose LPS position equals its (i, j, k) index
# ---------------------------------------------------------------------------------------

GRID_SHAPE = (140, 12, 100)      # (k, j, i)
POLY_TOP, POLY_RL, POLY_RR, POLY_BIF = (50, 5, 130), (50, 5, 90), (50, 5, 84), (50, 5, 30)
POLY_TIPS = {"aorta": POLY_TOP, "renal_left": (85, 5, 90), "renal_right": (15, 5, 84),
             "iliac_left": (80, 5, 0), "iliac_right": (20, 5, 0)}
POLY_LENGTHS = {"aorta": 40.0, "renal_left": 35.0, "renal_right": 35.0,
                "iliac_left": 30 * np.sqrt(2), "iliac_right": 30 * np.sqrt(2)}
AAA_LINES = [(POLY_TOP, POLY_RL), (POLY_RL, POLY_TIPS["renal_left"]), (POLY_RL, POLY_RR),
             (POLY_RR, POLY_TIPS["renal_right"]), (POLY_RR, POLY_BIF), (POLY_BIF, POLY_TIPS["iliac_left"]),
             (POLY_BIF, POLY_TIPS["iliac_right"])]


def random_masks(seed: int, count: int):
    """Binary 2D masks of random shapes: blobs with holes (smoothed noise cut at a random level)
    and salt-and-pepper masks, for properties that must hold on any mask."""
    from scipy import ndimage as ndi

    rng = np.random.default_rng(seed)
    for k in range(count):
        shape = tuple(rng.integers(1, 70, size=2))
        if k % 3 == 0:
            yield rng.random(shape) < rng.uniform(0.2, 0.95)
        else:
            yield ndi.gaussian_filter(rng.random(shape), rng.uniform(0.5, 5.0)) > rng.uniform(0.4, 0.6)


def draw_lines(lines, erase=()):
    """A skeleton Volume with digital lines between (x, y, z) points; ``erase`` clears points."""
    array = np.zeros(GRID_SHAPE, dtype=np.uint8)
    for start, end in lines:
        start, end = np.asarray(start, float), np.asarray(end, float)
        steps = int(np.abs(end - start).max())
        xyz = np.rint(start + np.linspace(0, 1, steps + 1)[:, None] * (end - start)).astype(int)
        array[xyz[:, 2], xyz[:, 1], xyz[:, 0]] = 1
    for x, y, z in erase:
        array[z, y, x] = 0
    return Volume(array, [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], np.eye(3))


# ---------------------------------------------------------------------------------------
# Registration cases
# ---------------------------------------------------------------------------------------

#: Antero-posterior C-arm of the synthetic cases (about 3.7 px per mm at the isocentre).
AP_VIEW = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(0.4, 0.4), primary_angle=0.0,
                       secondary_angle=0.0, rows=1024, cols=1024)

#: Vessel polylines (LPS mm): label -> vertices. Branches start on an aorta vertex.
_VESSELS = {
    "aorta": [[0, 0, 150], [2, 6, 110], [-3, 12, 60], [0, 8, 20], [0, 0, 0]],
    "renal_left": [[2, 6, 110], [25, 0, 114], [50, -10, 112]],
    "renal_right": [[2, 6, 110], [-22, -2, 108], [-46, -12, 111]],
    "iliac_left": [[0, 0, 0], [25, 6, -40], [40, 12, -80], [45, 0, -120]],
    "iliac_right": [[0, 0, 0], [-22, 8, -42], [-38, 14, -82], [-44, 2, -118]],
}


def _polyline_length(vertices: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(vertices, axis=0), axis=1).sum())


def _resample(vertices: np.ndarray, count: int) -> np.ndarray:
    """``count`` points equally spaced along a polyline, both ends included."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(vertices, axis=0), axis=1))])
    where = np.linspace(0.0, arc[-1], count)
    return np.stack([np.interp(where, arc, vertices[:, d]) for d in range(vertices.shape[1])], axis=1)


def vessel_tree(n_nodes: int) -> Centerline:
    """An AAA-like centreline tree with about ``n_nodes`` nodes, labelled by vessel."""
    polylines = {label: np.asarray(vertices, dtype=float) for label, vertices in _VESSELS.items()}
    total = sum(_polyline_length(v) for v in polylines.values())
    points, edges, labels = [], [], []
    for label, vertices in polylines.items():
        samples = _resample(vertices, max(3, int(round(n_nodes * _polyline_length(vertices) / total))))
        offset = len(points)
        if label != "aorta":
            root = int(np.argmin(np.linalg.norm(np.asarray(points) - samples[0], axis=1)))
            samples = samples[1:]
            edges.append([root, offset])
        points.extend(samples.tolist())
        labels.extend([label] * len(samples))
        edges.extend([[offset + i, offset + i + 1] for i in range(len(samples) - 1)])
    return Centerline(np.asarray(points), np.asarray(edges), labels)


def in_plane_deformation(points: np.ndarray, P_view: CArmGeometry, seed: int, amplitude_mm: float = 8.0,
                         width_mm: float = 60.0, bumps: int = 4) -> np.ndarray:
    """A smooth displacement field parallel to the detector: a sum of Gaussian bumps."""
    rng = np.random.default_rng(seed)
    _, u_axis, v_axis = carm_axes(P_view.primary_angle, P_view.secondary_angle)
    centres = points[rng.choice(len(points), size=bumps, replace=False)]
    directions = rng.normal(size=(bumps, 2))
    directions *= amplitude_mm / np.linalg.norm(directions, axis=1, keepdims=True)
    vectors = directions[:, :1] * u_axis + directions[:, 1:] * v_axis
    weights = np.exp(-((points[:, None, :] - centres[None]) ** 2).sum(axis=2) / (2 * width_mm ** 2))
    return points + weights @ vectors


def dense_projection(P: np.ndarray, centreline: Centerline, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The projected centreline as a 2D graph of about ``n_points`` points.

    Every vessel (the nodes of one label, in order, from the node it branches off) is
    projected and resampled evenly along its length, so the 2D points do not coincide
    with projected 3D nodes.
    """
    projected = project(P, centreline.points)
    labels = np.asarray(centreline.labels)
    chains = []
    for label in dict.fromkeys(centreline.labels):
        members = np.flatnonzero(labels == label)
        roots = [a for a, b in centreline.edges if b == members[0] and labels[a] != label]
        chains.append(projected[roots[:1] + members.tolist()])
    total = sum(_polyline_length(chain) for chain in chains)
    points, edges = [], []
    for chain in chains:
        samples = _resample(chain, max(2, int(round(n_points * _polyline_length(chain) / total))))
        offset = sum(len(p) for p in points)
        if offset:
            previous = np.vstack(points)
            edges.append([int(np.argmin(np.linalg.norm(previous - samples[0], axis=1))), offset])
            samples = samples[1:]
        points.append(samples)
        edges.extend([[offset + i, offset + i + 1] for i in range(len(samples) - 1)])
    return np.vstack(points), np.asarray(edges, dtype=np.int64)


def synthetic_case(n_nodes: int, seed: int = 0, skeleton_points: int = 1500) -> dict:
    """A registration case with ground truth: pre-op tree, deformed tree, P and 2D skeleton.

    The 2D skeleton's density does not depend on the 3D sampling, as with a real frame:
    1500 points put one about every 1.3 px along the projected tree.
    """
    preop = vessel_tree(n_nodes)
    isocentre = 0.5 * (preop.points.min(axis=0) + preop.points.max(axis=0))
    P = projection_matrix_from_carm(AP_VIEW, isocentre)
    truth = preop.with_points(in_plane_deformation(preop.points, AP_VIEW, seed))
    skeleton_points, skeleton_edges = dense_projection(P, truth, skeleton_points)
    return {"preop": preop, "truth": truth, "P": P, "skeleton_points": skeleton_points,
            "skeleton_edges": skeleton_edges}


#: The small AP view of the deformation tests (0.5 mm detector pixels, 512 x 512).
SMALL_VIEW = CArmGeometry(sid=1100.0, sod=750.0, pixel_spacing=(0.5, 0.5), primary_angle=0.0,
                          secondary_angle=0.0, rows=512, cols=512)


def carm(primary=0.0, secondary=0.0, isocenter=(0.0, 0.0, 0.0), geometry=SMALL_VIEW):
    """``P`` of ``geometry`` turned to ``primary`` (LAO +) and ``secondary`` (cranial +) degrees."""
    turned = CArmGeometry(**{**geometry.__dict__, "primary_angle": primary, "secondary_angle": secondary})
    return projection_matrix_from_carm(turned, isocenter)


def chain_edges(n):
    """Edges ``(i, i + 1)`` of a chain of ``n`` nodes."""
    return np.column_stack([np.arange(n - 1), np.arange(1, n)])


def bent_arc(n=41, bend_mm=10.0):
    """An arc in the frontal plane and the same arc bent ``bend_mm`` along the AP view's rays.

    Returns ``(preop, truth, rays, edges)``: ``rays`` are the unit AP ray directions at the
    pre-operative nodes. The AP view cannot see the bend; a second view 30-90 degrees away can.
    """
    s = np.linspace(0.0, 1.0, n)
    preop = np.column_stack([30.0 * np.sin(np.pi * s), np.zeros(n), 75.0 - 150.0 * s])
    rays = preop - source_position(carm(0.0))
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    return preop, preop + bend_mm * np.sin(np.pi * s)[:, None] * rays, rays, chain_edges(n)


# ---------------------------------------------------------------------------------------
# Phantom cases of the pipeline tests
# ---------------------------------------------------------------------------------------

#: An AP view of a phantom without the optional branches and without misalignment; each test
#: module changes what it studies (a bend, a turned upper aorta, ...).
PHANTOM_PARAMS = dict(ct_spacing_mm=1.25, detector_pixel_mm=0.7, sma=False, coeliac=False, internal_iliacs=False,
                      primary_angle_deg=0.0, secondary_angle_deg=0.0, misalign_shift_px=(0.0, 0.0),
                      misalign_rotation_deg=0.0, bend_anterior_deg=0.0)


def phantom_case(name: str = "phantom", seed: int = 11, **changes):
    """A phantom case drawn with ``default_rng(seed)`` from :data:`PHANTOM_PARAMS` with ``changes``."""
    params = phantom.random_params(np.random.default_rng(seed), **{**PHANTOM_PARAMS, **changes})
    return phantom.generate_case(params, name=name)


def coarse_phantom_folders(root, name: str, files) -> tuple:
    """A coarse phantom case (CT 2 mm, detector 1.2 mm, seed 3) written whole to ``root/full``
    and a case folder ``root/<name>`` holding only ``files`` of it; returns (full, case)."""
    import shutil

    from pathlib import Path

    root = Path(root)
    params = phantom.PhantomParams(ct_spacing_mm=2.0, detector_pixel_mm=1.2, seed=3)
    full = phantom.write_case(phantom.generate_case(params, name=name), root / "full")
    case = root / name
    case.mkdir()
    for file in files:
        shutil.copy2(full / file, case / file)
    return full, case


def preop_model(case):
    """The pre-operative model of a phantom case, from its rasterised pre-operative lumen."""
    return pipeline.preop_from_lumen(phantom.rasterize_lumen(case.preop, case.grid))


def drawn_mask(centerline: Centerline, P: np.ndarray, shape) -> np.ndarray:
    """The simulation protocol's 2D side: ``centerline`` projected with ``P`` (eq. 1) and drawn
    one pixel thin on a frame of ``shape`` (rows, cols)."""
    return benchmark.draw_skeleton_mask(project(P, centerline.points), centerline.edges, shape)


def phantom_case_fixtures(name: str, seed: int = 11, **changes):
    """Module-scoped pytest fixtures ``case`` (:func:`phantom_case`) and ``preop`` (its
    :func:`preop_model`); a test module binds them as ``case, preop = phantom_case_fixtures(...)``."""

    @pytest.fixture(scope="module")
    def case():
        return phantom_case(name, seed, **changes)

    @pytest.fixture(scope="module")
    def preop(case):
        return preop_model(case)

    return case, preop


def phantom_run_folder(root, n_frames: int, noise_at=None):
    """A mask-level phantom case (random seed 4, ``P`` not misaligned) whose ``fluoro.dcm`` is a
    run of ``n_frames`` noisy angiograms with C-arm tags, and a frame of pure noise inserted at
    ``noise_at`` when given; its ``fluoro_mask.png`` removed. Returns ``(folder, generated case)``."""
    from FevarPlannerLib import io

    generated = phantom.generate_case(phantom.random_params(np.random.default_rng(4), misalign_shift_px=(0.0, 0.0),
                                                            misalign_rotation_deg=0.0), name="run")
    folder = phantom.write_case(generated, root / "case", mask_only=True)
    frames = [phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                    np.random.default_rng(seed))[0] for seed in range(n_frames)]
    if noise_at is not None:
        frames.insert(noise_at, np.random.default_rng(7).integers(0, 4096, size=frames[0].shape).astype(frames[0].dtype))
    io.write_fluoro_dicom(folder / "fluoro.dcm", np.stack(frames), generated.carm)
    (folder / "fluoro_mask.png").unlink()
    return folder, generated


"""A digitally reconstructed radiograph (DRR) through ``P``: the picture that checks the geometry.

A DRR sums the CT's attenuation along each ray from the X-ray source through a detector
pixel. Rendered through the case's ``P`` (eq. 1, inverted per pixel) and shown beside the
real frame with each one's edges drawn on the other, it shows at a glance whether ``P``
is right: spine, pelvis and the contrast-filled aorta land where the frame has them, or
they are shifted / turned by the amount the in-plane correction must undo.

Rays: with ``P = [M | p4]`` the source is ``C = -M^-1 p4`` and every point
``X(t) = C + t M^-1 (u, v, 1)^T`` projects to ``(u, v)`` with homogeneous weight ``w = t``,
so the ray's depth range is the range of ``w`` over the volume's corners. The volume is
sampled trilinearly (``scipy.ndimage.map_coordinates``, order 1) at a fixed step in mm.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .files import atomic_path
from .io import Volume
from .projection import depth, source_position

__all__ = ["DEFAULT_SIZE", "CHECK_HU_FLOOR", "attenuation", "drr_grid", "render_drr", "check_drr", "resample_frame",
           "write_drr_check"]

#: Longest side of the rendered DRR, pixels (the frame is resampled to the same grid).
DEFAULT_SIZE = 256
#: Water's attenuation is 1 in these units; air (-1000 HU) 0.
HU_WATER, HU_AIR = 0.0, -1000.0
#: For the check picture only what is denser than soft tissue is summed (contrast-filled
#: lumen and bone), as digital subtraction shows the frame: the body's outline would
#: otherwise dominate the DRR and its edges.
CHECK_HU_FLOOR = 150.0
#: Rays are processed in blocks of this many (bounds the memory of the sample array).
RAYS_PER_BLOCK = 2048


def attenuation(volume: Volume, hu_floor: float = HU_AIR) -> np.ndarray:
    """Linear attenuation relative to water, float32 ``(k, j, i)``.

    A CT in Hounsfield units gives ``max(0, (HU - hu_floor) / 1000)``: with the default floor
    (air) that is the attenuation relative to water; a higher floor keeps only what is denser
    (:data:`CHECK_HU_FLOOR`). A binary mask (bool, or integers 0 / 1) gives 1 inside and 0
    outside, so a lumen mask renders as an angiogram.
    """
    array = np.asarray(volume.array)
    if array.dtype == bool or (array.dtype.kind in "iu" and array.size and array.max() <= 1 and array.min() >= 0):
        return array.astype(np.float32)
    return np.clip((array.astype(np.float32) - hu_floor) / (HU_WATER - HU_AIR), 0.0, None)


def drr_grid(image_shape, size: int = DEFAULT_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Frame coordinates ``(u, v)`` of the DRR's pixel centres: a ``size``-pixel grid over the frame.

    Returns ``(u, v)``, each of shape ``(h, w)`` with ``max(h, w) == min(size, max(rows, cols))``.
    """
    rows, cols = (int(n) for n in image_shape)
    scale = max(rows, cols) / min(size, max(rows, cols))
    h, w = max(1, int(round(rows / scale))), max(1, int(round(cols / scale)))
    u = (np.arange(w) + 0.5) * cols / w - 0.5
    v = (np.arange(h) + 0.5) * rows / h - 0.5
    return np.meshgrid(u, v)


def _corner_points(volume: Volume) -> np.ndarray:
    low, high = -0.5, np.array(volume.shape, dtype=float) - 0.5
    corners = np.array([[k, j, i] for k in (low, high[0]) for j in (low, high[1]) for i in (low, high[2])])
    return volume.index_to_lps(corners)


def render_drr(volume: Volume, P: np.ndarray, image_shape, *, size: int = DEFAULT_SIZE,
               step_mm: float | None = None, hu_floor: float = HU_AIR) -> np.ndarray:
    """Render the DRR of ``volume`` seen through ``P`` on a ``size``-pixel grid over the frame.

    Parameters
    ----------
    volume : Volume
        A CT (HU) or a binary lumen mask, LPS mm.
    P : (3, 4)
        The projection of the frame (eq. 1).
    image_shape : (rows, cols)
        The frame's size; the DRR covers the same field of view (:func:`drr_grid`).
    size : int
        Longest side of the DRR, pixels.
    step_mm : float, optional
        Sampling step along each ray; default the smallest voxel spacing.
    hu_floor : float
        HU below which nothing attenuates (:func:`attenuation`); :data:`CHECK_HU_FLOOR`
        for the check picture.

    Returns
    -------
    numpy.ndarray, float32, shape (h, w)
        Line integral of :func:`attenuation` (mm of water equivalent): bigger = more attenuating.
    """
    P = np.asarray(P, dtype=float)
    mu = attenuation(volume, hu_floor)
    step = float(step_mm or volume.spacing.min())
    u, v = drr_grid(image_shape, size)
    directions = np.linalg.solve(P[:, :3], np.stack([u.ravel(), v.ravel(), np.ones(u.size)])).T  # (n, 3)
    source = source_position(P)
    w = depth(P, _corner_points(volume))
    t_near, t_far = float(w.min()), float(w.max())
    lengths = np.linalg.norm(directions, axis=1)  # mm per unit of t along each ray
    n_samples = max(2, int(np.ceil((t_far - t_near) * lengths.max() / step)))
    t = np.linspace(t_near, t_far, n_samples)
    # the rays in voxel-index space (k, j, i): the index map is affine, so a ray stays a line
    source_kji = volume.lps_to_index(source)
    directions_kji = volume.lps_to_index(source + directions) - source_kji
    total = np.empty(len(directions), dtype=np.float32)
    for start in range(0, len(directions), RAYS_PER_BLOCK):
        block = directions_kji[start:start + RAYS_PER_BLOCK].T.astype(np.float32)  # (3, rays)
        # (3, rays, samples), laid out as map_coordinates wants it: no transposed copy
        kji = source_kji.astype(np.float32)[:, None, None] + block[:, :, None] * t.astype(np.float32)[None, None, :]
        samples = ndimage.map_coordinates(mu, kji.reshape(3, -1), order=1, mode="constant", cval=0.0,
                                          prefilter=False)
        # the sum of samples times the step along this ray (its own length per unit t)
        step_along = (t_far - t_near) / (n_samples - 1) * lengths[start:start + RAYS_PER_BLOCK]
        total[start:start + block.shape[1]] = samples.reshape(block.shape[1], n_samples).sum(axis=1) * step_along
    return total.reshape(u.shape)


def check_drr(volume: Volume, P: np.ndarray, image_shape, size: int = DEFAULT_SIZE) -> np.ndarray:
    """The DRR of the check picture: only what is denser than soft tissue (:data:`CHECK_HU_FLOOR`)."""
    return render_drr(volume, P, image_shape, size=size, hu_floor=CHECK_HU_FLOOR)


def _normalised(image: np.ndarray) -> np.ndarray:
    low, high = np.percentile(image, [1.0, 99.0])
    return np.clip((image - low) / (high - low if high > low else 1.0), 0.0, 1.0)


def _edges(image: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    from skimage.feature import canny

    return canny(_normalised(image), sigma=sigma)


def resample_frame(image: np.ndarray, size: int = DEFAULT_SIZE) -> np.ndarray:
    """The frame sampled (bilinear) at the DRR's pixel centres (:func:`drr_grid`)."""
    u, v = drr_grid(image.shape, size)
    return ndimage.map_coordinates(np.asarray(image, dtype=np.float32), [v, u], order=1, mode="nearest")


def write_drr_check(path, frame: np.ndarray, drr: np.ndarray, *, title: str = "", notes=(),
                    frame_color=(1.0, 0.2, 0.8), drr_color=(0.1, 0.85, 1.0)) -> None:
    """Save the geometry check picture: frame with the DRR's edges | DRR with the frame's edges.

    Parameters
    ----------
    path : path-like
        Output ``.png`` (written atomically).
    frame : (rows, cols)
        The fluoroscopic frame at full resolution (resampled here onto the DRR grid).
    drr : (h, w)
        :func:`render_drr`'s output for this frame.
    title : str
        First line of the caption (e.g. method and view).
    notes : sequence of str
        Further caption lines (e.g. the geometry's assumptions).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    small = resample_frame(frame, max(drr.shape))
    if small.shape != drr.shape:
        raise ValueError(f"DRR of shape {drr.shape} does not match the frame's grid {small.shape}")
    frame_edges, drr_edges = _edges(small), _edges(drr)
    # the DRR is shown as a radiograph: more attenuation darker, like the frame
    panels = [("frame + DRR edges", small, drr_edges, drr_color),
              ("DRR through P + frame edges", -drr, frame_edges, frame_color)]
    h, w = drr.shape
    caption_px = 18 * (1 + len(notes))
    figure = Figure(figsize=(2 * w / 100.0, (h + caption_px) / 100.0), dpi=100, facecolor="black")
    FigureCanvasAgg(figure)
    for index, (name, image, edges, color) in enumerate(panels):
        axes = figure.add_axes((index / 2.0, caption_px / (h + caption_px), 0.5, h / (h + caption_px)))
        axes.set_axis_off()
        rgb = np.repeat(_normalised(image)[..., None], 3, axis=2)
        rgb[edges] = color
        axes.imshow(rgb, interpolation="nearest")
        axes.text(4, 12, name, color="white", fontsize=8, bbox={"facecolor": "black", "alpha": 0.6, "pad": 1.5,
                                                                   "edgecolor": "none"})
    lines = [title, *notes] if title else list(notes)
    for row, line in enumerate(lines):
        figure.text(0.005, 1.0 - (h + 14 + 16 * row) / (h + caption_px), line, color="white", fontsize=7)
    with atomic_path(path, suffix=".png") as tmp:
        figure.savefig(tmp, dpi=100, format="png", facecolor="black")

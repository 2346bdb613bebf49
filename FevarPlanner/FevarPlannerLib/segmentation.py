"""Segmentation stage: CT -> aorta lumen mask -> surface, and fluoroscopy frame -> vessel mask.

CT side (paper Section II-A): a 6-block UNet (convolution, max-pooling, transposed
convolution) segments the lumen slice by slice; it is trained with cross-entropy, SGD with
momentum 0.9, learning rate 1e-3 and batch size 1, with "linear mapping" (random linear
intensity maps) and "window slicing" (random crop windows, i.e. varying aorta position) as
augmentation. The result is cleaned like MATLAB's ``regionprops`` / ``bwareaopen`` (largest
component, small objects removed) plus hole filling, and turned into a surface by marching
cubes. A learning-free alternative (HU window + seeded region growing) serves for
comparison and as a fallback.

Fluoroscopy side: multi-scale Hessian vesselness (Frangi) on a reduced-resolution copy of the
frame, hysteresis thresholding and a local-contrast refinement, upsampled back to the frame
grid.

Volumes are :class:`io.Volume` objects, arrays indexed ``(k, j, i)``; world coordinates are
LPS millimetres.
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import torch
import vtk
from scipy import ndimage as ndi
from skimage import measure
from skimage.filters import apply_hysteresis_threshold
from torch import nn
from torch.nn import functional as F
from vtk.util import numpy_support

from . import files, io
from .files import InputError, atomic_path
from .io import Volume
from .quality import DEFORMATION_MARGIN_MM, TYPICAL_RADIUS_MM, FluoroPrior

__all__ = [
    "UNet",
    "train_unet",
    "load_unet",
    "default_model_path",
    "segment_ct_unet",
    "segment_ct_threshold",
    "find_aorta_seed",
    "segment_ct",
    "postprocess_mask",
    "mask_surface",
    "write_surface_vtp",
    "segment_fluoro",
    "FluoroPrior",
    "select_frame",
    "frame_contrast_in_prior",
    "vesselness",
    "segment_ct_classical",
    "find_aorta_in_slices",
    "trace_aorta",
    "grow_branches",
    "dice",
    "read_case",
]

#: Where the shipped weights live, relative to this package (FevarPlanner/FevarPlannerLib).
#: Where the shipped weights lie relative to this package: inside an installed Slicer module
#: (``<module>/Resources``, copied there by FevarPlanner/CMakeLists.txt), then in the source tree.
MODEL_RELATIVE_PATHS = (Path("..", "Resources", "Models", "aorta_unet.pt"),
                        Path("..", "..", "Resources", "Models", "aorta_unet.pt"))

#: Default preprocessing of CT slices for the network: in-plane spacing (mm) the slices are
#: resampled to, and the HU window mapped linearly onto [0, 1].
DEFAULT_PIXEL_MM = 1.0
DEFAULT_NET_HU_WINDOW = (-200.0, 800.0)


# ----------------------------------------------------------------------------------------
# UNet
# ----------------------------------------------------------------------------------------

class _DoubleConv(nn.Sequential):
    """Two 3x3 convolutions, each followed by batch normalisation and ReLU."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )


class UNet(nn.Module):
    """A 2D UNet with ``depth`` resolution blocks (the paper's "6-block Unet").

    Encoder blocks (two conv + BN + ReLU) are separated by 2x2 max-pooling; decoder blocks
    upsample with a 2x2 transposed convolution, concatenate the skip connection and apply
    two conv + BN + ReLU; a 1x1 convolution gives per-class logits. Inputs of any size are
    padded (replicate) to a multiple of ``2 ** (depth - 1)`` and the output is cropped back.

    Parameters
    ----------
    in_channels : int
        Image channels (1 for CT).
    n_classes : int
        Output classes (2: background, lumen).
    base : int
        Channels of the first block; each deeper block doubles them up to ``max_channels``.
    depth : int
        Number of resolution blocks (6 in the paper).
    max_channels : int
        Cap on the channel count, to keep the weights small.
    """

    def __init__(self, in_channels: int = 1, n_classes: int = 2, base: int = 8, depth: int = 6,
                 max_channels: int = 64):
        super().__init__()
        if depth < 2:
            raise ValueError(f"UNet depth must be >= 2, got {depth}")
        self.config = {"in_channels": in_channels, "n_classes": n_classes, "base": base, "depth": depth,
                       "max_channels": max_channels}
        widths = [min(base * 2 ** level, max_channels) for level in range(depth)]
        self.encoders = nn.ModuleList()
        previous = in_channels
        for width in widths:
            self.encoders.append(_DoubleConv(previous, width))
            previous = width
        self.pool = nn.MaxPool2d(2)
        self.upsamplers = nn.ModuleList(
            nn.ConvTranspose2d(widths[level + 1], widths[level], 2, stride=2) for level in range(depth - 1))
        self.decoders = nn.ModuleList(_DoubleConv(2 * widths[level], widths[level]) for level in range(depth - 1))
        self.head = nn.Conv2d(widths[0], n_classes, 1)

    @property
    def size_multiple(self) -> int:
        """Spatial sizes the network sees internally are multiples of this."""
        return 2 ** (len(self.encoders) - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        height, width = x.shape[-2:]
        m = self.size_multiple
        pad_h, pad_w = (-height) % m, (-width) % m
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        skips = []
        for level, encoder in enumerate(self.encoders):
            if level:
                x = self.pool(x)
            x = encoder(x)
            skips.append(x)
        x = skips.pop()
        for level in reversed(range(len(self.decoders))):
            x = self.upsamplers[level](x)
            x = self.decoders[level](torch.cat([skips[level], x], dim=1))
        return self.head(x)[..., :height, :width]


# ----------------------------------------------------------------------------------------
# CT preprocessing shared by training and inference
# ----------------------------------------------------------------------------------------

def _window(hu: torch.Tensor | np.ndarray, hu_window) -> torch.Tensor | np.ndarray:
    """Linear map of ``hu_window`` onto [0, 1], clipped."""
    lo, hi = hu_window
    scaled = (hu - lo) / float(hi - lo)
    return scaled.clamp(0.0, 1.0) if isinstance(scaled, torch.Tensor) else np.clip(scaled, 0.0, 1.0)


def _model_grid_shape(ct: Volume, shape_ji: tuple[int, int], pixel_mm: float) -> tuple[int, int]:
    """In-plane size of a ``shape_ji`` slice region resampled to ``pixel_mm`` pixels."""
    return (max(1, int(round(shape_ji[0] * ct.spacing[1] / pixel_mm))),
            max(1, int(round(shape_ji[1] * ct.spacing[0] / pixel_mm))))


def _body_box(ct: Volume, threshold_hu: float = -400.0, margin_vox: int = 4) -> tuple[slice, slice]:
    """In-plane (j, i) bounding box of everything denser than air, over all slices."""
    body = (ct.array > threshold_hu).any(axis=0)
    if not body.any():
        return slice(0, ct.shape[1]), slice(0, ct.shape[2])
    rows, cols = np.nonzero(body.any(axis=1))[0], np.nonzero(body.any(axis=0))[0]
    return (slice(max(rows[0] - margin_vox, 0), min(rows[-1] + margin_vox + 1, ct.shape[1])),
            slice(max(cols[0] - margin_vox, 0), min(cols[-1] + margin_vox + 1, ct.shape[2])))


def _resample_slices(slices: np.ndarray, out_shape: tuple[int, int]) -> torch.Tensor:
    """(n, H, W) array -> (n, 1, h, w) float tensor on the model grid (bilinear)."""
    tensor = torch.as_tensor(np.ascontiguousarray(slices), dtype=torch.float32)[:, None]
    if tuple(tensor.shape[-2:]) == tuple(out_shape):
        return tensor
    return F.interpolate(tensor, size=out_shape, mode="bilinear", align_corners=False)


# ----------------------------------------------------------------------------------------
# Training
# ----------------------------------------------------------------------------------------

def read_case(case_dir) -> tuple[Volume, Volume]:
    """Read ``(ct, aorta_mask)`` from a case folder (docs/DESIGN.md section 4) for training.

    The CT is ``ct/`` (DICOM series) or ``ct.nrrd`` / ``.nii.gz`` / ``.mha``, the label
    ``aorta_mask.*`` on the same grid.
    """
    case_dir = Path(case_dir)
    found = {}
    for name in ("ct", "aorta_mask"):
        stem, suffixes = io.CASE_INPUTS[name]
        found[name] = io.find_case_file(case_dir, stem, suffixes)
        if found[name] is None:
            raise InputError(f"{case_dir}: no {name} input for training")
    ct = io.read_ct(found["ct"])
    mask = io.read_mask(found["aorta_mask"])
    io.check_same_grid(mask, ct, found["aorta_mask"])
    return ct, mask


class _SliceBank:
    """Training slices of all cases, LPS-oriented and resampled once to the model grid (HU)."""

    def __init__(self, pairs, pixel_mm: float):
        self.images, self.labels = [], []
        for ct, mask in pairs:
            if ct.shape != mask.shape:
                raise ValueError(f"CT shape {ct.shape} and mask shape {mask.shape} differ")
            rows, cols = _body_box(ct)
            shape = _model_grid_shape(ct, (rows.stop - rows.start, cols.stop - cols.start), pixel_mm)
            flips = _lps_flips(ct)
            image = np.flip(ct.array[:, rows, cols], flips).astype(np.float32)
            label = np.flip(mask.array[:, rows, cols], flips).astype(np.float32)
            self.images.append(_resample_slices(image, shape)[:, 0])
            self.labels.append(_resample_slices(label, shape)[:, 0] > 0.5)
        self.slices = [(c, k) for c, label in enumerate(self.labels) for k in range(label.shape[0])]
        self.foreground = [(c, k) for c, k in self.slices if self.labels[c][k].any()]
        if not self.slices:
            raise ValueError("no training slices")

    def sample(self, rng: np.random.Generator, crop: int, hu_window) -> tuple[torch.Tensor, torch.Tensor]:
        """One augmented (image, label) pair: random slice, crop window and intensity map."""
        pool = self.foreground if self.foreground and rng.random() < 0.9 else self.slices
        case, k = pool[rng.integers(len(pool))]
        image, label = self.images[case][k], self.labels[case][k]
        top, left = self._crop_origin(rng, label, crop)
        image = image[top:top + crop, left:left + crop]
        label = label[top:top + crop, left:left + crop]
        pad = (0, crop - image.shape[1], 0, crop - image.shape[0])
        if any(pad):
            image, label = F.pad(image, pad, value=-1000.0), F.pad(label, pad, value=False)
        gain, offset = rng.uniform(0.85, 1.15), rng.uniform(-60.0, 60.0)   # linear intensity mapping
        x = _window(image * gain + offset, hu_window)
        return x[None, None].float(), label[None].long()

    @staticmethod
    def _crop_origin(rng, label: torch.Tensor, crop: int) -> tuple[int, int]:
        """Window slicing: a crop that usually contains some lumen, at a random offset."""
        height, width = label.shape
        if height <= crop and width <= crop:
            return 0, 0
        if label.any() and rng.random() < 0.8:
            fg = torch.nonzero(label)
            centre = fg[rng.integers(len(fg))].numpy() + rng.integers(-crop // 3, crop // 3 + 1, size=2)
        else:
            centre = np.array([rng.integers(height), rng.integers(width)])
        top = int(np.clip(centre[0] - crop // 2, 0, max(height - crop, 0)))
        left = int(np.clip(centre[1] - crop // 2, 0, max(width - crop, 0)))
        return top, left


def _as_training_pairs(data) -> list[tuple[Volume, Volume]]:
    pairs = []
    for item in data:
        if isinstance(item, (str, Path)):
            pairs.append(read_case(item))
        else:
            ct, mask = item
            pairs.append((ct, mask.with_array(np.asarray(mask.array) > 0)))
    if not pairs:
        raise ValueError("train_unet needs at least one (ct, mask) pair or case folder")
    return pairs


def _save_checkpoint(path: Path, model: UNet, optimizer, iteration: int, rng: np.random.Generator,
                     settings: dict, losses: list[float]) -> None:
    state = {
        "format": "fevar-aorta-unet-1",
        "model_config": model.config,
        "model_state": model.state_dict(),
        "optimizer_state": optimizer.state_dict(),
        "iteration": iteration,
        "rng_state": rng.bit_generator.state,
        "torch_rng_state": torch.get_rng_state(),
        "settings": settings,
        "losses": losses,
    }
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(state, tmp)


def _load_checkpoint(path) -> dict:
    """A checkpoint's tensors and plain values; code hidden in the file is refused, not run.

    ``torch.load(weights_only=True)`` unpickles only tensors, containers and numbers, so a
    crafted ``.pt`` that would call a function on loading raises :class:`InputError`.
    """
    path = Path(path)
    files.check_input_file(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        globals_named = [line.strip() for line in str(exc).splitlines() if "global" in line.lower()]
        if not globals_named:
            raise InputError(f"{path}: not a readable PyTorch checkpoint (UnpicklingError)") from None
        raise InputError(f"{path}: refused to load: the checkpoint holds Python objects other than tensors "
                         f"and plain values, which could run code ({globals_named[0][:100]})") from None
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable PyTorch checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: not a FevarPlanner UNet checkpoint (holds a {type(state).__name__})")
    return state


def train_unet(data, out_path, *, iterations: int = 2000, lr: float = 1e-3, momentum: float = 0.9,
               batch_size: int = 1, seed: int = 0, resume=None, progress=None, crop: int = 128,
               base: int = 8, depth: int = 6, max_channels: int = 64, pixel_mm: float = DEFAULT_PIXEL_MM,
               hu_window=DEFAULT_NET_HU_WINDOW, checkpoint_every: int = 200) -> Path:
    """Train the lumen UNet with the paper's recipe and save a resumable checkpoint.

    Cross-entropy loss, SGD (``lr``, ``momentum``), ``batch_size`` slices per step; each sample
    is a random slice resampled to ``pixel_mm``, cut to a ``crop`` x ``crop`` window around the
    lumen ("window slicing") and mapped by a random linear intensity transform ("linear
    mapping") before the HU window.

    Parameters
    ----------
    data : iterable
        Case folders (with ``ct.*`` and ``aorta_mask.*``) or ``(ct, mask)`` Volume pairs.
    out_path : path
        Checkpoint file; rewritten atomically every ``checkpoint_every`` iterations and at the end.
    iterations : int
        Total number of optimiser steps (a resumed run continues up to this number).
    resume : path, optional
        Checkpoint to continue from (weights, optimiser, iteration count and random state).
    progress : callable, optional
        ``progress(done, total, message)`` after every iteration (``cli.ProgressBar.count``).

    Returns
    -------
    pathlib.Path
        ``out_path``.
    """
    if iterations < 0 or batch_size < 1:
        raise ValueError(f"iterations must be >= 0 and batch_size >= 1, got {iterations}, {batch_size}")
    if crop < 2 ** depth:
        raise ValueError(f"crop {crop} too small for a depth-{depth} UNet (need >= {2 ** depth})")
    out_path = Path(out_path)
    settings = {"lr": lr, "momentum": momentum, "batch_size": batch_size, "seed": seed, "crop": crop,
                "pixel_mm": pixel_mm, "hu_window": list(hu_window)}
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = UNet(1, 2, base=base, depth=depth, max_channels=max_channels)
    optimizer = torch.optim.SGD(model.parameters(), lr=lr, momentum=momentum)
    iteration, losses = 0, []
    if resume is not None:
        state = _load_checkpoint(resume)
        model = UNet(**state["model_config"])
        model.load_state_dict(state["model_state"])
        optimizer = torch.optim.SGD(model.parameters(), lr=state["settings"]["lr"],
                                    momentum=state["settings"]["momentum"])
        optimizer.load_state_dict(state["optimizer_state"])
        iteration, losses, settings = state["iteration"], list(state["losses"]), state["settings"]
        rng.bit_generator.state = state["rng_state"]
        torch.set_rng_state(state["torch_rng_state"])
    report = progress
    bank = _SliceBank(_as_training_pairs(data), settings["pixel_mm"])
    window = tuple(settings["hu_window"])
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    model.train()
    try:
        while iteration < iterations:
            samples = [bank.sample(rng, settings["crop"], window) for _ in range(settings["batch_size"])]
            losses.append(_training_step(model, optimizer, samples))
            iteration += 1
            if iteration % checkpoint_every == 0 or iteration == iterations:
                _save_checkpoint(out_path, model, optimizer, iteration, rng, settings, losses)
            if report:
                report(iteration, iterations, f"loss {float(np.mean(losses[-50:])):.4f}")
    finally:
        torch.use_deterministic_algorithms(was_deterministic)
    if not out_path.exists():
        _save_checkpoint(out_path, model, optimizer, iteration, rng, settings, losses)
    return out_path


def _training_step(model: UNet, optimizer, samples) -> float:
    """One SGD step on a list of (image, label) samples; cross-entropy, mean over the batch."""
    optimizer.zero_grad()
    total = 0.0
    for image, label in samples:
        loss = F.cross_entropy(model(image), label) / len(samples)
        loss.backward()
        total += float(loss.detach())
    optimizer.step()
    return total


def default_model_path() -> Path:
    """The shipped weights ``Resources/Models/aorta_unet.pt``: the Slicer module's copy, else the source tree's."""
    here = Path(__file__).resolve().parent
    candidates = [(here / relative).resolve() for relative in MODEL_RELATIVE_PATHS]
    return next((path for path in candidates if path.is_file()), candidates[-1])


def load_unet(path=None) -> UNet:
    """Load a trained UNet (eval mode) from a checkpoint of :func:`train_unet`.

    ``path=None`` loads the shipped weights; the preprocessing settings the network was
    trained with are attached as ``model.settings``.
    """
    path = Path(path) if path is not None else default_model_path()
    if not path.exists():
        raise InputError(f"{path}: UNet weights not found (train them with "
                         f"`fevar-planner train-unet`, see Resources/Models/README.md)")
    try:
        state = _load_checkpoint(path)
        model = UNet(**state["model_config"])
        model.load_state_dict(state["model_state"])
    except InputError:
        raise
    except (RuntimeError, KeyError, TypeError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: not a FevarPlanner UNet checkpoint ({type(exc).__name__})") from None
    model.settings = dict(state.get("settings", {}))
    model.settings.setdefault("pixel_mm", DEFAULT_PIXEL_MM)
    model.settings.setdefault("hu_window", list(DEFAULT_NET_HU_WINDOW))
    model.eval()
    return model


# ----------------------------------------------------------------------------------------
# CT inference
# ----------------------------------------------------------------------------------------

def segment_ct_unet(ct: Volume, model: UNet | None = None, *, progress=None, chunk: int = 8,
                    postprocess: bool = True) -> Volume:
    """Lumen mask of a CT by the UNet, slice by slice (paper Section II-A).

    Each axial slice is cropped to the body, resampled to the network's pixel size, HU
    windowed, segmented, and the logits are resampled back to the CT grid.

    Parameters
    ----------
    ct : Volume
        CT in HU.
    model : UNet, optional
        A loaded network; default the shipped weights (:func:`load_unet`).
    progress : callable, optional
        ``progress(done_slices, total_slices)``.
    postprocess : bool
        Apply :func:`postprocess_mask` (largest component, small objects, holes).

    Returns
    -------
    Volume
        Boolean lumen mask on the CT grid.
    """
    _check_ct(ct)
    model = model if model is not None else load_unet()
    settings = getattr(model, "settings", {"pixel_mm": DEFAULT_PIXEL_MM, "hu_window": DEFAULT_NET_HU_WINDOW})
    model.eval()
    rows, cols = _body_box(ct)
    crop_shape = (rows.stop - rows.start, cols.stop - cols.start)
    net_shape = _model_grid_shape(ct, crop_shape, settings["pixel_mm"])
    flips = _lps_flips(ct)
    mask = np.zeros(ct.shape, dtype=bool)
    n_slices = ct.shape[0]
    with torch.inference_mode():
        for start in range(0, n_slices, chunk):
            stop = min(start + chunk, n_slices)
            hu = np.flip(ct.array[start:stop, rows, cols], flips).astype(np.float32)
            logits = model(_window(_resample_slices(hu, net_shape), settings["hu_window"]))
            if tuple(logits.shape[-2:]) != crop_shape:
                logits = F.interpolate(logits, size=crop_shape, mode="bilinear", align_corners=False)
            mask[start:stop, rows, cols] = np.flip((logits[:, 1] > logits[:, 0]).numpy(), flips)
            if progress:
                progress(stop, n_slices)
    result = ct.with_array(mask)
    return postprocess_mask(result) if postprocess else result


def _lps_flips(ct: Volume) -> tuple[int, ...]:
    """Axes of a (k, j, i) slice stack to flip so that columns run to +x (patient left) and
    rows to +y (posterior), as in the LPS-aligned training CTs."""
    return tuple(axis for axis, column in ((2, 0), (1, 1)) if ct.direction[column, column] < 0)


def _check_ct(ct: Volume) -> None:
    if not isinstance(ct, Volume):
        raise TypeError(f"expected an io.Volume, got {type(ct).__name__}")
    if ct.array.ndim != 3 or min(ct.shape) < 1:
        raise InputError(f"CT has an unusable shape {ct.shape}")
    if np.issubdtype(ct.array.dtype, np.floating) and not np.isfinite(ct.array).all():
        raise InputError("CT contains NaN or infinite values")


def find_aorta_seed(ct: Volume, hu_window=(150, 600), *, top_fraction: float = 0.2,
                    area_mm2=(50.0, 2500.0), n_slices: int = 8) -> np.ndarray:
    """LPS position inside the upper aorta, found automatically.

    In evenly spaced axial slices of the superior ``top_fraction`` of the CT, the connected
    blobs inside ``hu_window`` of plausible area are scored by roundness (minor/major axis
    ratio times solidity) times mean HU; the centroid of the best blob is returned.
    """
    lo, hi = hu_window
    superior_last = ct.direction[2, 2] >= 0     # k axis pointing to +z (superior in LPS)
    n = ct.shape[0]
    span = max(1, int(math.ceil(n * top_fraction)))
    ks = np.arange(n - span, n) if superior_last else np.arange(0, span)
    ks = np.unique(np.linspace(ks[0], ks[-1], min(n_slices, len(ks))).round().astype(int))
    pixel_area = ct.spacing[0] * ct.spacing[1]
    best, best_score = None, -np.inf
    for k in ks:
        slice_hu = ct.array[k].astype(np.float32)
        inside = ndi.binary_opening((slice_hu >= lo) & (slice_hu <= hi), iterations=1)
        for region in measure.regionprops(measure.label(inside), intensity_image=slice_hu):
            area = region.area * pixel_area
            if not area_mm2[0] <= area <= area_mm2[1] or region.axis_major_length == 0:
                continue
            roundness = region.axis_minor_length / region.axis_major_length * region.solidity
            score = roundness ** 2 * region.intensity_mean
            if score > best_score:
                best_score, best = score, (k, *region.centroid)
    if best is None:
        raise InputError(f"no aorta-like blob in HU window {tuple(hu_window)} near the top of the CT; "
                         f"give a seed point")
    return ct.index_to_lps(np.array(best, dtype=float))


def segment_ct_threshold(ct: Volume, *, hu_window=(150, 600), seed_lps=None, separation_vox: int = 1,
                         postprocess: bool = True) -> Volume:
    """Lumen mask without learning: HU window plus seeded region growing.

    The window mask is eroded ``separation_vox`` times (cutting thin bridges to bone), the
    component holding the seed is kept and grown back inside the window by geodesic
    dilation (``separation_vox + 2`` steps).

    Parameters
    ----------
    ct : Volume
        CT in HU.
    hu_window : (float, float)
        Contrast-enhanced lumen intensities.
    seed_lps : array_like, optional
        A point in the lumen (LPS mm); default :func:`find_aorta_seed`.

    Returns
    -------
    Volume
        Boolean lumen mask.
    """
    _check_ct(ct)
    lo, hi = hu_window
    window = (ct.array >= lo) & (ct.array <= hi)
    seed_lps = find_aorta_seed(ct, hu_window) if seed_lps is None else np.asarray(seed_lps, dtype=float)
    seed = np.round(ct.lps_to_index(seed_lps)).astype(int)
    if np.any(seed < 0) or np.any(seed >= np.array(ct.shape)):
        raise InputError(f"seed {np.round(seed_lps, 1).tolist()} lies outside the CT")
    core = ndi.binary_erosion(window, iterations=separation_vox) if separation_vox else window
    seed = _nearest_true(core, seed)
    labels, _ = ndi.label(core)
    region = labels == labels[tuple(seed)]
    if separation_vox:
        region = ndi.binary_dilation(region, iterations=separation_vox + 2, mask=window)
    result = ct.with_array(region)
    return postprocess_mask(result) if postprocess else result


def _nearest_true(mask: np.ndarray, index: np.ndarray, radius: int = 6) -> np.ndarray:
    """``index`` if ``mask`` is set there, else the nearest set voxel within ``radius``."""
    if mask[tuple(index)]:
        return index
    lo = np.maximum(index - radius, 0)
    hi = np.minimum(index + radius + 1, mask.shape)
    local = np.argwhere(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]) + lo
    if len(local) == 0:
        raise InputError(f"seed voxel {index.tolist()} is not inside the HU window (nor near it)")
    return local[np.argmin(((local - index) ** 2).sum(axis=1))]


#: The CT segmenters :func:`segment_ct` knows.
CT_SEGMENTERS = ("classical", "unet", "threshold")


def segment_ct(ct: Volume, method: str = "classical", **kwargs) -> Volume:
    """Lumen mask by ``method``: ``'classical'`` (:func:`segment_ct_classical`, the default:
    no training, validated on a real CT), ``'unet'`` (:func:`segment_ct_unet`, trained on
    phantoms only) or ``'threshold'`` (:func:`segment_ct_threshold`)."""
    if method == "classical":
        return segment_ct_classical(ct, **kwargs)
    if method == "unet":
        return segment_ct_unet(ct, **kwargs)
    if method == "threshold":
        return segment_ct_threshold(ct, **kwargs)
    raise ValueError(f"unknown segmenter {method!r}; use one of {', '.join(CT_SEGMENTERS)}")


def postprocess_mask(mask, *, min_size_mm3: float = 50.0, keep_largest: bool = True,
                     fill_holes: bool = True):
    """Clean a lumen mask (the paper's ``regionprops`` / ``bwareaopen`` step, plus hole filling).

    Removes connected objects smaller than ``min_size_mm3``, keeps the largest component and
    fills holes (enclosed in 3D, and in each axial slice).

    Parameters
    ----------
    mask : Volume or numpy.ndarray
        Binary mask; an array is taken to have 1 mm voxels.

    Returns
    -------
    Volume or numpy.ndarray
        Boolean mask, of the same kind as the input.
    """
    array = np.asarray(mask.array if isinstance(mask, Volume) else mask) > 0
    if array.ndim != 3:
        raise ValueError(f"postprocess_mask expects a 3D mask, got shape {array.shape}")
    voxel_mm3 = float(np.prod(mask.spacing)) if isinstance(mask, Volume) else 1.0
    cleaned = np.zeros_like(array)
    if array.any():
        box = _bounding_box(array)        # nothing outside it changes, and it is much faster
        crop = _remove_small_objects(array[box], min_size_mm3 / voxel_mm3)
        if keep_largest:
            crop = _largest_component(crop)
        if fill_holes and crop.any():
            crop = ndi.binary_fill_holes(crop)
            crop = np.stack([ndi.binary_fill_holes(s) if s.any() else s for s in crop])
        cleaned[box] = crop
    return mask.with_array(cleaned) if isinstance(mask, Volume) else cleaned


def _bounding_box(array: np.ndarray) -> tuple[slice, ...]:
    """Index box of the non-zero voxels of a non-empty array."""
    box = []
    for axis in range(array.ndim):
        hit = np.nonzero(array.any(axis=tuple(a for a in range(array.ndim) if a != axis)))[0]
        box.append(slice(hit[0], hit[-1] + 1))
    return tuple(box)


def _component_sizes(array: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face-connected component labels and the size of each label (label 0 gets size 0)."""
    labels, _ = ndi.label(array)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels, sizes


def _remove_small_objects(array: np.ndarray, min_voxels: float) -> np.ndarray:
    """``array`` without the connected objects of fewer than ``min_voxels`` voxels (bwareaopen)."""
    labels, sizes = _component_sizes(array)
    return (sizes >= max(min_voxels, 1))[labels] if array.any() else array


def _largest_component(array: np.ndarray) -> np.ndarray:
    """The largest connected object of ``array`` (regionprops' largest area)."""
    if not array.any():
        return array
    labels, sizes = _component_sizes(array)
    return labels == np.argmax(sizes)


# ----------------------------------------------------------------------------------------
# Surface
# ----------------------------------------------------------------------------------------

def mask_surface(mask: Volume, *, smooth_sigma_vox: float = 0.0) -> vtk.vtkPolyData:
    """Closed triangle surface of a binary mask by marching cubes, points in LPS mm.

    The mask is cropped to its bounding box, padded by one voxel (so the surface closes) and
    iso-surfaced at 0.5 (optionally after a Gaussian blur of ``smooth_sigma_vox`` voxels).
    Normals point out of the lumen.
    """
    array = np.asarray(mask.array) > 0
    if not array.any():
        raise InputError("mask is empty: no surface to extract")
    box = _bounding_box(array)
    lo = np.array([b.start for b in box])
    field = np.pad(array[box].astype(np.float32), 1)
    if smooth_sigma_vox > 0:
        field = ndi.gaussian_filter(field, smooth_sigma_vox)
    verts, faces, normals, _ = measure.marching_cubes(field, level=0.5, gradient_direction="descent")
    points = mask.index_to_lps(verts + lo - 1)
    linear = mask.direction @ np.diag(mask.spacing)
    normals_lps = normals[:, ::-1] @ np.linalg.inv(linear)      # covector transform, (i, j, k) order
    normals_lps /= np.linalg.norm(normals_lps, axis=1, keepdims=True) + 1e-12
    faces = _wind_like_normals(points, faces, normals_lps)
    return _polydata(points, faces, normals_lps)


def _wind_like_normals(points: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Faces reordered, if needed, so that their right-hand normals agree with the vertex normals."""
    a, b, c = (points[faces[:, n]] for n in range(3))
    agreement = np.einsum("ij,ij->i", np.cross(b - a, c - a), normals[faces].sum(axis=1))
    return faces[:, ::-1] if agreement.sum() < 0 else faces


def _polydata(points: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> vtk.vtkPolyData:
    poly = vtk.vtkPolyData()
    vtk_points = vtk.vtkPoints()
    vtk_points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    poly.SetPoints(vtk_points)
    offsets = np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64)
    polys = vtk.vtkCellArray()
    polys.SetData(numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(faces.astype(np.int64).ravel(), deep=True))
    poly.SetPolys(polys)
    vtk_normals = numpy_support.numpy_to_vtk(np.ascontiguousarray(normals, dtype=np.float32), deep=True)
    vtk_normals.SetName("Normals")
    poly.GetPointData().SetNormals(vtk_normals)
    return poly


def write_surface_vtp(path, polydata: vtk.vtkPolyData) -> None:
    """Write a surface as VTK XML PolyData (``.vtp``), atomically."""
    path = Path(path)
    with atomic_path(path, suffix=".vtp") as tmp:
        writer = vtk.vtkXMLPolyDataWriter()
        writer.SetFileName(str(tmp))
        writer.SetInputData(polydata)
        writer.SetDataModeToBinary()
        if writer.Write() != 1:
            raise OSError(f"{path}: VTK could not write the surface")


# ----------------------------------------------------------------------------------------
# Fluoroscopy
# ----------------------------------------------------------------------------------------

def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Block mean (float32) by an integer ``factor``; the last rows / columns padded by replication.

    Sums of strided views: no float64 copy and no copy of the full-resolution ``image`` (any
    numeric dtype) beyond one float32 pass over its rows.
    """
    if factor == 1:
        return np.asarray(image, dtype=np.float32)
    pad = ((0, (-image.shape[0]) % factor), (0, (-image.shape[1]) % factor))
    if any(p for _, p in pad):
        image = np.pad(image, pad, mode="edge")
    rows = image[0::factor].astype(np.float32)
    for k in range(1, factor):
        rows += image[k::factor]
    blocks = rows[:, 0::factor].copy()
    for k in range(1, factor):
        blocks += rows[:, k::factor]
    blocks *= np.float32(1.0 / factor ** 2)
    return blocks


def _linear_weights(n_coarse: int, factor: int, n_fine: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices and weights of linear interpolation from a block-mean grid to the fine grid.

    Fine pixel centres sit at ``(u + 0.5) / factor - 0.5`` on the coarse grid, where the block
    means sit (``align_corners=False``); positions outside the coarse grid take the edge value.
    """
    position = np.clip((np.arange(n_fine) + 0.5) / factor - 0.5, 0.0, n_coarse - 1)
    below = np.floor(position).astype(np.intp)
    above = np.minimum(below + 1, n_coarse - 1)
    return below, above, (position - below).astype(np.float32)


def _upsample(image: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling (float32) of a block-mean grid back onto the full grid of ``shape``,
    done separably: rows, then columns."""
    if factor == 1:
        return image
    image = np.asarray(image, dtype=np.float32)
    below, above, weight = _linear_weights(image.shape[0], factor, shape[0])
    rows = image[below]
    rows += weight[:, None] * (image[above] - rows)
    below, above, weight = _linear_weights(image.shape[1], factor, shape[1])
    full = rows[:, below]
    full += weight * (rows[:, above] - full)
    return full


def _hessian_eigenvalues(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale-normalised Hessian eigenvalues (|l1| <= |l2|) of a Gaussian-smoothed image."""
    smooth = ndi.gaussian_filter(image, sigma, mode="nearest")
    hrr = np.empty_like(smooth)
    hcc = np.empty_like(smooth)
    hrr[1:-1] = smooth[2:] - 2 * smooth[1:-1] + smooth[:-2]
    hrr[0], hrr[-1] = hrr[1], hrr[-2]
    hcc[:, 1:-1] = smooth[:, 2:] - 2 * smooth[:, 1:-1] + smooth[:, :-2]
    hcc[:, 0], hcc[:, -1] = hcc[:, 1], hcc[:, -2]
    grad_r = np.gradient(smooth, axis=0)
    hrc = np.gradient(grad_r, axis=1)
    scale = sigma ** 2
    half_trace = 0.5 * (hrr + hcc) * scale
    root = np.sqrt((0.5 * (hrr - hcc)) ** 2 + hrc ** 2) * scale
    a, b = half_trace + root, half_trace - root
    swap = np.abs(a) > np.abs(b)
    return np.where(swap, b, a), np.where(swap, a, b)


def vesselness(image: np.ndarray, sigmas=(1.0, 2.0, 3.0, 4.5), *, polarities=("bright",), beta: float = 0.5,
               c_fraction: float = 0.5) -> dict:
    """Multi-scale Frangi vesselness of a 2D image, for bright and / or dark vessels.

    For each scale the Hessian eigenvalues ``l1, l2`` (``|l1| <= |l2|``) give
    ``V = exp(-Rb^2 / (2 beta^2)) (1 - exp(-S^2 / (2 c^2)))`` with ``Rb = l1 / l2``,
    ``S = sqrt(l1^2 + l2^2)`` and ``c = c_fraction * max S``; ``V = 0`` where ``l2`` has the
    wrong sign for the polarity (``l2 < 0`` for bright vessels, ``> 0`` for dark ones).

    Returns
    -------
    dict
        ``polarity -> V``, the maximum over scales (float32, same shape as ``image``).
    """
    image = np.asarray(image, dtype=np.float32)
    best = {polarity: np.zeros_like(image) for polarity in polarities}
    for sigma in sigmas:
        l1, l2 = _hessian_eigenvalues(image, float(sigma))
        structure = l1 ** 2 + l2 ** 2
        c2 = (c_fraction ** 2) * float(structure.max()) + 1e-12
        rb2 = (l1 / np.where(l2 == 0, 1e-12, l2)) ** 2
        response = np.exp(-rb2 / (2 * beta ** 2)) * (1 - np.exp(-structure / (2 * c2)))
        for polarity, running in best.items():
            right_sign = (l2 < 0) if polarity == "bright" else (l2 > 0)
            np.maximum(running, np.where(right_sign, response, 0.0), out=running)
    return best


def _grey_frame(image: np.ndarray, photometric: str | None) -> np.ndarray:
    """The frame as a float32 grey image (RGB averaged), MONOCHROME1 turned to MONOCHROME2."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[-1] in (3, 4):
        image = image[..., :3].mean(axis=-1)
    if image.ndim != 2 or min(image.shape) < 1:
        raise InputError(f"fluoroscopy frame must be 2D (or RGB), got shape {image.shape}")
    image = image.astype(np.float32, copy=False)
    if not np.isfinite(image).all():
        raise InputError("fluoroscopy frame contains NaN or infinite values")
    if photometric is not None and photometric.upper() == "MONOCHROME1":
        image = -image
    return image


def _normalise(image: np.ndarray) -> np.ndarray:
    """``image`` scaled to [0, 1] by its 0.5 / 99.5 percentiles."""
    lo, hi = np.percentile(image, [0.5, 99.5])
    if hi <= lo:
        raise InputError("fluoroscopy frame is flat (no contrast)")
    return np.clip((image - lo) / (hi - lo), 0.0, 1.0)


def _local_contrast(image: np.ndarray, radius: int) -> np.ndarray:
    """White top-hat: ``image`` minus its grey opening with a (2 radius + 1)^2 square."""
    size = 2 * radius + 1
    return image - ndi.grey_dilation(ndi.grey_erosion(image, size=(size, size)), size=(size, size))


def segment_fluoro(image: np.ndarray, prior: "FluoroPrior | None" = None, *, vessels: str = "auto",
                   photometric: str | None = None,
                   sigmas=(1.0, 2.0, 3.0, 4.5), work_size: int = 256, high: float = 0.25, low: float = 0.08,
                   contrast_fraction: float = 0.35, min_area_fraction: float = 0.002) -> np.ndarray:
    """Binary vessel mask of a fluoroscopy / DSA frame on the frame's pixel grid.

    The frame (MONOCHROME1 inverted when ``photometric`` says so) is reduced by a block mean
    to about ``work_size`` pixels, normalised, and turned so that vessels are bright. Frangi
    vesselness over ``sigmas`` (pixels of the reduced grid) is hysteresis-thresholded at
    ``high`` / ``low`` times its 99.5th percentile to find the vessel tree; its extent is then
    refined by local contrast (white top-hat above ``contrast_fraction`` of the tree's median
    contrast), objects smaller than ``min_area_fraction`` of the frame are dropped, and the
    slightly smoothed result is upsampled bilinearly to the input grid and cut at 0.5.

    With a ``prior`` (the pre-operative tree projected through P, :class:`FluoroPrior`) the
    search is confined to a band around the projected tree, widened by the expected
    deformation (:data:`DEFORMATION_MARGIN_MM`); the polarity is read off the frame (inside
    the projected tree darker or brighter than around it, so subtracted and plain frames of
    either polarity work); the Frangi scales follow the projected radii; a white top-hat
    removes bone, soft tissue, table and collimator edges (broad or step-like structures);
    long, straight components thinner than the vessel expected there (wires, catheters,
    sheaths) are dropped. A (n, rows, cols) run is reduced to its frame with the most
    contrast inside the projected tree (:func:`select_frame`).

    Parameters
    ----------
    image : numpy.ndarray
        2D frame (any numeric dtype; RGB is averaged) or a (n, rows, cols) run.
    prior : FluoroPrior, optional
        Where the vessels must be; None keeps the prior-free behaviour.
    vessels : {'dark', 'bright', 'auto'}
        Vessel polarity after the photometric correction; ``'auto'`` picks the one with the
        stronger tubular response (without a prior) or the one the prior sees (with it).
    photometric : str, optional
        DICOM Photometric Interpretation; ``'MONOCHROME1'`` inverts the grey scale.

    Returns
    -------
    numpy.ndarray of bool
        Vessel mask, same shape as (one frame of) ``image``.
    """
    if vessels not in ("dark", "bright", "auto"):
        raise ValueError(f"vessels must be 'dark', 'bright' or 'auto', got {vessels!r}")
    frames = _frames(image)
    image = frames[select_frame(image, prior, photometric=photometric)] if len(frames) > 1 else image
    frame = _grey_frame(image, photometric)
    if prior is not None:
        return _segment_fluoro_with_prior(frame, prior, vessels, work_size, high, low, contrast_fraction,
                                          min_area_fraction)
    factor = max(1, int(round(max(frame.shape) / work_size)))
    small = _normalise(_downsample(frame, factor))
    responses = vesselness(small, sigmas, polarities=("bright", "dark") if vessels == "auto" else (vessels,))
    if vessels == "auto":    # the polarity with the stronger tubular responses
        vessels = max(responses, key=lambda polarity: float(np.percentile(responses[polarity], 98)))
    oriented = small if vessels == "bright" else 1.0 - small
    vessel = _vessel_region(oriented, responses[vessels], max(sigmas), high, low, contrast_fraction)
    vessel = _remove_small_objects(vessel, min_area_fraction * vessel.size)
    soft = ndi.gaussian_filter(vessel.astype(np.float32), 0.5)     # smooth edges before upsampling
    return _upsample(soft, factor, frame.shape) > 0.5


def _vessel_region(oriented: np.ndarray, response: np.ndarray, max_sigma: float, high: float, low: float,
                   contrast_fraction: float, reference: float | None = None) -> np.ndarray:
    """Binary vessel mask on the reduced grid: the hysteresis tree widened by local contrast.

    ``reference`` (default: the 99.5th percentile of ``response``) is what ``high`` and ``low``
    are fractions of."""
    reference = (float(np.percentile(response, 99.5)) if reference is None else reference) + 1e-12
    tree = apply_hysteresis_threshold(response / reference, low, high)
    if not tree.any():
        return tree
    radius = int(math.ceil(3 * max_sigma))
    contrast = _local_contrast(oriented, radius)
    tree_contrast = float(np.median(contrast[tree]))
    if tree_contrast <= 0:
        return tree
    near_tree = ndi.binary_dilation(tree, iterations=int(math.ceil(max_sigma)))
    vessel = (contrast > contrast_fraction * tree_contrast) & near_tree
    labels, _ = ndi.label(vessel)
    touching = np.unique(labels[tree & vessel])
    return np.isin(labels, touching[touching > 0])


def dice(a, b) -> float:
    """Dice overlap ``2 |A & B| / (|A| + |B|)`` of two binary masks (1.0 when both are empty)."""
    a = np.asarray(a.array if isinstance(a, Volume) else a) > 0
    b = np.asarray(b.array if isinstance(b, Volume) else b) > 0
    if a.shape != b.shape:
        raise ValueError(f"mask shapes differ: {a.shape} vs {b.shape}")
    total = a.sum() + b.sum()
    return 1.0 if total == 0 else float(2.0 * np.logical_and(a, b).sum() / total)



# ----------------------------------------------------------------------------------------
# CT without learning: trace the aorta slice by slice, grow the lumen, follow the branches
# ----------------------------------------------------------------------------------------

#: Lumen radii (mm) a traced aorta may have, and the HU window of contrast-filled blood used
#: to find it before the seed's own statistics are known.
AORTA_RADIUS_MM = (7.0, 22.0)
CONTRAST_HU = (150.0, 600.0)
#: Cortical bone: denser than any contrast lumen.
BONE_HU = 700.0
#: Soft tissue around the vessels; the lumen edge is taken half way between it and the lumen.
SOFT_TISSUE_HU = 40.0
#: Smallest radius (mm) of a traced common iliac, and the scales (mm) of the branch vesselness.
ILIAC_MIN_RADIUS_MM = 2.5
BRANCH_SIGMAS_MM = (1.5, 2.5, 4.0)
#: How far (mm along the branch) a branch may reach from the aorta or iliacs.
BRANCH_REACH_MM = 70.0


def _slice_axes_mm(ct: Volume) -> tuple[float, float]:
    """In-plane spacing (row = j, column = i) in mm."""
    return float(ct.spacing[1]), float(ct.spacing[0])


def _superior_step(ct: Volume) -> int:
    """+1 when increasing k goes superior (towards +z in LPS), else -1."""
    return 1 if (ct.direction @ np.array([0.0, 0.0, 1.0]))[2] >= 0 else -1


def _posterior_sign_j(ct: Volume) -> float:
    """+1 when increasing j goes posterior (towards +y in LPS), else -1 (or 0 if oblique)."""
    return float(np.sign(ct.direction[1, 1]))


def _round_blobs(hu_slice: np.ndarray, spacing_ji, hu_window, radius_mm) -> list[dict]:
    """Round bright blobs of one axial slice: centre (j, i), inscribed radius (mm), circle score.

    The circle score is the area of the inscribed disc over the blob's area (1 for a disc,
    small for an elongated or branched blob) times the blob's solidity.
    """
    lo, hi = hu_window
    smooth = ndi.gaussian_filter(hu_slice.astype(np.float32), 0.7 / np.asarray(spacing_ji))
    inside = ndi.binary_opening((smooth >= lo) & (smooth <= hi), iterations=1)
    labels, n = ndi.label(inside)
    if n == 0:
        return []
    pixel_mm2 = spacing_ji[0] * spacing_ji[1]
    min_px = math.pi * radius_mm[0] ** 2 / pixel_mm2
    max_px = 4.0 * math.pi * radius_mm[1] ** 2 / pixel_mm2
    blobs = []
    for region in measure.regionprops(labels, intensity_image=smooth):
        if not min_px <= region.area <= max_px:
            continue
        r0, c0, r1, c1 = region.bbox
        edt = ndi.distance_transform_edt(np.pad(region.image, 1), sampling=spacing_ji)[1:-1, 1:-1]
        radius = float(edt.max())
        if not radius_mm[0] <= radius <= radius_mm[1]:
            continue
        peak = np.unravel_index(np.argmax(edt), edt.shape)
        disc_fraction = math.pi * radius ** 2 / (region.area * pixel_mm2)
        blobs.append({"centre": np.array([r0 + peak[0], c0 + peak[1]], dtype=float), "radius": radius,
                      "score": min(disc_fraction, 1.0) * region.solidity, "hu": float(region.intensity_mean)})
    return blobs


def _spine_behind(hu_slice: np.ndarray, centre_ji, radius_mm: float, spacing_ji, posterior: float,
                  reach_mm: float = 45.0, half_width_mm: float = 12.0) -> bool:
    """True if cortical bone lies within ``reach_mm`` posterior of a blob's edge (a vertebra)."""
    if posterior == 0:
        return True
    j0, i0 = centre_ji
    start = j0 + posterior * radius_mm / spacing_ji[0]
    stop = start + posterior * reach_mm / spacing_ji[0]
    rows = slice(int(max(min(start, stop), 0)), int(min(max(start, stop) + 1, hu_slice.shape[0])))
    half = int(round(half_width_mm / spacing_ji[1]))
    cols = slice(int(max(i0 - half, 0)), int(min(i0 + half + 1, hu_slice.shape[1])))
    strip = hu_slice[rows, cols]
    return strip.size > 0 and bool((strip > BONE_HU).sum() >= 3)


def _inside_bone(hu_slice: np.ndarray, centre_ji, radius_mm: float, spacing_ji, ring_mm: float = 4.0,
                 max_fraction: float = 0.25) -> bool:
    """True if a ring just outside the blob is largely cortical bone (a vertebral body's
    cancellous core is as bright and as round as the aorta, but the aorta is never walled by bone)."""
    reach = radius_mm + ring_mm
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int) + 1
    lo = np.maximum(np.floor(centre_ji).astype(int) - half, 0)
    hi = np.minimum(np.floor(centre_ji).astype(int) + half + 1, hu_slice.shape)
    rows, cols = np.ogrid[lo[0]:hi[0], lo[1]:hi[1]]
    dist = np.hypot((rows - centre_ji[0]) * spacing_ji[0], (cols - centre_ji[1]) * spacing_ji[1])
    ring = (dist > radius_mm + 0.5) & (dist <= reach)
    return bool(ring.any() and (hu_slice[lo[0]:hi[0], lo[1]:hi[1]][ring] > BONE_HU).mean() > max_fraction)


def find_aorta_in_slices(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, step_mm: float = 5.0):
    """The best aorta cross-section of the CT: a bright round blob in front of the spine.

    Axial slices every ``step_mm`` are searched for round blobs inside ``hu_window`` with an
    inscribed radius in ``radius_mm`` and cortical bone behind them (the vertebral body);
    the blob with the best circle score (times a preference for the middle of the range)
    wins.

    Returns
    -------
    (k, centre_ji, radius_mm, score) or None
    """
    spacing_ji = _slice_axes_mm(ct)
    posterior = _posterior_sign_j(ct)
    step = max(1, int(round(step_mm / ct.spacing[2])))
    best = None
    for k in range(step // 2, ct.shape[0], step):
        hu_slice = np.asarray(ct.array[k])
        for blob in _round_blobs(hu_slice, spacing_ji, hu_window, radius_mm):
            if not _spine_behind(hu_slice, blob["centre"], blob["radius"], spacing_ji, posterior):
                continue
            if _inside_bone(hu_slice, blob["centre"], blob["radius"], spacing_ji):
                continue
            if best is None or blob["score"] > best[3]:
                best = (k, blob["centre"], blob["radius"], blob["score"])
    return best


class _Trace:
    """One vessel followed through the axial slices: centre (j, i) and radius (mm) per slice."""

    def __init__(self, name: str, k: int, centre, radius: float, step: int, min_radius: float):
        self.name, self.step, self.min_radius = name, step, min_radius
        self.centres = {k: np.asarray(centre, dtype=float)}
        self.radii = {k: float(radius)}
        self.k, self.centre, self.radius = k, np.asarray(centre, dtype=float), float(radius)
        self.previous = None        # (cross-section mask, its (row, col) offset) in the last slice


def _lumen_in_slice(hu_slice: np.ndarray, centre, radius: float, spacing_ji, lumen_hu, min_radius: float,
                    max_growth: float = 1.45, previous=None, reference_radius: float | None = None,
                    detect_split: bool = True):
    """The lumen cross-section continuing a trace into the next slice.

    Pixels within ``lumen_hu`` (after a light smoothing) in a window around the predicted
    ``centre`` are labelled; the components touching the predicted core (a disc of 0.6
    ``radius``) form the candidate, clipped to ``max_growth`` ``radius`` + 2 mm. Its inscribed
    radius and the position of that maximum give the new radius and centre.

    Returns
    -------
    (mask, offset, centre, radius, split) or None
        ``mask`` is the cross-section in a window starting at ``offset`` (row, col);
        ``split`` lists (centre, radius) of the blobs the lumen split into when it is
        much narrower than before (the bifurcation).
    """
    reach = radius * max_growth + 12.0
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int)
    lo_ji = np.maximum(np.floor(centre).astype(int) - half, 0)
    hi_ji = np.minimum(np.floor(centre).astype(int) + half + 1, hu_slice.shape)
    window = hu_slice[lo_ji[0]:hi_ji[0], lo_ji[1]:hi_ji[1]].astype(np.float32)
    if min(window.shape) < 3:
        return None
    smooth = ndi.gaussian_filter(window, 0.6 / np.asarray(spacing_ji))
    inside = (smooth >= lumen_hu[0]) & (smooth <= lumen_hu[1])
    rows, cols = np.ogrid[:window.shape[0], :window.shape[1]]
    local = centre - lo_ji
    dist = np.hypot((rows - local[0]) * spacing_ji[0], (cols - local[1]) * spacing_ji[1])
    labels, _ = ndi.label(inside)
    core = dist <= 0.6 * radius
    if previous is not None:        # overlap with the last cross-section counts as well
        core |= _paste(previous[0], previous[1] - lo_ji, window.shape)
    touching = np.unique(labels[core & inside])
    touching = touching[touching > 0]
    if len(touching) == 0:      # the lumen left the predicted core: ended, or split into two
        near = np.unique(labels[(dist <= radius) & inside])
        candidate = np.isin(labels, near[near > 0]) & (dist <= max_growth * radius + 2.0)
        if not candidate.any():
            return None
        edt = ndi.distance_transform_edt(candidate, sampling=spacing_ji)
        return None, lo_ji, None, float(edt.max()), _split_blobs(candidate, edt, lo_ji, spacing_ji, ILIAC_MIN_RADIUS_MM)
    candidate = np.isin(labels, touching) & (dist <= max_growth * radius + 2.0)
    edt = ndi.distance_transform_edt(candidate, sampling=spacing_ji)
    new_radius = float(edt.max())
    split = _split_blobs(candidate, edt, lo_ji, spacing_ji, ILIAC_MIN_RADIUS_MM) if detect_split else []
    if len(split) == 2 and split[1][1] >= 0.5 * split[0][1]:     # two lumens of similar size: a bifurcation
        return None, lo_ji, None, new_radius, split
    if new_radius < min_radius:
        return None
    if new_radius < 0.6 * (reference_radius or radius):
        return None, lo_ji, None, new_radius, _split_blobs(candidate, edt, lo_ji, spacing_ji, ILIAC_MIN_RADIUS_MM)
    own = np.where(dist <= max(radius, 2.0 * max(spacing_ji)), edt, 0.0)   # this vessel's centre, not a neighbour's
    peak = np.array(np.unravel_index(np.argmax(own), own.shape), dtype=float)
    new_radius = float(own.max()) if own.max() >= min_radius else new_radius
    new_dist = np.hypot((rows - peak[0]) * spacing_ji[0], (cols - peak[1]) * spacing_ji[1])
    mask = candidate & (new_dist <= 1.25 * new_radius + 1.5)
    return mask, lo_ji, peak + lo_ji, new_radius, []


def _paste(mask: np.ndarray, offset, shape) -> np.ndarray:
    """``mask`` placed at ``offset`` (row, col) in an empty array of ``shape`` (clipped)."""
    out = np.zeros(shape, dtype=bool)
    r0, c0 = int(offset[0]), int(offset[1])
    rs, cs = max(r0, 0), max(c0, 0)
    re, ce = min(r0 + mask.shape[0], shape[0]), min(c0 + mask.shape[1], shape[1])
    if re > rs and ce > cs:
        out[rs:re, cs:ce] = mask[rs - r0:re - r0, cs - c0:ce - c0]
    return out


def _split_blobs(candidate, edt, offset, spacing_ji, min_radius: float) -> list:
    """(centre, radius) of the (at most two) widest separate lumens in ``candidate``: maxima of the
    distance map at least ``min_radius`` deep and two radii apart (the two iliacs below the
    bifurcation, still joined by partial volume or already apart)."""
    from skimage.feature import peak_local_max

    min_distance = max(1, int(round(2 * min_radius / max(spacing_ji))))
    peaks = peak_local_max(edt, min_distance=min_distance, threshold_abs=min_radius, num_peaks=2,
                           exclude_border=False)
    return [(np.asarray(p, dtype=float) + offset, float(edt[tuple(p)])) for p in peaks]


def _follow(trace: _Trace, ct: Volume, lumen_hu, out: np.ndarray, label: int, progress=None) -> list:
    """Extend ``trace`` slice by slice until the lumen ends; paint it into ``out``.

    Radius continuity (the new radius between 0.6 and ``max_growth`` times the last one,
    smoothed) keeps the trace out of the heart, the arch's far side and side branches.
    Returns the blobs the lumen split into where it stopped (for the iliacs), else [].
    """
    spacing_ji = _slice_axes_mm(ct)
    k = trace.k + trace.step
    while 0 <= k < ct.shape[0]:
        recent = [trace.radii[j] for j in sorted(trace.radii, key=lambda j: -abs(j - k))[-15:]]
        found = _lumen_in_slice(np.asarray(ct.array[k]), trace.centre, trace.radius, spacing_ji, lumen_hu,
                                trace.min_radius, previous=trace.previous, reference_radius=float(np.median(recent)),
                                detect_split=trace.name == "aorta")
        if found is None:
            return []
        mask, offset, centre, radius, split = found
        if mask is None:
            return [(k, c, r) for c, r in split]
        view = out[k, offset[0]:offset[0] + mask.shape[0], offset[1]:offset[1] + mask.shape[1]]
        view[mask & (view == 0)] = label
        trace.centres[k], trace.radii[k] = centre, radius
        trace.previous = (mask, offset)
        trace.centre = centre
        trace.radius = 0.7 * trace.radius + 0.3 * radius
        trace.k = k
        if progress is not None:
            progress()
        k += trace.step
    return []


def trace_aorta(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, progress=None):
    """Find the aorta and follow it up and down the CT, then the common iliacs below it.

    Returns
    -------
    labels : numpy.ndarray of uint8
        1 = aorta lumen, 2 = iliac lumen, per slice (no side branches yet).
    traces : list of _Trace
    lumen_hu : (float, float)
        The lumen intensity range taken from the seed's statistics.
    """
    found = find_aorta_in_slices(ct, hu_window=hu_window, radius_mm=radius_mm)
    if found is None:
        raise InputError(f"no aorta found: no round blob of {radius_mm[0]:.0f}-{radius_mm[1]:.0f} mm radius in "
                         f"HU {hu_window[0]:.0f}-{hu_window[1]:.0f} in front of the spine in any axial slice")
    k0, centre, radius, _ = found
    lumen_hu = _lumen_range(np.asarray(ct.array[k0]), centre, radius, _slice_axes_mm(ct))
    labels = np.zeros(ct.shape, dtype=np.uint8)
    first = _lumen_in_slice(np.asarray(ct.array[k0]), centre, radius, _slice_axes_mm(ct), lumen_hu, radius_mm[0])
    if first is None or first[0] is None:
        raise InputError(f"no aorta found: the blob in slice {k0} does not hold the lumen intensity {lumen_hu}")
    mask, offset, centre, radius, _ = first
    labels[k0, offset[0]:offset[0] + mask.shape[0], offset[1]:offset[1] + mask.shape[1]][mask] = 1
    counter = _SliceCounter(ct.shape[0], progress)
    up = _superior_step(ct)
    traces = []
    for step in (up, -up):
        trace = _Trace("aorta", k0, centre, radius, step, radius_mm[0] * 0.6)
        traces.append(trace)
        _follow(trace, ct, lumen_hu, labels, 1, counter)
        if step == -up:
            seeds = _bifurcation(ct, trace, lumen_hu)
            if seeds:
                _cut_trace_below(trace, seeds[0][0], labels)
                _fill_crotch(ct, trace, seeds[0][0], lumen_hu, labels)
            for k, c, r in seeds:
                iliac = _Trace("iliac", k - step, c, r, step, ILIAC_MIN_RADIUS_MM)
                traces.append(iliac)
                _follow(iliac, ct, lumen_hu, labels, 2, counter)
    return labels, traces, lumen_hu


def _two_lumens(ct: Volume, k: int, centre, radius: float, lumen_hu) -> list:
    """The two common iliacs in slice ``k`` just below an aortic cross-section (``centre``,
    ``radius`` in the slice above), or [].

    Two distance-map maxima of the lumen near the aorta, each at least ILIAC_MIN_RADIUS_MM
    deep and at most 0.9 ``radius``, of similar size (ratio >= 0.7: the common iliacs are
    nearly symmetric, a visceral or renal branch beside the aorta is not), at least 0.8 times the
    sum of their radii apart (two lumens, not one flattened one), and both inside the aortic
    cross-section above (+ 3 mm): the iliacs come out of the aorta, a neighbour (IVC, SMA) does not.
    """
    from skimage.feature import peak_local_max

    spacing_ji = _slice_axes_mm(ct)
    reach = 1.6 * radius + 8.0
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int)
    lo = np.maximum(np.floor(centre).astype(int) - half, 0)
    hi = np.minimum(np.floor(centre).astype(int) + half + 1, ct.shape[1:])
    rows, cols = np.ogrid[lo[0]:hi[0], lo[1]:hi[1]]
    disc = np.hypot((rows - centre[0]) * spacing_ji[0], (cols - centre[1]) * spacing_ji[1]) <= reach
    window = ndi.gaussian_filter(np.asarray(ct.array[k, lo[0]:hi[0], lo[1]:hi[1]], dtype=np.float32),
                                 0.6 / np.asarray(spacing_ji))
    edt = ndi.distance_transform_edt((window >= lumen_hu[0]) & (window <= lumen_hu[1]) & disc, sampling=spacing_ji)
    min_distance = max(1, int(round(2 * ILIAC_MIN_RADIUS_MM / max(spacing_ji))))
    peaks = peak_local_max(edt, min_distance=min_distance, threshold_abs=ILIAC_MIN_RADIUS_MM, num_peaks=2,
                           exclude_border=False)
    if len(peaks) < 2:
        return []
    radii = edt[tuple(peaks.T)]
    centres = peaks.astype(float) + lo
    apart = np.hypot(*((peaks[0] - peaks[1]) * np.asarray(spacing_ji)))
    from_aorta = np.hypot(*((centres - centre) * np.asarray(spacing_ji)).T)
    if (apart >= 0.8 * radii.sum() and radii.min() >= 0.7 * radii.max() and radii.max() <= 0.9 * radius
            and np.all(from_aorta <= radius + 3.0)):
        return [(k, c, float(r)) for c, r in zip(centres, radii)]
    return []


def _bifurcation(ct: Volume, aorta: _Trace, lumen_hu, search_mm: float = 30.0, tolerance_mm: float = 10.0) -> list:
    """Where the downward aorta trace splits into the common iliacs, or [].

    The split lies near or below the last slice where the trace still had the aorta's width
    (beyond it the trace may have followed one iliac): from ``tolerance_mm`` above that slice
    down to the trace's end, the first traced slice whose next slice holds :func:`_two_lumens`;
    else the first such slice within ``search_mm`` below that last full-width slice or below
    the trace's end. An aorta that keeps its width to the end of the scan has no split.

    Returns
    -------
    list of (k, centre_ji, radius_mm), two entries or none
    """
    ks = sorted(aorta.centres, key=lambda k: k * aorta.step)
    typical = float(np.median([aorta.radii[k] for k in ks]))
    k_wide = [k for k in ks if aorta.radii[k] >= 0.85 * typical][-1]     # the last slice of full aortic width
    first = k_wide - aorta.step * int(round(tolerance_mm / ct.spacing[2]))
    for k in ks:
        below = k + aorta.step
        if (k - first) * aorta.step >= 0 and 0 <= below < ct.shape[0]:
            found = _two_lumens(ct, below, aorta.centres[k], aorta.radii[k], lumen_hu)
            if found:
                return found
    for k_ref in dict.fromkeys((k_wide, ks[-1])):
        for n in range(1, int(search_mm / ct.spacing[2]) + 1):
            below = k_ref + n * aorta.step
            if not 0 <= below < ct.shape[0]:
                break
            found = _two_lumens(ct, below, aorta.centres[k_ref], aorta.radii[k_ref], lumen_hu)
            if found:
                return found
    return []


def _fill_crotch(ct: Volume, aorta: _Trace, k_split: int, lumen_hu, labels: np.ndarray) -> None:
    """Label as iliac (2) the lumen between the aorta's last slice and the slice where the two
    iliacs are first apart (the crotch), within the aorta's reach, so the tree stays connected."""
    k_last = max(aorta.centres, key=lambda k: k * aorta.step)
    centre, radius = aorta.centres[k_last], aorta.radii[k_last]
    spacing_ji = _slice_axes_mm(ct)
    reach = 1.45 * radius + 2.0
    half = np.ceil(reach / np.asarray(spacing_ji)).astype(int)
    lo = np.maximum(np.floor(centre).astype(int) - half, 0)
    hi = np.minimum(np.floor(centre).astype(int) + half + 1, ct.shape[1:])
    rows, cols = np.ogrid[lo[0]:hi[0], lo[1]:hi[1]]
    disc = np.hypot((rows - centre[0]) * spacing_ji[0], (cols - centre[1]) * spacing_ji[1]) <= reach
    for k in range(k_last + aorta.step, k_split + aorta.step, aorta.step):
        window = ndi.gaussian_filter(np.asarray(ct.array[k, lo[0]:hi[0], lo[1]:hi[1]], dtype=np.float32),
                                     0.6 / np.asarray(spacing_ji))
        view = labels[k, lo[0]:hi[0], lo[1]:hi[1]]
        view[(window >= lumen_hu[0]) & (window <= lumen_hu[1]) & disc & (view == 0)] = 2


def _cut_trace_below(trace: _Trace, k_cut: int, labels: np.ndarray) -> None:
    """Forget the part of a downward trace at and beyond slice ``k_cut`` (it followed one iliac)."""
    for k in [k for k in trace.centres if (k - k_cut) * trace.step >= 0]:
        labels[k][labels[k] == 1] = 0
        del trace.centres[k], trace.radii[k]


class _SliceCounter:
    """Calls ``progress(done, total)`` once per traced slice (capped at ``total``)."""

    def __init__(self, total: int, progress):
        self.total, self.progress, self.done = total, progress, 0

    def __call__(self):
        self.done = min(self.done + 1, self.total)
        if self.progress is not None:
            self.progress(self.done, self.total)


def _lumen_range(hu_slice: np.ndarray, centre, radius: float, spacing_ji) -> tuple[float, float]:
    """Lumen HU range from the seed disc: from half way to soft tissue up to below bone."""
    rows, cols = np.ogrid[:hu_slice.shape[0], :hu_slice.shape[1]]
    disc = np.hypot((rows - centre[0]) * spacing_ji[0], (cols - centre[1]) * spacing_ji[1]) <= 0.6 * radius
    values = hu_slice[disc].astype(np.float64)
    mean, std = float(np.median(values)), float(np.std(values))
    lo = 0.5 * (mean + SOFT_TISSUE_HU)
    hi = min(mean + max(4.0 * std, 250.0), BONE_HU + 200.0)
    return lo, hi


def _coarse_factor(ct: Volume, target_mm: float) -> np.ndarray:
    """Integer (k, j, i) block sizes bringing the voxels near ``target_mm``."""
    spacing_kji = np.asarray(ct.spacing, dtype=float)[::-1]
    return np.maximum(1, np.round(target_mm / spacing_kji)).astype(int)


def _block_reduce(array: np.ndarray, factor, func) -> np.ndarray:
    """``func`` (np.mean / np.max) over ``factor`` blocks, the array cropped to whole blocks."""
    factor = tuple(int(f) for f in factor)
    shape = tuple(s // f for s, f in zip(array.shape, factor))
    cropped = array[:shape[0] * factor[0], :shape[1] * factor[1], :shape[2] * factor[2]]
    blocks = cropped.reshape(shape[0], factor[0], shape[1], factor[1], shape[2], factor[2])
    return func(blocks, axis=(1, 3, 5))


def _trunk_box(labels: np.ndarray, ct: Volume, margin_mm: float) -> tuple[slice, ...]:
    """Index box of the traced lumen grown by ``margin_mm`` in plane and along z."""
    box = _bounding_box(labels > 0)
    margins = np.ceil(margin_mm / np.asarray(ct.spacing)[::-1]).astype(int)
    return tuple(slice(max(b.start - m, 0), min(b.stop + m, n)) for b, m, n in zip(box, margins, labels.shape))


def _symmetric_eigenvalues_3d(hxx, hyy, hzz, hxy, hxz, hyz) -> np.ndarray:
    """Eigenvalues of symmetric 3x3 matrices given by their six fields, sorted by absolute value
    (|l1| <= |l2| <= |l3|), in closed form (trigonometric solution of the characteristic cubic)."""
    q = (hxx + hyy + hzz) / 3.0
    p1 = hxy ** 2 + hxz ** 2 + hyz ** 2
    p2 = (hxx - q) ** 2 + (hyy - q) ** 2 + (hzz - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0) + 1e-12
    bxx, byy, bzz = (hxx - q) / p, (hyy - q) / p, (hzz - q) / p
    det = (bxx * (byy * bzz - (hyz / p) ** 2) - (hxy / p) * ((hxy / p) * bzz - (hyz / p) * (hxz / p))
           + (hxz / p) * ((hxy / p) * (hyz / p) - byy * (hxz / p)))
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    e1 = q + 2.0 * p * np.cos(phi)
    e3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    values = np.stack([e1, e2, e3])
    order = np.argsort(np.abs(values), axis=0)
    return np.take_along_axis(values, order, axis=0)


def tubularity_3d(volume: np.ndarray, sigmas_vox, *, blob_beta: float = 0.5) -> np.ndarray:
    """Bright-tube response of a 3D array, maximum over scales (Sato / Frangi family).

    At each scale the Hessian of the Gaussian-smoothed volume (finite differences) gives
    eigenvalues ``|l1| <= |l2| <= |l3|``; a bright tube has ``l2, l3 < 0`` and ``l1 ~ 0``. The
    response is ``sigma^2 (-l2)`` where ``l2, l3 < 0``, damped by ``exp(-(l1 / l2)^2 / (2
    blob_beta^2))`` when ``l1 < 0`` too (a blob: kidney, heart chamber, bowel loop).
    """
    volume = np.asarray(volume, dtype=np.float32)
    best = np.zeros_like(volume)
    for sigma in sigmas_vox:
        smooth = ndi.gaussian_filter(volume, sigma, mode="nearest")
        gk, gj, gi = np.gradient(smooth)
        hkk, hkj, hki = np.gradient(gk)
        hjj, hji = np.gradient(gj, axis=(1, 2))
        hii = np.gradient(gi, axis=2)
        l1, l2, l3 = _symmetric_eigenvalues_3d(hii, hjj, hkk, hji, hki, hkj)
        tube = (l2 < 0) & (l3 < 0)
        blob = np.where(l1 < 0, np.exp(-(l1 / np.where(l2 == 0, -1e-12, l2)) ** 2 / (2 * blob_beta ** 2)), 1.0)
        np.maximum(best, np.where(tube, sigma ** 2 * -l2 * blob, 0.0).astype(np.float32), out=best)
    return best


def grow_branches(ct: Volume, trunk: np.ndarray, lumen_hu, *, sigmas_mm=BRANCH_SIGMAS_MM,
                  reach_mm: float = BRANCH_REACH_MM, voxel_mm: float = 1.5, min_vesselness: float = 0.04):
    """Side branches (renal, visceral, iliac continuations) connected to the traced trunk.

    On a copy reduced to about ``voxel_mm`` voxels around the trunk, bright tubular voxels
    (:func:`tubularity_3d` over ``sigmas_mm`` above ``min_vesselness`` of the lumen contrast, inside
    ``lumen_hu``, away from cortical bone) are kept if they connect to the trunk within
    ``reach_mm`` (geodesic steps through the candidates); round blobs (kidneys, heart, bowel)
    respond weakly to the tubular filter and stay out. The result is brought back to the CT
    grid and intersected with the lumen intensity range.

    Returns
    -------
    numpy.ndarray of bool
        Branch voxels on the CT grid (not including ``trunk``).
    """
    box = _trunk_box(trunk, ct, reach_mm)
    factor = _coarse_factor(ct, voxel_mm)
    hu = np.asarray(ct.array[box], dtype=np.float32)
    coarse = _block_reduce(hu, factor, np.mean)
    coarse_trunk = _block_reduce(trunk[box] > 0, factor, np.max)
    bone = ndi.binary_dilation(_block_reduce(hu > BONE_HU, factor, np.max), iterations=1)
    coarse_mm = np.asarray(ct.spacing, dtype=float)[::-1] * factor
    sigmas = [s / float(coarse_mm.mean()) for s in sigmas_mm]
    contrast = float(lumen_hu[0] * 2 - SOFT_TISSUE_HU) - SOFT_TISSUE_HU
    tubular = tubularity_3d(np.clip(coarse, SOFT_TISSUE_HU - 200, lumen_hu[1]), sigmas) > min_vesselness * contrast
    candidate = tubular & (coarse >= 0.5 * (lumen_hu[0] + SOFT_TISSUE_HU)) & (coarse <= lumen_hu[1]) & ~bone
    seeds = ndi.binary_dilation(coarse_trunk, iterations=1) & candidate
    steps = int(math.ceil(reach_mm / float(coarse_mm.min())))
    reached = ndi.binary_dilation(seeds, iterations=steps, mask=candidate | coarse_trunk) & ~coarse_trunk
    full = np.zeros(trunk.shape, dtype=bool)
    if reached.any():
        grown = ndi.binary_dilation(reached, iterations=1)
        upsampled = np.repeat(np.repeat(np.repeat(grown, factor[0], 0), factor[1], 1), factor[2], 2)
        region = tuple(slice(b.start, b.start + n) for b, n in zip(box, upsampled.shape))
        smooth = ndi.gaussian_filter(np.asarray(ct.array[region], dtype=np.float32),
                                     0.6 / np.asarray(ct.spacing)[::-1])
        full[region] = upsampled & (smooth >= lumen_hu[0]) & (smooth <= lumen_hu[1])
    return full & (trunk == 0)


def segment_ct_classical(ct: Volume, *, hu_window=CONTRAST_HU, radius_mm=AORTA_RADIUS_MM, branches: bool = True,
                         progress=None, postprocess: bool = True, return_labels: bool = False):
    """Lumen mask of the aorta tree without any training (the fallback that always works).

    1. :func:`find_aorta_in_slices`: the roundest bright blob in front of the spine.
    2. :func:`trace_aorta`: follow it up and down slice by slice (overlap with the predicted
       core, radius continuity), then the two common iliacs below the bifurcation; the
       lumen range comes from the seed's own statistics.
    3. :func:`grow_branches`: tubular bright voxels connected to the trunk (renals, visceral
       arteries, iliac continuations); heart, kidneys, bowel and bone are not tubes.

    Parameters
    ----------
    ct : Volume
        Contrast CT in HU (any spacing, slice thickness and field of view).
    progress : callable, optional
        ``progress(done_slices, total_slices)`` while tracing.
    return_labels : bool
        Also return a label Volume: 1 aorta, 2 iliacs, 3 side branches.

    Returns
    -------
    Volume (and the label Volume)
        Boolean lumen mask on the CT grid.
    """
    _check_ct(ct)
    labels, _, lumen_hu = trace_aorta(ct, hu_window=hu_window, radius_mm=radius_mm, progress=progress)
    if branches:
        labels[grow_branches(ct, labels, lumen_hu)] = 3
    mask = ct.with_array(labels > 0)
    if postprocess:
        mask = postprocess_mask(mask)
    if progress is not None:
        progress(ct.shape[0], ct.shape[0])
    if return_labels:
        return mask, ct.with_array(np.where(mask.array, labels, 0).astype(np.uint8))
    return mask


# ----------------------------------------------------------------------------------------
# Fluoroscopy with the pre-operative tree as a prior
# ----------------------------------------------------------------------------------------

def _frames(image: np.ndarray) -> list[np.ndarray]:
    """The frames of a run: a (n, rows, cols) stack, or one 2D (or RGB) frame."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[-1] not in (3, 4):
        return [image[n] for n in range(image.shape[0])]
    return [image]


def _polarity_by_prior(small: np.ndarray, distance: np.ndarray, nearest: np.ndarray, prior: FluoroPrior,
                       factor: int) -> str:
    """'dark' or 'bright': the sign of (inside the projected tree) - (a ring just outside it)."""
    radius = prior.radii_px[nearest] / factor
    core = distance <= np.maximum(0.5 * radius, 1.0)
    ring = (distance > radius + 2.0) & (distance <= 2.0 * radius + 6.0)
    if not core.any() or not ring.any():
        return "dark"
    return "dark" if np.median(small[core]) < np.median(small[ring]) else "bright"


def frame_contrast_in_prior(frame: np.ndarray, prior: FluoroPrior, *, photometric=None, work_size: int = 256) -> float:
    """|median inside the projected tree - median of a ring around it| over the frame's spread."""
    grey = _grey_frame(frame, photometric)
    factor = max(1, int(round(max(grey.shape) / work_size)))
    small = _downsample(grey, factor)
    spread = float(np.subtract(*np.percentile(small, [99.5, 0.5])))
    if spread <= 0:
        return 0.0
    distance, nearest = prior.rasterise(small.shape, factor)
    radius = prior.radii_px[np.maximum(nearest, 0)] / factor
    core = distance <= np.maximum(0.5 * radius, 1.0)
    ring = (distance > radius + 2.0) & (distance <= 2.0 * radius + 6.0)
    if not core.any() or not ring.any():
        return 0.0
    return abs(float(np.median(small[core]) - np.median(small[ring]))) / spread


def select_frame(image: np.ndarray, prior: FluoroPrior | None = None, *, photometric=None) -> int:
    """Index of the frame of a run with the most contrast inside the projected tree.

    Without a prior: the frame with the strongest top-hat contrast (the fullest vessels).
    """
    frames = _frames(image)
    if len(frames) == 1:
        return 0
    if prior is not None:
        scores = [frame_contrast_in_prior(f, prior, photometric=photometric) for f in frames]
    else:
        scores = []
        for f in frames:
            small = _downsample(_grey_frame(f, photometric), max(1, int(round(max(f.shape[:2]) / 128))))
            lo, hi = np.percentile(small, [0.5, 99.5])
            scores.append(0.0 if hi <= lo else float(np.percentile(_local_contrast(-(small - lo) / (hi - lo), 4), 99)))
    return int(np.argmax(scores))


def _straight_thin_devices(mask: np.ndarray, expected_width: np.ndarray, *, straightness: float = 0.08,
                           width_ratio: float = 0.55, min_length: float = 20.0) -> np.ndarray:
    """Components that look like a wire, catheter or sheath: long, very straight and thinner than
    the vessel expected where they lie. Returns the mask of those components."""
    labels, n = ndi.label(mask)
    devices = np.zeros_like(mask)
    for index, region in enumerate(ndi.find_objects(labels), start=1):
        if region is None:
            continue
        component = labels[region] == index
        coords = np.argwhere(component).astype(float)
        if len(coords) < 3:
            continue
        centred = coords - coords.mean(axis=0)
        eigen = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred / len(coords)), 0.0))
        length = 2.0 * math.sqrt(3.0) * eigen[1]
        width = len(coords) / max(length, 1.0)
        expected = float(np.median(expected_width[region][component]))
        if length >= min_length and eigen[0] / max(eigen[1], 1e-9) <= straightness and width < width_ratio * expected:
            devices[region] |= component
    return devices


def _within_expected_width(vessel: np.ndarray, radius: np.ndarray, slack: float = 1.4) -> np.ndarray:
    """Pixels no farther from the mask's centre line than ``slack`` times the expected radius
    (+1 px): a vessel cannot be wider than the pre-operative lumen allows, a vertebra or a
    bowel loop touching it can."""
    from skimage.morphology import skeletonize

    if not vessel.any():
        return vessel
    spine = skeletonize(vessel)
    distance, (ri, ci) = ndi.distance_transform_edt(~spine, return_indices=True)
    return distance <= slack * radius[ri, ci] + 1.0


def _prior_scales(prior: FluoroPrior, factor: int, n_scales: int) -> np.ndarray:
    """Frangi scales (px of the reduced grid) spanning 0.6 x the projected radii (5th-99th percentile)."""
    r_min = max(float(np.percentile(prior.radii_px, 5)) / factor, 0.8)
    r_max = max(float(np.percentile(prior.radii_px, 99)) / factor, r_min)
    return np.geomspace(max(0.6 * r_min, 0.8), max(0.6 * r_max, 1.0), n_scales)


def _percentile_among_zeros(values: np.ndarray, q: float, total: int) -> float:
    """``np.percentile`` (linear) of ``values`` (>= 0) padded with zeros to ``total`` entries,
    without building the padded array: the cropped response ranks as the whole grid's would."""
    values = values.ravel()
    zeros = total - values.size
    position = q / 100.0 * (total - 1) - zeros
    if position < 0:
        return 0.0
    below = int(math.floor(position))
    low_high = np.partition(values, [below, min(below + 1, values.size - 1)])
    low, high = float(low_high[below]), float(low_high[min(below + 1, values.size - 1)])
    if below == -1:
        low = 0.0
    return low + (position - below) * (high - low)


def _segment_fluoro_with_prior(frame: np.ndarray, prior: FluoroPrior, vessels: str, work_size: int,
                               high: float, low: float, contrast_fraction: float, min_area_fraction: float,
                               n_scales: int = 4):
    """Vessel mask of one grey frame, looking only in the band around the projected tree.

    Everything runs on the band's bounding box (padded by the filters' reach), read off the
    prior once per grid (:meth:`FluoroPrior.band`); thresholds that are fractions of the
    whole reduced grid (response percentile, smallest object) keep counting the whole grid.
    """
    factor = max(1, int(round(max(frame.shape) / work_size)))
    small_shape = (-(-frame.shape[0] // factor), -(-frame.shape[1] // factor))
    sigmas = _prior_scales(prior, factor, n_scales)
    reach = int(math.ceil(4 * sigmas[-1])) + int(math.ceil(3 * sigmas[-1])) + 2
    where = prior.band(small_shape, factor, reach)
    rows, cols = where.box
    crop = frame[rows.start * factor:rows.stop * factor, cols.start * factor:cols.stop * factor]
    small = _normalise(_downsample(crop, factor))
    distance, nearest, radius, band = where.distance, where.nearest, where.radius, where.band
    if vessels == "auto":
        vessels = _polarity_by_prior(small, distance, nearest, prior, factor)
    oriented = small if vessels == "bright" else 1.0 - small
    response = vesselness(oriented, sigmas, polarities=("bright",))["bright"] * band
    total = small_shape[0] * small_shape[1]
    reference = _percentile_among_zeros(response, 99.5, total)
    vessel = _vessel_region(oriented, response, float(sigmas[-1]), high, low, contrast_fraction,
                            reference=reference) & band
    vessel &= _within_expected_width(vessel, radius)
    thin = vessel & ~ndi.binary_opening(vessel, structure=ndi.generate_binary_structure(2, 1))
    vessel &= ~(thin & (radius >= 2.0) & (distance > radius + 2.0))   # lines off a wide vessel's projection
    vessel &= ~_straight_thin_devices(vessel, 2.0 * radius)
    vessel = _remove_small_objects(vessel, min_area_fraction * total)
    soft = ndi.gaussian_filter(vessel.astype(np.float32), 0.5)
    full = np.zeros(frame.shape, dtype=bool)
    full[rows.start * factor:rows.stop * factor, cols.start * factor:cols.stop * factor] = \
        _upsample(soft, factor, crop.shape) > 0.5
    return full

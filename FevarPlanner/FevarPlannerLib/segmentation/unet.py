"""UNet: the network, its CT preprocessing, training and slice-by-slice inference (paper Section II-A)."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from .. import files, io
from ..files import InputError, atomic_path
from ..io import Volume
from .threshold import _check_ct, _lps_flips, postprocess_mask


#: Where the shipped weights lie relative to FevarPlannerLib: inside an installed Slicer module
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
               hu_window=DEFAULT_NET_HU_WINDOW, checkpoint_every: int = 200, init=None) -> Path:
    """Train the lumen UNet with the paper's recipe and save a resumable checkpoint.

    Cross-entropy loss, SGD (``lr``, ``momentum``), ``batch_size`` slices per step; each sample
    is a random slice resampled to ``pixel_mm``, cut to a ``crop`` x ``crop`` window around the
    lumen ("window slicing") and mapped by a random linear intensity transform ("linear
    mapping") before the HU window.

    Parameters
    ----------
    data : iterable or slice source
        Case folders (with ``ct.*`` and ``aorta_mask.*``) or ``(ct, mask)`` Volume pairs; or an
        object with ``sample(rng, crop, hu_window) -> (image, label)`` tensors, such as
        :class:`.synthetic.SyntheticSlices` (slices drawn afresh at every step).
    out_path : path
        Checkpoint file; rewritten atomically every ``checkpoint_every`` iterations and at the end.
    iterations : int
        Total number of optimiser steps (a resumed run continues up to this number).
    resume : path, optional
        Checkpoint to continue from (weights, optimiser, iteration count and random state).
    progress : callable, optional
        ``progress(done, total, message)`` after every iteration (``cli.ProgressBar.count``).
    init : path, optional
        Checkpoint whose network (configuration and weights) starts this run (fine-tuning);
        the optimiser, iteration count and random state start afresh. Ignored with ``resume``.

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
    if init is not None and resume is None:
        start = _load_checkpoint(init)
        model = UNet(**start["model_config"])
        model.load_state_dict(start["model_state"])
        optimizer = torch.optim.SGD(model.parameters(), lr=lr, momentum=momentum)
        settings["init"] = str(init)
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
    bank = data if hasattr(data, "sample") else _SliceBank(_as_training_pairs(data), settings["pixel_mm"])
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
    here = Path(__file__).resolve().parent.parent   # FevarPlannerLib
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

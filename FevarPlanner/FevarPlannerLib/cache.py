"""The pre-operative model of a patient, computed once and kept on disk.

Segmenting the CT (tens of seconds) and thinning, classifying and centring its skeleton
(seconds) depend only on the CT side of a case. :func:`preop_model` does that work once
and stores the result (lumen mask, skeleton graph with its classification, the labelled
centreline, and the lumen surface on demand) under a key made of

* the bytes and grid of the 3D input actually used (CT, given lumen mask or skeleton),
* the segmenter and, for the UNet, the bytes of its weights (only when the CT is segmented),
* the code version: the bytes of every module of this package.

Any change to one of them gives a new key, so a stale entry is never used. Entries are
pickles in :func:`default_cache_dir` (``$FEVAR_PLANNER_CACHE``, else
``$XDG_CACHE_HOME/fevar-planner``, else ``~/.cache/fevar-planner``), written through a
temporary file and a rename; an unreadable entry is recomputed and replaced.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .files import write_bytes_atomic
from .io import Case, Volume
from .preop import build_preop

__all__ = ["CACHE_FORMAT", "PreopModel", "default_cache_dir", "volume_digest", "code_digest", "preop_key",
           "preop_model", "clear_cache"]

#: Bumped when the layout of a cache entry changes (the code digest covers the rest).
CACHE_FORMAT = 1
PACKAGE_DIR = Path(__file__).resolve().parent


@dataclass
class PreopModel:
    """Everything pre-operative about one patient, as :func:`preop_model` returns it.

    Attributes
    ----------
    preop : preop.Preoperative
        The classified, centred, labelled 3D skeleton graph (paper Algorithm 2 rows 1-2).
    lumen : Volume or None
        The lumen mask (bool) it came from; None when the case gave only a skeleton.
    key : str
        The cache key (hex).
    timings : dict
        Seconds of the work as it was first done, plus ``preop_cache_load`` on a hit.
    from_cache : bool
        True when it was read from disk.
    """

    preop: object
    lumen: Volume | None
    key: str
    timings: dict = field(default_factory=dict)
    from_cache: bool = False
    _surface: object = field(default=None, repr=False)

    def surface(self, case: Case | None = None):
        """The lumen surface (vtkPolyData, LPS mm), made once per model.

        Without a lumen (the case gave a skeleton), the surface of the ``case``'s aorta mask
        when it offers one (read by the case's own rules, :meth:`io.Case.load_input`);
        else None.
        """
        if self._surface is None:
            lumen = self.lumen
            if lumen is None and case is not None and "aorta_mask" in case.available:
                lumen = case.load_input("aorta_mask")
            if lumen is not None:
                from .segmentation import mask_surface

                self._surface = mask_surface(lumen, smooth_sigma_vox=1.0)
        return self._surface


def default_cache_dir() -> Path:
    """``$FEVAR_PLANNER_CACHE``, else ``$XDG_CACHE_HOME/fevar-planner``, else ``~/.cache/fevar-planner``."""
    if os.environ.get("FEVAR_PLANNER_CACHE"):
        return Path(os.environ["FEVAR_PLANNER_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fevar-planner"


def volume_digest(volume: Volume) -> str:
    """SHA-256 of a volume's voxels (with their type and shape) and its LPS grid."""
    digest = hashlib.sha256()
    array = np.ascontiguousarray(volume.array)
    digest.update(f"{array.dtype.str}{array.shape}".encode())
    digest.update(memoryview(array).cast("B"))
    for values in (volume.spacing, volume.origin, volume.direction):
        digest.update(np.round(np.asarray(values, dtype=float), 6).tobytes())
    return digest.hexdigest()


def code_digest() -> str:
    """SHA-256 of every module of this package and its subpackages: any code change invalidates the cache."""
    digest = hashlib.sha256(f"format {CACHE_FORMAT}".encode())
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        digest.update(path.relative_to(PACKAGE_DIR).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def preop_key(case: Case, segmenter: str = "classical") -> str:
    """The cache key of a case's pre-operative model (see the module docstring)."""
    stage = case.stage_3d
    parts = [f"stage {stage}", volume_digest(case.reference_volume), code_digest()]
    if stage == "ct":
        parts.append(f"segmenter {segmenter}")
        if segmenter == "unet":
            from .segmentation import default_model_path

            weights = default_model_path()
            parts.append(_file_digest(weights) if weights.is_file() else "no weights")
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _packed(lumen: Volume | None):
    """A lumen mask as bits (an 8th of the bytes: a 512 x 512 x 300 CT's mask is 10 MB, not 79)."""
    if lumen is None:
        return None
    array = np.asarray(lumen.array) > 0
    return {"bits": np.packbits(array), "shape": array.shape, "spacing": lumen.spacing, "origin": lumen.origin,
            "direction": lumen.direction}


def _unpacked(packed) -> Volume | None:
    if packed is None:
        return None
    count = int(np.prod(packed["shape"]))
    array = np.unpackbits(packed["bits"], count=count).astype(bool).reshape(packed["shape"])
    return Volume(array, packed["spacing"], packed["origin"], packed["direction"])


def _entry_path(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / f"preop-{key[:32]}.pkl"


#: numpy's own helpers an array pickle calls (everything else from numpy must be a class).
_NUMPY_FUNCTIONS = {"_reconstruct", "_frombuffer", "scalar"}


class _EntryUnpickler(pickle.Unpickler):
    """Unpickles only what a cache entry is made of: classes of this package, numpy arrays and
    dtypes, scipy sparse matrices. Anything else (``os.system``, ``builtins.eval``, ...) in a
    planted or foreign file raises instead of running."""

    def find_class(self, module: str, name: str):
        found = super().find_class(module, name)
        package = __package__ or "FevarPlannerLib"
        allowed = ((module.startswith(package + ".") or module.startswith("scipy.sparse")) and isinstance(found, type)
                   or module.split(".")[0] == "numpy" and (isinstance(found, type) or name in _NUMPY_FUNCTIONS))
        if not allowed:
            raise pickle.UnpicklingError(f"{module}.{name} is not part of a cache entry")
        return found


def _load_entry(path: Path, key: str):
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):   # a pipe or device is never opened
            return None
        with open(path, "rb") as handle:
            entry = _EntryUnpickler(handle).load()
    except FileNotFoundError:
        return None
    except Exception:  # a truncated, foreign or planted file is recomputed and replaced, never trusted
        return None
    return entry if isinstance(entry, dict) and entry.get("key") == key else None


def preop_model(case: Case, *, segmenter: str = "classical", progress=None, cache_dir=None,
                use_cache: bool = True) -> PreopModel:
    """The case's pre-operative model: from the cache when the same inputs were seen, else computed.

    Parameters
    ----------
    case : Case
    segmenter : {"classical", "unet", "threshold"}
        CT segmentation for a case holding only a CT.
    progress : callable, optional
        ``progress(fraction, message)``.
    cache_dir : path, optional
        Default :func:`default_cache_dir`.
    use_cache : bool
        False: compute, and neither read nor write the cache.
    """
    key = preop_key(case, segmenter) if use_cache else ""
    path = _entry_path(cache_dir or default_cache_dir(), key) if use_cache else None
    if path is not None:
        start = time.perf_counter()
        entry = _load_entry(path, key)
        if entry is not None:
            timings = dict(entry["timings"], preop_cache_load=time.perf_counter() - start)
            if progress is not None:
                progress(0.3, f"pre-operative model from the cache ({path.name})")
            return PreopModel(entry["preop"], _unpacked(entry["lumen"]), key, timings, from_cache=True)
    preop, lumen = build_preop(case, progress, segmenter)
    model = PreopModel(preop, lumen, key, dict(preop.timings))
    if path is not None:
        payload = {"key": key, "preop": preop, "lumen": _packed(lumen), "timings": model.timings}
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL))
    return model


def clear_cache(cache_dir=None) -> int:
    """Delete every cache entry in ``cache_dir``; returns how many were deleted."""
    folder = Path(cache_dir or default_cache_dir())
    entries = list(folder.glob("preop-*.pkl")) if folder.is_dir() else []
    for entry in entries:
        entry.unlink()
    return len(entries)

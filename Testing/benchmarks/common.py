"""What every benchmark shares: the test fixtures, machine facts, timing and the JSON report.

Benchmarks run as scripts (``python Testing/benchmarks/bench_x.py --out DIR``), so this folder
is on their path and ``from common import ...`` works; the shared test fixtures
(``Testing/fixtures.py``) are registered from their file as the module ``fixtures``, so that
``from fixtures import ...`` works after ``import common`` too. They run lazily, on first
use: importing this module imports no NumPy, so the BLAS thread count can still be set
after it.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import sys
import time
from pathlib import Path

__all__ = ["fixtures", "blas_threads", "single_threaded_blas", "argument_parser", "machine", "timed", "write_report",
           "pyplot", "save_figure"]

TESTING = Path(__file__).resolve().parents[1]


def blas_threads(count: int) -> None:
    """``count`` BLAS / OpenMP threads unless the caller set otherwise; call before NumPy is imported."""
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, str(count))


def single_threaded_blas() -> None:
    """One BLAS / OpenMP thread unless the caller set otherwise; call before NumPy is imported.

    The registration stages are many small BLAS calls, where extra threads only add
    contention (10x slower L-BFGS-B on a busy 2-core machine).
    """
    blas_threads(1)


def _load_fixtures():
    if "fixtures" in sys.modules:
        return sys.modules["fixtures"]
    spec = importlib.util.spec_from_file_location("fixtures", TESTING / "fixtures.py")
    spec.loader = importlib.util.LazyLoader(spec.loader)      # runs (imports NumPy) on first use
    module = importlib.util.module_from_spec(spec)
    sys.modules["fixtures"] = module
    spec.loader.exec_module(module)
    return module


def argument_parser(doc: str) -> argparse.ArgumentParser:
    """A parser described by the first line of ``doc``, with the required ``--out`` folder."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the JSON and PNG")
    return parser


def machine() -> dict:
    """Python, platform, CPU count, BLAS threads and load: what a time depends on."""
    return {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "load_average": os.getloadavg()}


def timed(function, *args, **kwargs):
    """``(function(*args, **kwargs), wall seconds, CPU seconds of this process)``."""
    wall, cpu = time.perf_counter(), time.process_time()
    value = function(*args, **kwargs)
    return value, time.perf_counter() - wall, time.process_time() - cpu


def write_report(out: Path, name: str, payload: dict) -> Path:
    """Write ``payload`` (with :func:`machine` facts added) to ``out/<name>.json``; returns the path."""
    path = Path(out) / f"{name}.json"
    path.write_text(json.dumps({"benchmark": name.removeprefix("bench_"), "machine": machine(), **payload}, indent=2))
    return path


def pyplot():
    """``matplotlib.pyplot`` on the file-only Agg backend (benchmarks run headless)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 120) -> None:
    """Lay out ``fig``, write it to ``path`` and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


fixtures = _load_fixtures()

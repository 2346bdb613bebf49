"""Sets of cases: the paper's simulation protocol (Sec. III-A/B) and random sets.

See the package docstring ("Paper protocol").
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from .case import generate_case, write_case
from .params import _DEFORMATION_FIELDS, PARAM_RANGES, PhantomParams, _draw, random_params


PAPER_STATES = 5
#: Out-of-plane bend of the sac between the paper protocol's states, degrees (see
#: :func:`paper_protocol`).
PAPER_OUT_OF_PLANE_DEG = 0.0


def paper_protocol(seed: int = 0, out_of_plane_deg: float = PAPER_OUT_OF_PLANE_DEG) -> list:
    """The paper's simulation protocol (Sec. III-A/B): 20 ``(pre_params, intra_params)`` pairs.

    One phantom (shape drawn from ``seed``) with the five main vessels only (like the
    paper's endovascular evaluator), in five deformed states, AP view, no misalignment;
    every ordered pair of different states ``(i, j)`` is one case, in the order
    ``(0, 1), (0, 2), ..., (4, 3)``.

    The paper's phantom lay on a table and was bent by a string (paper Sec. III), so its states
    differ by bending in the frontal (coronal) plane, which an AP frame sees: the sac's
    anterior bend is drawn from ``+-out_of_plane_deg`` (0 by default). The vessels' own 3D
    curvature still moves in depth as the iliacs straighten and the renals tilt. A non-zero
    ``out_of_plane_deg`` adds a bend that one view cannot see (the benchmark reports it as
    a separate set); the other parameters are drawn identically whatever its value.
    """
    rng = np.random.default_rng(seed)
    shape = random_params(rng, primary_angle_deg=0.0, secondary_angle_deg=0.0, misalign_shift_px=(0.0, 0.0),
                          misalign_rotation_deg=0.0, sma=False, coeliac=False, internal_iliacs=False)
    defaults = PhantomParams()
    ranges = {**PARAM_RANGES, "bend_anterior_deg": (-out_of_plane_deg, out_of_plane_deg)}
    states = []
    for _ in range(PAPER_STATES):
        deformation = {name: _draw(rng, getattr(defaults, name), ranges[name]) for name in _DEFORMATION_FIELDS}
        states.append(replace(shape, seed=int(rng.integers(0, 2**31 - 1)), **deformation).validate())
    return [(states[i], states[j]) for i in range(PAPER_STATES) for j in range(PAPER_STATES) if i != j]


def _planned_cases(n: int, seed: int, preset: str) -> list:
    """(name, pre_params, intra_params or None, info) for each case of a set."""
    if preset == "paper":
        planned, batch = [], 0
        while len(planned) < n:
            pairs = paper_protocol(seed + batch)
            order = [(i, j) for i in range(PAPER_STATES) for j in range(PAPER_STATES) if i != j]
            for (pre, intra), (i, j) in zip(pairs, order):
                info = {"protocol": "paper", "protocol_seed": seed + batch, "preop_state": i, "intraop_state": j}
                planned.append((f"paper{batch:02d}_pre{i}_intra{j}", pre, intra, info))
            batch += 1
        return planned[:n]
    if preset == "random":
        children = np.random.SeedSequence(seed).spawn(n)
        return [(f"case_{i:03d}", random_params(np.random.default_rng(child)), None,
                 {"protocol": "random", "set_seed": seed, "index": i}) for i, child in enumerate(children)]
    raise ValueError(f"unknown phantom preset {preset!r} (expected 'paper' or 'random')")


def write_phantom_set(out_dir, n: int = 20, seed: int = 0, preset: str = "paper", mask_only: bool = False,
                      progress=None) -> list:
    """Write ``n`` phantom cases under ``out_dir`` and return their folders.

    Parameters
    ----------
    out_dir : path
    n : int
        Number of cases; the paper preset has 20 per phantom and draws a further phantom
        (seed + 1, ...) for more.
    seed : int
    preset : {"paper", "random"}
        ``paper``: :func:`paper_protocol` pairs; ``random``: independent random cases.
    mask_only : bool
        Skip the CT series and the DICOM frame (masks, geometry and ground truth only).
    progress : callable, optional
        Called as ``progress(i, n, name)`` before case ``i`` is written.
    """
    if n < 1:
        raise ValueError(f"number of phantom cases must be positive, got {n}")
    out_dir = Path(out_dir)
    folders = []
    planned = _planned_cases(n, seed, preset)
    for i, (name, pre, intra, info) in enumerate(planned):
        if progress is not None:
            progress(i, len(planned), name)
        case = generate_case(pre, intra, name=name, info=info)
        folders.append(write_case(case, out_dir / name, mask_only=mask_only))
    return folders


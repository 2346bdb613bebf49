"""Case folders of a scenario (docs/DESIGN.md section 4; package docstring):
:func:`write_scenario` and :func:`write_scenario_set`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import files, io
from ..projection import write_geometry_json

from .plans import KINDS, Scenario, plan_scenarios
from .frames import ScenarioCase, generate, render_ct, render_dsa
from .bench import jpeg_damaged, roughened, thinned_skeleton

__all__ = [
    "write_scenario",
    "write_scenario_set",
]


def write_scenario(case: ScenarioCase | Scenario, folder, *, images: bool | None = None) -> Path:
    """Write a scenario as a case folder (docs/DESIGN.md section 4), atomically; returns the folder.

    Mask level: ``aorta_mask.nrrd`` and ``fluoro_mask.png``; a bench phantom
    (``bench_pinhole``, :mod:`scenarios.bench`) gives ``skeleton3d.nrrd`` (its rough lumen
    thinned) and a JPEG-damaged grey ``fluoro_mask.png`` instead; with ``images`` (default: the
    scenario's ``info["images"]``, the image-only kind) ``ct.nrrd`` (HU, :func:`render_ct`)
    and ``fluoro.png`` (16-bit DSA-like, :func:`render_dsa`) instead, so that the pipeline
    segments both. Beside them ``geometry.json`` (the first view's given ``P``;
    ``true_projection_matrix`` too), ``views/<name>/`` for any further view, ``gt.json``
    and ``scenario.json``.
    """
    if isinstance(case, Scenario):
        case = generate(case)
    images = bool(case.scenario.info.get("images")) if images is None else images
    rng = np.random.default_rng([case.scenario.seed, 7])
    folder = Path(folder)
    with files.atomic_folder(folder) as tmp:
        if images:
            io.write_volume(tmp / "ct.nrrd", render_ct(case.preop, case.lumen, rng))
        elif "voxel_mm" in case.scenario.info:      # a bench phantom: the raw thinned skeleton only
            rough = roughened(case.lumen, np.random.default_rng([case.scenario.seed, 11]))
            io.write_volume(tmp / "skeleton3d.nrrd", thinned_skeleton(rough))
        else:
            io.write_volume(tmp / "aorta_mask.nrrd", case.lumen)
        for k, view in enumerate(case.views):
            where = tmp if k == 0 else tmp / "views" / view.name
            where.mkdir(parents=True, exist_ok=True)
            if images:
                io.write_png(where / "fluoro.png", render_dsa(case.intraop, view.P_true, view.mask.shape, rng))
            elif "jpeg_quality" in case.scenario.info:      # a bench label as a JPEG returned it
                io.write_png(where / "fluoro_mask.png", jpeg_damaged(view.mask, case.scenario.info["jpeg_quality"]))
            else:
                io.write_mask_png(where / "fluoro_mask.png", view.mask)
            write_geometry_json(where / "geometry.json", view.P_given, true_projection_matrix=view.P_true.tolist(),
                                view=view.name, primary_angle=view.carm.primary_angle,
                                secondary_angle=view.carm.secondary_angle)
        files.write_text_atomic(tmp / "gt.json", json.dumps(case.ground_truth()))
        files.write_text_atomic(tmp / "scenario.json", json.dumps(case.scenario.to_dict(), indent=1))
    return folder


def write_scenario_set(out_dir, kinds=KINDS, n_per_kind: int = 4, seed: int = 0, progress=None) -> list:
    """Write ``n_per_kind`` cases of each kind under ``out_dir``; returns ``[(kind, folder), ...]``."""
    out_dir = Path(out_dir)
    written = []
    for kind in kinds:
        for scenario in plan_scenarios(kind, n_per_kind, seed):
            if progress is not None:
                progress(scenario.name)
            written.append((kind, write_scenario(scenario, out_dir / scenario.name)))
    return written

"""What each scenario kind draws from its seed (:func:`plan_scenarios`): the tree's shape, its
deformation, the views and the frame options of every case of a benchmark set.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .tree import SIDES, TreeShape, random_shape
from .deformations import Deformation
from .bench import bench_plan

__all__ = [
    "View",
    "Scenario",
    "plan_scenarios",
    "KINDS",
    "EXTRA_KINDS",
    "OUT_OF_PLANE_SEVERITIES_DEG",
    "ANGULATED_VIEWS_DEG",
    "SECOND_VIEW_DEG",
]

#: The scenario kinds, one benchmark set each.
KINDS = ("out_of_plane", "straightening", "clipped", "distal_forks", "wide_sac", "extra_branches", "misaligned",
         "angulated", "two_views", "image_only", "patient_like", "bench_pinhole")   # new kinds at the end: seeds kept
#: Kinds beside the benchmark sets (not in :data:`KINDS`, so not in the default independent
#: benchmark): ``misaligned_along``, a given pose off mostly along the upper aorta with a small
#: turn (:func:`_along_aorta_misalignment`), the pose check's hardest misalignment.
EXTRA_KINDS = ("misaligned_along",)
#: Severities of the out-of-plane set, degrees (bend at the bifurcation and along each iliac).
OUT_OF_PLANE_SEVERITIES_DEG = (0.0, 5.0, 10.0, 20.0)
#: Angulated views of the angulated set: (primary, LAO +; secondary, cranial +), degrees.
ANGULATED_VIEWS_DEG = ((30.0, 15.0), (-30.0, -15.0), (30.0, -15.0), (-30.0, 15.0))
#: Angle of the second view from the main (AP) one in the two-view set, degrees.
SECOND_VIEW_DEG = (30.0, 50.0, 70.0, 90.0)


@dataclass
class View:
    """One C-arm view: angles (degrees), optional top clipping and a misaligned given pose."""

    name: str = "main"
    primary_deg: float = 0.0
    secondary_deg: float = 0.0
    clip_top_mm: float | None = None      # the top border cuts the aorta this far below its top
    misalign_shift_px: tuple = (0.0, 0.0)
    misalign_rotation_deg: float = 0.0


@dataclass
class Scenario:
    """Everything one case is made of (JSON-ready through :meth:`to_dict`)."""

    name: str
    kind: str
    seed: int
    shape: TreeShape
    deformation: Deformation
    views: list = field(default_factory=lambda: [View()])
    sid_mm: float = 1150.0
    sod_mm: float = 760.0
    detector_pixel_mm: float = 0.6
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"version": 1, "family": "scenarios", "name": self.name, "kind": self.kind, "seed": self.seed,
                "shape": self.shape.to_dict(), "deformation": self.deformation.to_dict(),
                "views": [asdict(v) for v in self.views], "sid_mm": self.sid_mm, "sod_mm": self.sod_mm,
                "detector_pixel_mm": self.detector_pixel_mm, **self.info}


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def _base_deformation(rng: np.random.Generator, out_of_plane_deg: tuple = (3.0, 8.0)) -> Deformation:
    """A moderate deformation in any direction: what a stiff wire does on every kind of case."""
    return Deformation(
        aorta_bend_deg=float(rng.uniform(2.0, 6.0)), aorta_dir_deg=float(rng.uniform(0.0, 360.0)),
        bifurcation_bend_deg=float(rng.uniform(*out_of_plane_deg)), bifurcation_dir_deg=float(rng.uniform(0, 360)),
        iliac_bend_deg=tuple(float(v) for v in rng.uniform(*out_of_plane_deg, size=2)),
        iliac_dir_deg=tuple(float(v) for v in rng.uniform(0.0, 360.0, size=2)),
        straighten=tuple(float(v) for v in rng.uniform(0.2, 0.5, size=2)),
        renal_shift_mm=tuple(_signed(rng, 0.5, 3.0) for _ in SIDES),
        renal_tilt_deg=tuple(_signed(rng, 1.0, 8.0) for _ in SIDES))


def _out_of_plane_direction(rng: np.random.Generator) -> float:
    """A bend direction at least half out of an AP frame's plane: within 45 degrees of 0 or 180."""
    return float(rng.choice([0.0, 180.0]) + rng.uniform(-45.0, 45.0))


def _out_of_plane(rng: np.random.Generator, severity: float) -> Deformation:
    """Bends of ``severity`` degrees at the bifurcation and along each iliac, forwards or
    backwards and obliquely (:func:`_out_of_plane_direction`), so that severity means depth.

    The aorta bends only in the frontal plane (90 degrees), so at severity 0 nothing moves in depth.
    """
    return Deformation(aorta_bend_deg=float(rng.uniform(1.0, 4.0)), aorta_dir_deg=90.0,
                       bifurcation_bend_deg=severity, bifurcation_dir_deg=_out_of_plane_direction(rng),
                       iliac_bend_deg=(severity, severity),
                       iliac_dir_deg=(_out_of_plane_direction(rng), _out_of_plane_direction(rng)))


def _patient_like_shape(rng: np.random.Generator) -> dict:
    """Shape overrides of a patient-like tree: every side branch a CT angiogram shows (coeliac
    trunk, SMA, IMA, four lumbar arteries, internal iliacs, in the CT tree and in the
    frame; the CT reaches 40-55 mm above the coeliac trunk), an accessory renal artery running beside the main one (and narrower) on one side or both, a
    tortuous neck and tortuous iliacs that loop in projection. The internal iliacs run back
    and down into the pelvis, so that no two lumens merge in the CT."""
    # above the main renal and flatter, or below and steeper: beside it, diverging from it
    below = float(rng.choice([-1.0, 1.0]))
    accessory_below = below * float(rng.uniform(7.0, 14.0))
    coeliac_above = float(rng.uniform(28.0, 40.0))
    return {"upper_aorta": coeliac_above + float(rng.uniform(40.0, 55.0)), "sma": True, "coeliac": True, "ima": True, "lumbars": "ct", "internal_iliacs": "ct",
            "accessory_renal": str(rng.choice(["left", "right", "both"])), "accessory_below": accessory_below,
            "accessory_descent_deg": below * float(rng.uniform(8.0, 16.0)),
            "accessory_length": float(rng.uniform(40.0, 60.0)), "renal_radius": float(rng.uniform(2.8, 3.4)),
            "accessory_radius": float(rng.uniform(1.8, 2.4)),
            "accessory_turn_deg": float(rng.uniform(5.0, 30.0)),
            "sma_above": float(rng.uniform(12.0, 22.0)), "coeliac_above": coeliac_above,
            "tortuosity_mm": tuple(float(v) for v in rng.uniform(5.0, 9.0, size=2)),
            "tortuosity_waves": tuple(float(v) for v in rng.uniform(1.5, 2.5, size=2)),
            "tortuosity_plane_deg": tuple(float(rng.choice([90.0, 270.0]) + rng.uniform(-30.0, 30.0)) for _ in SIDES),
            "iliac_loop_mm": tuple(float(v) for v in rng.uniform(3.0, 6.0, size=2)),
            "neck_kink_mm": float(rng.uniform(5.0, 12.0)), "neck_kink_dir_deg": float(rng.uniform(0.0, 360.0)),
            "internal_direction": (0.2, 0.75, -0.65)}


def _along_aorta_misalignment(rng: np.random.Generator) -> dict:
    """A given pose off mostly along the upper aorta: 3-7 px along its projected course, up to
    1.5 px across it and a 1-3 degree turn about its projected centre (issue 10: a shift along a
    straight vessel barely moves it off itself, so only the turn and the renal ostia show it).
    Applied to the main view by ``frames`` (it needs the true projection of the upper aorta)."""
    return {"misalign_along_aorta": {"along_px": _signed(rng, 3.0, 7.0), "across_px": _signed(rng, 0.0, 1.5),
                                     "rotation_deg": _signed(rng, 1.0, 3.0)}}


def _kind_plan(kind: str, index: int, rng: np.random.Generator) -> tuple[dict, Deformation, list, dict]:
    """Shape overrides, deformation, views and info of case ``index`` of ``kind``."""
    shape, views, info = {}, [View()], {}
    deformation = _base_deformation(rng)
    if kind == "out_of_plane":
        severity = OUT_OF_PLANE_SEVERITIES_DEG[index % len(OUT_OF_PLANE_SEVERITIES_DEG)]
        deformation, info = _out_of_plane(rng, severity), {"severity_deg": severity}
    elif kind == "straightening":
        shape = {"tortuosity_mm": tuple(float(v) for v in rng.uniform(5.0, 9.0, size=2)),
                 "tortuosity_waves": tuple(float(v) for v in rng.uniform(1.5, 2.5, size=2))}
        deformation = replace(deformation, straighten=tuple(float(v) for v in rng.uniform(0.6, 0.9, size=2)))
    elif kind == "clipped":
        views = [View(clip_top_mm=float(rng.uniform(25.0, 45.0)))]
    elif kind == "distal_forks":
        shape = {"internal_iliacs": "frame"}
    elif kind == "wide_sac":
        shape = {"sac_radius": float(rng.uniform(28.0, 36.0)), "sac_length": float(rng.uniform(95.0, 120.0))}
    elif kind == "extra_branches":
        shape = {"sma": True, "coeliac": True, "accessory_renal": str(rng.choice(SIDES)), "lumbars": "frame",
                 "internal_iliacs": "ct"}
    elif kind == "misaligned":
        views = [View(misalign_shift_px=(_signed(rng, 3.0, 8.0), _signed(rng, 3.0, 8.0)),
                      misalign_rotation_deg=_signed(rng, 2.0, 4.0))]
    elif kind == "misaligned_along":
        info = _along_aorta_misalignment(rng)
    elif kind == "angulated":
        primary, secondary = ANGULATED_VIEWS_DEG[index % len(ANGULATED_VIEWS_DEG)]
        views = [View(primary_deg=primary, secondary_deg=secondary)]
    elif kind == "image_only":
        info = {"images": True}
    elif kind == "patient_like":
        shape = _patient_like_shape(rng)
        # the family's deformation; a wire straightens a looping iliac less (0.1-0.3): the same
        # share of a long tortuous vessel would carry its end 50-80 mm, beyond any patient's
        deformation = replace(deformation, straighten=tuple(float(v) for v in rng.uniform(0.1, 0.3, size=2)))
    elif kind == "bench_pinhole":
        shape, deformation, (primary, secondary), info = bench_plan(rng)
        views = [View(primary_deg=primary, secondary_deg=secondary)]
    elif kind == "two_views":
        angle = SECOND_VIEW_DEG[index % len(SECOND_VIEW_DEG)] * (1.0 if index % 2 == 0 else -1.0)
        name = f"{'lao' if angle > 0 else 'rao'}{abs(angle):g}"
        views = [View(), View(name=name, primary_deg=angle)]
        info = {"second_view_deg": abs(angle)}
    else:
        raise ValueError(f"unknown scenario kind {kind!r}; choose one of {', '.join(KINDS + EXTRA_KINDS)}")
    return shape, deformation, views, info


def plan_scenarios(kind: str, n: int, seed: int = 0) -> list[Scenario]:
    """``n`` scenarios of ``kind``, drawn from ``seed`` (the kind's own stream of it)."""
    if n < 1:
        raise ValueError(f"number of scenarios must be positive, got {n}")
    every = KINDS + EXTRA_KINDS
    stream = np.random.SeedSequence([seed, every.index(kind) if kind in every else len(every)])
    scenarios = []
    for index, child in enumerate(stream.spawn(n)):
        rng = np.random.default_rng(child)
        case_seed = int(rng.integers(0, 2**31 - 1))
        overrides, deformation, views, info = _kind_plan(kind, index, rng)
        shape = random_shape(rng, **overrides)
        geometry = {"sid_mm": float(rng.uniform(1050.0, 1200.0)), "sod_mm": float(rng.uniform(720.0, 800.0))}
        geometry.update(info.pop("geometry", {}))    # a kind's own C-arm (bench_pinhole) wins
        scenarios.append(Scenario(f"{kind}_{index:02d}", kind, case_seed, shape, deformation, views, **geometry,
                                  info=info))
    return scenarios

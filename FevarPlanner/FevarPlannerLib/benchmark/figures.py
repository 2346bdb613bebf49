"""The benchmark's figures (matplotlib, Agg): bars per case, robustness curves, the
independent sets and their per-vessel depth errors. Each takes its numbers ready-made."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["bar_figure", "robustness_figure", "independent_sets_figure", "independent_vessels_figure"]


def bar_figure(path: Path, cases: list[dict], title: str, methods) -> None:
    """Per case: mean ± std 2D and 3D error of each method in ``methods`` (labels), side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    x = np.arange(len(cases))
    width = 0.8 / len(methods)
    for k, label in enumerate(methods):
        for ax, key in zip(axes, ("2d_px", "3d_mm")):
            rows = [c["results"].get(label, {}) for c in cases]
            means = [r[key]["mean"] if key in r else np.nan for r in rows]
            stds = [r[key]["std"] if key in r else 0.0 for r in rows]
            ax.bar(x + (k - 1) * width, means, width, yerr=stds, label=label, capsize=2)
    for ax, ylabel in zip(axes, ("2D distance (px)", "3D distance (mm)")):
        ax.set_xticks(x, [c["name"] for c in cases], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(ylabel)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def robustness_figure(path: Path, robustness: dict) -> None:
    """Error against the in-plane translation and rotation of the frame, per method (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("2d_px", "2D distance (px)"), ("3d_mm", "3D distance (mm), patient moved"),
              ("3d_mm_if_P_off", "3D distance (mm), P off instead"))
    fig, axes = plt.subplots(2, 3, figsize=(16, 7.5))
    for row, kind in enumerate(("translation_px", "rotation_deg")):
        points = robustness[kind]
        offsets = [p["offset"] for p in points]
        for label in points[0]["results"]:
            for col, (key, ylabel) in enumerate(panels):
                values = [p["results"][label].get(key, {}).get("mean", np.nan) for p in points]
                stds = [p["results"][label].get(key, {}).get("std", 0.0) for p in points]
                axes[row, col].errorbar(offsets, values, yerr=stds, marker="o", capsize=3, label=label)
                axes[row, col].set_xlabel("in-plane translation (px)" if row == 0 else "in-plane rotation (deg)")
                axes[row, col].set_ylabel(ylabel)
                axes[row, col].set_yscale("log")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"Robustness to an in-plane offset of the frame ({robustness['case']}); the methods keep P")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def independent_sets_figure(path: Path, summaries: dict, methods) -> None:
    """Per set: 3D, in-plane and along-ray error of each method (means), the depth floor drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summaries)
    x = np.arange(len(names))
    width = 0.8 / len(methods)
    panels = (("3d_mm", "3D error (mm)", True), ("in_plane_mm", "in-plane part (mm)", False),
              ("along_ray_mm", "along-ray part (mm)", True))
    fig, axes = plt.subplots(1, 3, figsize=(19, 5.2), sharey=True)
    floors = [summaries[n]["depth_floor_mm"] for n in names]
    for ax, (key, title, with_floor) in zip(axes, panels):
        for k, label in enumerate(methods):
            offset = (k - (len(methods) - 1) / 2) * width
            ax.bar(x + offset, [summaries[n]["methods"][label].get(key, np.nan) for n in names], width, label=label)
        if with_floor:
            ax.hlines(floors, x - 0.45, x + 0.45, colors="k", linewidth=2, label="depth floor")
        ax.set_xticks(x, [n.replace("Independent: ", "") for n in names], rotation=35, ha="right")
        ax.set_title(title)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("mean over the set's cases (mm)")
    fig.suptitle("Independent sets (scenarios family, case-folder route) and the single-view depth floor")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def independent_vessels_figure(path: Path, pooled: dict, n_cases: int, vessels) -> None:
    """Per vessel over all independent cases: along-ray error per method against the floor, and
    the fraction of the true along-ray motion recovered. ``pooled``: method label -> vessel ->
    its means (the independent sets' per-vessel summary over every case)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(vessels))
    width = 0.8 / len(pooled)
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.8))
    for k, label in enumerate(pooled):
        offset = (k - (len(pooled) - 1) / 2) * width
        along = [pooled[label].get(v, {}).get("along_ray_mm") for v in vessels]
        recovered = [pooled[label].get(v, {}).get("out_of_plane_recovered") for v in vessels]
        axes[0].bar(x + offset, [np.nan if a is None else a for a in along], width, label=label)
        axes[1].bar(x + offset, [np.nan if r is None else r for r in recovered], width, label=label)
    reference = pooled.get("SV", {})
    floors = [reference.get(v, {}).get("depth_floor_mm") for v in vessels]
    true_along = [reference.get(v, {}).get("true_along_ray_mm") for v in vessels]
    axes[0].hlines([np.nan if f is None else f for f in floors], x - 0.45, x + 0.45, colors="k", label="depth floor")
    axes[0].plot(x, [np.nan if t is None else t for t in true_along], "kx", label="true along-ray motion")
    axes[0].set_ylabel("along-ray error, mean (mm)")
    axes[1].axhline(0.0, color="k", linewidth=0.8)
    axes[1].set_ylim(-1.05, 1.05)
    axes[1].set_ylabel("out-of-plane motion recovered (1 = all; clipped at -1)")
    for ax in axes:
        ax.set_xticks(x, vessels)
        ax.legend(fontsize=8)
    fig.suptitle(f"Per vessel, all independent cases ({n_cases})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

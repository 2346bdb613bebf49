"""The rows of the results table: a planning result in words, for every front end.

The workstation and the Slicer module both fill their table from :func:`summary_rows`,
so that both describe a result in the same words. Pure Python (no Qt, no VTK).
"""

from __future__ import annotations

from numbers import Real

__all__ = ["METRIC_NAMES", "FIT_NAMES", "format_metric", "summary_rows"]

#: Readable names of the metrics that :func:`FevarPlannerLib.evaluation.evaluate` returns.
METRIC_NAMES = {
    "2d_px": "2D error: result \u2192 skeleton (px)",
    "2d_reverse_px": "2D error: skeleton \u2192 result (px)",
    "3d_mm": "3D error: result \u2192 truth (mm)",
    "3d_reverse_mm": "3D error: truth \u2192 result (mm)",
    "3d_symmetric_mm": "3D error: symmetric (mm)",
}
#: Without ground truth the 2D distances measure how well the result fits the frame's own
#: skeleton; they are not errors and are not called so.
FIT_NAMES = {
    "2d_px": "2D fit to the frame's skeleton: result \u2192 skeleton (px)",
    "2d_reverse_px": "2D fit to the frame's skeleton: skeleton \u2192 result (px)",
}


def format_metric(value) -> str:
    """One metric as text: ``mean ± std (max m)`` for distance statistics, else ``str``."""
    if value is None:
        return "n/a (no ground truth)"
    if isinstance(value, dict) and {"mean", "std"} <= set(value):
        text = f"{value['mean']:.2f} ± {value['std']:.2f}"
        return text + (f" (max {value['max']:.2f})" if "max" in value else "")
    if isinstance(value, Real) and not isinstance(value, bool):
        return f"{value:.3g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(str(item) for item in value)
    return str(value)


def summary_rows(result) -> list[tuple[str, str]]:
    """``(quantity, value)`` rows describing a :class:`FevarPlannerLib.pipeline.PlanResult`.

    The order is the one a reader wants: what was run, the path, the views used, the errors
    against the ground truth (when the case has one), with several views each view's own 2D
    fit, then the timings, slowest first.
    """
    path = result.path
    rows = [("Method", result.method)]
    correspondence = getattr(result, "inputs", {}).get("correspondence")
    if correspondence:
        rows.append(("Correspondence", str(correspondence)))
    rows += [
        ("Path", f"{path.start_label} → {path.target_label}"),
        ("Path length (mm)", f"{path.length_mm:.1f}"),
        ("Path points", str(len(path.points))),
        ("Nodes (pre-op / recovered)", f"{len(result.preop)} / {len(result.deformed)}"),
        ("2D skeleton nodes", str(len(result.skeleton2d_points))),
    ]
    geometry = getattr(result, "geometry", None)
    if geometry:
        rows.append(("Geometry", geometry["source"] + (" (assumed isocentre, see notes)"
                                                        if geometry.get("assumptions") else "")))
    views = getattr(result, "views", None) or []
    if views:
        rows.append(("Views used", f"{len(views)} ({', '.join(view['name'] for view in views)})"))
    if hasattr(result, "depth_source"):
        rows.append(("Depth along the X-ray", result.depth_source()["note"]))
    errors = result.errors or {}
    names = METRIC_NAMES if errors.get("3d_mm") is not None else {**METRIC_NAMES, **FIT_NAMES}
    for key, value in errors.items():
        rows.append((names.get(key, key.replace("_", " ")), format_metric(value)))
    if len(views) > 1:
        rows += [(f"2D fit, view {view['name']}: result \u2192 skeleton (px)",
                  format_metric(view["2d_px"]) if view.get("2d_px") else "n/a (no node inside the frame)")
                 for view in views]
    timings = sorted(result.timings.items(), key=lambda item: (item[0] != "total", -item[1]))
    rows += [(f"Time: {name} (s)", f"{seconds:.3f}") for name, seconds in timings]
    return rows

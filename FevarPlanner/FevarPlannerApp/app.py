"""Command line of the workstation: ``fevar-planner-gui [CASE_DIR] [--run] [--view NAME] [--screenshot PNG]``.

Without a display (no ``DISPLAY`` / ``WAYLAND_DISPLAY``) Qt draws offscreen and VTK renders
with OSMesa (``libosmesa6``), so ``--run --screenshot out.png`` works on a headless server.
This module imports Qt and VTK only inside :func:`main`, after that set-up.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

__all__ = ["configure_headless", "parse_args", "main"]

METHODS = ("proposed", "icp-tps", "rigid")
STARTS = ("iliac_right", "iliac_left")
TARGETS = ("renal_left", "renal_right")


def configure_headless(environ=os.environ) -> bool:
    """Select offscreen Qt and OSMesa VTK when there is no display; returns True if it did.

    Settings the caller already made are kept.
    """
    if environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY") or sys.platform in ("win32", "darwin"):
        return False
    environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
    return True


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"window size must look like 1600x900, got {text!r}") from None
    if width < 400 or height < 300:
        raise argparse.ArgumentTypeError(f"window size must be at least 400x300, got {text!r}")
    return width, height


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="fevar-planner-gui",
        description="FevarPlanner workstation: recover the intra-operative aorta from a pre-operative CT and one "
                    "fluoroscopic frame, and plan a catheter path (Zheng et al., ICRA 2019).")
    parser.add_argument("case_dir", nargs="?", type=Path, help="case folder (ct/ or ct.nrrd, fluoro.dcm or .png, ...)")
    parser.add_argument("--method", choices=METHODS, default="proposed")
    parser.add_argument("--start", choices=STARTS, default="iliac_right", help="access vessel")
    parser.add_argument("--target", choices=TARGETS, default="renal_left", help="target vessel")
    parser.add_argument("--out", type=Path, help="also write result.json, .vtp, .mrk.json and overlay.png here")
    parser.add_argument("--run", action="store_true", help="plan the case as soon as the window opens")
    parser.add_argument("--view", metavar="NAME",
                        help="after the run, show this view's frame (main, or a views/<name>/ folder of the case)")
    parser.add_argument("--screenshot", type=Path, metavar="PNG",
                        help="save the window to PNG and quit (after the run, with --run)")
    parser.add_argument("--size", type=_size, default=(1600, 900), metavar="WxH", help="window size (default 1600x900)")
    args = parser.parse_args(argv)
    if args.run and args.case_dir is None:
        parser.error("--run needs a CASE_DIR")
    if args.view is not None and not args.run:
        parser.error("--view needs --run")
    if args.case_dir is not None and not args.case_dir.is_dir():
        parser.error(f"{args.case_dir}: case folder does not exist")
    return args


def _set_combo(window, name: str, text: str) -> None:
    combo = window.widget(name)
    combo.setCurrentIndex(combo.findText(text))


def main(argv=None) -> int:
    """Open the workstation; returns the process exit code."""
    args = parse_args(argv)
    headless = configure_headless()

    from PySide6.QtWidgets import QApplication

    from FevarPlannerApp.window import MainWindow, apply_dark_palette

    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setApplicationName("FevarPlanner")
    apply_dark_palette(app)
    window = MainWindow(args.case_dir, interactive=not (headless or args.screenshot))
    for name, value in (("methodComboBox", args.method), ("startComboBox", args.start),
                        ("targetComboBox", args.target)):
        _set_combo(window, name, value)
    if args.out is not None:
        window.widget("outputDirLineEdit").setText(str(args.out))
    window.resize(*args.size)
    window.show()
    app.processEvents()

    if args.run:
        window.run_plan()
        window.wait_until_done()
        if window.last_error:
            print(f"fevar-planner-gui: {window.last_error}", file=sys.stderr)
            if args.screenshot:
                return 1
        elif args.view is not None and args.view not in window.view_names():
            print(f"fevar-planner-gui: {args.case_dir}: no view {args.view!r}; the views are "
                  f"{', '.join(window.view_names())}", file=sys.stderr)
            if args.screenshot:
                return 2
        elif args.view is not None:
            window.show_view(window.view_names().index(args.view))
    if args.screenshot:
        app.processEvents()
        print(window.save_screenshot(args.screenshot))
        window.close()
        return 0
    return app.exec()


if __name__ == "__main__":
    raise SystemExit(main())

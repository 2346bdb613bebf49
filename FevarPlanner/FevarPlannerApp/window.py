"""The workstation's main window: the shared .ui panel beside the 3D and 2D views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import QFile, QPoint, Qt, QThread, QTimer
from PySide6.QtGui import QAction, QColor, QIcon, QImage, QKeySequence, QPainter, QPalette, QPixmap
from PySide6.QtUiTools import QUiLoader
from PySide6.QtWidgets import (QApplication, QDialog, QDialogButtonBox, QFileDialog, QHBoxLayout, QHeaderView, QLabel,
                               QMainWindow, QMessageBox, QPushButton, QScrollArea, QSlider, QSplitter, QTabBar,
                               QTableWidgetItem, QVBoxLayout, QWidget)

from FevarPlannerApp.views import FluoroView, View3D
from FevarPlannerApp.worker import PlanOutcome, PlanRequest, PlanWorker
from FevarPlannerLib.export import summary_rows

__all__ = ["resource_path", "load_panel", "MainWindow", "RefusalDialog", "apply_dark_palette", "as_array"]

OVERRIDES = {"ct": "ct", "aortaMask": "aorta_mask", "skeleton3d": "skeleton3d", "fluoro": "fluoro",
             "fluoroMask": "fluoro_mask", "geometry": "geometry"}
DISPLAY = {"showPreopCheckBox": "preop", "showDeformedCheckBox": "deformed", "showPathCheckBox": "path",
           "showSurfaceCheckBox": "surface"}


def resource_path(relative) -> Path:
    """A file of the repository's ``Resources`` folder.

    The workstation runs from the source tree (or an editable install), where
    ``Resources/`` sits two levels above this package: ``<repo>/FevarPlanner/FevarPlannerApp``.
    """
    path = Path(__file__).resolve().parents[2] / "Resources" / relative
    if not path.is_file():
        raise FileNotFoundError(f"FevarPlanner resource not found: {path}")
    return path


def load_panel(parent=None) -> QWidget:
    """The control panel built from ``Resources/UI/FevarPlanner.ui`` with QUiLoader."""
    ui_file = QFile(str(resource_path("UI/FevarPlanner.ui")))
    if not ui_file.open(QFile.ReadOnly):
        raise OSError(f"cannot open {ui_file.fileName()}: {ui_file.errorString()}")
    try:
        loader = QUiLoader()
        panel = loader.load(ui_file, parent)
    finally:
        ui_file.close()
    if panel is None:
        raise OSError(f"{ui_file.fileName()}: {loader.errorString()}")
    return panel


def apply_dark_palette(app: QApplication) -> None:
    """A dark Fusion theme, easy on the eyes next to the dark render views."""
    app.setStyle("Fusion")
    palette = QPalette()
    for role, color in ((QPalette.Window, "#23262e"), (QPalette.WindowText, "#e4e7ec"), (QPalette.Base, "#1a1c22"),
                        (QPalette.AlternateBase, "#262932"), (QPalette.Text, "#e4e7ec"), (QPalette.Button, "#2d313b"),
                        (QPalette.ButtonText, "#e4e7ec"), (QPalette.Highlight, "#2f7fb8"),
                        (QPalette.HighlightedText, "#ffffff"), (QPalette.ToolTipBase, "#2d313b"),
                        (QPalette.ToolTipText, "#e4e7ec"), (QPalette.PlaceholderText, "#7d8594")):
        palette.setColor(role, QColor(color))
    palette.setColor(QPalette.Disabled, QPalette.ButtonText, QColor("#6b717d"))
    palette.setColor(QPalette.Disabled, QPalette.Text, QColor("#6b717d"))
    palette.setColor(QPalette.Disabled, QPalette.WindowText, QColor("#6b717d"))
    app.setPalette(palette)


def _titled(title: str, widget: QWidget) -> QWidget:
    """``widget`` under a small caption."""
    box = QWidget()
    layout = QVBoxLayout(box)
    layout.setContentsMargins(2, 2, 2, 2)
    layout.setSpacing(2)
    caption = QLabel(title)
    caption.setStyleSheet("color: #9aa3b2; font-weight: bold; padding: 2px 4px;")
    layout.addWidget(caption)
    layout.addWidget(widget, 1)
    return box


class MainWindow(QMainWindow):
    """Panel on the left, the 3D view and the fluoroscopy view on the right.

    Parameters
    ----------
    case_dir : path, optional
        Fills the case folder field.
    interactive : bool
        Show message boxes on failure (off for headless runs).
    """

    def __init__(self, case_dir=None, *, interactive: bool = True):
        super().__init__()
        self.interactive = interactive
        self.outcome: PlanOutcome | None = None
        self._run: tuple = (None, None, None)      # (outcome, its run's FluoroRun, its prior): see _run_of
        self.last_error: str | None = None
        self.last_qc_picture: Path | None = None
        self.refusal_dialog: RefusalDialog | None = None
        self._thread: QThread | None = None
        self._worker: PlanWorker | None = None
        self.setWindowTitle("FevarPlanner \u2014 FEVAR path planning from one fluoroscopic frame")
        icon = resource_path("Icons/FevarPlanner.png")
        self.setWindowIcon(QIcon(str(icon)))

        self.panel = load_panel()
        scroll = QScrollArea()
        scroll.setWidget(self.panel)
        scroll.setWidgetResizable(True)
        scroll.setMinimumWidth(440)
        scroll.setFrameShape(QScrollArea.NoFrame)
        self.view3d = View3D()
        self.fluoro_view = FluoroView()
        self.drawings: list = []  # the shown result's ViewDrawings, one per view
        views = QSplitter(Qt.Horizontal)
        views.addWidget(_titled("Recovered intra-operative anatomy (LPS, mm)", self.view3d))
        fluoro_box = _titled("Fluoroscopic frame (u \u2192, v \u2193, pixels)", self.fluoro_view)
        fluoro_box.layout().insertWidget(1, self._view_tabs())
        fluoro_box.layout().addWidget(self._run_controls())
        views.addWidget(fluoro_box)
        views.setSizes([1, 1])
        splitter = QSplitter(Qt.Horizontal)
        splitter.addWidget(scroll)
        splitter.addWidget(views)
        splitter.setStretchFactor(0, 0)
        splitter.setStretchFactor(1, 1)
        self.setCentralWidget(splitter)
        self._menus()
        self._connect()
        if case_dir is not None:
            self.widget("caseDirLineEdit").setText(str(case_dir))
        self._update_run_button()
        self.statusBar().showMessage("Ready")

    def _view_tabs(self) -> QTabBar:
        """One tab per view of a case with several views (``views/<name>/``), above the frame view.

        The panel's own view selector (``viewComboBox``, the one the Slicer module uses) is
        hidden here: the tabs sit where the frames are seen.
        """
        self.view_tabs = QTabBar()
        self.view_tabs.setExpanding(False)
        self.view_tabs.setDrawBase(False)
        self.view_tabs.setStyleSheet(
            "QTabBar::tab { padding: 3px 12px; margin-right: 3px; color: #9aa3b2; background: #2d313b;"
            " border: 1px solid #3a3f4b; border-bottom: none; border-top-left-radius: 4px;"
            " border-top-right-radius: 4px; }"
            "QTabBar::tab:selected { color: #ffffff; background: #2f7fb8; border-color: #2f7fb8; }")
        self.view_tabs.setToolTip("The frames of the case's views: each shows its own 2D skeleton and the "
                                  "centrelines projected through its own P")
        self.view_tabs.currentChanged.connect(self.show_view)
        self.view_tabs.setVisible(False)
        for name in ("viewLabel", "viewComboBox"):
            self.widget(name).setVisible(False)
        return self.view_tabs

    def _run_controls(self) -> QWidget:
        """Frame slider and Play button for a multi-frame run (hidden for a single frame)."""
        self.run_bar = QWidget()
        layout = QHBoxLayout(self.run_bar)
        layout.setContentsMargins(4, 0, 4, 0)
        self.play_button = QPushButton("Play run")
        self.play_button.setCheckable(True)
        self.play_button.toggled.connect(self._toggle_play)
        self.frame_slider = QSlider(Qt.Horizontal)
        self.frame_slider.valueChanged.connect(self.show_frame)
        self.frame_label = QLabel("")
        for item in (self.play_button, self.frame_slider, self.frame_label):
            layout.addWidget(item)
        self._play_timer = QTimer(self)
        self._play_timer.setInterval(200)
        self._play_timer.timeout.connect(self._next_frame)
        self.run_bar.setVisible(False)
        return self.run_bar

    # ------------------------------------------------------------------ panel
    def widget(self, name: str):
        """A child of the .ui panel by object name (the names Slicer's childWidgetVariables uses)."""
        child = self.panel.findChild(QWidget, name)
        if child is None:
            raise KeyError(f"the panel has no widget named {name!r}")
        return child

    def _menus(self) -> None:
        menu = self.menuBar().addMenu("&File")
        for text, shortcut, slot in (("&Open case folder\u2026", QKeySequence.Open, self._browse_case),
                                     ("&Save screenshot\u2026", QKeySequence.Save, self._save_screenshot_dialog),
                                     ("&Quit", QKeySequence.Quit, self.close)):
            action = QAction(text, self)
            action.setShortcut(shortcut)
            action.triggered.connect(slot)
            menu.addAction(action)

    def _connect(self) -> None:
        self.widget("caseDirBrowseButton").clicked.connect(self._browse_case)
        self.widget("outputDirBrowseButton").clicked.connect(
            lambda: self._browse_folder(self.widget("outputDirLineEdit")))
        for key in OVERRIDES:
            edit = self.widget(f"{key}LineEdit")
            self.widget(f"{key}BrowseButton").clicked.connect(lambda _=False, e=edit: self._browse_file(e))
        self.widget("caseDirLineEdit").textChanged.connect(self._update_run_button)
        self.widget("runButton").clicked.connect(self.run_plan)
        for combo in ("startComboBox", "targetComboBox"):
            self.widget(combo).currentTextChanged.connect(lambda _text: self.replan())
        for box, layer in DISPLAY.items():
            self.widget(box).toggled.connect(lambda visible, name=layer: self._set_layer_visible(name, visible))

    def _browse_case(self) -> None:
        self._browse_folder(self.widget("caseDirLineEdit"))

    def _browse_folder(self, edit) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Choose a folder", edit.text())
        if folder:
            edit.setText(folder)

    def _browse_file(self, edit) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Choose an input file", edit.text())
        if path:
            edit.setText(path)

    def _update_run_button(self, *_) -> None:
        text = self.widget("caseDirLineEdit").text().strip()
        busy = self._thread is not None
        self.widget("runButton").setEnabled(bool(text) and Path(text).is_dir() and not busy)

    def _set_layer_visible(self, layer: str, visible: bool) -> None:
        for view in (self.view3d, self.fluoro_view):
            view.set_layer_visible(layer, visible)

    def request(self) -> PlanRequest:
        """The planning request the panel describes now."""
        overrides = {}
        if self.widget("overridesGroupBox").isChecked():
            overrides = {name: self.widget(f"{key}LineEdit").text().strip() for key, name in OVERRIDES.items()}
        out_dir = self.widget("outputDirLineEdit").text().strip()
        return PlanRequest(Path(self.widget("caseDirLineEdit").text().strip()),
                           method=self.widget("methodComboBox").currentText(),
                           start=self.widget("startComboBox").currentText(),
                           target=self.widget("targetComboBox").currentText(),
                           out_dir=Path(out_dir) if out_dir else None, overrides=overrides,
                           with_surface=self.widget("showSurfaceCheckBox").isChecked())

    # ------------------------------------------------------------------ running
    def run_plan(self) -> None:
        """Start planning in a worker thread; the panel reports progress and the result."""
        if self._thread is not None:
            return
        self.last_error, self.last_qc_picture = None, None
        self._thread = QThread(self)
        self._worker = PlanWorker(self.request())
        self._worker.moveToThread(self._thread)
        self._thread.started.connect(self._worker.run)
        self._worker.progress.connect(self._on_progress)
        self._worker.succeeded.connect(self._on_succeeded)
        self._worker.failed.connect(self._on_failed)
        self._worker.done.connect(self._thread.quit)
        self._thread.finished.connect(self._on_thread_finished)
        self._set_status(f"Planning {self._worker.request.case_dir.name} ({self._worker.request.method})\u2026")
        self.widget("progressBar").setValue(0)
        self._thread.start()
        self._update_run_button()

    def replan(self) -> bool:
        """Re-plan the path for the panel's access and target vessels on the shown result.

        Only the path search runs (on the recovered centreline already there): no
        registration, no segmentation. Returns whether the path changed.
        """
        from FevarPlannerLib.planning import plan_path

        if self.outcome is None or self._thread is not None:
            return False
        result = self.outcome.result
        start, target = self.widget("startComboBox").currentText(), self.widget("targetComboBox").currentText()
        if (result.path.start_label, result.path.target_label) == (start, target):
            return False
        try:
            result.path = plan_path(result.deformed, start=start, target=target)
        except ValueError as exc:
            self._on_failed(str(exc).splitlines()[0])
            return False
        for view in (self.view3d, self.fluoro_view):
            view.update_path(result)
        self._fill_table(summary_rows(result))
        self._set_status(f"re-planned on the {result.method} result: {start} \u2192 {target}, "
                         f"{result.path.length_mm:.1f} mm")
        return True

    def _run_of(self, outcome: PlanOutcome) -> tuple:
        """(io.FluoroRun, quality.FluoroPrior) of ``outcome``'s run, made once per outcome: the file
        parsed and the prior's band rasterised once, not for every frame shown."""
        from FevarPlannerLib.io import FluoroRun
        from FevarPlannerLib.quality import FluoroPrior

        if self._run[0] is not outcome:
            preop = outcome.model.preop
            self._run = (outcome, FluoroRun(outcome.case.fluoro.path),
                         FluoroPrior.from_centerline(preop.centerline, outcome.case.P))
        return self._run[1:]

    def show_frame(self, index: int) -> bool:
        """Register frame ``index`` of the shown case's run against the cached pre-operative model and show it.

        Only the frame, the recovered centreline and the path are redrawn. Returns whether
        the frame was shown.
        """
        from FevarPlannerLib.pipeline import refusal_picture
        from FevarPlannerLib.tracking import register_run_frame

        outcome = self.outcome
        if outcome is None or outcome.case is None or outcome.model is None or self._thread is not None:
            return False
        if outcome.result.inputs.get("frame", outcome.case.fluoro.frame) == index:
            return False  # already shown
        path = outcome.result.path
        run, prior = self._run_of(outcome)
        try:
            result, times = register_run_frame(outcome.model.preop, outcome.case, int(index),
                                               method=outcome.result.method, start=path.start_label,
                                               target=path.target_label, prior=prior, run=run)
        except ValueError as exc:          # a gate's refusal of this frame comes with its QC picture
            picture = refusal_picture(exc)
            self._on_failed(f"frame {index}: {str(exc).splitlines()[0]}", str(picture or ""))
            return False
        outcome.result = result
        self._set_views(result)
        self.view3d.update_recovered(result)
        for box, layer in DISPLAY.items():
            self._set_layer_visible(layer, self.widget(box).isChecked())
        self._fill_table(summary_rows(result))
        self.frame_label.setText(f"frame {index + 1}/{outcome.case.fluoro.n_frames}, {1000 * times['total']:.0f} ms")
        return True

    def show_view(self, index: int) -> bool:
        """Show view ``index`` of the shown result (its frame, 2D skeleton and projections); returns
        whether it was shown. Only the 2D view is redrawn: the registration used every view at once."""
        outcome = self.outcome
        if outcome is None or not 0 <= index < len(self.drawings):
            return False
        frame = self.drawings[index]
        self.fluoro_view.set_result(outcome.result, frame)
        for box, layer in DISPLAY.items():
            self._set_layer_visible(layer, self.widget(box).isChecked())
        if self.view_tabs.currentIndex() != index:
            self.view_tabs.blockSignals(True)
            self.view_tabs.setCurrentIndex(index)
            self.view_tabs.blockSignals(False)
        return True

    def view_names(self) -> list[str]:
        """The names of the views the shown result can display (``main`` first)."""
        return [frame.name for frame in self.drawings]

    def _set_views(self, result, case=None) -> None:
        """One tab per view of ``result`` (shown when there are several), the first view displayed."""
        self.drawings = result.view_drawings(case)
        self.view_tabs.blockSignals(True)
        while self.view_tabs.count():
            self.view_tabs.removeTab(0)
        for frame in self.drawings:
            fit = f"  (2D fit {frame.fit['mean']:.2f} px)" if frame.fit else ""
            index = self.view_tabs.addTab(f"{frame.name}{fit}")
            if frame.fit:
                fit = f"{frame.fit['mean']:.2f} \u00b1 {frame.fit['std']:.2f} px"
                self.view_tabs.setTabToolTip(index, f"view {frame.name}: the recovered centreline projected through "
                                                    f"its P lies {fit} from its 2D skeleton")
        self.view_tabs.setCurrentIndex(0)
        self.view_tabs.blockSignals(False)
        self.view_tabs.setVisible(len(self.drawings) > 1)
        self.fluoro_view.set_result(result, self.drawings[0])

    def _toggle_play(self, playing: bool) -> None:
        (self._play_timer.start if playing else self._play_timer.stop)()

    def _next_frame(self) -> None:
        self.frame_slider.setValue((self.frame_slider.value() + 1) % (self.frame_slider.maximum() + 1))

    def is_running(self) -> bool:
        """Whether a plan is being computed."""
        return self._thread is not None

    def wait_until_done(self, poll_ms: int = 20) -> None:
        """Process events until the running plan has ended (for scripted and headless use)."""
        while self._thread is not None:
            self._thread.wait(poll_ms)
            QApplication.processEvents()
        QApplication.processEvents()

    def _on_progress(self, fraction: float, message: str) -> None:
        self.widget("progressBar").setValue(int(round(100 * fraction)))
        self._set_status(message)

    def _on_succeeded(self, outcome: PlanOutcome) -> None:
        self.show_outcome(outcome)
        path = outcome.result.path
        timings = outcome.result.timings
        message = (f"{path.start_label} \u2192 {path.target_label}: {path.length_mm:.1f} mm, "
                   f"registration {timings.get('registration', float('nan')):.2f} s, "
                   f"total {timings.get('total', float('nan')):.2f} s{self._views_note()}")
        if outcome.written:
            message += f"; saved to {Path(next(iter(outcome.written.values()))).parent}"
        self._set_status(message)

    def _on_failed(self, message: str, picture: str = "") -> None:
        """One line in the status bar; a refusal's QC picture in a window beside, else a message box."""
        self.last_error = message
        self.last_qc_picture = Path(picture) if picture else None
        self.widget("progressBar").setValue(0)
        self._set_status(message, error=True)
        if self.last_qc_picture is not None:
            if self.refusal_dialog is not None:
                self.refusal_dialog.close()
            self.refusal_dialog = RefusalDialog(message, self.last_qc_picture, self)
            if self.interactive:
                self.refusal_dialog.show()     # not modal: the case can be mended and run again
        elif self.interactive:
            QMessageBox.critical(self, "FevarPlanner could not plan this case", message)

    def _on_thread_finished(self) -> None:
        self._thread.deleteLater()
        self._worker.deleteLater()
        self._thread, self._worker = None, None
        self._update_run_button()

    def _set_status(self, message: str, error: bool = False) -> None:
        label = self.widget("statusLabel")
        label.setText(message)
        label.setStyleSheet("color: #ff6b6b;" if error else "")
        self.statusBar().showMessage(message)

    # ------------------------------------------------------------------ showing
    def show_outcome(self, outcome: PlanOutcome) -> None:
        """Display a planning outcome in both views and the results table."""
        self.outcome = outcome
        self.widget("progressBar").setValue(100)
        self.view3d.set_result(outcome.result, outcome.surface)
        self._set_views(outcome.result, outcome.case)
        for box, layer in DISPLAY.items():
            self._set_layer_visible(layer, self.widget(box).isChecked())
        self._fill_table(summary_rows(outcome.result))
        frames = outcome.case.fluoro.n_frames if outcome.case is not None else 1
        self.run_bar.setVisible(frames > 1 and outcome.model is not None)
        if frames > 1:
            self.frame_slider.blockSignals(True)
            self.frame_slider.setRange(0, frames - 1)
            self.frame_slider.setValue(outcome.case.fluoro.frame)
            self.frame_slider.blockSignals(False)
            self.frame_label.setText(f"frame {outcome.case.fluoro.frame + 1}/{frames}")
        path = outcome.result.path
        self._set_status(f"{outcome.result.method}: {path.start_label} \u2192 {path.target_label}, "
                         f"{path.length_mm:.1f} mm{self._views_note()}")

    def _views_note(self) -> str:
        """``"; 2 views (main, lao30)"`` for a result registered on several views, else nothing."""
        result = self.outcome.result if self.outcome is not None else None
        views = getattr(result, "views", None) or []
        if len(views) < 2:
            return ""
        return f"; {len(views)} views ({', '.join(view['name'] for view in views)})"

    def show_result(self, result, surface=None) -> None:
        """Display a :class:`FevarPlannerLib.pipeline.PlanResult` (and an optional surface)."""
        self.show_outcome(PlanOutcome(result, surface))

    def _fill_table(self, rows) -> None:
        table = self.widget("resultsTableWidget")
        table.setRowCount(len(rows))
        for row, (quantity, value) in enumerate(rows):
            table.setItem(row, 0, QTableWidgetItem(quantity))
            item = QTableWidgetItem(value)
            item.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
            table.setItem(row, 1, item)
        header = table.horizontalHeader()
        header.setSectionResizeMode(0, QHeaderView.ResizeToContents)
        header.setSectionResizeMode(1, QHeaderView.Stretch)
        table.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        table.resizeRowsToContents()

    # ------------------------------------------------------------------ pictures
    def grab_image(self) -> QImage:
        """The whole window as an image, the VTK views' pixels painted in.

        ``QWidget.grab`` draws the Qt widgets but not what OpenGL drew into the VTK views,
        so each view's pixels are read back (vtkWindowToImageFilter) and painted over it.
        """
        image = self.grab().toImage().convertToFormat(QImage.Format_RGB888)
        painter = QPainter(image)
        ratio = image.width() / max(self.width(), 1)
        for view in (self.view3d, self.fluoro_view):
            pixels = view.pixels()
            rows, cols, _ = pixels.shape
            frame = QImage(pixels.tobytes(), cols, rows, 3 * cols, QImage.Format_RGB888)
            origin = view.mapTo(self, QPoint(0, 0))
            painter.drawImage(QPoint(int(origin.x() * ratio), int(origin.y() * ratio)),
                              frame.scaled(int(view.width() * ratio), int(view.height() * ratio)))
        painter.end()
        return image

    def save_screenshot(self, path) -> Path:
        """Write :meth:`grab_image` to a PNG file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not self.grab_image().save(str(path), "PNG"):
            raise OSError(f"{path}: could not write the screenshot")
        return path

    def _save_screenshot_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save screenshot", "fevar_planner.png", "PNG images (*.png)")
        if path:
            self._set_status(f"Screenshot saved to {self.save_screenshot(path)}")

    def closeEvent(self, event):  # noqa: N802  (Qt naming)
        if self._thread is not None:
            self._thread.quit()
            self._thread.wait(2000)
        for view in (self.view3d, self.fluoro_view):
            view.Finalize()
        super().closeEvent(event)


class RefusalDialog(QDialog):
    """Why a case was refused: the gate's one line over its QC picture.

    The picture is the one ``plan`` writes on a refusal (``segmentation_qc.png``: the frame
    with its vessel mask and the projected pre-operative tree, or CT slices and a MIP with
    the mask), shown at its own size up to ``max_width`` pixels, scrollable, with where it
    was saved.
    """

    def __init__(self, message: str, picture: Path, parent=None, max_width: int = 1100):
        super().__init__(parent)
        self.setWindowTitle("FevarPlanner refused this case")
        self.message_label = QLabel(message)
        self.message_label.setWordWrap(True)
        self.message_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.message_label.setStyleSheet("color: #ff6b6b; font-weight: bold;")
        pixmap = QPixmap(str(picture))
        if pixmap.isNull():
            raise OSError(f"{picture}: the QC picture cannot be read")
        if pixmap.width() > max_width:
            pixmap = pixmap.scaledToWidth(max_width, Qt.SmoothTransformation)
        self.picture_label = QLabel()
        self.picture_label.setPixmap(pixmap)
        scroll = QScrollArea()
        scroll.setWidget(self.picture_label)
        scroll.setMinimumSize(min(pixmap.width() + 24, max_width), min(pixmap.height() + 24, 720))
        saved = QLabel(f"QC picture saved as {picture}")
        saved.setTextInteractionFlags(Qt.TextSelectableByMouse)
        buttons = QDialogButtonBox(QDialogButtonBox.Close)
        buttons.rejected.connect(self.reject)
        layout = QVBoxLayout(self)
        for item in (self.message_label, scroll, saved, buttons):
            layout.addWidget(item)


def as_array(image: QImage) -> np.ndarray:
    """A QImage as an (rows, cols, 3) uint8 array."""
    image = image.convertToFormat(QImage.Format_RGB888)
    stride = image.bytesPerLine()
    data = np.frombuffer(image.constBits(), dtype=np.uint8, count=stride * image.height())
    return data.reshape(image.height(), stride)[:, :3 * image.width()].reshape(image.height(), image.width(), 3).copy()

"""The standalone workstation, headless: offscreen Qt and OSMesa VTK in one window.

The display tests show a PlanResult built from a phantom's true centrelines (the GUI only
displays results); the end-to-end test runs the real pipeline on a phantom case in the
worker thread.
"""

import json
import os

if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ["QT_QPA_PLATFORM"] = "offscreen"
    os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSOpenGLRenderWindow"

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("PySide6.QtUiTools")

from PySide6.QtGui import QImage  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

from FevarPlannerApp import app as cli  # noqa: E402
from FevarPlannerLib.export import summary_rows  # noqa: E402
from FevarPlannerApp.views import BACKGROUND_BOTTOM, BACKGROUND_TOP, COLORS  # noqa: E402
from FevarPlannerApp.window import MainWindow, as_array  # noqa: E402
from FevarPlannerLib import phantom, planning  # noqa: E402
from FevarPlannerLib.centerline import Centerline  # noqa: E402
from FevarPlannerLib.pipeline import METHODS, PlanResult  # noqa: E402
from FevarPlannerLib.projection import project  # noqa: E402

GREEN = np.array(COLORS["path"]) * 255


@pytest.fixture(scope="module")
def qapp():
    return QApplication.instance() or QApplication([])


@pytest.fixture(scope="module")
def plan_result():
    """The phantom's true intra-operative centreline shown as if it were the deformed one."""
    case = phantom.generate_case(phantom.PhantomParams())
    image, _ = phantom.render_fluoro(case.intraop, case.P_true, case.carm, case.params, np.random.default_rng(1))
    preop, intraop = case.preop.to_centerline(2.0), case.intraop.to_centerline(2.0)
    skeleton = project(case.P_true, intraop.points) + [3.0, 0.0]
    return PlanResult("proposed", preop, intraop, planning.plan_path(intraop), case.P_true, skeleton, intraop.edges,
                      image, {"total": 1.5, "registration": 0.25},
                      {"3d_mm": {"mean": 1.0, "std": 0.5, "median": 0.9, "max": 2.5}, "labels": ["aorta"]})


@pytest.fixture()
def window(qapp):
    win = MainWindow(interactive=False)
    win.resize(1400, 800)
    win.show()
    qapp.processEvents()
    yield win
    win.close()
    qapp.processEvents()


def _green_mask(pixels: np.ndarray) -> np.ndarray:
    """Pixels within a small distance of the path colour (lit tubes vary a little)."""
    return np.linalg.norm(pixels.astype(float) - GREEN, axis=2) < 60


def _green_rows_cols(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Path-coloured pixels below the legend (top 130 rows) and above the title (bottom 40)."""
    return np.nonzero(_green_mask(pixels[130:-40]))


def _runs_from_lower_left_to_upper_right(pixels: np.ndarray) -> bool:
    """The path (right iliac -> left renal) as seen from the front: bottom part left of the top part."""
    rows, cols = _green_rows_cols(pixels)
    low, high = np.percentile(rows, [15, 85])
    return cols[rows >= high].mean() < cols[rows <= low].mean()


def test_panel_comes_from_the_shared_ui_file(window):
    assert [window.widget("methodComboBox").itemText(i) for i in range(3)] == list(METHODS)
    assert window.widget("startComboBox").currentText() == "iliac_right"
    assert window.widget("targetComboBox").currentText() == "renal_left"
    assert window.widget("resultsTableWidget").columnCount() == 2
    with pytest.raises(KeyError, match="noSuchWidget"):
        window.widget("noSuchWidget")


def test_run_button_needs_an_existing_case_folder(window, tmp_path):
    edit, button = window.widget("caseDirLineEdit"), window.widget("runButton")
    assert not button.isEnabled()
    edit.setText(str(tmp_path))
    assert button.isEnabled()
    edit.setText(str(tmp_path / "missing"))
    assert not button.isEnabled()


def test_overrides_reach_the_request_only_when_checked(window, tmp_path):
    window.widget("caseDirLineEdit").setText(str(tmp_path))
    window.widget("fluoroMaskLineEdit").setText("/data/mask.png")
    window.widget("methodComboBox").setCurrentIndex(2)
    assert window.request().overrides == {}
    window.widget("overridesGroupBox").setChecked(True)
    request = window.request()
    assert request.overrides["fluoro_mask"] == "/data/mask.png"
    assert request.method == "rigid"
    assert request.case_dir == tmp_path


def test_result_is_drawn_in_both_views_and_the_table(window, plan_result, qapp):
    window.show_result(plan_result)
    qapp.processEvents()
    table = window.widget("resultsTableWidget")
    rows = summary_rows(plan_result)
    assert table.rowCount() == len(rows)
    assert (table.item(0, 0).text(), table.item(0, 1).text()) == ("Method", "proposed")
    assert window.widget("progressBar").value() == 100
    assert "iliac_right \u2192 renal_left" in window.widget("statusLabel").text()
    for view in (window.view3d, window.fluoro_view):
        pixels = view.pixels()
        assert pixels.shape[0] > 100 and pixels.shape[1] > 100
        background = pixels[-1, pixels.shape[1] // 2]
        assert (np.abs(pixels.astype(int) - background).sum(axis=2) > 30).mean() > 0.02
        assert _green_mask(pixels).sum() > 200
    # seen from the front with the head up: the right iliac at the bottom left
    assert _runs_from_lower_left_to_upper_right(window.view3d.pixels())


def _display_row_col(view, u: float, v: float) -> tuple[int, int]:
    """Where image point (u, v) lands in the view's pixels (row 0 at the top)."""
    renderer = view.renderer
    renderer.SetWorldPoint(u, v, -4.0, 1.0)
    renderer.WorldToDisplay()
    x, y, _ = renderer.GetDisplayPoint()
    return int(round(view.GetRenderWindow().GetSize()[1] - 1 - y)), int(round(x))


def test_fluoro_view_keeps_u_right_and_v_down(window, plan_result, qapp):
    window.show_result(plan_result)
    qapp.processEvents()
    pixels = window.fluoro_view.pixels()
    green = _green_mask(pixels)
    uv = project(plan_result.P, plan_result.path.points[[0, -1]])
    ends = [_display_row_col(window.fluoro_view, u, v) for u, v in uv]
    for row, col in ends:
        assert green[row - 3:row + 4, col - 3:col + 4].any()
    (row0, col0), (row1, col1) = ends
    assert np.sign(col1 - col0) == np.sign(uv[1, 0] - uv[0, 0])
    assert np.sign(row1 - row0) == np.sign(uv[1, 1] - uv[0, 1])
    assert row1 < row0  # the renal artery lies above the groin on the monitor


def test_display_checkboxes_hide_layers_in_both_views(window, plan_result, qapp):
    window.show_result(plan_result)
    window.widget("showPathCheckBox").setChecked(False)
    qapp.processEvents()
    for view in (window.view3d, window.fluoro_view):
        assert _green_mask(view.pixels()).sum() < 20
    window.widget("showPathCheckBox").setChecked(True)
    qapp.processEvents()
    assert _green_mask(window.fluoro_view.pixels()).sum() > 200


def test_fluoro_view_is_pixel_aligned_with_the_frame(window, plan_result, qapp):
    """The frame fills the 2D view's height (minus a margin) and keeps its aspect."""
    window.show_result(plan_result)
    qapp.processEvents()
    pixels = window.fluoro_view.pixels()
    column = pixels[:, 3 * pixels.shape[1] // 4]  # right of the legend, inside the frame
    lit = np.nonzero(column.max(axis=1) > 40)[0]
    frame_rows = np.ptp(lit) + 1
    rows, cols = plan_result.fluoro_image.shape
    assert frame_rows == pytest.approx(min(pixels.shape[0], pixels.shape[1] * rows / cols) / 1.04, rel=0.05)


def test_screenshot_holds_the_vtk_pixels(window, plan_result, qapp, tmp_path):
    window.show_result(plan_result)
    qapp.processEvents()
    path = window.save_screenshot(tmp_path / "shot.png")
    shot = as_array(QImage(str(path)))
    assert shot.shape[:2] == (window.height(), window.width())
    origin = window.view3d.mapTo(window, window.view3d.rect().topLeft())
    region = shot[origin.y():origin.y() + window.view3d.height(), origin.x():origin.x() + window.view3d.width()]
    assert _green_mask(region).sum() > 200
    assert _green_mask(shot[:, :origin.x()]).sum() < 50  # the panel has no path colour


def test_a_failing_case_reports_one_line_and_frees_the_button(window, tmp_path, qapp):
    window.widget("caseDirLineEdit").setText(str(tmp_path))
    window.run_plan()
    assert window.is_running() and not window.widget("runButton").isEnabled()
    window.wait_until_done()
    assert window.last_error.startswith("InputError")
    assert "\n" not in window.last_error
    assert window.widget("statusLabel").text() == window.last_error
    assert window.widget("runButton").isEnabled()
    assert window.outcome is None


def test_a_refused_case_shows_its_qc_picture_beside_the_one_line(window, tmp_path, qapp):
    """A frame whose mask is a bar across the image, not this case's vessels: the frame check
    refuses; the window shows the one line and, in a window of its own, the QC picture that
    ``plan`` writes, saved in the output folder."""
    from PIL import Image

    folder = phantom.write_phantom_set(tmp_path / "cases", n=1, seed=0, preset="random", mask_only=True)[0]
    bar = np.zeros(np.asarray(Image.open(folder / "fluoro_mask.png")).shape, dtype=np.uint8)
    bar[100:112, 50:-60] = 255
    Image.fromarray(bar).save(folder / "fluoro_mask.png")
    window.widget("caseDirLineEdit").setText(str(folder))
    window.widget("outputDirLineEdit").setText(str(tmp_path / "out"))
    window.run_plan()
    window.wait_until_done()
    assert window.last_error.startswith("QualityError") and "aorta not found in the frame" in window.last_error
    assert window.last_qc_picture == tmp_path / "out" / "segmentation_qc.png"
    assert str(window.last_qc_picture) in window.last_error          # "see <the picture>"
    assert window.outcome is None and window.widget("runButton").isEnabled()
    dialog = window.refusal_dialog
    assert dialog.message_label.text() == window.last_error
    dialog.show()
    qapp.processEvents()
    shown = as_array(dialog.picture_label.pixmap().toImage())
    saved = np.asarray(Image.open(window.last_qc_picture).convert("RGB"))
    assert shown.shape[:2] == saved.shape[:2] and shown.shape[1] > 400     # at its own size (under 1100 px)
    assert len(np.unique(shown.reshape(-1, 3), axis=0)) > 50               # a picture, not a blank
    dialog.close()


def test_a_failure_without_a_picture_shows_none(window, tmp_path, qapp):
    window.widget("caseDirLineEdit").setText(str(tmp_path))
    window.run_plan()
    window.wait_until_done()
    assert window.last_error.startswith("InputError")
    assert window.last_qc_picture is None and window.refusal_dialog is None


def test_command_line_options(tmp_path):
    with pytest.raises(SystemExit):
        cli.parse_args(["--run"])
    with pytest.raises(SystemExit):
        cli.parse_args([str(tmp_path / "missing")])
    with pytest.raises(SystemExit):
        cli.parse_args(["--size", "10x10"])
    with pytest.raises(SystemExit):
        cli.parse_args([str(tmp_path), "--view", "lao30"])  # a view is chosen after a run
    args = cli.parse_args([str(tmp_path), "--method", "icp-tps", "--size", "1024x700", "--start", "iliac_left"])
    assert (args.method, args.size, args.start, args.target) == ("icp-tps", (1024, 700), "iliac_left", "renal_left")
    environ = {}
    assert cli.configure_headless(environ) is True
    assert environ == {"QT_QPA_PLATFORM": "offscreen", "VTK_DEFAULT_OPENGL_WINDOW": "vtkOSOpenGLRenderWindow"}
    assert cli.configure_headless({"DISPLAY": ":0"}) is False


def test_main_saves_a_screenshot_of_the_empty_window(qapp, tmp_path):
    """The PNG shows the window: the panel's widgets and the 3D view's background and title."""
    target = tmp_path / "empty.png"
    assert cli.main(["--screenshot", str(target), "--size", "1200x700"]) == 0
    image = QImage(str(target))
    assert (image.width(), image.height()) == (1200, 700)
    shot = as_array(image).astype(float)

    def near(rgb):
        return np.linalg.norm(shot - np.array(rgb) * 255, axis=2) < 8

    top, bottom = near(BACKGROUND_TOP), near(BACKGROUND_BOTTOM)
    assert top.mean() > 0.01 and bottom.mean() > 0.01                 # the 3D view's gradient ...
    assert np.nonzero(top)[0].mean() < np.nonzero(bottom)[0].mean()   # ... light at the top
    assert near(COLORS["text"]).mean() > 5e-4                          # its title
    assert len(np.unique(shot.reshape(-1, 3), axis=0)) > 200           # and the panel's widgets and text


def test_end_to_end_phantom_case_in_the_worker_thread(window, tmp_path, qapp):
    folder = phantom.write_phantom_set(tmp_path / "cases", n=1, seed=0, preset="random", mask_only=True)[0]
    window.widget("caseDirLineEdit").setText(str(folder))
    window.widget("outputDirLineEdit").setText(str(tmp_path / "out"))
    window.run_plan()
    window.wait_until_done()
    assert window.last_error is None
    result = window.outcome.result
    assert (result.path.start_label, result.path.target_label) == ("iliac_right", "renal_left")
    assert window.outcome.surface is not None and window.outcome.surface.GetNumberOfPolys() > 1000
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == \
        ["deformed_centerline.vtp", "overlay.png", "path.mrk.json", "result.json", "segmentation_qc.png"]
    assert json.loads((tmp_path / "out" / "result.json").read_text())["method"] == "proposed"
    assert window.widget("resultsTableWidget").rowCount() == len(summary_rows(result))
    truth = Centerline.from_dict(json.loads((folder / "gt.json").read_text())["intraop_centerline"])
    renal = truth.points[np.asarray(truth.labels) == "renal_left"]
    assert np.linalg.norm(renal - result.path.points[-1], axis=1).min() < 10.0
    qapp.processEvents()
    for view in (window.view3d, window.fluoro_view):
        assert _green_mask(view.pixels()).sum() > 200


def test_changing_the_target_replans_on_the_shown_result_without_a_worker(window, plan_result, qapp):
    import copy

    result = copy.deepcopy(plan_result)
    window.show_result(result)
    registered = result.deformed
    window.widget("targetComboBox").setCurrentText("renal_right")
    qapp.processEvents()
    assert window._thread is None  # nothing was re-registered
    assert window.outcome.result.deformed is registered
    assert window.outcome.result.path.target_label == "renal_right"
    expected = planning.plan_path(registered, start="iliac_right", target="renal_right")
    np.testing.assert_allclose(window.outcome.result.path.points, expected.points)
    rows = dict(summary_rows(window.outcome.result))
    assert rows["Path"] == "iliac_right \u2192 renal_right"
    assert window.replan() is False  # already planned for these vessels


def test_views_use_the_one_palette():
    from FevarPlannerLib.conventions import PALETTE

    for layer in ("preop", "deformed", "path", "skeleton2d"):
        assert COLORS[layer] == PALETTE[layer]


def test_a_multi_frame_run_plays_back_against_the_cached_model(window, tmp_path, qapp, monkeypatch):
    from FevarPlannerLib import io

    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(tmp_path / "cache"))
    generated = phantom.generate_case(phantom.random_params(np.random.default_rng(4), misalign_shift_px=(0.0, 0.0),
                                                            misalign_rotation_deg=0.0), name="run")
    folder = phantom.write_case(generated, tmp_path / "case", mask_only=True)
    frames = [phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                    np.random.default_rng(seed))[0] for seed in range(3)]
    io.write_fluoro_dicom(folder / "fluoro.dcm", np.stack(frames), generated.carm)
    (folder / "fluoro_mask.png").unlink()
    window.widget("caseDirLineEdit").setText(str(folder))
    window.run_plan()
    window.wait_until_done()
    assert window.last_error is None and window.run_bar.isVisibleTo(window)
    assert window.frame_slider.maximum() == 2
    first = window.outcome.result
    window.frame_slider.setValue(2)
    qapp.processEvents()
    shown = window.outcome.result
    assert shown is not first and shown.inputs["frame"] == 2
    assert shown.preop is first.preop  # the same pre-operative model, nothing re-segmented in 3D
    np.testing.assert_array_equal(shown.fluoro_image, io.read_fluoro(folder / "fluoro.dcm", frame=2).image)
    assert shown.errors["2d_px"]["mean"] < 6.0
    assert "frame 3/3" in window.frame_label.text()
    assert _green_mask(window.fluoro_view.pixels()).sum() > 200


@pytest.fixture(scope="module")
def two_view_case(tmp_path_factory):
    """An independent-family two-view case (AP and LAO/RAO 30-90): masks, geometry.json, views/<name>/."""
    from FevarPlannerLib import scenarios

    scenario = scenarios.plan_scenarios("two_views", 1, seed=0)[0]
    return scenarios.write_scenario(scenario, tmp_path_factory.mktemp("two_views") / "case")


def _deformed_uv(view) -> np.ndarray:
    """The (u, v) points of the recovered centreline as the 2D view draws them."""
    polydata = view.layers["deformed"][0].GetMapper().GetInput()
    return np.array([polydata.GetPoint(i)[:2] for i in range(polydata.GetNumberOfPoints())])


def _inside_fraction(uv: np.ndarray, mask: np.ndarray) -> float:
    """The share of image points ``(u, v)`` that land on a vessel pixel of ``mask``."""
    col, row = np.rint(uv).astype(int).T
    shown = (col >= 0) & (col < mask.shape[1]) & (row >= 0) & (row < mask.shape[0])
    return float(np.where(shown, mask[np.clip(row, 0, mask.shape[0] - 1), np.clip(col, 0, mask.shape[1] - 1)],
                          False).mean())


@pytest.fixture(scope="module")
def two_view_cache(tmp_path_factory):
    """One pre-operative cache for the two-view tests: the CT side is worked out once."""
    return tmp_path_factory.mktemp("two_view_cache")


def test_a_two_view_case_shows_each_view_with_its_own_projection(window, two_view_case, two_view_cache, qapp,
                                                                 monkeypatch):
    """Planned through the worker: tabs list both views; each tab shows its own frame, with the
    recovered tree projected through its own P onto its vessels (not the other view's)."""
    from FevarPlannerLib import io

    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(two_view_cache))
    window.widget("caseDirLineEdit").setText(str(two_view_case))
    window.run_plan()
    window.wait_until_done()
    assert window.last_error is None
    second = next((two_view_case / "views").iterdir()).name
    assert window.view_names() == ["main", second]
    assert window.view_tabs.isVisibleTo(window) and window.view_tabs.count() == 2
    assert not window.widget("viewComboBox").isVisibleTo(window)  # the tabs replace the panel's selector here
    assert f"2 views (main, {second})" in window.widget("statusLabel").text()
    table = window.widget("resultsTableWidget")
    rows = {table.item(r, 0).text(): table.item(r, 1).text() for r in range(table.rowCount())}
    assert rows["Views used"] == f"2 (main, {second})"
    for name in ("main", second):
        fit = float(rows[f"2D fit, view {name}: result \u2192 skeleton (px)"].split()[0])
        assert 0.0 < fit < 1.5
    result = window.outcome.result
    masks = {"main": io.read_mask_2d(two_view_case / "fluoro_mask.png"),
             second: io.read_mask_2d(two_view_case / "views" / second / "fluoro_mask.png")}
    Ps = {frame.name: frame.P for frame in result.view_frames}
    window.widget("showPathCheckBox").setChecked(False)  # the path would hide the recovered tree under it
    qapp.processEvents()
    shown = {}
    for index, name in enumerate(("main", second)):
        window.view_tabs.setCurrentIndex(index)  # as a click on the tab does
        qapp.processEvents()
        assert window.fluoro_view.frame.name == name
        uv = _deformed_uv(window.fluoro_view)
        np.testing.assert_allclose(uv, project(Ps[name], result.deformed.points), atol=1e-6)
        other = next(n for n in masks if n != name)
        assert _inside_fraction(uv, masks[name]) > 0.99          # on this frame's vessels ...
        assert _inside_fraction(uv, masks[other]) < 0.97         # ... which the other view's P would miss
        pixels = window.fluoro_view.pixels()
        cyan = np.linalg.norm(pixels.astype(float) - np.array(COLORS["deformed"]) * 255, axis=2) < 60
        ends = [_display_row_col(window.fluoro_view, u, v) for u, v in uv[::40]]
        assert np.mean([cyan[row - 2:row + 3, col - 2:col + 3].any() for row, col in ends]) > 0.8
        shown[name] = pixels
    assert shown["main"].shape == shown[second].shape
    assert (np.abs(shown["main"].astype(int) - shown[second].astype(int)).sum(axis=2) > 60).mean() > 0.02
    assert f"view {second}" in window.fluoro_view.title.GetInput()


def test_a_one_view_result_has_no_view_tabs(window, plan_result, qapp):
    window.show_result(plan_result)
    qapp.processEvents()
    assert window.view_names() == ["main"] and not window.view_tabs.isVisibleTo(window)
    assert window.show_view(1) is False
    assert "Views used" not in dict(summary_rows(plan_result))


def test_main_names_the_views_when_asked_for_one_the_case_lacks(two_view_case, two_view_cache, qapp, tmp_path,
                                                                monkeypatch, capsys):
    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(two_view_cache))
    second = next((two_view_case / "views").iterdir()).name
    target = tmp_path / "shot.png"
    assert cli.main([str(two_view_case), "--run", "--view", "lateral", "--screenshot", str(target)]) == 2
    assert capsys.readouterr().err.strip().endswith(f"no view 'lateral'; the views are main, {second}")
    assert not target.exists()

import copy
import json

import numpy as np
import pytest
from PIL import Image

from FevarPlannerLib.centerline import ANATOMY_LABELS, Centerline
from FevarPlannerLib.export import (
    RESULT_VERSION, OverlayLayer, build_result_dict, centerline_layer, path_layer, read_centerline_vtp, read_path_markups,
    read_result_json, render_centerlines_3d, render_overlay, validate_result, write_centerline_vtp, warning_lines,
    write_path_markups, write_result_json)
from FevarPlannerLib.io import InputError
from FevarPlannerLib.conventions import PALETTE
from FevarPlannerLib.planning import CatheterPath, plan_path
from FevarPlannerLib.projection import CArmGeometry, project, projection_matrix_from_carm


@pytest.fixture()
def tree():
    """A small labelled Y: aorta down the z axis, a renal branch and two iliacs (LPS mm)."""
    aorta = np.column_stack([np.zeros(6), np.zeros(6), np.linspace(100.0, 0.0, 6)])
    renal = [[8.0, 1, 60], [16.0, 2, 58]]
    iliac_left = [[6.0, 0, -10], [12.0, 2, -25]]
    iliac_right = [[-6.0, 0, -10], [-12.0, 2, -25]]
    points = np.vstack([aorta, renal, iliac_left, iliac_right])
    edges = [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [2, 6], [6, 7], [5, 8], [8, 9], [5, 10], [10, 11]]
    labels = ["aorta"] * 6 + ["renal_left"] * 2 + ["iliac_left"] * 2 + ["iliac_right"] * 2
    return Centerline(points, np.array(edges), labels)


@pytest.fixture()
def result(tree):
    deformed = tree.with_points(tree.points + np.array([1.5, -2.0, 0.5]))
    path = plan_path(deformed)
    P = projection_matrix_from_carm(CArmGeometry(1100, 750, (0.5, 0.5), 0, 0, 200, 160), [0, 0, 40])
    return build_result_dict("proposed", tree, deformed, path, {"total": 1.25, "registration": 0.5},
                             projection_matrix=P, errors={"per_node_mm": np.linspace(0, 1, len(tree))},
                             inputs={"fluoro": "fluoro.png"})


def test_result_dict_has_the_contract_keys_and_round_trips(tmp_path, result, tree):
    assert result["version"] == RESULT_VERSION == 1
    assert list(result)[:6] == ["version", "method", "preop_centerline", "deformed_centerline", "path", "timings_s"]
    assert result["path"]["from"] == "iliac_right" and result["path"]["to"] == "renal_left"
    assert result["path"]["points"][0] == pytest.approx((tree.points[11] + [1.5, -2.0, 0.5]).tolist())
    assert result["timings_s"] == {"total": 1.25, "registration": 0.5}
    target = tmp_path / "out" / "result.json"
    write_result_json(target, result)
    loaded = read_result_json(target)
    assert loaded == json.loads(json.dumps(result))
    np.testing.assert_allclose(loaded["projection_matrix"], result["projection_matrix"])
    assert Centerline.from_dict(loaded["deformed_centerline"]).labels == tree.labels
    assert sorted(p.name for p in target.parent.iterdir()) == ["result.json"]


def _set(key_path, value):
    def mutate(data):
        *parents, last = key_path
        for key in parents:
            data = data[key]
        data[last] = value
    return mutate


def _drop_node(data):
    data["deformed_centerline"]["points"].pop()
    data["deformed_centerline"]["labels"].pop()


def _swap_labels(data):
    labels = data["deformed_centerline"]["labels"]
    labels[0], labels[-1] = labels[-1], labels[0]


BAD_RESULTS = {
    "version 2": (_set(["version"], 2), "version must be 1, got 2"),
    "version string": (_set(["version"], "1"), "version must be 1, got '1'"),
    "version bool": (_set(["version"], True), "version must be 1, got True"),
    "missing path": (lambda d: d.pop("path"), r"result lacks \['path'\]"),
    "node count": (_drop_node, "deformed_centerline has 11 nodes, preop_centerline has 12"),
    "node order": (_swap_labels, "node 0 is 'aorta' in preop_centerline but 'iliac_right'"),
    "NaN point": (_set(["deformed_centerline", "points", 3, 1], float("nan")),
                  r"deformed_centerline.points\[3\] is not finite"),
    "NaN path": (_set(["path", "points", 1, 0], float("inf")), r"path.points\[1\] is not finite"),
    "NaN extra": (_set(["errors", "per_node_mm", 4], float("nan")), r"result.errors.per_node_mm\[4\] is not finite"),
    "unknown label": (_set(["preop_centerline", "labels", 2], "sma"), r"preop_centerline.labels\[2\] = 'sma'"),
    "unknown path end": (_set(["path", "to"], "renal"), "path.to = 'renal' is not one of"),
    "edge out of range": (_set(["preop_centerline", "edges", 0, 1], 99), "preop_centerline.edges refers to nodes"),
    "float edges": (_set(["preop_centerline", "edges"], [[0.0, 1.0]]), "must be an .m, 2. array of integer"),
    "points shape": (_set(["preop_centerline", "points"], [[0.0, 1.0]] * 12), r"must have shape \(n, 3\)"),
    "no total time": (lambda d: d["timings_s"].pop("total"), r"timings_s lacks \['total'\]"),
    "negative time": (_set(["timings_s", "registration"], -1.0), "timings_s.registration must be a non-negative"),
    "empty method": (_set(["method"], ""), "method must be a non-empty string"),
    "bad P": (_set(["projection_matrix"], [[1, 0, 0, 0], [0, 1, 0, 0]]), "projection_matrix: expected a 3x4"),
}


@pytest.mark.parametrize("case", sorted(BAD_RESULTS))
def test_validation_names_each_kind_of_bad_input(result, case):
    mutate, message = BAD_RESULTS[case]
    bad = copy.deepcopy(result)
    mutate(bad)
    with pytest.raises(ValueError, match=message):
        validate_result(bad)


def test_failed_write_leaves_the_existing_file_untouched(tmp_path, result):
    target = tmp_path / "result.json"
    write_result_json(target, result)
    before = target.read_bytes()
    bad = copy.deepcopy(result)
    bad["deformed_centerline"]["points"][0][0] = float("nan")
    with pytest.raises(ValueError, match=r"result.json: not written: deformed_centerline.points\[0\]"):
        write_result_json(target, bad)
    unserialisable = dict(result, inputs={"fluoro": object()})
    with pytest.raises(ValueError, match="not written"):
        write_result_json(target, unserialisable)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_build_refuses_core_key_overrides_and_reading_reports_the_file(tmp_path, tree):
    path = CatheterPath(tree.points[:3], np.arange(3), "iliac_right", "renal_left", 1.0)
    with pytest.raises(ValueError, match=r"may not replace core keys: \['version'\]"):
        build_result_dict("proposed", tree, tree, path, {"total": 1, "registration": 1}, version=2)
    empty = tmp_path / "result.json"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="result.json: file is empty"):
        read_result_json(empty)
    empty.write_text('{"version": 1}')
    with pytest.raises(InputError, match=r"result.json: result lacks \['method'"):
        read_result_json(empty)


def test_vtp_round_trip_keeps_points_edges_labels_and_arrays(tmp_path, tree):
    target = tmp_path / "deformed_centerline.vtp"
    error = np.linspace(0.0, 2.0, len(tree))
    write_centerline_vtp(target, tree, arrays={"error_mm": error})
    back = read_centerline_vtp(target)
    np.testing.assert_allclose(back.points, tree.points, atol=0)
    np.testing.assert_array_equal(back.edges, tree.edges)
    assert back.labels == tree.labels

    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(target))
    reader.Update()
    polydata = reader.GetOutput()
    assert polydata.GetNumberOfLines() == len(tree.edges)
    assert polydata.GetFieldData().GetAbstractArray("SPACE").GetValue(0) == "LPS"
    codes = [int(polydata.GetPointData().GetArray("label").GetValue(i)) for i in range(len(tree))]
    assert [ANATOMY_LABELS[c] for c in codes] == tree.labels
    stored = polydata.GetPointData().GetArray("error_mm")
    np.testing.assert_allclose([stored.GetValue(i) for i in range(len(tree))], error)


def test_vtp_errors_name_the_file_and_keep_old_output(tmp_path, tree):
    corrupt = tmp_path / "broken.vtp"
    corrupt.write_text("<VTKFile garbage")
    with pytest.raises(InputError, match="broken.vtp: cannot read VTK polydata"):
        read_centerline_vtp(corrupt)
    target = tmp_path / "c.vtp"
    write_centerline_vtp(target, tree)
    before = target.read_bytes()
    with pytest.raises(ValueError, match="'error_mm' must be numeric with 12 rows"):
        write_centerline_vtp(target, tree, arrays={"error_mm": np.zeros(5)})
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.vtp", "c.vtp"]


def _slicer_curve(path):
    slicer = pytest.importorskip("slicer")
    scene = slicer.vtkMRMLScene()
    curve = slicer.vtkMRMLMarkupsCurveNode()
    scene.AddNode(curve)
    storage = slicer.vtkMRMLMarkupsJsonStorageNode()
    scene.AddNode(storage)
    storage.SetFileName(str(path))
    assert storage.ReadData(curve) == 1
    positions = []
    for i in range(curve.GetNumberOfControlPoints()):
        position = [0.0, 0.0, 0.0]
        curve.GetNthControlPointPosition(i, position)
        positions.append(position)
    return curve, np.array(positions)


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_markups_load_in_slicer_mrml_as_ras(tmp_path, system):
    rng = np.random.default_rng(7)
    points_lps = np.cumsum(rng.normal(size=(9, 3)) * 5.0, axis=0) + [10.0, -20.0, 30.0]
    target = tmp_path / "path.mrk.json"
    write_path_markups(target, points_lps, name="CatheterPath", coordinate_system=system)
    document = json.loads(target.read_text())
    assert document["markups"][0]["coordinateSystem"] == system
    assert document["markups"][0]["type"] == "Curve"
    curve, ras = _slicer_curve(target)
    assert curve.GetNumberOfControlPoints() == 9
    assert curve.GetName() == "CatheterPath"
    np.testing.assert_allclose(ras, points_lps * [-1.0, -1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(read_path_markups(target), points_lps, atol=1e-12)


def test_reading_a_markups_file_written_by_slicer(tmp_path):
    slicer = pytest.importorskip("slicer")
    scene = slicer.vtkMRMLScene()
    curve = slicer.vtkMRMLMarkupsCurveNode()
    scene.AddNode(curve)
    for ras in ([1.0, 2.0, 3.0], [-4.0, 5.5, 6.0]):
        curve.AddControlPoint(ras)
    storage = slicer.vtkMRMLMarkupsJsonStorageNode()
    scene.AddNode(storage)
    storage.SetFileName(str(tmp_path / "slicer.mrk.json"))
    assert storage.WriteData(curve) == 1
    np.testing.assert_allclose(read_path_markups(tmp_path / "slicer.mrk.json"), [[-1, -2, 3], [4, -5.5, 6]])


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def test_overlay_draws_layers_at_their_pixels(tmp_path):
    rows, cols = 60, 80
    image = np.zeros((rows, cols))
    image[30, 50] = 1.0  # one bright frame pixel
    layers = [OverlayLayer("dot", [[17.0, 9.0]], (1.0, 0.0, 0.0)),
              OverlayLayer("line", [[5.0, 44.0], [70.0, 44.0]], (0.0, 1.0, 0.0), polyline=True)]
    target = tmp_path / "overlay.png"
    render_overlay(target, image, layers=layers)
    picture = _png(target)
    assert picture.shape[0] > rows and picture.shape[1] >= cols
    frame = picture[:rows, :cols]
    assert frame[30, 50].min() > 200 and frame[30, 49].max() < 60 and frame[29, 50].max() < 60

    red = (frame[..., 0] > 150) & (frame[..., 1] < 90)
    rr, cc = np.nonzero(red)
    assert len(rr) > 0
    assert abs(rr.mean() - 9.0) < 0.1 and abs(cc.mean() - 17.0) < 0.1

    green = (frame[..., 1] > 150) & (frame[..., 0] < 90)
    rr, cc = np.nonzero(green)
    assert abs(np.average(rr, weights=frame[rr, cc, 1]) - 44.0) < 0.1
    assert abs(cc.min() - 5) <= 1 and abs(cc.max() - 70) <= 1


def test_overlay_of_projected_centrelines_and_skeleton(tmp_path, tree):
    P = projection_matrix_from_carm(CArmGeometry(1100, 750, (0.6, 0.6), 0, 0, 200, 160), [0, 0, 40])
    uv = project(P, tree.points)
    image = np.random.default_rng(1).normal(100.0, 5.0, (200, 160))
    target = tmp_path / "overlay.png"
    render_overlay(target, image, skeleton2d=uv + 3.0,
                   layers=[centerline_layer("pre-op", P, tree, "blue")])
    frame = _png(target)[:200, :160]
    blue = (frame[..., 2] > 150) & (frame[..., 0] < 90) & (frame[..., 1] < 90)
    # the projected aorta (nodes 0..5) runs down a single column of the frame
    aorta_column = int(round(uv[0, 0]))
    rows = np.arange(int(uv[0, 1]) + 2, int(uv[5, 1]) - 2)
    assert blue[rows, aorta_column - 1:aorta_column + 2].any(axis=1).all()
    yellow = (frame[..., 0] > 150) & (frame[..., 1] > 150) & (frame[..., 2] < 90)
    u, v = np.round(uv[7] + 3.0).astype(int)
    assert yellow[v - 1:v + 2, u - 1:u + 2].any()
    with pytest.raises(ValueError, match="NaN"):
        render_overlay(target, np.full((4, 4), np.nan))
    render_overlay(target, np.zeros((517, 613)), layers=[path_layer("path", P, tree.points[[11, 10, 5]], "red")])
    assert _png(target).shape[:2] == (517 + 28, 613)


def test_overlay_draws_plausibility_warnings_in_the_warning_colour(tmp_path):
    rows, cols = 240, 480
    image = np.random.default_rng(4).normal(100.0, 5.0, (rows, cols))
    warnings = ["2D fit of renal_left is poor (9.1 px mean); its pre-operative shape kept, carried rigidly "
                "with the aorta", "anatomy length changed by 14 %"]
    plain, warned = tmp_path / "plain.png", tmp_path / "warned.png"
    render_overlay(plain, image)
    render_overlay(warned, image, warnings=warnings)
    before, after = _png(plain)[:rows, :cols], _png(warned)[:rows, :cols]
    changed = np.abs(after - before).max(axis=2) > 30
    rr, cc = np.nonzero(changed)
    # the box sits in the bottom-left corner and leaves the top and right of the frame alone
    assert changed.sum() > 2000
    assert rr.min() > rows / 3 and cc.min() < 10 and cc.max() < 0.7 * cols
    warning_rgb = np.array(PALETTE["warning"]) * 255
    coloured = (np.abs(after - warning_rgb).max(axis=2) < 40)
    assert coloured.sum() > 300 and (np.abs(before - warning_rgb).max(axis=2) < 40).sum() == 0
    lines = warning_lines(warnings, cols)
    assert len(lines) >= 3 and all(len(line) <= int(0.5 * cols / 5.5) for line in lines)
    assert lines[0].startswith("! 2D fit") and lines[-1].startswith("! anatomy length")
    many = warning_lines([f"warning {i}" for i in range(20)], cols)
    assert len(many) == 6 and many[-1] == "(+15 more lines in result.json)"


def test_3d_render_is_an_anterior_head_up_picture(tmp_path, tree):
    target = tmp_path / "centerlines.png"
    left_arm = Centerline([[0.0, 0, 0], [60.0, 0, 0]], [[0, 1]], ["renal_left"] * 2)
    head = Centerline([[0.0, 0, 0], [0.0, 0, 60]], [[0, 1]], ["aorta"] * 2)
    render_centerlines_3d(target, [(left_arm, (0.0, 0.0, 1.0), ""), (head, (0.0, 1.0, 0.0), "")], size=(240, 180))
    picture = _png(target)
    assert picture.shape == (180, 240, 3)
    background = picture[0, 0]
    assert (np.abs(picture - background).sum(axis=2) > 60).sum() > 200
    blue = (picture[..., 2] > 120) & (picture[..., 0] < 60) & (picture[..., 1] < 80)
    green = (picture[..., 1] > 120) & (picture[..., 0] < 60) & (picture[..., 2] < 80)
    # both start at the origin: the patient's left (+x) runs to the viewer's right, the head (+z) up
    assert blue.sum() > 50 and green.sum() > 50
    assert np.nonzero(blue)[1].mean() > np.nonzero(green)[1].mean() + 30
    assert np.nonzero(green)[0].mean() < np.nonzero(blue)[0].mean() - 30

    from vtkmodules.vtkFiltersSources import vtkSphereSource
    sphere = vtkSphereSource()
    sphere.SetCenter(0.0, 0.0, 50.0)
    sphere.SetRadius(30.0)
    sphere.Update()
    render_centerlines_3d(target, [(tree, "red", "tree"), (tree.points[[11, 10, 5, 4, 3, 2, 6]], "yellow", "path")],
                          surface=sphere.GetOutput(), size=(120, 200))
    picture = _png(target)
    assert picture.shape == (200, 120, 3)
    yellow = (picture[..., 0] > 150) & (picture[..., 1] > 150) & (picture[..., 2] < 90)
    assert yellow.sum() > 30
    with pytest.raises(ValueError, match="nothing to render"):
        render_centerlines_3d(target, [])


@pytest.mark.parametrize("primary, secondary", [(30.0, 15.0), (-25.0, -10.0), (0.0, 0.0)])
def test_view_name_reads_the_c_arm_angles_back_from_P(primary, secondary):
    from FevarPlannerLib.export import view_name
    from FevarPlannerLib.projection import view_label

    P = projection_matrix_from_carm(CArmGeometry(1100, 750, (0.5, 0.5), primary, secondary, 200, 160), [5, -3, 40])
    assert view_name(P, [5, -3, 40]) == view_label(primary, secondary)
    assert view_name(-P, [5, -3, 40]) == view_label(primary, secondary)  # P's overall sign is free
    assert view_label(30, -10) == "LAO 30 / CAU 10"


def test_overlay_marks_right_and_left_where_the_patient_lies(tmp_path, tree):
    """AP view, radiological display: the patient's right is on the image's left."""
    from matplotlib.figure import Figure
    from FevarPlannerLib.export import _orientation_marks

    P = projection_matrix_from_carm(CArmGeometry(1100, 750, (0.5, 0.5), 0, 0, 200, 160), [0, 0, 40])
    figure = Figure()
    axes = figure.add_subplot(1, 1, 1)
    _orientation_marks(axes, P, [0.0, 0.0, 40.0], 200, 160)
    marks = {text.get_text(): text.get_position() for text in axes.texts}
    assert marks["R"][0] < 80 < marks["L"][0]
    scale = next(text for text in axes.texts if text.get_text().endswith(" mm"))
    bar = axes.lines[0].get_xdata()
    pixels_per_mm = np.linalg.norm(project(P, [1.0, 0, 40]) - project(P, [0.0, 0, 40]))
    assert (bar[1] - bar[0]) == pytest.approx(float(scale.get_text().split()[0]) * pixels_per_mm)
    render_overlay(tmp_path / "o.png", np.zeros((200, 160)), layers=[centerline_layer("c", P, tree, "cyan")],
                   title="proposed | AP", P=P, anchor=[0.0, 0.0, 40.0])
    assert (tmp_path / "o.png").stat().st_size > 0


def test_path_markups_take_the_path_colour(tmp_path, tree):
    from FevarPlannerLib.conventions import PALETTE

    write_path_markups(tmp_path / "p.mrk.json", tree.points[:4])
    display = json.loads((tmp_path / "p.mrk.json").read_text())["markups"][0]["display"]
    assert display["color"] == list(PALETTE["path"]) and display["selectedColor"] == list(PALETTE["path"])

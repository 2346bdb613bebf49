"""The Slicer module outside Slicer: MRML conversion under slicer-core, and the CMake build.

``FevarPlanner/FevarPlanner.py`` is imported with the MRML classes of the slicer-core
wheel; the application-only classes (module, widget, self-test) must then be absent.
"""

import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import vtk
from vtk.util import numpy_support

slicer = pytest.importorskip("slicer")

from FevarPlannerLib import export, io, phantom, planning  # noqa: E402
from FevarPlannerLib.centerline import ANATOMY_LABELS  # noqa: E402
from FevarPlannerLib.pipeline import PlanResult  # noqa: E402
from FevarPlannerLib.projection import project  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MODULE_DIR = REPO / "FevarPlanner"


def _load_module():
    spec = importlib.util.spec_from_file_location("FevarPlanner", MODULE_DIR / "FevarPlanner.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("FevarPlanner", module)
    spec.loader.exec_module(module)
    return module


fp = _load_module()


@pytest.fixture(scope="module")
def anatomy():
    """A real phantom case's pre- and intra-operative centrelines and projection (no raster)."""
    case = phantom.generate_case(phantom.PhantomParams())
    return case.preop.to_centerline(2.0), case.intraop.to_centerline(2.0), case.P_true, case.carm


@pytest.fixture()
def scene():
    mrml = slicer.vtkMRMLScene()
    mrml.AddNode(slicer.vtkMRMLSelectionNode())  # markups look up their length unit here
    return mrml


def _plan_result(anatomy) -> PlanResult:
    preop, intraop, P, carm = anatomy
    uv = project(P, intraop.points)
    image = np.zeros((carm.rows, carm.cols), dtype=np.float32)
    return PlanResult("proposed", preop, intraop, planning.plan_path(intraop), P, uv, intraop.edges, image,
                      {"total": 1.0, "registration": 0.5})



def _saved_and_reloaded(scene, path):
    """The scene written to ``path`` (.mrml) and imported into a new scene."""
    scene.SetURL(str(path))
    assert scene.Commit() == 1
    other = slicer.vtkMRMLScene()
    other.SetURL(str(path))
    other.Import()
    return other

def test_import_under_slicer_core_defines_only_the_mrml_side():
    assert fp.SLICER_APPLICATION is False
    for name in ("FevarPlanner", "FevarPlannerWidget", "FevarPlannerTest"):
        assert not hasattr(fp, name)
    assert fp.FevarPlannerLogic.__mro__[1] is object
    assert fp.module_resource_path("UI/FevarPlanner.ui") == REPO / "Resources" / "UI" / "FevarPlanner.ui"
    with pytest.raises(FileNotFoundError, match="missing.ui"):
        fp.module_resource_path("UI/missing.ui")


def test_missing_requirements_names_pip_packages():
    assert fp.missing_requirements() == []
    assert fp.missing_requirements({"numpy": "numpy", "fevar_no_such_module": "fevar-no-such"}) == ["fevar-no-such"]
    core_imports = set()
    for file in (MODULE_DIR / "FevarPlannerLib").glob("*.py"):
        for found in re.findall(r"^\s*(?:from (\w+)[\w.]* import|import (\w+))", file.read_text(encoding="utf-8"),
                                flags=re.MULTILINE):
            core_imports |= set(found) - {""}
    third_party = {name for name in core_imports
                   if name not in sys.stdlib_module_names and name not in ("FevarPlannerLib", "vtk", "vtkmodules")}
    assert third_party - set(fp.CORE_REQUIREMENTS) <= {"torch"}


def test_lps_to_ras_flips_x_and_y_only():
    points = np.array([[10.0, -20.0, 30.0], [0.5, 0.25, -7.0]])
    assert fp.lps_to_ras(points).tolist() == [[-10.0, 20.0, 30.0], [-0.5, -0.25, -7.0]]
    np.testing.assert_array_equal(fp.ras_to_lps(fp.lps_to_ras(points)), points)


def test_centerline_model_node_holds_ras_lines_and_reads_back_as_lps(scene, anatomy):
    preop = anatomy[0]
    node = fp.centerline_to_model_node(scene, preop, "pre-op", role="preop")
    polydata = node.GetPolyData()
    assert scene.GetNumberOfNodesByClass("vtkMRMLModelNode") == 1
    assert polydata.GetNumberOfPoints() == len(preop)
    assert polydata.GetNumberOfLines() == len(preop.edges)
    first = np.array(polydata.GetPoint(0))
    np.testing.assert_allclose(first, preop.points[0] * [-1.0, -1.0, 1.0])
    back = fp.model_node_to_centerline(node)
    np.testing.assert_allclose(back.points, preop.points, atol=1e-9)
    assert back.labels == preop.labels
    assert node.GetAttribute(fp.ROLE_ATTRIBUTE) == "preop"
    np.testing.assert_allclose(node.GetDisplayNode().GetColor(), fp.STYLE["preop"][0])
    with pytest.raises(ValueError, match="display role"):
        fp.centerline_to_model_node(scene, preop, "bad", role="surface")


def test_path_curve_node_survives_a_markups_json_round_trip(scene, anatomy, tmp_path):
    path = planning.plan_path(anatomy[1], start="iliac_left", target="renal_right")
    node = fp.path_to_curve_node(scene, path)
    assert node.GetName() == "iliac_left to renal_right"
    assert node.GetNumberOfControlPoints() == len(path.points)
    ras = np.array([node.GetNthControlPointPositionWorld(i) for i in range(node.GetNumberOfControlPoints())])
    np.testing.assert_allclose(ras, path.points * [-1.0, -1.0, 1.0], atol=1e-9)
    assert node.GetCurveLengthWorld() == pytest.approx(path.length_mm, rel=1e-6)

    file = tmp_path / "path.mrk.json"
    writer = slicer.vtkMRMLMarkupsJsonStorageNode()
    scene.AddNode(writer)
    writer.SetFileName(str(file))
    assert writer.WriteData(node) == 1
    other = slicer.vtkMRMLScene()
    reader = slicer.vtkMRMLMarkupsJsonStorageNode()
    other.AddNode(reader)
    loaded = reader.AddNewMarkupsNodeFromFile(str(file))
    assert loaded.GetClassName() == "vtkMRMLMarkupsCurveNode"
    loaded_ras = np.array([loaded.GetNthControlPointPositionWorld(i)
                           for i in range(loaded.GetNumberOfControlPoints())])
    np.testing.assert_allclose(loaded_ras, ras, atol=1e-6)
    # the core's own reader agrees: the file Slicer wrote holds the path in LPS
    np.testing.assert_allclose(export.read_path_markups(file), path.points, atol=1e-6)


def test_curve_node_rejects_a_one_point_path(scene, anatomy):
    path = planning.plan_path(anatomy[1])
    path.points = path.points[:1]
    with pytest.raises(ValueError, match="at least 2 points"):
        fp.path_to_curve_node(scene, path)


def test_fluoro_volume_node_keeps_the_pixel_grid(scene):
    image = np.arange(15, dtype=np.float32).reshape(3, 5)  # 3 rows, 5 columns
    node = fp.fluoro_to_volume_node(scene, image)
    data = node.GetImageData()
    assert data.GetDimensions() == (5, 3, 1)
    assert data.GetScalarComponentAsDouble(4, 2, 0, 0) == image[2, 4]
    vtk_matrix = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(vtk_matrix)
    ijk_to_ras = np.array([[vtk_matrix.GetElement(r, c) for c in range(4)] for r in range(4)])
    np.testing.assert_allclose(ijk_to_ras @ [4, 2, 0, 1], [-4.0, -2.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="2D array"):
        fp.fluoro_to_volume_node(scene, np.zeros((2, 2, 2)))


OVERLAYS = {"overlay_skeleton2d", "overlay_preop", "overlay_deformed", "overlay_path"}


def test_logic_replaces_the_nodes_of_an_earlier_run(scene, anatomy):
    result = _plan_result(anatomy)
    logic = fp.FevarPlannerLogic(scene)
    first = logic.add_result(result)
    second = logic.add_result(result, show_fluoro=False)
    assert set(first) == {"preop", "deformed", "path", "fluoro"} | OVERLAYS
    assert set(second) == {"preop", "deformed", "path"}
    assert scene.GetNumberOfNodesByClass("vtkMRMLModelNode") == 2
    assert scene.GetNumberOfNodesByClass("vtkMRMLMarkupsCurveNode") == 1
    assert scene.GetNumberOfNodesByClass("vtkMRMLScalarVolumeNode") == 0
    assert {role: node.GetID() for role, node in fp.result_nodes(scene).items()} == \
        {role: node.GetID() for role, node in second.items()}
    assert second["deformed"].GetName() == "FevarPlanner recovered centreline (proposed)"
    assert fp.remove_result_nodes(scene) == 3
    assert fp.result_nodes(scene) == {}


def test_the_frame_gets_its_own_view_and_the_overlay_lands_on_its_pixels(scene, anatomy):
    result = _plan_result(anatomy)
    ct = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode")
    ct_view = scene.AddNewNodeByClass("vtkMRMLSliceCompositeNode")
    ct_view.SetLayoutName("Red")
    ct_view.SetBackgroundVolumeID(ct.GetID())
    nodes = fp.FevarPlannerLogic(scene).add_result(result)
    frame_view, composite = fp.frame_view_nodes(scene)
    assert composite.GetBackgroundVolumeID() == nodes["fluoro"].GetID()
    assert ct_view.GetBackgroundVolumeID() == ct.GetID()  # the CT's view is left alone
    for role in OVERLAYS:
        display = nodes[role].GetDisplayNode()
        assert [display.GetNthViewNodeID(i) for i in range(display.GetNumberOfViewNodeIDs())] == [frame_view.GetID()]
        assert not display.GetVisibility3D()
    # the projected path's points are the frame's pixels (u, v) through the frame's IJK-to-RAS
    uv = project(result.P, result.path.points)
    matrix = vtk.vtkMatrix4x4()
    nodes["fluoro"].GetIJKToRASMatrix(matrix)
    ijk_to_ras = np.array([[matrix.GetElement(r, c) for c in range(4)] for r in range(4)])
    overlay = np.array([nodes["overlay_path"].GetPolyData().GetPoint(i) for i in range(len(uv))])
    np.testing.assert_allclose(overlay, (np.column_stack([uv, np.zeros(len(uv)), np.ones(len(uv))]) @ ijk_to_ras.T)[:, :3],
                               atol=1e-9)
    # the frame view looks at the frame: u to the screen's right, v down
    slice_to_ras = np.array([[frame_view.GetSliceToRAS().GetElement(r, c) for c in range(4)] for r in range(4)])
    np.testing.assert_allclose(slice_to_ras[:3, 0], ijk_to_ras[:3, 0] / np.linalg.norm(ijk_to_ras[:3, 0]), atol=1e-9)
    np.testing.assert_allclose(slice_to_ras[:3, 1], -ijk_to_ras[:3, 1] / np.linalg.norm(ijk_to_ras[:3, 1]), atol=1e-9)


def test_parameter_node_keeps_values_and_node_references_and_is_saved_with_the_scene(scene, tmp_path):
    logic = fp.FevarPlannerLogic(scene)
    parameters = logic.getParameterNode()
    assert (parameters.method, parameters.start, parameters.target) == ("proposed", "iliac_right", "renal_left")
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode")
    parameters.ctVolume, parameters.target = volume, "renal_right"
    assert logic.getParameterNode().node is parameters.node  # one per scene
    assert logic.getParameterNode().ctVolume is volume
    with pytest.raises(AttributeError, match="no field"):
        parameters.cttVolume = volume
    reloaded = _saved_and_reloaded(scene, tmp_path / "scene.mrml")  # kept: the nodes live in it
    loaded = fp.FevarPlannerParameters.of_scene(reloaded)
    assert loaded.target == "renal_right"
    assert loaded.ctVolume is not None and loaded.ctVolume.GetID() == volume.GetID()


def test_summary_rows_describe_the_result(anatomy):
    from FevarPlannerLib.export import format_metric, summary_rows

    result = _plan_result(anatomy)
    result.errors = {"3d_mm": {"mean": 1.234, "std": 0.5, "median": 1.0, "max": 3.0}, "2d_px": None,
                     "labels": list(ANATOMY_LABELS[:2])}
    rows = dict(summary_rows(result))
    assert rows["Path"] == "iliac_right → renal_left"
    assert rows["Path length (mm)"] == f"{result.path.length_mm:.1f}"
    assert rows["3D error: result \u2192 truth (mm)"] == "1.23 ± 0.50 (max 3.00)"
    assert rows["2D error: result \u2192 skeleton (px)"] == "n/a (no ground truth)"
    assert rows["labels"] == "aorta, renal_left"
    assert list(rows).index("Time: total (s)") < list(rows).index("Time: registration (s)")
    assert format_metric(0.000123456) == "0.000123"


def _cmake_listing(tmp_path) -> tuple[list[str], set[str]]:
    """Configure FevarPlanner/CMakeLists.txt with a stand-in for Slicer's build macro."""
    source = tmp_path / "src"
    source.mkdir()
    (source / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.16)\nproject(probe NONE)\n"
        "macro(slicerMacroBuildScriptedModule)\n"
        "  cmake_parse_arguments(MY \"WITH_GENERIC_TESTS\" \"NAME\" \"SCRIPTS;RESOURCES\" ${ARGN})\n"
        "  foreach(s ${MY_SCRIPTS})\n    message(\"SCRIPT=${s}\")\n  endforeach()\nendmacro()\n"
        "set(Slicer_QTSCRIPTEDMODULES_LIB_DIR lib/qt-scripted-modules)\n"
        f"add_subdirectory(\"{MODULE_DIR.as_posix()}\" module)\n")
    build = tmp_path / "build"
    run = subprocess.run(["cmake", "-S", str(source), "-B", str(build), "-DBUILD_TESTING=OFF"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    scripts = re.findall(r"^SCRIPT=(.+)$", run.stdout + run.stderr, flags=re.MULTILINE)
    copied = {p.relative_to(build / "lib" / "qt-scripted-modules").as_posix()
              for p in (build / "lib" / "qt-scripted-modules").rglob("*") if p.is_file()}
    return scripts, copied


@pytest.mark.skipif(shutil.which("cmake") is None, reason="cmake is not installed")
def test_cmake_build_ships_every_core_module_and_the_resources(tmp_path):
    scripts, copied = _cmake_listing(tmp_path)
    core = sorted(p.relative_to(MODULE_DIR).as_posix() for p in (MODULE_DIR / "FevarPlannerLib").rglob("*.py"))
    assert [s for s in scripts if s.startswith("FevarPlannerLib/")] == core
    # subpackages ship too
    assert {"FevarPlannerLib/pipeline/frame.py", "FevarPlannerLib/phantom/case.py", "FevarPlannerLib/deformation/tps.py"} \
        <= set(core)
    assert "FevarPlanner.py" in scripts and not any(s.startswith("FevarPlannerApp/") for s in scripts)
    assert all((MODULE_DIR / s).is_file() for s in scripts)
    # the module talks to the core only: nothing of the workstation is imported
    assert not re.findall(r"^\s*(?:from|import) FevarPlannerApp\b", (MODULE_DIR / "FevarPlanner.py").read_text(),
                          flags=re.MULTILINE)
    assert {"Resources/UI/FevarPlanner.ui", "Resources/Icons/FevarPlanner.png"} <= copied


def test_top_level_cmake_is_a_slicer_extension():
    text = (REPO / "CMakeLists.txt").read_text()
    for needle in ("project(FevarPlanner)", "find_package(Slicer REQUIRED)", "include(${Slicer_USE_FILE})",
                   "add_subdirectory(FevarPlanner)", "include(${Slicer_EXTENSION_GENERATE_CONFIG})",
                   "include(${Slicer_EXTENSION_CPACK})", 'set(EXTENSION_DEPENDS "NA")'):
        assert needle in text
    for key in ("HOMEPAGE", "CATEGORY", "CONTRIBUTORS", "DESCRIPTION", "ICONURL", "SCREENSHOTURLS"):
        assert re.search(rf'set\(EXTENSION_{key} "[^"]+"\)', text), key


def test_only_the_module_file_imports_slicer_or_qt():
    pattern = re.compile(r"^\s*(import|from)\s+(slicer|qt|ctk)\b", flags=re.MULTILINE)
    offenders = [p.relative_to(REPO).as_posix() for p in (REPO / "FevarPlanner").rglob("*.py")
                 if pattern.search(p.read_text(encoding="utf-8"))]
    assert offenders == ["FevarPlanner/FevarPlanner.py"]


def test_logic_plans_a_phantom_case_into_the_scene(scene, tmp_path):
    """The module's self-test route (run_phantom_check), on the slicer-core scene."""
    check = fp.run_phantom_check(scene, tmp_path)
    assert (check["models"], check["curves"], check["volumes"]) == (2 + len(OVERLAYS), 1, 1)
    curve = check["nodes"]["path"]
    assert curve.GetLocked() and curve.GetCurveTypeAsString(curve.GetCurveType()) == "linear"
    # linear: the curve's length in Slicer is the one result.json reports
    assert curve.GetCurveLengthWorld() == pytest.approx(check["result"].path.length_mm, abs=1e-4)
    assert len(check["path_ras"]) >= 10
    np.testing.assert_allclose(check["path_ras"], fp.lps_to_ras(check["result"].path.points), atol=1e-9)
    assert check["start_right_of_aorta_mm"] > 5.0  # the access is on the patient's right ...
    assert check["start_below_aorta_mm"] > 20.0  # ... in the iliac, below the bifurcation
    assert check["end_mm"] < 10.0  # and the path ends at the left renal artery
    assert check["path_ras"][0][0] > check["path_ras"][-1][0]  # RAS: +x is the patient's right


def test_a_refused_case_shows_its_qc_picture_in_the_frame_view_and_clears_the_last_result(scene, anatomy, tmp_path):
    """A frame whose mask is a bar across the image: the logic raises the frame check's one
    line, removes the earlier run's nodes and shows the QC picture, upright, in the frame view."""
    from PIL import Image

    from FevarPlannerLib.quality import QualityError

    fp.FevarPlannerLogic(scene).add_result(_plan_result(anatomy))
    assert "deformed" in fp.result_nodes(scene)
    folder = phantom.write_phantom_set(tmp_path / "cases", n=1, seed=0, preset="random", mask_only=True)[0]
    bar = np.zeros(np.asarray(Image.open(folder / "fluoro_mask.png")).shape, dtype=np.uint8)
    bar[100:112, 50:-60] = 255
    Image.fromarray(bar).save(folder / "fluoro_mask.png")
    with pytest.raises(QualityError, match="aorta not found in the frame") as refused:
        fp.FevarPlannerLogic(scene).run(folder, out_dir=tmp_path / "out")
    picture = tmp_path / "out" / "segmentation_qc.png"
    assert f"see {picture}" in str(refused.value)
    nodes = fp.result_nodes(scene)
    assert sorted(nodes) == ["refusal"]                   # the earlier result is gone
    node = nodes["refusal"]
    saved = np.asarray(Image.open(picture).convert("RGB"))
    cols, rows, _ = node.GetImageData().GetDimensions()
    assert (rows, cols) == saved.shape[:2] and node.GetImageData().GetNumberOfScalarComponents() == 3
    pixels = numpy_support.vtk_to_numpy(node.GetImageData().GetPointData().GetScalars())
    np.testing.assert_array_equal(pixels.reshape(rows, cols, 3), saved)   # row j of the node = row j of the picture
    _, composite = fp.frame_view_nodes(scene)
    assert composite.GetBackgroundVolumeID() == node.GetID()


@pytest.fixture(scope="module")
def node_route(tmp_path_factory):
    """The Slicer route once: inputs as loaded nodes, a segmentation given, through the parameter node."""
    mrml = slicer.vtkMRMLScene()
    mrml.AddNode(slicer.vtkMRMLSelectionNode())
    return mrml, fp.run_node_check(mrml, tmp_path_factory.mktemp("nodes"))


def test_nodes_route_creates_the_results_in_ras_and_references_them(node_route):
    scene, check = node_route
    result, nodes, parameters = check["result"], check["nodes"], check["parameters"]
    assert check["start_right_of_aorta_mm"] > 5.0 and check["start_below_aorta_mm"] > 20.0 and check["end_mm"] < 10.0
    assert check["ct_view"].GetBackgroundVolumeID() == parameters.ctVolume.GetID()  # the CT keeps its view
    assert parameters.recoveredModel is nodes["deformed"] and parameters.pathCurve is nodes["path"]
    assert parameters.preopModel is nodes["preop"]
    recovered = np.array([nodes["deformed"].GetPolyData().GetPoint(i) for i in range(len(result.deformed))])
    np.testing.assert_allclose(recovered, fp.lps_to_ras(result.deformed.points), atol=1e-9)
    radius = nodes["deformed"].GetPolyData().GetPointData().GetArray("Radius")
    aorta = np.asarray(result.deformed.labels) == "aorta"
    radii = np.array([radius.GetValue(i) for i in range(len(result.deformed))])
    assert 4.0 < np.median(radii[aorta]) < 16.0  # the phantom's aorta is 9-12 mm in radius
    assert np.median(radii[aorta]) > np.median(radii[~aorta])
    assert nodes["path"].GetLocked()


def test_an_edited_segmentation_is_used_on_the_next_run(node_route):
    scene, check = node_route
    parameters, mask = check["parameters"], check["mask"]
    logic = fp.FevarPlannerLogic(scene)
    before = logic.case_from_nodes(parameters).aorta_mask
    np.testing.assert_array_equal(before.array, mask.array)
    # "Segment Editor": erase the distal right iliac (patient's right = -x LPS, lowest 20 mm)
    lps = mask.index_to_lps(np.argwhere(mask.array))
    right_iliac = (lps[:, 0] < np.median(lps[:, 0]) - 10.0) & (lps[:, 2] < lps[:, 2].min() + 20.0)
    edited = mask.array.copy()
    edited[tuple(np.argwhere(mask.array)[right_iliac].T)] = False
    segmentation = parameters.aortaSegmentation
    segmentation.GetSegmentation().RemoveAllSegments()
    labelmap = fp.volume_to_node(scene, mask.with_array(edited), "edited", node_class="vtkMRMLLabelMapVolumeNode")
    slicer.vtkSlicerSegmentationsModuleLogic.ImportLabelmapToSegmentationNode(labelmap, segmentation)
    scene.RemoveNode(labelmap)

    np.testing.assert_array_equal(logic.case_from_nodes(parameters).aorta_mask.array, edited)
    result, nodes = logic.process(parameters)
    assert parameters.aortaSegmentation is segmentation  # kept across runs, not replaced
    lowest_right = lambda centerline: centerline.points[np.asarray(centerline.labels) == "iliac_right"][:, 2].min()
    assert lowest_right(result.preop) > lowest_right(check["result"].preop) + 10.0
    ras = np.array([nodes["path"].GetNthControlPointPositionWorld(i)
                    for i in range(nodes["path"].GetNumberOfControlPoints())])
    np.testing.assert_allclose(ras, fp.lps_to_ras(result.path.points), atol=1e-9)


def test_application_classes_build_with_the_research_statement_and_the_wrapped_parameters(monkeypatch):
    """The Slicer-only part, loaded with stand-ins for Slicer's application modules."""
    import types

    from FevarPlannerLib import RESEARCH_USE_STATEMENT

    class _Base:
        def __init__(self, parent=None):
            self.parent = parent

    application = types.ModuleType("slicer.ScriptedLoadableModule")
    for name in ("ScriptedLoadableModule", "ScriptedLoadableModuleLogic", "ScriptedLoadableModuleTest",
                 "ScriptedLoadableModuleWidget"):
        setattr(application, name, type(name, (_Base,), {}))
    wrapped = {}
    wrapper = types.ModuleType("slicer.parameterNodeWrapper")
    wrapper.parameterNodeWrapper = lambda cls: wrapped.setdefault("class", cls)
    for name, module in (("slicer.ScriptedLoadableModule", application), ("slicer.parameterNodeWrapper", wrapper),
                         ("qt", types.ModuleType("qt")), ("ctk", types.ModuleType("ctk"))):
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("FevarPlanner_in_slicer", MODULE_DIR / "FevarPlanner.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    assert module.SLICER_APPLICATION
    description = types.SimpleNamespace()
    module.FevarPlanner(description)
    assert RESEARCH_USE_STATEMENT in description.helpText
    for handler in ("enter", "exit", "cleanup", "onSceneStartClose", "onSceneEndClose", "initializeParameterNode"):
        assert callable(getattr(module.FevarPlannerWidget, handler))
    fields = wrapped["class"].__annotations__
    assert fields["ctVolume"] is slicer.vtkMRMLScalarVolumeNode
    assert fields["aortaSegmentation"] is slicer.vtkMRMLSegmentationNode
    assert fields["pathCurve"] is slicer.vtkMRMLMarkupsCurveNode and fields["target"] is str
    assert fields["extraFrameVolumes"] == list[slicer.vtkMRMLScalarVolumeNode]
    assert fields["extraGeometryFiles"] == fields["extraFluoroFiles"] == list[str] and fields["shownView"] is str
    assert wrapped["class"].method == "proposed"
    assert {"test_phantom_case", "test_nodes_route", "test_two_view_nodes_route"} <= set(dir(module.FevarPlannerTest))
    for handler in ("onAddViewButton", "onRemoveViewButton", "_fill_views", "_on_view_chosen"):
        assert callable(getattr(module.FevarPlannerWidget, handler))


def test_further_views_are_kept_as_the_parameter_node_wrappers_lists(scene, tmp_path):
    """extraFrameVolumes / extraGeometryFiles / extraFluoroFiles: <field>_len and <field>_<i>, saved with the scene."""
    parameters = fp.FevarPlannerLogic(scene).getParameterNode()
    assert parameters.extraFrameVolumes == [] and parameters.shownView == "main"
    frames = [scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode") for _ in range(3)]
    for index, node in enumerate(frames):
        node.SetName(f"LAO{30 * (index + 1)}")
        fp.add_extra_view(parameters, node, f"/data/view{index}/geometry.json" if index != 1 else "",
                          "/data/lao60.dcm" if index == 1 else "")
    fp.remove_extra_view(parameters, 0)
    assert [node.GetName() for node in parameters.extraFrameVolumes] == ["LAO60", "LAO90"]
    assert parameters.extraGeometryFiles == ["", "/data/view2/geometry.json"]
    assert parameters.extraFluoroFiles == ["/data/lao60.dcm", ""]
    node = parameters.node
    assert node.GetParameter("extraFrameVolumes_len") == "2" and not node.GetParameter("extraGeometryFiles_2")
    assert node.GetNodeReference("extraFrameVolumes_1") is frames[2]
    assert node.GetNodeReference("extraFrameVolumes_2") is None  # the dropped entry is gone
    reloaded = _saved_and_reloaded(scene, tmp_path / "scene.mrml")  # kept: the nodes live in it
    loaded = fp.FevarPlannerParameters.of_scene(reloaded)
    assert [n.GetID() for n in loaded.extraFrameVolumes] == [frames[1].GetID(), frames[2].GetID()]
    assert loaded.extraFluoroFiles == ["/data/lao60.dcm", ""]
    assert [n.GetName() for n, _, _ in fp.extra_views(loaded)] == ["LAO60", "LAO90"]


def test_further_views_need_distinct_names_and_matching_lists(scene):
    from FevarPlannerLib.io import InputError

    parameters = fp.FevarPlannerLogic(scene).getParameterNode()
    node = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode")
    node.SetName("main")
    fp.add_extra_view(parameters, node, "g.json")
    with pytest.raises(InputError, match="'main' has the name of another view"):
        fp.extra_views(parameters)
    node.SetName("LAO30")
    parameters.extraGeometryFiles = []
    with pytest.raises(InputError, match="1 frame nodes .* 0 geometry files"):
        fp.extra_views(parameters)
    with pytest.raises(ValueError, match="needs its frame node"):
        fp.add_extra_view(parameters, None)
    assert fp.MAIN_VIEW_NAME == io.MAIN_VIEW


@pytest.fixture(scope="module")
def two_view_nodes(tmp_path_factory):
    """The Slicer route with two frame nodes (AP and a second C-arm angle), each with its own geometry.json."""
    mrml = slicer.vtkMRMLScene()
    mrml.AddNode(slicer.vtkMRMLSelectionNode())
    return mrml, fp.run_node_check(mrml, tmp_path_factory.mktemp("two_view_nodes"), two_views=True)


def _overlay_uv(overlay, frame_node) -> np.ndarray:
    """An overlay model's points back on its frame's pixel grid (u, v), through the frame's IJK-to-RAS."""
    matrix = vtk.vtkMatrix4x4()
    frame_node.GetIJKToRASMatrix(matrix)
    ras_to_ijk = np.linalg.inv(np.array([[matrix.GetElement(r, c) for c in range(4)] for r in range(4)]))
    polydata = overlay.GetPolyData()
    ras = np.array([polydata.GetPoint(i) for i in range(polydata.GetNumberOfPoints())])
    return (np.column_stack([ras, np.ones(len(ras))]) @ ras_to_ijk.T)[:, :2]


def _on_vessels(uv: np.ndarray, mask: np.ndarray) -> float:
    col, row = np.rint(uv).astype(int).T
    inside = (col >= 0) & (col < mask.shape[1]) & (row >= 0) & (row < mask.shape[0])
    return float(np.where(inside, mask[np.clip(row, 0, mask.shape[0] - 1), np.clip(col, 0, mask.shape[1] - 1)],
                          False).mean())


def test_two_frame_nodes_are_registered_together_and_each_gets_its_overlay(two_view_nodes):
    scene, check = two_view_nodes
    result, nodes, parameters = check["result"], check["nodes"], check["parameters"]
    second = check["view_folders"][0].name
    assert [view["name"] for view in result.views] == ["main", second] == fp.result_views(scene)
    assert all(view["2d_px"]["mean"] < 1.5 for view in result.views)
    assert check["start_right_of_aorta_mm"] > 5.0 and check["end_mm"] < 10.0
    frames = {"main": parameters.fluoroVolume, second: parameters.extraFrameVolumes[0]}
    masks = {"main": io.read_mask_2d(check["folder"] / "fluoro_mask.png"),
             second: io.read_mask_2d(check["view_folders"][0] / "fluoro_mask.png")}
    Ps = {frame.name: frame.P for frame in result.view_frames}
    assert not np.allclose(Ps["main"], Ps[second])
    for name, frame_node in frames.items():
        roles = {f"{role}:{name}" if name != "main" else role for role in OVERLAYS}
        assert roles <= set(nodes)
        overlay = nodes[f"overlay_deformed:{name}" if name != "main" else "overlay_deformed"]
        assert overlay.GetNodeReference(fp.FRAME_REFERENCE) is frame_node  # drawn on this view's own frame
        assert overlay.GetAttribute(fp.VIEW_ATTRIBUTE) == name
        uv = _overlay_uv(overlay, frame_node)
        np.testing.assert_allclose(uv, project(Ps[name], result.deformed.points), atol=1e-6)
        other = next(n for n in masks if n != name)
        assert _on_vessels(uv, masks[name]) > 0.99 and _on_vessels(uv, masks[other]) < 0.97
    assert scene.GetNumberOfNodesByClass("vtkMRMLModelNode") == 2 + 2 * len(OVERLAYS)


def test_the_view_selector_swaps_the_frame_and_its_overlays(two_view_nodes):
    scene, check = two_view_nodes
    parameters, nodes = check["parameters"], check["nodes"]
    second = check["view_folders"][0].name
    slice_node, composite = fp.frame_view_nodes(scene)
    assert parameters.shownView == "main" and composite.GetBackgroundVolumeID() == parameters.fluoroVolume.GetID()
    logic = fp.FevarPlannerLogic(scene)
    logic.show_view(second, parameters)
    assert parameters.shownView == second
    assert composite.GetBackgroundVolumeID() == parameters.extraFrameVolumes[0].GetID()
    for role in OVERLAYS:
        assert not nodes[role].GetDisplayNode().GetVisibility()
        assert nodes[f"{role}:{second}"].GetDisplayNode().GetVisibility()
    assert check["ct_view"].GetBackgroundVolumeID() == parameters.ctVolume.GetID()  # the CT keeps its view
    with pytest.raises(ValueError, match="no view 'lateral'"):
        logic.show_view("lateral")
    logic.show_view("main")
    assert nodes["overlay_deformed"].GetDisplayNode().GetVisibility()


def test_the_case_folder_route_shows_every_view_of_the_folder(two_view_nodes):
    """run(): the folder's own frame and views/<name>/ each become a frame volume with its overlays."""
    _, check = two_view_nodes
    scene = slicer.vtkMRMLScene()
    scene.AddNode(slicer.vtkMRMLSelectionNode())
    result, nodes = fp.FevarPlannerLogic(scene).run(check["folder"])
    second = check["view_folders"][0].name
    assert fp.result_views(scene) == ["main", second]
    assert scene.GetNumberOfNodesByClass("vtkMRMLScalarVolumeNode") == 2
    frame = nodes[f"fluoro:{second}"]
    assert frame.GetAttribute(fp.VIEW_ATTRIBUTE) == second and frame.GetName() == f"FevarPlanner fluoroscopy ({second})"
    np.testing.assert_array_equal(fp.node_to_volume(frame).array[0],
                                  result.view_drawings(io.load_case(check["folder"]))[1].image)
    assert nodes[f"overlay_path:{second}"].GetNodeReference(fp.FRAME_REFERENCE) is frame

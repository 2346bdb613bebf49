"""Every file type we write, saved and loaded through slicer-core's real storage nodes.

The core writes LPS; Slicer's scene is RAS. Each test goes both ways through the storage
node Slicer itself uses for that file type and compares coordinates within 1e-6 mm.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import vtk

slicer = pytest.importorskip("slicer")

from FevarPlannerLib import export, io  # noqa: E402
from FevarPlannerLib.centerline import Centerline  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TOLERANCE_MM = 1e-6


def _load_module():
    spec = importlib.util.spec_from_file_location("FevarPlanner", REPO / "FevarPlanner" / "FevarPlanner.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("FevarPlanner", module)
    spec.loader.exec_module(module)
    return module


fp = _load_module()


@pytest.fixture()
def scene():
    mrml = slicer.vtkMRMLScene()
    mrml.AddNode(slicer.vtkMRMLSelectionNode())
    return mrml


@pytest.fixture()
def tree():
    """A labelled Y far from the origin on every axis (a sign error cannot hide), LPS mm."""
    rng = np.random.default_rng(3)
    aorta = np.column_stack([np.full(8, 31.25), np.full(8, -142.5), np.linspace(410.0, 300.0, 8)])
    left = aorta[-1] + np.cumsum(np.tile([6.0, 1.0, -9.0], (4, 1)), axis=0)
    right = aorta[-1] + np.cumsum(np.tile([-6.0, 1.5, -9.0], (4, 1)), axis=0)
    points = np.vstack([aorta, left, right]) + rng.normal(scale=0.1, size=(16, 3))
    edges = [[i, i + 1] for i in range(7)] + [[7, 8], [8, 9], [9, 10], [10, 11], [7, 12], [12, 13], [13, 14],
                                              [14, 15]]
    labels = ["aorta"] * 8 + ["iliac_left"] * 4 + ["iliac_right"] * 4
    return Centerline(points, np.array(edges), labels)


def _storage(scene, storage_class, path):
    """A storage node of ``storage_class`` in ``scene``, pointed at ``path``."""
    storage = storage_class()
    scene.AddNode(storage)
    storage.SetFileName(str(path))
    return storage


def _save(scene, storage_class, node, path):
    """Write ``node`` to ``path`` through Slicer's own storage node; that node."""
    storage = _storage(scene, storage_class, path)
    assert storage.WriteData(node) == 1
    return storage


def _load(scene, node_class, storage_class, path):
    """A new ``node_class`` node read from ``path`` through Slicer's own storage node; (node, storage)."""
    node = scene.AddNewNodeByClass(node_class)
    storage = _storage(scene, storage_class, path)
    assert storage.ReadData(node) == 1
    return node, storage


def _model_points_ras(node) -> np.ndarray:
    return np.array([node.GetPolyData().GetPoint(i) for i in range(node.GetPolyData().GetNumberOfPoints())])


@pytest.mark.parametrize("suffix", [".vtp", ".vtk"])
def test_a_model_slicer_saved_reads_back_in_lps(scene, tree, tmp_path, suffix):
    node = fp.centerline_to_model_node(scene, tree, "recovered", role="deformed")
    # the old module tagged its models RAS; Slicer keeps such a tag, stale, beside its own SPACE
    stale = vtk.vtkStringArray()
    stale.SetName("coordinateSystem")
    stale.InsertNextValue("RAS")
    node.GetPolyData().GetFieldData().AddArray(stale)
    _save(scene, slicer.vtkMRMLModelStorageNode, node, tmp_path / f"model{suffix}")
    back = export.read_centerline_vtp(tmp_path / f"model{suffix}")
    assert np.abs(back.points - tree.points).max() < TOLERANCE_MM
    np.testing.assert_array_equal(back.edges, tree.edges)
    assert back.labels == tree.labels


@pytest.mark.parametrize("suffix", [".vtp", ".vtk"])
def test_a_model_slicer_saved_in_ras_reads_back_in_lps(scene, tree, tmp_path, suffix):
    node = fp.centerline_to_model_node(scene, tree, "recovered", role="deformed")
    storage = _storage(scene, slicer.vtkMRMLModelStorageNode, tmp_path / f"model{suffix}")
    storage.SetCoordinateSystem(slicer.vtkMRMLStorageNode.CoordinateSystemRAS)
    assert storage.WriteData(node) == 1
    back = export.read_centerline_vtp(tmp_path / f"model{suffix}")
    assert np.abs(back.points - tree.points).max() < TOLERANCE_MM


def test_our_vtp_loads_in_slicer_where_it_belongs_and_survives_a_resave(scene, tree, tmp_path):
    export.write_centerline_vtp(tmp_path / "ours.vtp", tree)
    node, storage = _load(scene, "vtkMRMLModelNode", slicer.vtkMRMLModelStorageNode, tmp_path / "ours.vtp")
    assert np.abs(_model_points_ras(node) - fp.lps_to_ras(tree.points)).max() < TOLERANCE_MM
    assert np.abs(fp.model_node_to_centerline(node).points - tree.points).max() < TOLERANCE_MM
    storage.SetFileName(str(tmp_path / "resaved.vtp"))
    assert storage.WriteData(node) == 1
    assert np.abs(export.read_centerline_vtp(tmp_path / "resaved.vtp").points - tree.points).max() < TOLERANCE_MM


def test_space_tag_wins_over_the_legacy_tag(tree):
    polydata = export.centerline_to_polydata(tree, space="RAS")
    stale = vtk.vtkStringArray()
    stale.SetName("coordinateSystem")
    stale.InsertNextValue("LPS")
    polydata.GetFieldData().AddArray(stale)
    assert export.coordinate_system_of(polydata) == "RAS"
    np.testing.assert_allclose(export.polydata_to_centerline(polydata).points, tree.points, atol=1e-12)
    assert export.coordinate_system_of(polydata, header="3D Slicer output. SPACE=LPS") == "LPS"
    untagged = export.centerline_to_polydata(tree, space=None)
    assert export.coordinate_system_of(untagged) == "LPS"  # Slicer's default for a file that says nothing
    with pytest.raises(ValueError, match="space must be"):
        export.centerline_to_polydata(tree, space="XYZ")


def test_path_markups_load_in_slicer_and_slicer_saved_ones_read_back(scene, tree, tmp_path):
    points = tree.points[:8]
    export.write_path_markups(tmp_path / "path.mrk.json", points)
    reader = _storage(scene, slicer.vtkMRMLMarkupsJsonStorageNode, tmp_path / "path.mrk.json")
    curve = reader.AddNewMarkupsNodeFromFile(str(tmp_path / "path.mrk.json"))
    ras = np.array([curve.GetNthControlPointPositionWorld(i) for i in range(curve.GetNumberOfControlPoints())])
    assert np.abs(ras - fp.lps_to_ras(points)).max() < TOLERANCE_MM
    _save(scene, slicer.vtkMRMLMarkupsJsonStorageNode, curve, tmp_path / "resaved.mrk.json")
    assert np.abs(export.read_path_markups(tmp_path / "resaved.mrk.json") - points).max() < TOLERANCE_MM


def _oblique_volume(dtype=np.int16) -> io.Volume:
    angle = np.deg2rad(20.0)
    direction = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1.0]])
    array = (np.arange(6 * 7 * 8).reshape(6, 7, 8) % 97).astype(dtype)  # (k, j, i)
    return io.Volume(array, [0.7, 0.8, 2.5], [-120.25, 35.5, 812.0], direction)


def _index_to_ras(node) -> np.ndarray:
    matrix = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(matrix)
    return np.array([[matrix.GetElement(r, c) for c in range(4)] for r in range(4)])


def test_our_nrrd_volume_loads_in_slicer_and_slicer_saved_ones_read_back(scene, tmp_path):
    volume = _oblique_volume()
    io.write_volume(tmp_path / "ct.nrrd", volume)
    node, storage = _load(scene, "vtkMRMLScalarVolumeNode", slicer.vtkMRMLVolumeArchetypeStorageNode,
                          tmp_path / "ct.nrrd")
    corner = np.array([7, 6, 5, 1.0])  # i, j, k
    expected_ras = fp.lps_to_ras(volume.index_to_lps([5, 6, 7]))
    assert np.abs((_index_to_ras(node) @ corner)[:3] - expected_ras).max() < TOLERANCE_MM
    back = fp.node_to_volume(node)
    np.testing.assert_array_equal(back.array, volume.array)
    assert np.abs(back.index_to_lps_matrix - volume.index_to_lps_matrix).max() < TOLERANCE_MM

    storage.SetFileName(str(tmp_path / "resaved.nrrd"))
    assert storage.WriteData(node) == 1
    again = io.read_volume(tmp_path / "resaved.nrrd")
    np.testing.assert_array_equal(again.array, volume.array)
    assert np.abs(again.index_to_lps_matrix - volume.index_to_lps_matrix).max() < TOLERANCE_MM


def test_module_volume_node_matches_the_core_volume(scene):
    volume = _oblique_volume(np.float32)
    node = fp.volume_to_node(scene, volume, "CT")
    assert np.abs(_index_to_ras(node) - fp.LPS_TO_RAS_4X4 @ volume.index_to_lps_matrix).max() < 1e-12
    back = fp.node_to_volume(node)
    np.testing.assert_array_equal(back.array, volume.array)
    assert np.abs(back.index_to_lps_matrix - volume.index_to_lps_matrix).max() < 1e-9


def test_segmentation_saved_by_slicer_reads_back_on_the_ct_grid(scene, tmp_path):
    ct = _oblique_volume(np.float32)
    mask = np.zeros(ct.shape, dtype=bool)
    mask[1:5, 2:6, 3:7] = True
    ct_node = fp.volume_to_node(scene, ct, "CT")
    segmentation = fp.mask_to_segmentation_node(scene, ct.with_array(mask), ct_node)
    assert segmentation.GetSegmentation().GetNumberOfSegments() == 1
    assert segmentation.GetSegmentation().GetNthSegment(0).GetName() == "aorta"
    _save(scene, slicer.vtkMRMLSegmentationStorageNode, segmentation, tmp_path / "aorta.seg.nrrd")

    other = slicer.vtkMRMLScene()
    loaded, _ = _load(other, "vtkMRMLSegmentationNode", slicer.vtkMRMLSegmentationStorageNode,
                      tmp_path / "aorta.seg.nrrd")
    back = fp.segmentation_node_to_mask(loaded, fp.volume_to_node(other, ct, "CT"), "aorta")
    np.testing.assert_array_equal(back.array, mask)
    assert np.abs(back.index_to_lps_matrix - ct.index_to_lps_matrix).max() < TOLERANCE_MM
    # and the core reads Slicer's .seg.nrrd as a mask in the same place
    core = io.read_mask(tmp_path / "aorta.seg.nrrd")
    lps_of_core = core.index_to_lps(np.argwhere(core.array))
    lps_of_truth = ct.index_to_lps(np.argwhere(mask))
    assert np.abs(np.sort(lps_of_core, axis=0) - np.sort(lps_of_truth, axis=0)).max() < TOLERANCE_MM

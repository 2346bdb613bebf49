"""Synthetic AAA phantoms: geometry, ground truth, files and the paper protocol."""

import json
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from FevarPlannerLib import io
from FevarPlannerLib import phantom as ph
from FevarPlannerLib.centerline import Centerline
from FevarPlannerLib.projection import project, projection_matrix_from_carm, read_geometry_json

SMALL = dict(ct_spacing_mm=2.0, ct_margin_mm=10.0, detector_pixel_mm=1.5, sma=True, coeliac=True,
             internal_iliacs=True)


def small_params(seed=7, **overrides):
    return ph.random_params(np.random.default_rng(seed), **{**SMALL, **overrides})


@pytest.fixture(scope="module")
def full_case(tmp_path_factory):
    params = small_params(misalign_shift_px=(6.0, -4.0), misalign_rotation_deg=2.0)
    case = ph.generate_case(params, name="t1")
    folder = ph.write_case(case, tmp_path_factory.mktemp("phantom") / "t1")
    return case, folder


def read_gt(folder):
    gt = json.loads((folder / "gt.json").read_text())
    return gt, Centerline.from_dict(gt["preop_centerline"]), Centerline.from_dict(gt["intraop_centerline"])


def test_case_folder_has_every_file(full_case):
    _, folder = full_case
    names = {p.name for p in folder.iterdir()}
    assert {"ct", "aorta_mask.nrrd", "fluoro.dcm", "fluoro_mask.png", "geometry.json", "gt.json",
            "case.json"} <= names
    assert len(list((folder / "ct").glob("*.dcm"))) > 50


def test_projected_intraop_centerline_lies_in_fluoro_mask(full_case):
    case, folder = full_case
    gt, _, intra = read_gt(folder)
    mask = np.array(Image.open(folder / "fluoro_mask.png")) > 0
    uv = np.rint(project(np.array(gt["projection_matrix_true"]), intra.points)).astype(int)
    assert np.all((uv >= 0) & (uv < [mask.shape[1], mask.shape[0]]))
    assert mask[uv[:, 1], uv[:, 0]].mean() >= 0.99
    assert 0.02 < mask.mean() < 0.5


def test_preop_centerline_lies_in_aorta_mask(full_case):
    _, folder = full_case
    _, pre, _ = read_gt(folder)
    mask = io.read_volume(folder / "aorta_mask.nrrd")
    kji = np.rint(mask.lps_to_index(pre.points)).astype(int)
    assert mask.array[tuple(kji.T)].mean() >= 0.99
    assert mask.array.mean() < 0.2


def test_dicom_carm_tags_give_the_true_projection(full_case):
    case, folder = full_case
    fluoro = io.read_fluoro(folder / "fluoro.dcm")
    ct = io.read_ct(folder / "ct")
    P_tags = projection_matrix_from_carm(fluoro.carm, ct.center_lps())
    scale = np.abs(case.P_true).max()
    assert np.abs(P_tags - case.P_true).max() < 1e-6 * scale
    P_given = read_geometry_json(folder / "geometry.json")
    assert np.allclose(P_given, case.P_given)
    assert not np.allclose(P_given, case.P_true)
    assert np.allclose(json.loads((folder / "geometry.json").read_text())["true_projection_matrix"], case.P_true)


def test_ct_intensities_follow_the_tissues(full_case):
    case, folder = full_case
    ct = io.read_ct(folder / "ct")
    lumen = io.read_volume(folder / "aorta_mask.nrrd").array > 0
    core = ndimage.binary_erosion(lumen)  # away from partial-volume edges
    assert abs(np.median(ct.array[core]) - case.preop_params.lumen_hu) < 60
    assert ct.array.max() > 500  # bone
    assert np.median(ct.array[~lumen]) < 100


def test_fluoro_vessels_are_dark_on_a_grey_background(full_case):
    _, folder = full_case
    frame = io.read_fluoro(folder / "fluoro.dcm").image
    mask = np.array(Image.open(folder / "fluoro_mask.png")) > 0
    assert frame[mask].mean() < 0.85 * frame[~mask].mean()
    assert frame[~mask].std() > 0  # noise


def test_lengths_are_preserved_and_the_shape_changes():
    params = small_params(seed=3)
    pre = ph.build_preop_anatomy(params)
    intra = ph.deform_anatomy(pre, params)
    for name, length in pre.lengths().items():
        assert abs(intra.lengths()[name] - length) <= 0.05 * length
    a, b = pre.to_centerline(), intra.to_centerline()
    assert len(a) == len(b) and a.labels == b.labels and np.array_equal(a.edges, b.edges)
    displacement = np.linalg.norm(a.points - b.points, axis=1)
    assert displacement.mean() > 1.0


def test_deformation_magnitude_follows_one_parameter():
    base = small_params(seed=4)
    pre = ph.build_preop_anatomy(base).to_centerline()
    mean_shift = []
    for scale in (0.0, 0.5, 1.0):
        moved = ph.deform_anatomy(ph.build_preop_anatomy(base), ph.PhantomParams.from_dict(
            {**base.to_dict(), "deformation_scale": scale})).to_centerline()
        mean_shift.append(np.linalg.norm(moved.points - pre.points, axis=1).mean())
    assert mean_shift[0] < 1e-9
    assert 0 < mean_shift[1] < mean_shift[2]


def test_anatomy_is_oriented_in_lps():
    params = small_params(seed=5, renal_left_above_mm=6.0)
    anatomy = ph.build_preop_anatomy(params)
    aorta = anatomy.vessels["aorta"]
    left, right = anatomy.vessels["renal_left"], anatomy.vessels["renal_right"]
    assert left.points[-1, 0] > aorta.points[left.parent_index, 0] + 20
    assert right.points[-1, 0] < aorta.points[right.parent_index, 0] - 20
    assert left.points[0, 2] > right.points[0, 2]
    bifurcation = aorta.points[-1]
    for side in ("left", "right"):
        iliac = anatomy.vessels[f"iliac_{side}"]
        assert iliac.points[-1, 2] < bifurcation[2] - 40
    assert anatomy.vessels["iliac_left"].points[-1, 0] > anatomy.vessels["iliac_right"].points[-1, 0]
    assert anatomy.vessels["sma"].points[-1, 1] < aorta.points[anatomy.vessels["sma"].parent_index, 1] - 10
    assert aorta.points[0, 2] > aorta.points[-1, 2] + 150
    sac = aorta.outer_radius.max()
    assert sac == pytest.approx(params.sac_outer_radius_mm, abs=0.5)
    assert aorta.radius.max() < sac - 3


def test_centerline_is_one_connected_graph_with_all_labels():
    anatomy = ph.build_preop_anatomy(small_params(seed=6))
    line = anatomy.to_centerline(step_mm=2.0)
    n = len(line)
    adjacency = coo_matrix((np.ones(len(line.edges)), tuple(line.edges.T)), shape=(n, n))
    assert connected_components(adjacency, directed=False)[0] == 1
    assert len(line.edges) == n - 1  # a tree
    assert {"aorta", "renal_left", "renal_right", "iliac_left", "iliac_right", "other"} == set(line.labels)
    steps = np.linalg.norm(line.points[line.edges[:, 0]] - line.points[line.edges[:, 1]], axis=1)
    assert steps.max() < 2.6


def test_rasterize_lumen_matches_on_a_flipped_grid():
    anatomy = ph.build_preop_anatomy(small_params(seed=8, sma=False, coeliac=False, internal_iliacs=False))
    grid = ph.ct_grid(anatomy, spacing_mm=2.5, margin_mm=5.0)
    reference = ph.rasterize_lumen(anatomy, grid)
    flip = np.diag([-1.0, 1.0, -1.0])
    k, j, i = np.array(grid.shape) - 1
    far_corner = np.asarray(grid.origin) + np.array([i, 0, k]) * 2.5
    flipped = io.Volume(np.zeros(grid.shape, np.uint8), grid.spacing, far_corner, flip)
    result = ph.rasterize_lumen(anatomy, flipped)
    assert np.array_equal(result.array[::-1, :, ::-1], reference.array)
    assert reference.array.sum() > 100


def test_same_seed_gives_identical_files(tmp_path):
    first = ph.write_phantom_set(tmp_path / "a", n=2, seed=11, preset="random", mask_only=True)
    second = ph.write_phantom_set(tmp_path / "b", n=2, seed=11, preset="random", mask_only=True)
    for a, b in zip(first, second):
        for file in sorted(a.iterdir()):
            assert file.read_bytes() == (b / file.name).read_bytes(), file.name
    assert (first[0] / "gt.json").read_bytes() != (first[1] / "gt.json").read_bytes()
    params = small_params(seed=2)
    case = ph.generate_case(params)
    ct1 = ph.render_ct(case.preop, params, np.random.default_rng(1), case.grid)
    ct2 = ph.render_ct(case.preop, params, np.random.default_rng(1), case.grid)
    assert ct1.array.dtype == np.int16 and np.array_equal(ct1.array, ct2.array)


def test_paper_protocol_pairs_five_states_of_one_phantom(tmp_path):
    pairs = ph.paper_protocol(seed=0)
    assert len(pairs) == 20
    shapes = {json.dumps(pre.shape_dict(), sort_keys=True) for pre, _ in pairs}
    assert len(shapes) == 1
    states = {json.dumps(p.to_dict(), sort_keys=True) for pair in pairs for p in pair}
    assert len(states) == 5
    assert all(pre.to_dict() != intra.to_dict() for pre, intra in pairs)
    assert all(intra.misalign_shift_px == (0.0, 0.0) and intra.primary_angle_deg == 0.0 for _, intra in pairs)
    folders = ph.write_phantom_set(tmp_path, n=2, seed=0, preset="paper", mask_only=True)
    assert [f.name for f in folders] == ["paper00_pre0_intra1", "paper00_pre0_intra2"]
    gt, pre, intra = read_gt(folders[0])
    assert len(pre) == len(intra)
    for name, length in gt["vessel_lengths_mm"]["preop"].items():
        assert gt["vessel_lengths_mm"]["intraop"][name] == pytest.approx(length, rel=0.05)
    case = json.loads((folders[1] / "case.json").read_text())
    assert (case["preop_state"], case["intraop_state"]) == (0, 2)


def test_paper_protocol_bends_in_the_frontal_plane_unless_asked_otherwise():
    frontal = [p for pair in ph.paper_protocol(seed=3) for p in pair]
    tilted = [p for pair in ph.paper_protocol(seed=3, out_of_plane_deg=1.0) for p in pair]
    assert all(p.bend_anterior_deg == 0.0 for p in frontal)
    bends = np.array([p.bend_anterior_deg for p in tilted])
    assert np.all(np.abs(bends) <= 1.0) and np.ptp(bends) > 0.2
    # everything else is drawn the same, so the two sets differ by the out-of-plane bend only
    for a, b in zip(frontal, tilted):
        assert replace(a, bend_anterior_deg=b.bend_anterior_deg) == b


def test_params_round_trip_and_reject_bad_values():
    params = small_params(seed=9)
    again = ph.PhantomParams.from_dict(json.loads(json.dumps(params.to_dict())))
    assert again == params
    with pytest.raises(ValueError, match="unknown phantom parameters"):
        ph.PhantomParams.from_dict({"aorta_radius": 3})
    with pytest.raises(ValueError, match="sod_mm"):
        ph.PhantomParams(sod_mm=1300.0).validate()
    with pytest.raises(ValueError, match="preset"):
        ph.write_phantom_set("unused", n=1, preset="nope")


def test_paired_states_must_share_one_phantom():
    a, b = small_params(seed=1), small_params(seed=2)
    with pytest.raises(ValueError, match="different phantoms"):
        ph.generate_case(a, b)

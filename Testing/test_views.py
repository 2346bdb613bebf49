"""Several views of the same intra-operative anatomy (issue 10): depth from a second C-arm angle.

One AP view cannot see a bend towards or away from the X-ray source; a second view at
another C-arm angle can. The case: a phantom whose sac is bent 12 degrees anteriorly,
seen AP and at LAO 45 / LAO 60.
"""

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from FevarPlannerLib import evaluation, io, phantom, pipeline
from FevarPlannerLib.projection import project, projection_matrix_from_carm, write_geometry_json
from fixtures import drawn_mask, phantom_case_fixtures


def view_geometry(case, primary_deg: float):
    """P and frame shape of a C-arm at ``primary_deg`` (LAO +) around the case's isocentre."""
    params = replace(case.params, primary_angle_deg=primary_deg)
    isocentre = case.grid.center_lps()
    carm = phantom.fit_detector(case.intraop, params, isocentre)
    return projection_matrix_from_carm(carm, isocentre), carm


case, preop = phantom_case_fixtures("bent", bend_anterior_deg=12.0)


@pytest.fixture(scope="module")
def frames(case):
    truth = case.intraop.to_centerline()
    out = {}
    for angle in (0, 45, 60):
        P, carm = view_geometry(case, angle)
        out[angle] = (drawn_mask(truth, P, (carm.rows, carm.cols)), P)
    return out


def error_3d(frame, case):
    truth = case.intraop.to_centerline()
    return evaluation.evaluate(frame.deformed, truth, frame.P, frame.skeleton2d.positions,
                               frame.skeleton2d.edges())["3d_mm"]["mean"]


def test_two_views_recover_the_out_of_plane_bend(case, preop, frames):
    """AP alone keeps the pre-operative depth (> 2 mm); AP + LAO 45 or 60 recover it (< 1 mm)."""
    single = error_3d(pipeline.register_views(preop, [frames[0]]), case)
    sv = error_3d(pipeline.register_views(preop, [frames[0]], method="rigid"), case)
    assert single > 2.0 and sv > 2.0
    for other in (45, 60):
        both = pipeline.register_views(preop, [frames[0], frames[other]], names=["ap", f"lao{other}"])
        assert error_3d(both, case) < 1.0
        assert [v.name for v in both.views] == ["ap", f"lao{other}"]
        for view, (mask, P) in zip(both.views, (frames[0], frames[other])):
            fit = evaluation.error_2d(both.deformed.points, P, view.skeleton2d.positions, view.skeleton2d.edges())
            assert fit["mean"] < 1.0          # each view still fits in 2D
    assert both.warnings == []


def test_register_frame_is_the_one_view_case(case, preop, frames):
    mask, P = frames[0]
    one = pipeline.register_frame(preop, mask, P)
    same = pipeline.register_views(preop, [(mask, P)])
    np.testing.assert_allclose(one.deformed.points, same.deformed.points)
    assert one.correspondence == same.correspondence and one.views[0].name == "main"


def test_register_views_refuses_clashing_names(preop, frames):
    with pytest.raises(ValueError, match="distinct name"):
        pipeline.register_views(preop, [frames[0], frames[45]], names=["a", "a"])
    with pytest.raises(ValueError, match="no view"):
        pipeline.register_views(preop, [])


def write_view(folder, mask, P):
    folder.mkdir(parents=True)
    io.write_mask_png(folder / "fluoro_mask.png", mask)
    write_geometry_json(folder / "geometry.json", P)


@pytest.fixture(scope="module")
def two_view_case_dir(tmp_path_factory, case):
    """A mask-only case folder (rendered lumen masks) with a second view in views/lao30/."""
    folder = phantom.write_case(case, tmp_path_factory.mktemp("views") / "case", mask_only=True)
    P, carm = view_geometry(case, 30)
    _, mask = phantom.render_fluoro(case.intraop, P, carm, case.params, np.random.default_rng(5))
    write_view(folder / "views" / "lao30", mask, P)
    return folder


def test_load_case_exposes_every_view(two_view_case_dir, case):
    loaded = io.load_case(two_view_case_dir)
    assert [v.name for v in loaded.views] == ["main", "lao30"]
    main, lao = loaded.views
    np.testing.assert_allclose(main.P, loaded.P)
    assert main.fluoro_mask is loaded.fluoro_mask and not lao.has_frame
    np.testing.assert_allclose(lao.P, view_geometry(case, 30)[0])
    assert lao.paths["geometry"].parent.name == "lao30"


def test_plan_uses_every_view_and_lists_them(two_view_case_dir, tmp_path):
    """Rendered lumen masks, AP + LAO 30: measured 1.1 mm against 8.4 mm for AP alone."""
    loaded = io.load_case(two_view_case_dir)
    loaded.views = loaded.views[:1]
    single = pipeline.run_case(loaded)
    result = pipeline.plan_case(two_view_case_dir, tmp_path / "out")
    data = json.loads((tmp_path / "out" / "result.json").read_text())
    assert [v["name"] for v in data["views"]] == ["main", "lao30"]
    for view in data["views"]:
        assert view["2d_px"]["mean"] < 1.5 and len(view["projection_matrix"]) == 3
    assert set(data["visibility"]) == {"main", "lao30"}
    assert data["visibility"]["main"]["clipped_border"] == []
    assert data["warnings"] == []
    assert single.errors["3d_mm"]["mean"] > 4.0 and result.errors["3d_mm"]["mean"] < 1.5


def test_a_view_that_cannot_be_read_is_left_out_with_a_warning(preop, frames):
    blank = (np.zeros_like(frames[45][0]), frames[45][1])
    result = pipeline.register_views(preop, [frames[0], blank], names=["ap", "blank"])
    assert [v.name for v in result.views] == ["ap"]
    assert any(w.startswith("view blank not used") for w in result.warnings)
    with pytest.raises(ValueError, match="view blank"):
        pipeline.register_views(preop, [blank, blank], names=["blank", "other"])


def test_a_case_may_hold_views_only(tmp_path, case, frames):
    folder = phantom.write_case(case, tmp_path / "case", mask_only=True)
    for name in ("fluoro_mask.png", "geometry.json"):
        (folder / name).unlink()
    for angle in (0, 60):
        write_view(folder / "views" / f"a{angle:02d}", *frames[angle])
    loaded = io.load_case(folder)
    assert [v.name for v in loaded.views] == ["a00", "a60"]
    np.testing.assert_allclose(loaded.P, frames[0][1])


def test_bad_view_folders_are_named(tmp_path, two_view_case_dir):
    import shutil

    folder = tmp_path / "case"
    shutil.copytree(two_view_case_dir, folder)
    (folder / "views" / "empty").mkdir()
    with pytest.raises(io.InputError, match="empty: view without a frame"):
        io.load_case(folder)
    (folder / "views" / "empty").rename(folder / "views" / "main")
    with pytest.raises(io.InputError, match="belongs to the case folder's own frame"):
        io.load_case(folder)


def test_a_lateral_view_without_classification_still_gives_depth(case, preop):
    """At 90 degrees the renals and iliacs overlap and Algorithm 1 cannot name the branches;
    the view then gives its nearest 2D skeleton points as targets (measured: 8.4 mm for AP
    alone, 0.69 mm with the lateral view). The renals run along the lateral view's rays,
    inside the aorta's silhouette: they take no target there (before: they were pulled onto
    the aorta's 2D centre line, 1.04 mm in 3D, 0.85 px in 2D), so the lateral 2D fit of the
    whole tree is looser (1.53 px) while the 3D result is closer."""
    truth = case.intraop.to_centerline()
    frames = []
    for angle in (0, 90):
        P, carm = view_geometry(case, angle)
        _, mask = phantom.render_fluoro(case.intraop, P, carm, case.params, np.random.default_rng(5))
        frames.append((mask, P))
    single = pipeline.register_views(preop, frames[:1])
    both = pipeline.register_views(preop, frames, names=["ap", "lateral"])
    assert both.views[1].classification2d is None and both.views[1].correspondence == "nearest points"
    assert any(w.startswith("view lateral: no anatomical classification") for w in both.warnings)
    assert error_3d(single, case) > 4.0 and error_3d(both, case) < 0.9
    lateral = both.views[1]
    assert evaluation.error_2d(both.deformed.points, lateral.P, lateral.skeleton2d.positions,
                               lateral.skeleton2d.edges())["mean"] < 2.0


def test_chain_refinement_lets_the_views_agree(case, preop, frames, monkeypatch):
    """After the first deformation (AP alone) the AP view's nodes take the nearest point of their
    matched 2D chain from the current estimate (ICP-like) while the second view follows by
    nearest points: the bent sac's first targets slid along the vessel where it turned out of
    the view's plane (measured: 0.48 / 0.40 / 0.38 mm without, 0.43 / 0.37 / 0.31 mm with,
    AP + LAO 30 / 45 / 60). Before the second view followed the first (it used its own labels
    and soft assignment) this phantom gave 0.32 / 0.23 / 0.24 mm; the scenario two-view sets
    gain more the other way (multiview, README). Since the trunk's knots follow its
    projection (matching.paper._sliding_trunk_lengths) the first targets slide less and the
    first pass is already 0.47 / 0.35 / 0.32 mm (refined 0.44 / 0.36 / 0.30 mm): the
    refinement must not make it worse."""
    from FevarPlannerLib.pipeline import multiview
    for other in (45, 60):
        pair = [frames[0], frames[other]]
        refined = error_3d(pipeline.register_views(preop, pair, names=["ap", "lao"]), case)
        monkeypatch.setattr(multiview, "_chain_closest_data", lambda view, c, nodes, preop, estimate, first: first)
        first = error_3d(pipeline.register_views(preop, pair, names=["ap", "lao"]), case)
        monkeypatch.undo()
        assert refined < 0.45 and refined < first + 0.01


def test_nearest_point_on_a_polyline_and_past_its_ends():
    from FevarPlannerLib.pipeline.multiview import _closest_on_polyline
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    points = np.array([[5.0, 2.0], [12.0, 4.0], [10.0, 13.0], [-3.0, 1.0], [11.0, -1.0]])
    foot, past = _closest_on_polyline(points, line)
    np.testing.assert_allclose(foot, [[5, 0], [10, 4], [10, 10], [0, 0], [10, 0]], atol=1e-12)
    assert past.tolist() == [False, False, True, True, False]


def test_a_match_across_vessels_or_along_the_rays_gives_no_target():
    """A 3D vessel crossing the view's only 2D vessel at right angles, and one running
    nearly along the rays, get no nearest-point target; one running along the 2D vessel does."""
    from FevarPlannerLib.graph import SkeletonGraph
    from FevarPlannerLib.pipeline.multiview import _crosses_vessels
    P = np.array([[1000.0, 0, 0, 0], [0, 1000.0, 0, 0], [0, 0, 1, 1000.0]])       # looks along +z
    s = np.linspace(-20, 20, 41)
    along = np.c_[s, np.zeros_like(s), np.zeros_like(s)]                            # along u
    across = np.c_[np.zeros_like(s), s, np.zeros_like(s)]                           # along v
    deep = np.c_[0.05 * s, np.zeros_like(s), s]                                     # along the ray
    positions = np.vstack([along, across + [0, 0, 100], deep + [0, 50, 0]])
    edges = np.vstack([np.c_[np.arange(40), np.arange(1, 41)] + 41 * k for k in range(3)])
    g3 = SkeletonGraph.from_points(positions, edges)
    u = np.linspace(-30, 30, 61)
    g2 = SkeletonGraph.from_points(np.c_[u, np.zeros_like(u)], np.c_[np.arange(60), np.arange(1, 61)])
    view = SimpleNamespace(g2=g2, P=P)
    nodes = np.arange(len(positions))
    uv = project(P, positions)
    _, index = cKDTree(g2.positions).query(uv)
    preop = SimpleNamespace(graph=g3, classification=SimpleNamespace(branches=[]))
    crossing = _crosses_vessels(view, nodes, preop, positions, uv, index)
    assert not crossing[1:40].any()
    assert crossing[42:81].all() and crossing[83:122].all()
    assert not crossing[[0, 40, 41, 81]].any()          # ends: no direction to compare
    # a branch more than half hidden gives no target at all, its ends included
    deep_branch = SimpleNamespace(nodes=np.arange(82, 123), label="renal_left")
    preop.classification.branches = [deep_branch, SimpleNamespace(nodes=np.arange(41), label="aorta")]
    crossing = _crosses_vessels(view, nodes, preop, positions, uv, index)
    assert crossing[82:123].all() and not crossing[:41].any()
    # with radii: a thin vessel whose nearest 2D centre line is three times wider than the rest
    g3.radii = np.r_[np.full(41, 3.0), np.full(82, 1.0)]
    g2.radii = np.where(np.arange(61) > 45, 9.0, 3.0)          # 1 px per mm: 2D radius = 3D radius
    preop.classification.branches = []
    crossing = _crosses_vessels(view, np.arange(41), preop, positions, uv[:41], index[:41])
    assert not crossing[1:35].any() and crossing[37:40].all()        # u > 15 lies on the wide part


def test_a_branch_the_views_disagree_on_is_dropped_from_the_worse_view():
    """One view fits a branch within 0.2 mm and the other is 3 mm off: the other gives way on
    that branch only; a branch both views miss alike (1.5 and 2 mm) stays in both."""
    from FevarPlannerLib.pipeline.multiview import _disagreeing_views, _without
    P = np.array([[1000.0, 0, 0, 0], [0, 1000.0, 0, 0], [0, 0, 1, 1000.0]])     # 1 px per mm at z = 0
    points = np.c_[np.arange(20.0), np.zeros(20), np.zeros(20)]
    branches = [SimpleNamespace(nodes=np.arange(10), label="renal_left"),
                SimpleNamespace(nodes=np.arange(10, 20), label="renal_right")]
    preop = SimpleNamespace(graph=SimpleNamespace(positions=points), centre=np.zeros(3),
                            classification=SimpleNamespace(branches=branches))
    uv = project(P, points)
    offsets = [np.r_[np.full(10, 0.2), np.full(10, 1.5)], np.r_[np.full(10, 3.0), np.full(10, 2.0)]]
    data = [(uv + np.c_[o, np.zeros(20)], np.ones(20)) for o in offsets]
    views = [SimpleNamespace(P=P), SimpleNamespace(P=P)]
    drop = _disagreeing_views(views, data, np.arange(20), points, preop)
    assert not drop[0].any() and drop[1][:10].all() and not drop[1][10:].any()
    _, weights = _without(data[1], drop[1])
    np.testing.assert_allclose(weights, np.r_[np.zeros(10), np.full(10, 2.0)])    # mean over the 10 kept



def test_a_branch_chain_bridge_across_the_parent_lumen_gives_no_target():
    """Thinning joins a 2D branch to its parent's centre line across the parent's lumen (radius
    10 px at the junction). 3D branch nodes whose nearest chain point lies on that bridge get
    no target from the chain; the rest keep theirs (nearest chain point); without 2D radii all do."""
    from FevarPlannerLib.graph import SkeletonGraph
    from FevarPlannerLib.pipeline.multiview import _chain_closest_data
    P = np.array([[1000.0, 0, 0, 0], [0, 1000.0, 0, 0], [0, 0, 1, 1000.0]])     # 1 px per mm at z = 0
    u2 = np.arange(-10.0, 41.0)
    g2 = SkeletonGraph.from_points(np.c_[u2, np.zeros_like(u2)], np.c_[np.arange(50), np.arange(1, 51)])
    g2.radii = np.r_[10.0, np.full(50, 3.0)]                     # the junction node lies in the parent
    u3 = np.arange(-8.0, 32.0, 2.0)
    positions = np.c_[u3, np.full_like(u3, 0.5), np.zeros_like(u3)]
    branch = SimpleNamespace(nodes=np.arange(len(u3)), label="renal_left")
    preop = SimpleNamespace(graph=SimpleNamespace(positions=positions), kept=np.arange(len(u3)),
                            classification=SimpleNamespace(branches=[branch]))
    correspondence = SimpleNamespace(trunk_pairs=[], branch_chains={0: np.arange(51)}, branch_pairs=[])
    view = SimpleNamespace(P=P, g2=g2)
    nodes = np.arange(len(u3))
    fallback = (project(P, positions), np.ones(len(u3)))
    targets, weights = _chain_closest_data(view, correspondence, nodes, preop, positions, fallback)
    on_bridge = u3 < 0.0                                         # within 10 px of the junction at u = -10
    assert on_bridge.sum() == 4 and not weights[on_bridge].any() and weights[~on_bridge].all()
    np.testing.assert_allclose(targets[~on_bridge], np.c_[u3[~on_bridge], np.zeros((~on_bridge).sum())], atol=1e-9)
    g2.radii = None
    assert _chain_closest_data(view, correspondence, nodes, preop, positions, fallback)[1].all()

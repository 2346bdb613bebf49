"""Pre-operative cache, the `track` route, the geometry note and correction, through the CLI."""

import csv
import json
import shutil

import numpy as np
import pytest

from FevarPlannerLib import cache, cli, io, phantom
from FevarPlannerLib.projection import apply_in_plane_correction, projection_matrix_from_carm
from FevarPlannerLib.tracking import CSV_COLUMNS, track_case, write_track_outputs
from fixtures import phantom_run_folder

N_FRAMES = 3


@pytest.fixture(scope="module")
def run_case_dir(tmp_path_factory):
    """A mask-level phantom case whose fluoro.dcm is a run of N_FRAMES noisy frames with C-arm tags."""
    return phantom_run_folder(tmp_path_factory.mktemp("run"), N_FRAMES)


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    """One cache for the module: the pre-operative model is computed once, then read."""
    return tmp_path_factory.mktemp("shared") / "cache"


@pytest.fixture()
def cache_dir(shared_cache, monkeypatch):
    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(shared_cache))
    return shared_cache


def test_the_cache_returns_the_same_model_and_notices_changed_inputs(run_case_dir, tmp_path, monkeypatch):
    cache_dir = tmp_path / "own-cache"
    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(cache_dir))
    case = io.load_case(run_case_dir[0])
    first = cache.preop_model(case)
    second = cache.preop_model(case)
    assert (first.from_cache, second.from_cache) == (False, True)
    assert len(list(cache_dir.glob("preop-*.pkl"))) == 1
    np.testing.assert_array_equal(second.preop.centerline.points, first.preop.centerline.points)
    assert second.preop.centerline.labels == first.preop.centerline.labels
    np.testing.assert_array_equal(second.lumen.array, first.lumen.array)
    assert "preop_cache_load" in second.timings

    changed = io.load_case(run_case_dir[0])
    flipped = changed.aorta_mask.array.copy()
    flipped[tuple(np.argwhere(flipped)[0])] = False
    changed.aorta_mask = changed.aorta_mask.with_array(flipped)
    assert cache.preop_key(changed) != cache.preop_key(case)
    assert cache.preop_key(case, "threshold") == cache.preop_key(case)  # a given mask is not segmented

    entry = next(cache_dir.glob("preop-*.pkl"))
    entry.write_bytes(b"truncated")
    again = cache.preop_model(case)
    assert not again.from_cache and cache.preop_model(case).from_cache
    assert cache.clear_cache() == 1


def test_track_registers_every_frame_and_writes_csv_and_json(run_case_dir, cache_dir, tmp_path):
    folder, _ = run_case_dir
    result = track_case(folder, target="renal_right")
    assert [r.frame for r in result.records] == list(range(N_FRAMES))
    assert all(r.fit_2d_px is not None and r.fit_2d_px < 6.0 for r in result.records)
    assert all(r.times["registration"] > 0 for r in result.records)
    paths = write_track_outputs(result, tmp_path / "out")
    rows = list(csv.DictReader(paths["track.csv"].open()))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == N_FRAMES
    assert [int(r["frame"]) for r in rows] == list(range(N_FRAMES))
    summary = json.loads(paths["track.json"].read_text())
    assert summary["n_frames"] == N_FRAMES and summary["per_frame_total_ms"]["median"] > 0
    assert summary["geometry"]["source"] == "geometry.json"  # which geometry every frame used
    assert json.loads((tmp_path / "out" / "result.json").read_text())["path"]["to"] == "renal_right"
    # a second run finds the pre-operative model in the cache
    again = track_case(folder, count=1)
    assert again.preop_from_cache and len(again.records) == 1


def test_track_refuses_a_frame_that_is_not_an_angiogram_and_keeps_the_others(run_case_dir, cache_dir, tmp_path):
    folder, generated = run_case_dir
    case = tmp_path / "case"
    shutil.copytree(folder, case)
    good = [phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                  np.random.default_rng(seed))[0] for seed in (0, 1)]
    noise = np.random.default_rng(7).integers(0, 4096, size=good[0].shape).astype(good[0].dtype)
    io.write_fluoro_dicom(case / "fluoro.dcm", np.stack([good[0], noise, good[1]]), generated.carm)
    result = track_case(case)
    refused = result.records[1]
    assert refused.fit_2d_px is None and refused.path_length_mm is None
    assert len(refused.warnings) == 1 and "fluoro.dcm (frame 1)" in refused.warnings[0]
    assert "not a usable angiogram" in refused.warnings[0]
    assert all(r.fit_2d_px is not None and r.fit_2d_px < 6.0 for r in (result.records[0], result.records[2]))


def test_track_refuses_a_frame_of_another_anatomy_by_the_registration_check(run_case_dir, cache_dir, tmp_path):
    """A run holding one frame of another phantom (seed 8, rendered through this case's C-arm):
    it passes the frame check and registers, but leaves over a quarter of its vessels
    unexplained; that frame is refused, the others answered."""
    folder, generated = run_case_dir
    case = tmp_path / "case"
    shutil.copytree(folder, case)
    good = [phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                  np.random.default_rng(seed))[0] for seed in (0, 1)]
    other = phantom.generate_case(phantom.random_params(np.random.default_rng(8), misalign_shift_px=(0.0, 0.0),
                                                        misalign_rotation_deg=0.0), name="other")
    foreign = phantom.render_fluoro(other.intraop, generated.P_true, generated.carm, generated.params,
                                    np.random.default_rng(2))[0]
    io.write_fluoro_dicom(case / "fluoro.dcm", np.stack([good[0], foreign.astype(good[0].dtype), good[1]]),
                          generated.carm)
    result = track_case(case)
    refused = result.records[1]
    assert refused.fit_2d_px is None and len(refused.warnings) == 1
    assert "fluoro.dcm (frame 1): registration check" in refused.warnings[0]
    assert all(r.fit_2d_px is not None and r.fit_2d_px < 6.0 for r in (result.records[0], result.records[2]))


def test_track_refuses_a_mirrored_run_whole_by_the_mirror_test(run_case_dir, cache_dir, tmp_path):
    """The run's frames flipped left-right (the wrong side convention): frame 0 registers and fits
    (until the faint renals were tracked, 2026-11-30, the registration check refused it and frame 1
    was the first registered); registered flipped too, it fits better on every count, so the
    whole run is refused, naming that frame."""
    folder, generated = run_case_dir
    case = tmp_path / "case"
    shutil.copytree(folder, case)
    frames = [phantom.render_fluoro(generated.intraop, generated.P_true, generated.carm, generated.params,
                                    np.random.default_rng(seed))[0] for seed in range(2, 4)]
    io.write_fluoro_dicom(case / "fluoro.dcm", np.stack([frame[:, ::-1] for frame in frames]), generated.carm)
    with pytest.raises(io.InputError, match=r"fluoro.dcm \(frame 0\): registration check: the frame looks mirrored "
                                            r"left-right: registered flipped.*every frame is refused"):
        track_case(case)


def test_bad_option_values_fail_before_any_work(run_case_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FEVAR_PLANNER_CACHE", str(tmp_path / "untouched"))
    with pytest.raises(ValueError, match="target vessel must be one of"):
        track_case(run_case_dir[0], target="sma")
    assert not (tmp_path / "untouched").exists()
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["track", str(run_case_dir[0]), "--out", str(tmp_path / "o"), "--target", "sma"])
    assert exit_info.value.code == 2 and "invalid choice: 'sma'" in capsys.readouterr().err


def test_version_and_help_say_research_use_only(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--version"])
    assert "not a medical device" in capsys.readouterr().out
    for command in ("plan", "track", "geometry", "demo", "segment", "phantoms", "benchmark", "train-unet"):
        with pytest.raises(SystemExit):
            cli.main([command, "--help"])
        text = capsys.readouterr().out
        assert "not a medical device" in " ".join(text.split()), command
    parser = cli.build_parser()
    for action in parser._subparsers._group_actions[0].choices.values():
        for option in action._actions:
            assert option.help, f"{action.prog} {option.option_strings or option.dest} has no help"


def test_tags_only_geometry_is_announced_recorded_checked_and_correctable(run_case_dir, cache_dir, tmp_path, capsys):
    folder = tmp_path / "case"
    shutil.copytree(run_case_dir[0], folder)
    (folder / "geometry.json").unlink()
    generated = run_case_dir[1]
    assert cli.main(["-q", "plan", str(folder), "--out", str(tmp_path / "out"), "--method", "rigid"]) == 0
    captured = capsys.readouterr()
    assert "fevar-planner: note: geometry from dicom-tags" in captured.err
    assert "isocentre lies at the centre of the CT volume" in captured.err and "table position" in captured.err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["geometry"]["source"] == "dicom-tags"
    assert result["geometry"]["tags"]["PositionerPrimaryAngle"] == pytest.approx(generated.carm.primary_angle, abs=1e-9)
    assert (tmp_path / "out" / "drr_check.png").stat().st_size > 1000
    loaded = io.load_case(folder)
    P_tags = loaded.P
    np.testing.assert_allclose(P_tags, projection_matrix_from_carm(loaded.fluoro.carm, loaded.aorta_mask.center_lps()))
    np.testing.assert_allclose(result["projection_matrix"], P_tags)

    assert cli.main(["geometry", str(folder), "--shift", "5", "-3", "--rotate", "2"]) == 0
    stored = json.loads((folder / "geometry.json").read_text())
    assert stored == {"in_plane_correction": {"translation_px": [5.0, -3.0], "rotation_deg": 2.0}}
    corrected = io.load_case(folder)
    shape = corrected.fluoro.shape
    np.testing.assert_allclose(corrected.P, apply_in_plane_correction(P_tags, stored["in_plane_correction"], shape))
    assert corrected.geometry.in_plane_correction["translation_px"] == [5.0, -3.0]
    assert cli.main(["geometry", str(folder), "--reset"]) == 0
    assert not (folder / "geometry.json").exists()
    # a folder that is not there is an error, and nothing is created
    assert cli.main(["geometry", str(tmp_path / "nope"), "--shift", "1", "1"]) == 2
    assert not (tmp_path / "nope").exists()


def test_surface_of_a_skeleton_case_comes_from_its_aorta_mask_by_the_case_rules(run_case_dir, tmp_path):
    from FevarPlannerLib import skeleton

    folder = shutil.copytree(run_case_dir[0], tmp_path / "case")
    mask = io.read_mask(folder / "aorta_mask.nrrd")
    io.write_volume(folder / "skeleton3d.nrrd", mask.with_array(skeleton.skeletonize_3d(mask).array.astype(np.uint8)))
    case = io.load_case(folder)
    assert case.stage_3d == "skeleton3d" and case.aorta_mask is None
    model = cache.PreopModel(preop=None, lumen=None, key="")
    assert model.surface() is None                                  # no lumen and no case: nothing to show
    surface = model.surface(case)
    assert surface.GetNumberOfPolys() > 1000
    bounds = np.array(surface.GetBounds()).reshape(3, 2)
    corners = np.array([mask.index_to_lps(np.argwhere(mask.array).min(axis=0)),
                        mask.index_to_lps(np.argwhere(mask.array).max(axis=0))])
    np.testing.assert_allclose(bounds, np.sort(corners, axis=0).T, atol=2 * max(mask.spacing))
    # a flag for the 3D side hides the folder's mask (the case's rules): no surface then
    flagged = io.load_case(folder, skeleton3d=folder / "skeleton3d.nrrd")
    assert cache.PreopModel(preop=None, lumen=None, key="").surface(flagged) is None

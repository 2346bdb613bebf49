import io
from pathlib import Path

import numpy as np
import pytest

from FevarPlannerLib.cli import ProgressBar, build_parser, main


def test_progress_bar_draws_fraction_and_ends_the_line():
    stream = io.StringIO()
    bar = ProgressBar(stream=stream, width=10, tty=True)
    bar(0.5, "halfway")
    bar.count(4, 4, "done")
    text = stream.getvalue()
    assert "[#####.....]  50.0%" in text and "halfway" in text
    assert "[##########] 100.0%" in text and text.endswith("\n")
    silent = io.StringIO()
    ProgressBar(stream=silent, enabled=False)(0.3, "x")
    assert silent.getvalue() == ""


def test_progress_without_a_terminal_is_one_line_per_step_or_tenth():
    stream = io.StringIO()
    bar = ProgressBar(stream=stream)  # a StringIO is not a TTY
    for done in range(41):
        bar(0.05 + 0.1 * done / 40, f"segmenting the aorta: slice {done}/40")
    bar(0.25, "3D skeleton graph")
    bar(1.0, "done")
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    assert len(lines) == 4  # the step at 5 %, its 10 % decile, the next step, done
    assert lines[0].startswith("[  5%]") and "slice 0/40" in lines[0]
    assert lines[-1].startswith("[100%]") and lines[-1].endswith("done")


class _Reached(Exception):
    """Raised by a stand-in for a stage entry point: which one ran, and with what."""


def _stand_in(name):
    def reached(*args, **kwargs):
        raise _Reached(name, args, kwargs)
    return reached


#: subcommand argv -> (the core entry point it must reach, an argument that must arrive there)
_WIRING = {
    "plan": (["plan", "case_dir", "--out", "o"], "FevarPlannerLib.pipeline.plan_case", "case_dir"),
    "phantoms": (["phantoms", "--out", "o", "--n", "3"], "FevarPlannerLib.phantom.write_phantom_set", 3),
    "demo": (["demo", "--out", "o", "--seed", "11"], "FevarPlannerLib.phantom.random_params", None),
    "benchmark": (["benchmark", "--out", "o", "--seed", "5"], "FevarPlannerLib.benchmark.run_benchmark", 5),
    "train-unet": (["train-unet", "c", "--out", "w.pt", "--iterations", "9"], "FevarPlannerLib.segmentation.train_unet", 9),
    "segment": (["segment", "ct.nrrd", "--out", "m.nrrd"], "FevarPlannerLib.io.read_ct", "ct.nrrd"),
    "track": (["track", "case_dir", "--out", "o", "--count", "7"], "FevarPlannerLib.tracking.track_case", 7),
    "geometry": (["geometry", "case_dir", "--shift", "1", "2"], "FevarPlannerLib.projection.update_in_plane_correction",
                 "case_dir"),
}


@pytest.mark.parametrize("command", sorted(_WIRING))
def test_every_subcommand_is_wired(command, monkeypatch):
    """Each subcommand reaches its own core entry point (and passes its arguments on)."""
    for _, target, _ in _WIRING.values():
        monkeypatch.setattr(target, _stand_in(target))
    argv, target, passed = _WIRING[command]
    with pytest.raises(_Reached) as reached:
        main(["-q", *argv])
    name, args, kwargs = reached.value.args
    assert name == target
    if passed is not None:
        values = [str(v) if isinstance(v, Path) else v for v in (*args, *kwargs.values())]
        assert (str(passed) if isinstance(passed, str) else passed) in values
    assert build_parser().parse_args(argv).command == command


def test_missing_case_folder_is_a_one_line_error(tmp_path, capsys):
    assert main(["-q", "plan", str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0] and "does not exist" in err[0]
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- one run, one output set

import json as _json
import os as _os
import shutil as _shutil
import subprocess as _subprocess
import sys as _sys
import warnings as _warnings

from FevarPlannerLib import io as fio
from FevarPlannerLib import phantom

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small_case(tmp_path_factory):
    params = phantom.PhantomParams(ct_spacing_mm=2.0, detector_pixel_mm=1.2, seed=5)
    return phantom.write_case(phantom.generate_case(params, name="cli"), tmp_path_factory.mktemp("cli") / "case",
                              mask_only=True)


def _result_without_timings(folder: Path) -> bytes:
    """result.json with its timings blanked, as bytes (everything else must be byte-identical)."""
    text = (folder / "result.json").read_text()
    data = _json.loads(text)
    data["timings_s"] = {key: 0.0 for key in data["timings_s"]}
    return _json.dumps(data).encode()


def _run_in_process(case, out, threads: int | None = None) -> None:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=threads):
        assert main(["-q", "plan", str(case), "--out", str(out)]) == 0


def test_same_inputs_give_the_same_outputs_across_runs_processes_and_threads(small_case, tmp_path):
    _run_in_process(small_case, tmp_path / "a", threads=1)
    _run_in_process(small_case, tmp_path / "b", threads=2)
    env = dict(_os.environ, PYTHONPATH=str(REPO / "FevarPlanner"), OMP_NUM_THREADS="2", OPENBLAS_NUM_THREADS="2",
               MKL_NUM_THREADS="2", PYTHONHASHSEED="123")
    _subprocess.run([_sys.executable, "-m", "FevarPlannerLib.cli", "-q", "plan", str(small_case), "--out",
                     str(tmp_path / "c")], env=env, check=True, capture_output=True)
    reference = _result_without_timings(tmp_path / "a")
    for other in ("b", "c"):
        assert _result_without_timings(tmp_path / other) == reference
        for name in ("deformed_centerline.vtp", "path.mrk.json"):
            assert (tmp_path / other / name).read_bytes() == (tmp_path / "a" / name).read_bytes(), name
    # the timings are the only difference: the raw files differ in nothing else
    raw = _json.loads((tmp_path / "c" / "result.json").read_text())
    assert set(raw["timings_s"]) >= {"total", "registration"}


def test_outputs_honour_the_umask(small_case, tmp_path):
    previous = _os.umask(0o027)
    try:
        assert main(["-q", "plan", str(small_case), "--out", str(tmp_path / "out")]) == 0
    finally:
        _os.umask(previous)
    assert (tmp_path / "out").stat().st_mode & 0o777 == 0o750
    for path in (tmp_path / "out").iterdir():
        assert path.stat().st_mode & 0o777 == 0o640, path.name


def test_a_rerun_replaces_the_previous_set_whole(small_case, tmp_path):
    out = tmp_path / "out"
    assert main(["-q", "plan", str(small_case), "--out", str(out), "--method", "rigid"]) == 0
    assert main(["-q", "plan", str(small_case), "--out", str(out), "--method", "proposed"]) == 0
    assert _json.loads((out / "result.json").read_text())["method"] == "proposed"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


# --------------------------------------------------------------------------- what the user hears

def test_an_error_starts_on_a_line_of_its_own_after_the_progress_bar(small_case, tmp_path, capsys):
    _shutil.copytree(small_case, tmp_path / "case")
    (tmp_path / "case" / "gt.json").write_text("[]")
    assert main(["plan", str(tmp_path / "case"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    error_lines = [line for line in err.splitlines() if "error:" in line]
    assert len(error_lines) == 1 and error_lines[0].startswith("fevar-planner: error: ")
    assert "gt.json" in error_lines[0]


def test_notes_about_the_inputs_reach_stderr_and_result_json_and_library_warnings_do_not(small_case, tmp_path,
                                                                                        capsys, monkeypatch):
    _shutil.copytree(small_case, tmp_path / "case")
    # a second 3D input of the same kind: the reader notes which one it used
    _shutil.copy2(tmp_path / "case" / "aorta_mask.nrrd", tmp_path / "case" / "aorta_mask.mha")
    from FevarPlannerLib import pipeline

    real = pipeline.run_case

    def noisy_run_case(*args, **kwargs):
        _warnings.warn("a library's internal warning", RuntimeWarning)
        return real(*args, **kwargs)
    monkeypatch.setattr(pipeline.case, "run_case", noisy_run_case)   # plan_case calls it there
    assert main(["-q", "plan", str(tmp_path / "case"), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "internal warning" not in err
    notes = [line for line in err.splitlines() if line.startswith("fevar-planner: note: ")]
    assert len(notes) == 1 and "aorta_mask.nrrd" in notes[0] and "aorta_mask.mha" in notes[0]
    assert err.count("\n") == len(notes)
    result = _json.loads((tmp_path / "out" / "result.json").read_text())
    assert any("aorta_mask.mha" in note for note in result["warnings"])


def test_two_series_and_junk_in_the_ct_folder_are_named_with_the_choice(tmp_path):
    volume = fio.Volume(np.zeros((4, 6, 7), np.int16), (0.7, 0.8, 2.5), (0, 0, 0), np.eye(3))
    fio.write_ct_dicom_series(volume, tmp_path / "long", series_uid="1.2.3.9.1")
    fio.write_ct_dicom_series(fio.Volume(np.ones((2, 6, 7), np.int16), (0.7, 0.8, 2.5), (0, 0, 9), np.eye(3)),
                              tmp_path / "short", series_uid="1.2.3.9.2")
    ct = tmp_path / "ct"
    ct.mkdir()
    for folder in ("long", "short"):
        for path in (tmp_path / folder).iterdir():
            path.rename(ct / f"{folder}_{path.name}")
    (ct / "README.txt").write_text("exported from the PACS")
    (ct / ".DS_Store").write_bytes(b"\0\0\0\1Bud1" * 10)
    with _warnings.catch_warnings(record=True) as caught:
        _warnings.simplefilter("always")
        back = fio.read_ct(ct)
    assert back.shape == (4, 6, 7)
    messages = [str(w.message) for w in caught if issubclass(w.category, fio.InputWarning)]
    assert any("README.txt (not DICOM)" in m and ".DS_Store" in m for m in messages)
    choice = next(m for m in messages if "DICOM series found" in m)
    assert "using 1.2.3.9.1 (4 slices" in choice and "1.2.3.9.2 (2 slices" in choice and "--ct" in choice


def test_plan_runs_one_case_without_starting_the_view_worker(small_case, tmp_path):
    """A one-case process gains nothing from the view worker (it is not ready before the case
    is done), so ``plan`` does not start it, and it leaves the caller's setting as it was."""
    from FevarPlannerLib.pipeline import workers

    workers.shutdown()
    previous = workers.set_enabled(True)
    try:
        assert main(["-q", "plan", str(small_case), "--out", str(tmp_path / "out")]) == 0
        assert workers._state["worker"] is None
        assert workers.set_enabled(previous) is True
    finally:
        workers.set_enabled(previous)
        workers.shutdown()

import io
from pathlib import Path

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

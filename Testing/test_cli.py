import io

import pytest

from FevarPlannerLib.cli import ProgressBar, build_parser, main


def test_progress_bar_draws_fraction_and_ends_the_line():
    stream = io.StringIO()
    bar = ProgressBar(stream=stream, width=10)
    bar(0.5, "halfway")
    bar.count(4, 4, "done")
    text = stream.getvalue()
    assert "[#####.....]  50.0%" in text and "halfway" in text
    assert "[##########] 100.0%" in text and text.endswith("\n")
    silent = io.StringIO()
    ProgressBar(stream=silent, enabled=False)(0.3, "x")
    assert silent.getvalue() == ""


def test_every_subcommand_is_wired():
    parser = build_parser()
    for argv in (["plan", "c", "--out", "o"], ["phantoms", "--out", "o"], ["demo"], ["benchmark", "--out", "o"],
                 ["train-unet", "c", "--out", "w.pt"], ["segment", "ct.nrrd", "--out", "m.nrrd"]):
        assert callable(parser.parse_args(argv).func)


def test_missing_case_folder_is_a_one_line_error(tmp_path, capsys):
    assert main(["-q", "plan", str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0] and "does not exist" in err[0]
    assert not (tmp_path / "out").exists()

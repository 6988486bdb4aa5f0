"""Command-line values that used to run nothing, trace back or be ignored now give one clear error (exit 2)."""
from __future__ import annotations

import pytest

from hil.cli import build_parser, main


@pytest.mark.parametrize("value", ["-5", "0", "nan", "inf", "soon"])
def test_a_duration_that_is_not_a_positive_finite_number_is_refused(value, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", "seed000", "--duration", value, "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --duration" in err and "Traceback" not in err


@pytest.mark.parametrize("args, needle", [
    (["--pace", "5"], "--pace only applies with --realtime"),
    (["--ecus-per-process", "4"], "--ecus-per-process only applies with --realtime"),
    (["--ideal", "--can-log"], "--can-log has no effect with --ideal"),
])
def test_options_that_would_do_nothing_are_errors(args, needle, capsys, tmp_path):
    rc = main(["run", "seed000", "--duration", "1", "--quiet", "--no-record", "--out", str(tmp_path), *args])
    assert rc == 2 and needle in capsys.readouterr().err
    assert not (tmp_path / "metrics.json").exists()  # refused before anything ran


def test_can_analysis_given_a_scenario_file_says_what_it_expected(capsys):
    rc = main(["can-analysis", "hil/packaged/scenarios/seed000.toml"])
    err = capsys.readouterr().err
    assert rc == 2 and "looks like a scenario file" in err and "--scenario" in err


def test_version_names_the_rig_and_the_engine(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("hil (trainhil) ") and "frame engine" in out


def test_run_help_describes_both_runtimes_and_gives_examples():
    parser = build_parser()
    run = next(a for a in parser._subparsers._group_actions[0].choices.items() if a[0] == "run")[1]
    text = run.format_help()
    assert "--realtime" in text and "examples:" in text and "Exit codes" in text
    top = parser.format_help()
    assert "virtual time, or --realtime" in top

"""Malformed sweep files: every one is a SweepError whose message names the file and the field (or axis and value)."""
from __future__ import annotations

from pathlib import Path

import pytest

from hil.sweep import SweepError, load_sweep

HEAD = 'name = "x"\nbase = "seed000"\nduration_s = 5\n'

# (case id, sweep text, substrings the message must contain besides the file name)
CASES = [
    ("unknown-key", HEAD + "seeeds = [1]\n", ("seeeds", "Extra inputs")),
    ("no-base", 'name = "x"\n', ("base", "Field required")),
    ("empty-name", 'name = ""\nbase = "seed000"\n', ("name",)),
    ("duration-string", 'name = "x"\nbase = "seed000"\nduration_s = "60"\n', ("duration_s", "expected a number")),
    ("duration-nan", 'name = "x"\nbase = "seed000"\nduration_s = nan\n', ("duration_s", "finite number")),
    ("duration-below-a-period", 'name = "x"\nbase = "seed000"\nduration_s = 0.001\n', ("duration_s", "shorter than")),
    ("seeds-empty", HEAD + "seeds = []\n", ("seeds",)),
    ("seeds-twice", HEAD + "seeds = [1, 1]\n", ("seeds", "not distinct")),
    ("seeds-strings", HEAD + 'seeds = ["1"]\n', ("seeds", "item 0")),
    ("seeds-negative", HEAD + "seeds = [-1]\n", ("seed", ">= 0")),
    ("axis-empty", HEAD + '[axes]\n"radio.latency_s" = []\n', ("radio.latency_s", "no values")),
    ("axis-scalar", HEAD + '[axes]\n"radio.latency_s" = 0.1\n', ("axes.radio.latency_s",)),
    ("axis-twice", HEAD + '[axes]\n"radio.latency_s" = [0.1, 0.1]\n', ("radio.latency_s", "twice")),
    ("axis-typo", HEAD + '[axes]\n"radio.latncy_s" = [0.1]\n', ("radio.latncy_s", "Extra inputs")),
    ("axis-bad-value", HEAD + '[axes]\n"radio.latency_s" = [0.0, -0.5]\n', ("axes.'radio.latency_s' value -0.5",)),
    ("axis-nan", HEAD + '[axes]\n"radio.latency_s" = [0.1, nan]\n', ("axis 'radio.latency_s': value 1 is NaN",)),
    ("axis-wrong-type", HEAD + '[axes]\n"trains.count" = ["3"]\n', ("axes.'trains.count' value '3'", "expected a number")),
    ("axis-unquoted", HEAD + "[axes]\nradio.latency_s = [0.1]\n", ("axis 'radio' is a table",)),
    ("axis-bad-key", HEAD + '[axes]\n"radio..latency" = [0.1]\n', ("not a dotted scenario key",)),
    ("axis-seed", HEAD + '[axes]\n"seed" = [1, 2]\n', ("'seed' cannot be set here",)),
    ("override-section", HEAD + "[overrides]\nradio = { latency_s = 0.1 }\n", ("would replace the whole [radio] section",)),
    ("override-invalid", HEAD + '[overrides]\n"trains.unit_mass_kg" = -1.0\n', ("[overrides]", "trains.unit_mass_kg")),
    ("combination-invalid", HEAD + '[axes]\n"trains.spacing_m" = [3000.0, 2000.0]\n"trains.emergency_gap_m" = [1500.0, 2500.0]\n',
     ("grid point", "emergency_gap_m")),
    ("base-missing", 'name = "x"\nbase = "nope.toml"\n', ("base = 'nope.toml'", "no such scenario file")),
    ("plot-unknown-column", HEAD + '[axes]\n"radio.latency_s" = [0.1]\n[plots]\nlines = [{ metric = "m", x = "latency" }]\n',
     ("plots.lines.0.x", "not an axis column")),
    ("plot-missing-metric", HEAD + '[axes]\n"radio.latency_s" = [0.1]\n[plots]\nlines = [{ x = "radio.latency_s" }]\n',
     ("plots.lines.0.metric", "Field required")),
    ("not-toml", "name = \n", ("not valid TOML",)),
]


@pytest.mark.parametrize(("text", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_malformed_sweep_names_file_and_field(tmp_path: Path, text: str, expected: tuple[str, ...]) -> None:
    path = tmp_path / "sweep.toml"
    path.write_text(text)
    with pytest.raises(SweepError) as err:
        load_sweep(path)
    msg = str(err.value)
    assert msg.startswith(str(path)), msg
    for part in expected:
        assert part in msg, f"{part!r} not in:\n{msg}"


def test_a_bad_base_scenario_is_named_with_the_sweep(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text("name = 'b'\nduration_s = 'long'\n")
    path = tmp_path / "sweep.toml"
    path.write_text('name = "x"\nbase = "base.toml"\n')
    with pytest.raises(SweepError) as err:
        load_sweep(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: base = 'base.toml' is not a valid scenario") and "base.toml" in msg
    assert "duration_s" in msg and "trains" in msg


def test_the_head_alone_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "sweep.toml"
    path.write_text(HEAD + '[axes]\n"radio.latency_s" = [0.0, 0.1]\n')
    assert len(load_sweep(path).points) == 2


def test_a_metric_typo_in_the_plots_is_refused_before_any_run(tmp_path: Path) -> None:
    from hil.sweep.runner import run_sweep

    path = tmp_path / "sweep.toml"
    path.write_text(HEAD + '[axes]\n"radio.latency_s" = [0.0, 0.1]\n'
                    '[plots]\nlines = [{ metric = "gap_min_overal_m", x = "radio.latency_s" }]\n')
    spec = load_sweep(path)
    with pytest.raises(SweepError) as exc:
        run_sweep(spec, tmp_path / "out", workers=1, progress=False)
    msg = str(exc.value)
    assert "plots.lines.0.metric" in msg and "gap_min_overal_m" in msg and "did you mean 'gap_min_overall_m'" in msg
    assert not list((tmp_path / "out").rglob("metrics.json"))  # nothing ran

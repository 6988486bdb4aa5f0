"""The signal summary (hil/record/signal_summary.py): the metrics and the safety verdicts of a run whose samples
were summarised in chunks and let go equal those of the whole run, and the samples held stay few."""
from __future__ import annotations

import numpy as np
import pytest

from hil.record.runlog import SUMMARY_BLOCK_ROWS

from hil.record.metrics import compute_metrics
from hil.record.runlog import RunLog
from hil.record.safety import MAX_LISTED, check_safety
from tests.test_safety import BAND, synthetic

NOT_SUMMARISED = ("wall_time_s", "realtime_factor")


def chunked_copy(log: RunLog, seed: int, band=BAND) -> RunLog:
    """The same samples appended in random chunks, each chunk released (summarised, let go) as it comes."""
    out = RunLog(log.layout)
    out.reference_change_times, out.events, out.sim_time_s = log.reference_change_times, log.events, log.sim_time_s
    out.summary(band)
    rows, rng, i = log.signals.array, np.random.default_rng(seed), 0
    while i < len(rows):
        j = min(len(rows), i + int(rng.integers(1, 60)))
        for r in rows[i:j]:
            out.signals.append(r)
        out.release_signals(j - int(rng.integers(0, 3)))
        i = j
    return out


def assert_same(a, b, path: str = "") -> None:
    """Equal, floats bit for bit, however the samples were chunked."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            if k not in NOT_SUMMARISED:
                assert_same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{k}]")
    else:  # floats too, bit for bit: the summary takes rows in blocks at fixed row numbers
        assert a == b, path


def wavy() -> RunLog:
    """Gaps below l_e and a collision, couplers out of band and overspeed, each several times, crossing chunks."""
    log = synthetic(lambda t: 1600.0 - 700.0 * np.sin(t / 3.0) ** 2, coupler_of_t=lambda t: 0.15 * np.sin(t),
                    v_extra_of_t=lambda t: 4.0 * np.sin(t / 2.0) + 1.0, t_end=120.0)
    log.reference_change_times = [0.0, 40.0, 80.0]
    return log


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_run_summarised_in_chunks_has_the_metrics_of_the_whole_run(seed):
    whole = wavy()
    expected = compute_metrics(whole, BAND)
    assert all(expected["safety"][v]["count"] >= 2 for v in ("gap_below_le", "coupler_out_of_band", "overspeed"))
    chunked = chunked_copy(whole, seed)
    assert len(chunked.signals.array) < SUMMARY_BLOCK_ROWS + 3 and len(chunked.signals) == len(whole.signals)
    assert_same(compute_metrics(chunked, BAND), expected)


def test_violations_are_all_counted_and_the_earliest_listed():
    log = synthetic(lambda t: 3000.0, coupler_of_t=lambda t: 0.15 if int(t * 10) % 4 == 0 else 0.0, t_end=60.0)
    report = compute_metrics(chunked_copy(log, 7), BAND)["safety"]["coupler_out_of_band"]
    assert report["count"] == 151 and len(report["violations"]) == MAX_LISTED
    starts = [v["start_s"] for v in report["violations"]]
    assert starts == sorted(starts) and starts[0] == 0.0 and starts[-1] == pytest.approx(19.6)
    assert len(check_safety(log, BAND)) == MAX_LISTED


def test_an_interval_open_at_the_end_ends_at_the_last_sample():
    log = synthetic(lambda t: 3000.0 if t < 90.0 else 1400.0)
    (v,) = check_safety(chunked_copy(log, 3), BAND)
    assert (v.verdict, v.start_s, v.end_s) == ("gap_below_le", pytest.approx(90.0), pytest.approx(100.0))


def test_released_samples_without_a_summary_are_an_error_not_a_wrong_metric():
    log = wavy()
    log.signals.release_before(100)
    with pytest.raises(ValueError, match="released without one"):
        compute_metrics(log, BAND)


def test_hil_run_lets_the_samples_go_and_reports_the_same_metrics(tmp_path):
    """``keep_signals=False`` (``hil run``, sweeps): the session releases the recorded samples and load windows as
    it goes (what waits for the next flush of the recording stays: at most 2 s of wall time of samples); the
    metrics equal those of the run that kept everything."""
    from hil.scenario import load_scenario
    from hil.session import run_scenario

    sc = load_scenario("seed000")
    kept = run_scenario(sc, tmp_path / "kept", duration_s=30.0)
    let_go = run_scenario(sc, tmp_path / "let-go", duration_s=30.0, keep_signals=False, chunk_s=1.0,
                          min_flush_wall_s=0.0)  # recorded every simulated second: let go as often
    assert len(kept.log.signals.array) == len(let_go.log.signals) == 300
    assert len(let_go.log.signals.array) < SUMMARY_BLOCK_ROWS + 11  # the summary's block and a chunk at most
    assert all(len(b.load.array) <= 11 and len(b.load) == 300 for b in let_go.log.buses)
    drop = ("wall_time_s", "realtime_factor", "provenance")
    assert_same({k: v for k, v in let_go.metrics.items() if k not in drop},
                {k: v for k, v in kept.metrics.items() if k not in drop})


def test_the_ideal_loop_records_as_it_goes_and_lets_its_samples_go(tmp_path):
    from hil.scenario import load_scenario
    from hil.session import run_scenario

    sc = load_scenario("seed000")
    kept = run_scenario(sc, tmp_path / "kept", duration_s=20.0, ideal=True)
    let_go = run_scenario(sc, tmp_path / "let-go", duration_s=20.0, ideal=True, keep_signals=False, chunk_s=1.0,
                          min_flush_wall_s=0.0)
    assert len(let_go.log.signals) == len(kept.log.signals.array) == 200 and len(let_go.log.signals.array) < SUMMARY_BLOCK_ROWS + 11
    drop = ("wall_time_s", "realtime_factor", "provenance")
    assert_same({k: v for k, v in let_go.metrics.items() if k not in drop},
                {k: v for k, v in kept.metrics.items() if k not in drop})

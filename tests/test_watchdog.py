"""The one ECU watchdog policy (hil.faults.watchdog) that the virtual rig, the orchestrator and the ECU process share."""
import pytest

from hil.faults.watchdog import Watchdog, restart_text


def test_a_crash_without_a_duration_and_a_controller_error_restart_after_the_delay() -> None:
    w = Watchdog(0.5)
    assert w.stopped(3, "crash", 1.0) == 1.5
    assert w.stopped(4, "error", 1.2) == pytest.approx(1.7)
    assert w.due(1.49) == []
    assert w.due(1.5) == [(3, "crash")]
    assert w.is_down(4, "error") and not w.is_down(3)
    assert w.due(2.0) == [(4, "error")]
    assert w.down == {}


def test_a_crash_with_a_duration_comes_back_at_its_end_not_by_the_watchdog() -> None:
    w = Watchdog(0.5)
    assert w.stopped(1, "crash", 1.0, lasts_s=3.0) is None
    assert w.due(10.0) == [] and w.is_down(1, "crash")
    assert w.up(1) == "crash" and not w.is_down(1)


def test_a_hang_is_restarted_only_if_the_watchdog_is_shorter_than_the_hang() -> None:
    w = Watchdog(0.5)
    assert w.stopped(1, "hang", 0.0, lasts_s=0.4) is None  # the hang ends first: it resumes
    assert w.stopped(2, "hang", 0.0, lasts_s=2.0) == 0.5
    assert w.stopped(5, "hang", 0.0) == 0.5
    assert w.due(0.5) == [(2, "hang"), (5, "hang")]


def test_a_unit_that_came_back_meanwhile_is_not_restarted_and_no_watchdog_restarts_nothing() -> None:
    w = Watchdog(0.5)
    w.stopped(1, "hang", 0.0)
    w.up(1)  # the hang ended (resumed)
    assert w.due(1.0) == []
    w.stopped(1, "crash", 2.0)  # down again, for another reason: only the new timer counts
    assert w.due(2.4) == [] and w.due(2.5) == [(1, "crash")]
    off = Watchdog(None)
    assert off.stopped(1, "error", 0.0) is None and off.due(1e9) == [] and off.is_down(1)
    with pytest.raises(ValueError, match="unknown reason 'nap'"):
        off.stopped(1, "nap", 0.0)


def test_the_timeline_text_names_who_restarted_and_after_what() -> None:
    assert restart_text("watchdog", "error") == "restarted with a reset controller (watchdog, after a controller error)"
    assert restart_text("the crash ended", "crash").endswith("(the crash ended, after a crash)")

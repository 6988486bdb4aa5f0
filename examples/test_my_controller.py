"""Firmware tests for my cruise law (my_controller.py) on the trainhil rig: copy this folder and make it yours.

Run:  python -m pytest examples            (add --hil-record runs/failed to keep the .rrd of every failing test)

The fixture ``hil_rig`` comes from the trainhil pytest plugin (installed with trainhil). Signals are numpy arrays
keyed by the recording's entity paths (``/trains/2/units/1/speed_error_kmh``); the assert_* helpers report which
signal failed, when, and by how much. The tests share one 20 s virtual-time run (identical runs are simulated once).
"""
from __future__ import annotations

import pytest

from hil.testing import (
    assert_frame_period,
    assert_never_below,
    assert_no_e2e_errors,
    assert_no_events,
    assert_settles,
    assert_within,
)
from my_controller import MyCruise

SCENARIO = "cruise.toml"  # next to this file: 2 trains x 3 units at 200 km/h, traction limits on
DURATION_S = 20.0


@pytest.fixture
def run(hil_rig):
    """The scenario with my law on every ECU, 20 s of virtual time."""
    return hil_rig(SCENARIO, controller=MyCruise).run(DURATION_S)


def test_every_unit_settles_to_the_reference_speed(run):
    assert_settles(run, "/trains/*/units/*/speed_error_kmh", within=18.0, tol=0.5)


def test_trains_reach_their_slots(run):
    assert_within(run, "/trains/*/units/*/position_error_m", -1.0, 1.0, after=18.0)


def test_couplers_stay_in_their_band(run):
    lo, hi = run.scenario.plant.coupler_band_m
    assert_within(run, "/trains/*/couplers/*/displacement_m", lo, hi)


def test_gap_never_below_the_emergency_distance(run):
    assert_never_below(run, "/trains/2/gap_ahead_m", run.scenario.trains.emergency_gap_m)


def test_every_ecu_sends_its_traction_command_every_cycle(run):
    assert_frame_period(run, "TractionCmd_U*", max_gap_ms=12.0)


def test_no_e2e_errors_and_no_error_events(run):
    assert_no_e2e_errors(run)
    assert_no_events(run, "WARN")


def test_signals_are_numpy_arrays_by_entity_path(run):
    t, v = run.signals["/trains/1/units/1/speed_kmh"]
    assert t[0] == 0.0 and abs(v[-1] - 200.0) < 0.5
    assert run.metrics["settling_time_s"] < 18.0


def test_with_sensor_noise_still_holds_the_speed(hil_rig):
    """Override any scenario field with dotted keys, as `hil run --set` does."""
    rig = hil_rig(SCENARIO, controller=MyCruise, set={"plant.sensor.speed_noise_mps": 0.05, "seed": 7})
    assert_within(rig.run(DURATION_S), "/trains/*/units/*/speed_error_kmh", -1.0, 1.0, after=18.0)


@pytest.mark.xfail(strict=True, reason="deliberately failing: shows what a failing check reports")
def test_deliberately_failing_settles_within_5_s(run):
    assert_settles(run, "/trains/*/units/*/speed_error_kmh", within=5.0, tol=0.5)


@pytest.mark.hil_realtime(pace=1.0)
def test_runs_in_real_time_over_python_can(hil_rig):
    """The same law as separate ECU processes on emulated CAN buses, paced to the wall clock (2 s)."""
    run = hil_rig(SCENARIO, controller=MyCruise).run(2.0)
    assert run.runtime == "realtime"
    assert_no_e2e_errors(run, statuses=("CRC_ERROR",))  # a late process may skip counters: not an error here
    assert_frame_period(run, "TractionCmd_U*", max_gap_ms=100.0, after=0.5)
    assert_within(run, "/trains/1/units/*/speed_error_kmh", -6.0, 1.0)

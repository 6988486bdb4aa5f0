"""Reference profile (exact x_r for position profiles) and the event kernel's ordering."""
from __future__ import annotations

import pytest

from hil.reference_profile import ReferenceProfile
from hil.runtime.kernel import Kernel, to_ns
from hil.scenario import load_scenario
from hil.scenario.model import ReferenceConfig


def test_position_profile_switches_speed_where_x_r_crosses_a_boundary():
    cfg = ReferenceConfig(by="position", x0_m=109_000.0, segments=[
        {"start": 109_000.0, "end": 161_000.0, "speed_kmh": 316.0},
        {"start": 161_000.0, "end": 294_000.0, "speed_kmh": 342.0},
    ])
    ref = ReferenceProfile.from_config(cfg)
    t1 = 52_000.0 / (316 / 3.6)  # 592.4 s to cover 52 km at 316 km/h
    assert ref.change_times == [pytest.approx(t1)]
    x, v = ref.at(t1 - 1e-6)
    assert v == pytest.approx(316 / 3.6) and x == pytest.approx(161_000.0, abs=1e-3)
    x, v = ref.at(t1 + 10.0)
    assert v == pytest.approx(342 / 3.6) and x == pytest.approx(161_000.0 + 10 * 342 / 3.6)


def test_time_profile_integrates_position():
    cfg = ReferenceConfig(by="time", x0_m=1000.0, segments=[
        {"start": 0.0, "end": 100.0, "speed_mps": 65.0},
        {"start": 100.0, "end": 200.0, "speed_mps": 73.0},
    ])
    ref = ReferenceProfile.from_config(cfg)
    assert ref.at(150.0) == (pytest.approx(1000 + 6500 + 50 * 73), 73.0)
    assert ref.change_times == [100.0]


def test_kernel_runs_in_time_order_and_fifo_at_equal_times():
    k, seen = Kernel(), []
    k.at(20, seen.append, "c")
    k.at(10, seen.append, "a")
    k.at(10, seen.append, "b")
    k.run(15)
    assert seen == ["a", "b"] and k.now == 15
    k.run(100)
    assert seen == ["a", "b", "c"]
    with pytest.raises(ValueError, match="past"):
        k.at(50, seen.append, "late")


def test_kernel_periodic_does_not_drift():
    k, ticks = Kernel(), []
    k.every(to_ns(0.002), to_ns(0.01), ticks.append)
    k.run(to_ns(100.0))
    assert len(ticks) == 10_000
    assert ticks[-1] == to_ns(0.002) + 9_999 * to_ns(0.01)  # exact integer ns, no float accumulation


def test_packaged_seed000_reference_changes_at_592_s():
    sc = load_scenario("seed000")
    ref = ReferenceProfile.from_config(sc.reference)
    assert ref.change_times[0] == pytest.approx(592.405, abs=1e-3)


"""Tests of hil.can.wcrt: hand-computed response times, multi-instance busy periods, overload,
and a brute-force discrete-event simulation of CAN arbitration that must stay within the bounds."""

from __future__ import annotations

import itertools
import math
from collections import deque

import pytest

from hil.can.frame import worst_case_frame_bits
from hil.can.wcrt import BusRates, CanMessage, bus_utilisation, response_times

# Davis et al. (2007), section 4 shape: three messages of C = 1 ms with T = 2.5, 3.5, 3.5 ms.
# Here C is exact: extended frames with 2 data bytes are 54+16+13+floor(69/4) = 100 bits worst case,
# and at 100 kbit/s a bit is 10 us, so C = 1 ms. In bits: C = 100, T = 250, 350, 350, D(B, C) = 325.
PAPER_BITRATE = 100_000
PAPER_SET = [
    CanMessage("A", 1, 2.5e-3, 2, extended=True),
    CanMessage("B", 2, 3.5e-3, 2, extended=True, deadline_s=3.25e-3),
    CanMessage("C", 3, 3.5e-3, 2, extended=True, deadline_s=3.25e-3),
]


def test_paper_example_second_instance_is_critical():
    # All in bits (tau = 1 bit). C_A = C_B = C_C = 100.
    # A: B_A = 100 (B or C blocks). w = 100 (no hp). R_A = 100 + 100 = 200 bits = 2.0 ms.
    #    busy: t = 100 + ceil(t/250)*100: 100 -> 200 -> 200; Q = ceil(200/250) = 1.
    # B: B_B = 100 (C). q=0: w = 100 + ceil((w+1)/250)*100: 100 -> 200 -> 200; R = 200+100 = 300 (3.0 ms).
    #    busy: t = 100 + ceil(t/250)*100 + ceil(t/350)*100: 100 -> 300 -> 400 -> 500 -> 500; Q = 2.
    #    q=1: w = 200 + ceil((w+1)/250)*100: 200 -> 300 -> 400 -> 400; R = 400 - 350 + 100 = 150.
    #    R_B = 300 <= 325: schedulable.
    # C: B_C = 0 (lowest). q=0: w = ceil((w+1)/250)*100 + ceil((w+1)/350)*100: 0 -> 200 -> 200;
    #    R(0) = 300 (3.0 ms) -- what the original 1994 analysis reports, wrongly "schedulable".
    #    busy: t = 100*(ceil(t/250) + 2*ceil(t/350)): 100 -> 300 -> 400 -> 600 -> 700 -> 700; Q = 2.
    #    q=1: w = 100 + ceil((w+1)/250)*100 + ceil((w+1)/350)*100:
    #         100 -> 300 -> 400 -> 500 -> 600 (ceil(501/250) = 3: A's third release at 500) -> 600;
    #    R(1) = 600 - 350 + 100 = 350 bits = 3.5 ms > D = 3.25 ms: NOT schedulable.
    res = response_times(PAPER_SET, PAPER_BITRATE)
    a, b, c = res["A"], res["B"], res["C"]
    assert [x.c_s for x in (a, b, c)] == pytest.approx([1e-3] * 3, abs=1e-12)
    assert a.r_s == pytest.approx(2.0e-3, abs=1e-12) and a.schedulable and a.instances == 1
    assert a.blocking_s == pytest.approx(1e-3, abs=1e-12)
    assert b.r_s == pytest.approx(3.0e-3, abs=1e-12) and b.schedulable
    assert (b.busy_period_s, b.instances, b.critical_instance) == (pytest.approx(5e-3, abs=1e-12), 2, 0)
    assert c.r_s == pytest.approx(3.5e-3, abs=1e-12)
    assert not c.schedulable
    assert (c.busy_period_s, c.instances, c.critical_instance) == (pytest.approx(7e-3, abs=1e-12), 2, 1)
    assert c.blocking_s == 0.0
    assert c.utilisation_hp == pytest.approx(1 / 2.5 + 1 / 3.5)
    assert c.utilisation_hep == pytest.approx(1 / 2.5 + 2 / 3.5)


# Two standard frames at 500 kbit/s (tau = 2 us): M1 8 bytes -> 135 bits = 270 us, M2 4 bytes -> 95 bits = 190 us.
def _jitter_set(j1: float) -> list[CanMessage]:
    return [
        CanMessage("M2", 0x200, 2e-3, 4, jitter_s=0.1e-3),  # listed first: order must come from can_id
        CanMessage("M1", 0x100, 1e-3, 8, jitter_s=j1),
    ]


def test_two_messages_with_own_jitter():
    # In us. M1: B = 190, no hp: w = 190; busy 270 -> 190+270 = 460 -> 460, Q = 1; R1 = 0 + 190 + 270 = 460.
    # M2: B = 0, busy: 190 -> ceil(190/1000)*270 + ceil(290/2000)*190 = 460 -> 460, Q = ceil(560/2000) = 1.
    #     w = ceil((w + 0 + 2)/1000)*270: 0 -> 270 -> 270; R2 = J2 + w + C2 = 100 + 270 + 190 = 560.
    res = response_times(_jitter_set(0.0), 500_000)
    assert res["M1"].r_s == pytest.approx(460e-6, abs=1e-12)
    assert res["M2"].r_s == pytest.approx(560e-6, abs=1e-12)
    assert res["M1"].schedulable and res["M2"].schedulable
    assert res["M1"].c_s == pytest.approx(270e-6, abs=1e-12) and res["M2"].c_s == pytest.approx(190e-6, abs=1e-12)


def test_higher_priority_jitter_adds_interference_and_instances():
    # J1 = 750 us. M1: busy: 270 -> 190 + ceil(1020/1000)*270 = 730 -> ceil(1480/1000) = 2 -> 730;
    #     Q1 = ceil((730 + 750)/1000) = 2.  q=0: w = 190, R = 750 + 190 + 270 = 1210 > D = 1000.
    #     q=1: w = 190 + 270 = 460, R = 750 + 460 - 1000 + 270 = 480.  R1 = 1210, not schedulable.
    # M2: w = ceil((w + 750 + 2)/1000)*270: 0 -> 270 -> 540 (ceil(1022/1000) = 2) -> 540;
    #     busy: 190 -> 460 -> 730 -> 730, Q2 = ceil(830/2000) = 1.  R2 = 100 + 540 + 190 = 830.
    res = response_times(_jitter_set(0.75e-3), 500_000)
    m1, m2 = res["M1"], res["M2"]
    assert m1.r_s == pytest.approx(1210e-6, abs=1e-12)
    assert (m1.instances, m1.critical_instance, m1.schedulable) == (2, 0, False)
    assert m2.r_s == pytest.approx(830e-6, abs=1e-12) and m2.schedulable


def test_bus_utilisation_by_hand():
    # 270/1000 + 190/2000 = 0.365
    assert bus_utilisation(_jitter_set(0.0), 500_000) == pytest.approx(0.365)
    assert bus_utilisation(PAPER_SET, PAPER_BITRATE) == pytest.approx(0.4 + 2 / 3.5)


def test_overload_marks_affected_messages_unbounded():
    # C = 1 ms each (ext, 2 bytes, 100 kbit/s), T = 1.5 ms: U = 4/3.  The top message is still
    # bounded (R = B + C = 2 ms, misses its 1.5 ms deadline); the lower one has no bound.
    msgs = [CanMessage("hi", 1, 1.5e-3, 2, True), CanMessage("lo", 2, 1.5e-3, 2, True)]
    res = response_times(msgs, PAPER_BITRATE)
    assert res["hi"].r_s == pytest.approx(2e-3, abs=1e-12) and not res["hi"].schedulable
    assert math.isinf(res["lo"].r_s) and not res["lo"].schedulable
    assert res["lo"].instances == 0 and res["lo"].critical_instance == -1
    # Exactly 100 % load counts as unbounded too (no margin for any extra bit).
    msgs = [CanMessage("hi", 1, 2e-3, 2, True), CanMessage("lo", 2, 2e-3, 2, True)]
    res = response_times(msgs, PAPER_BITRATE)
    assert res["hi"].schedulable and math.isinf(res["lo"].r_s)


def test_heavily_overloaded_large_set_returns_promptly():
    msgs = [CanMessage(f"m{i}", i, 1e-3, 8) for i in range(200)]  # 200 x 270 us every 1 ms at 500 kbit/s
    res = response_times(msgs, 500_000)
    assert res["m0"].schedulable  # 270 + 270 us
    assert all(math.isinf(res[f"m{i}"].r_s) for i in range(3, 200))


def test_empty_set():
    assert response_times([], 500_000) == {}
    assert bus_utilisation([], 500_000) == 0.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(name="x", can_id=0x800, period_s=0.01, dlc=8), "can_id"),
        (dict(name="x", can_id=1 << 29, period_s=0.01, dlc=8, extended=True), "can_id"),
        (dict(name="x", can_id=1, period_s=0.0, dlc=8), "period_s"),
        (dict(name="x", can_id=1, period_s=math.nan, dlc=8), "period_s"),
        (dict(name="x", can_id=1, period_s=0.01, dlc=65), "dlc=65"),
        (dict(name="x", can_id=1, period_s=0.01, dlc=8, jitter_s=-1e-3), "jitter_s"),
        (dict(name="x", can_id=1, period_s=0.01, dlc=8, deadline_s=0.0), "deadline_s"),
    ],
)
def test_bad_message_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CanMessage(**kwargs)


def test_a_length_the_bus_format_lacks_is_rejected_naming_the_message():
    """9 data bytes: no classical frame carries them, and no CAN FD DLC gives exactly 9 (pad to 12)."""
    nine = [CanMessage("x", 1, 0.01, 9)]
    with pytest.raises(ValueError, match=r"message 'x': dlc=9 out of range 0..8"):
        response_times(nine, 500_000)
    with pytest.raises(ValueError, match=r"message 'x': length=9 is not a CAN FD payload length"):
        response_times(nine, BusRates(500_000, 2_000_000, fd=True))
    assert response_times([CanMessage("x", 1, 0.01, 12)], BusRates(500_000, 2_000_000, fd=True))["x"].schedulable


def test_duplicates_and_unsupported_options_rejected():
    with pytest.raises(ValueError, match="can_id=0x10"):
        response_times([CanMessage("a", 0x10, 0.01, 8), CanMessage("b", 0x10, 0.01, 8, extended=True)], 500_000)
    with pytest.raises(ValueError, match="'a'"):
        response_times([CanMessage("a", 0x10, 0.01, 8), CanMessage("a", 0x11, 0.01, 8)], 500_000)
    with pytest.raises(NotImplementedError):
        response_times(PAPER_SET, PAPER_BITRATE, error_overhead=1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="bitrate"):
        response_times(PAPER_SET, 333_333)


# ---------------------------------------------------------------- brute-force simulation


def simulate(frames: list[tuple[int, int, int]], horizon: int) -> list[int]:
    """Worst response (bits) per frame: (C, T, offset) in priority order, strictly periodic releases
    before `horizon`, non-preemptive arbitration when the bus goes idle (releases at that instant join)."""
    pending: list[deque[int]] = [deque() for _ in frames]
    next_release = [offset for _, _, offset in frames]
    worst = [0] * len(frames)
    t = 0
    while True:
        for k, (_, period, _) in enumerate(frames):
            while next_release[k] <= t and next_release[k] < horizon:
                pending[k].append(next_release[k])
                next_release[k] += period
        winner = next((k for k, queue in enumerate(pending) if queue), None)
        if winner is None:
            t = min(next_release)
            if t >= horizon:
                return worst
            continue
        released = pending[winner].popleft()
        t += frames[winner][0]
        worst[winner] = max(worst[winner], t - released)


def _bounds_in_bits(msgs: list[CanMessage], bitrate: int) -> list[int]:
    res = response_times(msgs, bitrate)
    return [round(res[m.name].r_s * bitrate) for m in sorted(msgs, key=lambda m: m.can_id)]


def _frames(msgs: list[CanMessage], bitrate: int, offsets: tuple[int, ...]) -> list[tuple[int, int, int]]:
    ordered = sorted(msgs, key=lambda m: m.can_id)
    return [
        (worst_case_frame_bits(m.dlc, m.extended), round(m.period_s * bitrate), off)
        for m, off in zip(ordered, offsets, strict=True)
    ]


def test_simulator_by_hand():
    # Paper set, synchronous release, releases before 501: A 0-100, B 100-200, C 200-300;
    # A(250) waits for C: 300-400 (150); B(350) 400-500 (150); A(500) is queued as the bus goes idle
    # and wins: 500-600 (100); C(350) 600-700 -> 350 bits.
    frames = _frames(PAPER_SET, PAPER_BITRATE, (0, 0, 0))
    assert simulate(frames, 501) == [150, 200, 350]


def test_simulation_paper_set_never_exceeds_bound_and_reaches_it():
    bounds = _bounds_in_bits(PAPER_SET, PAPER_BITRATE)
    assert bounds == [200, 300, 350]
    seen = [0, 0, 0]
    for off_b, off_c in itertools.product(range(0, 350, 10), repeat=2):
        frames = _frames(PAPER_SET, PAPER_BITRATE, (0, off_b, off_c))
        worst = simulate(frames, 350 + 2 * 1750)  # offsets + two hyperperiods (lcm(250, 350) = 1750)
        seen = [max(s, w) for s, w in zip(seen, worst)]
    assert all(s <= b for s, b in zip(seen, bounds)), (seen, bounds)
    assert seen[2] == 350  # the second-instance case is real: the q = 0 analysis (300) is unsafe


MIXED_BITRATE = 500_000  # 2 us per bit; periods chosen as whole bits with hyperperiod 2400 bits
MIXED_SET = [
    CanMessage("m0", 0x10, 400 * 2e-6, 8),  # 135 bits
    CanMessage("m1", 0x20, 600 * 2e-6, 4),  # 95 bits
    CanMessage("m2", 0x30, 800 * 2e-6, 1),  # 65 bits
    CanMessage("m3", 0x40, 600 * 2e-6, 8),  # 135 bits
]


def test_simulation_mixed_set_never_exceeds_bound():
    bounds = _bounds_in_bits(MIXED_SET, MIXED_BITRATE)
    assert bus_utilisation(MIXED_SET, MIXED_BITRATE) == pytest.approx(135 / 400 + 95 / 600 + 65 / 800 + 135 / 600)
    seen = [0] * 4
    for offs in itertools.product(range(0, 600, 50), range(0, 800, 50), range(0, 600, 50)):
        worst = simulate(_frames(MIXED_SET, MIXED_BITRATE, (0, *offs)), 800 + 2 * 2400)
        seen = [max(s, w) for s, w in zip(seen, worst)]
    assert all(s <= b for s, b in zip(seen, bounds)), (seen, bounds)
    assert seen[3] == bounds[3]  # the lowest-priority message (no blocking) meets its bound on the grid


def test_critical_instant_highest_priority_within_one_bit():
    # m0's bound: B = 135 (m3) + C = 135 -> 270 bits. Critical instant: m3 starts at 0, m0 is queued
    # one bit later (at 0 it would win arbitration); m1, m2 come after m0 has finished.
    bounds = _bounds_in_bits(MIXED_SET, MIXED_BITRATE)
    assert bounds[0] == 270
    worst = simulate(_frames(MIXED_SET, MIXED_BITRATE, (1, 300, 300, 0)), 301)
    assert bounds[0] - 1 <= worst[0] <= bounds[0]
    assert worst[0] == 269

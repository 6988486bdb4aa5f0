"""The real-time nodes' one scheduler (hil.runtime.realtime.paced_kernel): the virtual-time kernel with only step()
overridden, against a fake clock and frame I/O."""
from __future__ import annotations

import math

import pytest

from hil.runtime.kernel import to_ns
from hil.runtime.realtime.paced_kernel import PacedKernel
class FakeClock:
    """A SimClock at pace 1 that the fake I/O moves forward as it 'sleeps'."""

    def __init__(self) -> None:
        self.t = 0.0
        self.pace = 1.0

    def now(self) -> float:
        return self.t

    def wall_until(self, sim_t: float) -> float:
        return sim_t - self.t


class FakeFrames:
    """The node frame I/O: frames (t, bus, id, data) that 'arrive' as the clock passes their time."""

    def __init__(self, clock: FakeClock, frames: list[tuple[float, int, int, bytes]]) -> None:
        self.clock, self.pending, self.waits = clock, sorted(frames), 0

    def _deliver(self, on_frame) -> None:
        while self.pending and self.pending[0][0] <= self.clock.t + 1e-12:
            t, bus, fid, data = self.pending.pop(0)
            if on_frame is not None:
                on_frame(bus, fid, data, t)

    def wait(self, sim_t, on_frame, stop, spin_s=0.0) -> None:
        self.waits += 1
        self.clock.t = max(self.clock.t, sim_t)
        self._deliver(on_frame)

    def wait_any(self, wall_s, on_frame) -> None:
        self.waits += 1
        nxt = self.pending[0][0] if self.pending else math.inf
        self.clock.t = min(self.clock.t + wall_s, max(nxt, self.clock.t))
        self._deliver(on_frame)


class Stop:
    def __init__(self) -> None:
        self.requested = False

    def __bool__(self) -> bool:
        return self.requested


def test_the_paced_kernel_runs_each_event_when_the_clock_reaches_it_and_hands_frames_in_between():
    clock = FakeClock()
    io = FakeFrames(clock, [(0.0015, 0, 0x80, b"a"), (0.0019, 1, 0x81, b"b")])
    seen = []
    k = PacedKernel(clock, io, Stop(), on_frame=lambda bus, fid, data, t: seen.append(("frame", fid, t, clock.t)))
    k.every(0, to_ns(0.001), lambda t: seen.append(("tick", t, clock.t)))
    k.run(to_ns(0.003))
    assert [s[:2] for s in seen] == [("tick", 0), ("tick", 1_000_000), ("frame", 0x80), ("frame", 0x81),
                                     ("tick", 2_000_000)]
    assert [s[2] for s in seen if s[0] == "frame"] == [0.0015, 0.0019]  # with their bus timestamps
    assert all(s[2] == pytest.approx(s[1] * 1e-9) for s in seen if s[0] == "tick")  # each at its time, not before
    assert k.now == to_ns(0.003)


def test_waking_on_frames_lets_a_handler_schedule_an_event_before_the_one_waited_for():
    """The radio's case: a frame at 1.0 ms schedules a delivery 0.2 ms later, before the next idle tick at 50 ms."""
    clock = FakeClock()
    io = FakeFrames(clock, [(0.001, 0, 0x100, b"x")])
    sent = []
    k = PacedKernel(clock, io, Stop(), wake_on_frame=True)
    k.on_frame = lambda bus, fid, data, t: k.at(to_ns(t + 0.0002), lambda _: sent.append(clock.t))
    k.every(0, to_ns(0.05), lambda t: None)
    k.run(to_ns(0.1))
    assert sent == [pytest.approx(0.0012)]


def test_a_stop_request_ends_the_wait_and_runs_no_further_event():
    clock, stop, ran = FakeClock(), Stop(), []
    k = PacedKernel(clock, FakeFrames(clock, []), stop)

    def tick(t: int) -> None:
        ran.append(t)
        if t >= 2_000_000:
            stop.requested = True

    k.every(0, 1_000_000, tick)
    k.run(to_ns(1.0))
    assert ran == [0, 1_000_000, 2_000_000]
    assert k.next_time() is None


def test_events_due_at_the_same_time_run_after_one_wait_in_their_order_and_a_stop_ends_the_batch():
    """Several units' cycles of one ECU host at one instant: one wait (one SYNC) for them all; a later instant
    waits again, and a stop request between two same-time events runs no further one."""
    clock, stop, ran = FakeClock(), Stop(), []
    io = FakeFrames(clock, [])
    k = PacedKernel(clock, io, stop)
    for name in ("a", "b", "c"):
        k.at(to_ns(0.005), ran.append, name)
    k.at(to_ns(0.006), ran.append, "d")
    k.run(to_ns(0.01))
    assert ran == ["a", "b", "c", "d"] and io.waits == 2

    def stopping(name: str) -> None:
        ran.append(name)
        stop.requested = True

    ran.clear()
    k2 = PacedKernel(clock, FakeFrames(clock, []), stop)
    k2.at(to_ns(0.02), stopping, "e")
    k2.at(to_ns(0.02), ran.append, "f")
    k2.run(to_ns(0.03))
    assert ran == ["e"]

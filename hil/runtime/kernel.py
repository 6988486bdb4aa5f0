"""A tiny discrete-event kernel (SimPy-like, no coroutines): callbacks on one time-ordered queue.

Time is integer nanoseconds so periodic events never drift and CAN bit times are exact.
Events at equal times run in the order they were scheduled, which makes a run reproducible bit for bit.
Real time is a subclass that overrides only :meth:`Kernel.step` (``hil.runtime.realtime.paced_kernel``), as
SimPy's ``RealtimeEnvironment`` does.
"""
from __future__ import annotations

import heapq
from typing import Any, Callable, Protocol, runtime_checkable

NS = 1_000_000_000


def to_ns(seconds: float) -> int:
    """Seconds -> integer nanoseconds (rounded)."""
    return int(round(seconds * NS))


@runtime_checkable
class EventKernel(Protocol):
    """The seam: callbacks at integer-nanosecond times on one queue, ``run`` processing them up to a time. This
    ``Kernel``, the engine's ``EngineKernel`` (hil/runtime/engine_net.py) and the real-time ``PacedKernel`` meet it."""

    @property
    def now(self) -> int: ...

    def at(self, t_ns: int, fn: Callable[[Any], None], arg: Any = None) -> None: ...

    def every(self, first_ns: int, period_ns: int, fn: Callable[[int], None]) -> None: ...

    def run(self, until_ns: int) -> None: ...


class Kernel:
    """Event queue with a clock. ``at(t, fn, arg)`` runs ``fn(arg)`` when the clock reaches t."""

    def __init__(self) -> None:
        self.now: int = 0
        self._queue: list[tuple[int, int, Callable[[Any], None], Any]] = []
        self._seq = 0

    def at(self, t_ns: int, fn: Callable[[Any], None], arg: Any = None) -> None:
        if t_ns < self.now:
            raise ValueError(f"event scheduled in the past: {t_ns} ns < now {self.now} ns")
        self._seq += 1
        heapq.heappush(self._queue, (t_ns, self._seq, fn, arg))

    def every(self, first_ns: int, period_ns: int, fn: Callable[[int], None]) -> None:
        """Run ``fn(t)`` at first_ns, first_ns + period_ns, ... (rescheduled after each run)."""
        if period_ns <= 0:
            raise ValueError(f"period must be positive, got {period_ns} ns")

        def tick(t: int) -> None:
            fn(t)
            self.at(t + period_ns, tick, t + period_ns)

        self.at(first_ns, tick, first_ns)

    def next_time(self) -> int | None:
        """Time of the next pending event (None when the queue is empty)."""
        return self._queue[0][0] if self._queue else None

    def step(self) -> None:
        """Run the next event: the clock moves to its time."""
        t, _, fn, arg = heapq.heappop(self._queue)
        self.now = t
        fn(arg)

    def run(self, until_ns: int) -> None:
        """Process every event with time < until_ns, then set the clock to until_ns."""
        queue = self._queue
        while queue and queue[0][0] < until_ns:
            self.step()
        self.now = until_ns

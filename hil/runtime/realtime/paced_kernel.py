"""The event kernel against the wall clock: the one scheduler of every real-time node (plant, ECU host, radio).

``PacedKernel`` is :class:`hil.runtime.kernel.Kernel` with only ``step()`` overridden, on the pattern of SimPy's
``RealtimeEnvironment``: before an event runs, it waits until the node's ``SimClock`` reaches the event's time,
receiving the node's frames meanwhile. A lazy reader on the emulated buses waits instead until its bus servers
have synced it to that time, which they may do up to one frame before it (``frame_io.EngineFrames.wait``):
the event then runs at once, as at its time (its handler takes ``max(clock.now(), t)``), and the frames it sends
carry that time. Nodes schedule their work with ``at``/``every`` in integer nanoseconds of
simulated time, as in the virtual rig.

Two ways to wait, because the nodes differ in what a frame means to them:

* ``wake_on_frame=False`` (plant, ECU hosts): sleep to the event, the last ``spin_s`` wall seconds polled, then
  hand every frame that arrived to ``on_frame`` in time order with its bus timestamp (a mailbox keeps the latest
  frame of each stream and the plant integrates lazily, so no wake-up per frame is needed);
* ``wake_on_frame=True`` (radio): wake at every arrival, since a frame's handler may schedule an event (a
  delivery) before the one waited for.

A stop request (``stop``, the node's ``StopFlag``) ends the wait, and no further event runs. ``heartbeat`` (the
ECU and plant nodes' ``pacing.Heartbeat``) is called after each event: a node whose event never returns falls
silent, and the orchestrator's hang watch stops it. ``run(until)`` waits
only for events before ``until``: a node that must listen up to the end schedules an event there (plant, radio).
"""
from __future__ import annotations

from typing import Callable

from hil.runtime.kernel import NS, Kernel
from hil.runtime.realtime.frame_io import FrameHandler
from hil.runtime.realtime.pacing import SimClock, StopFlag

MAX_WAIT_S = 0.05  # wall seconds between stop checks while waking on frames


class PacedKernel(Kernel):
    """Runs each event when ``clock`` reaches its time; frames on ``io`` go to ``on_frame`` while it waits."""

    def __init__(self, clock: SimClock, io, stop: StopFlag, on_frame: FrameHandler | None = None,
                 spin_s: float = 0.0, wake_on_frame: bool = False, heartbeat: Callable[[], None] | None = None) -> None:
        super().__init__()
        self.clock, self.io, self.stop = clock, io, stop
        self.on_frame, self.spin_s, self.wake_on_frame = on_frame, spin_s, wake_on_frame
        self.heartbeat = heartbeat

    def step(self) -> None:
        """Wait for the next event's time (receiving frames), then run it; after a stop request, run nothing.

        Sleeping on frames, the events due at that same time run after the one wait (the cycles of units of several
        trains at one offset, in one ECU host): a frame sent at that instant cannot end by it, so a second wait would
        hand over nothing they may read, and would only cost its system calls and bookkeeping."""
        t_ns = self._queue[0][0]
        if self.wake_on_frame:
            self._wait_waking()
        else:
            self.io.wait(t_ns / NS, self.on_frame, self.stop, self.spin_s)
        if self.stop:
            self._queue.clear()
            return
        self._run_next()
        if not self.wake_on_frame:
            queue = self._queue
            while queue and queue[0][0] == t_ns and not self.stop:
                self._run_next()

    def _run_next(self) -> None:
        """The next event, then a heartbeat (a node whose event never returns falls silent)."""
        super().step()
        if self.heartbeat is not None:
            self.heartbeat()

    def _wait_waking(self) -> None:
        """Sleep until the earliest event is due, waking at every frame (its handler may schedule an earlier one)."""
        while not self.stop:
            remaining = self.clock.wall_until(self._queue[0][0] / NS)
            if remaining <= 0:
                return
            self.io.wait_any(min(remaining, MAX_WAIT_S), self.on_frame)

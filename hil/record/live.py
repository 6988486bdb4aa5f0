"""Live viewing: where a run's recording streams while it runs (``hil run --connect [URL]`` or ``--serve [PORT]``).

``--connect`` sends to a rerun viewer (or a ``rerun --save`` proxy) that is already listening, as
``rr.connect_grpc`` does; ``--serve`` hosts a gRPC server on loopback that viewers connect to
(``rerun --connect rerun+http://127.0.0.1:PORT/proxy``). The stream carries the same batches as the file: in
virtual time they follow the simulation, in real time the wall clock (hil/runtime/realtime/live_tail.py).

The live view is a convenience: it has its own rerun stream (``LiveStream``), flushed in the background, so a
viewer that is absent, slow or stalled never holds up the run or the files it writes; one that takes nothing for
LIVE_STALL_S is dropped with a warning.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # rerun is imported where a stream is made: the CLI and the nodes import this module for its
    import rerun as rr  # constants and targets, and rerun costs about 0.3 s of every process's start

DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"  # rerun's own default viewer address
DEFAULT_PORT = 9876
LIVE_FLUSH_WALL_S = 0.5  # a live view is refreshed this often (each flush costs ~20 ms of rerun calls)


@dataclass(frozen=True)
class LiveTarget:
    """A viewer to stream to (``url``), or a loopback port to serve on (``port``)."""

    url: str | None = None
    port: int | None = None

    def __post_init__(self) -> None:
        if (self.url is None) == (self.port is None):
            raise ValueError("a live target is either a viewer URL (--connect) or a port to serve on (--serve)")
        if self.url is not None and not self.url.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ValueError(f"--connect {self.url!r}: expected a rerun URL such as {DEFAULT_URL}")
        if self.port is not None and not 0 < self.port < 65536:
            raise ValueError(f"--serve {self.port}: a port must be in 1..65535")

    def sink(self):
        """The rerun sink: a gRPC client of the viewer, or a gRPC server bound to loopback only."""
        import rerun as rr

        if self.url is not None:
            return rr.GrpcSink(self.url)
        return rr.GrpcServerSink(bind_ip="127.0.0.1", port=self.port)

    def describe(self) -> str:
        if self.url is not None:
            return f"streaming live to {self.url}"
        return f"serving live on rerun+http://127.0.0.1:{self.port}/proxy (rerun --connect rerun+http://127.0.0.1:{self.port}/proxy)"


LIVE_STALL_S = 10.0  # a viewer that has not taken a flush for this long is dropped; the run goes on
LIVE_CLOSE_S = 3.0  # at the end of a run, the last flush to the viewer waits at most this long

#: Live streams given up on (a viewer that stopped reading, or never answered). rerun waits for their pending
#: messages at interpreter exit, forever when the peer never reads: ``exit_now_if_abandoned`` skips that wait.
ABANDONED: list["LiveStream"] = []
#: Served streams (--serve), kept up for late viewers until the process ends.
SERVING: list[rr.RecordingStream] = []


class LiveStream:
    """The live copy of a recording, a rerun stream of its own: a viewer that is absent or stalls never holds up the
    file's stream or the run. Connecting and flushing run in a background thread; a flush still pending after
    LIVE_STALL_S drops the viewer (a warning on stderr, once) and nothing more is sent to it."""

    def __init__(self, target: LiveTarget, application_id: str, recording_id: str) -> None:
        import rerun as rr

        self.target = target
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id, make_default=False,
                                      make_thread_default=False)  # buffers until the sink is set
        self.lost: str | None = None  # why the viewer was dropped
        self._failed = False
        self._pending_since = time.monotonic()
        # rerun's set_sinks waits for the connection (5 s on a dead port): in the background too
        self._worker = self._start(lambda: self.rec.set_sinks(target.sink()), "live view connect")

    @property
    def alive(self) -> bool:
        return self.lost is None

    def _start(self, job, name: str) -> threading.Thread:
        def run() -> None:
            try:
                job()
            except RuntimeError:  # "Flush timed out", a sink that failed
                self._failed = True

        self._pending_since = time.monotonic()
        worker = threading.Thread(target=run, name=name, daemon=True)
        worker.start()
        return worker

    def _stalled(self) -> bool:
        """Whether the viewer has failed, or has had a flush pending for LIVE_STALL_S."""
        pending = time.monotonic() - self._pending_since
        return self._failed or (self._worker.is_alive() and pending > LIVE_STALL_S)

    def flush(self) -> None:
        """Start pushing what was sent to the viewer, without waiting; drop a viewer that has stalled."""
        if self.lost is not None:
            return
        if self._stalled():
            self._drop(f"it took nothing for {time.monotonic() - self._pending_since:.0f} s")
        elif not self._worker.is_alive():
            self._worker = self._start(lambda: self.rec.flush(timeout_sec=LIVE_STALL_S), "live view flush")

    def close(self) -> None:
        """The last flush, bounded by LIVE_CLOSE_S, then let go: a served stream stays up for late viewers, a
        healthy client disconnects, a stalled one is abandoned (``exit_now_if_abandoned``)."""
        if self.lost is not None:
            return
        self._worker.join(LIVE_CLOSE_S)
        if not self._failed and not self._worker.is_alive():
            self._worker = self._start(lambda: self.rec.flush(timeout_sec=LIVE_CLOSE_S), "live view last flush")
            self._worker.join(LIVE_CLOSE_S + 1.0)
        if self._failed or self._worker.is_alive():
            self._drop(f"it did not take the end of the run within {LIVE_CLOSE_S:g} s")
        elif self.target.port is not None:
            SERVING.append(self.rec)
        else:
            self.rec.disconnect()

    def _drop(self, why: str) -> None:
        self.lost = why
        ABANDONED.append(self)
        where = self.target.url if self.target.url is not None else f"port {self.target.port}"
        print(f"hil: warning: live view at {where} dropped ({why}); the run goes on, recorded to its files",
              file=sys.stderr, flush=True)


def exit_now_if_abandoned(code: int) -> None:
    """End the process at once with ``code`` when a live view was dropped: rerun would otherwise wait at exit for
    the messages that viewer never took (forever, for a peer that accepts and never reads). Call it only once
    every file is written."""
    if ABANDONED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

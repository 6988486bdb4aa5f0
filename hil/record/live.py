"""Live viewing: where a run's recording streams while it runs (``hil run --connect [URL]`` or ``--serve [PORT]``).

``--connect`` sends to a rerun viewer (or a ``rerun --save`` proxy) that is already listening, as
``rr.connect_grpc`` does; ``--serve`` hosts a gRPC server on loopback that viewers connect to
(``rerun --connect rerun+http://127.0.0.1:PORT/proxy``). The stream carries the same batches as the file: in
virtual time they follow the simulation, in real time the wall clock (hil/runtime/realtime/live_tail.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import rerun as rr

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
        if self.url is not None:
            return rr.GrpcSink(self.url)
        return rr.GrpcServerSink(bind_ip="127.0.0.1", port=self.port)

    def describe(self) -> str:
        if self.url is not None:
            return f"streaming live to {self.url}"
        return f"serving live on rerun+http://127.0.0.1:{self.port}/proxy (rerun --connect rerun+http://127.0.0.1:{self.port}/proxy)"

"""The run log: every sampled signal, frame latency and event of one run, as numpy arrays.

The runtimes append to it while running (preallocated chunks, no per-sample allocation);
metrics and the rerun writer read it. Arrays are indexed [sample, unit] front to back.
"""
from __future__ import annotations

from array import array
from dataclasses import dataclass, field

import numpy as np

from hil.layout import TrainLayout


@dataclass
class Event:
    """Something that happened at a time: a fault, a timeout, an emergency brake."""

    t: float
    level: str  # "INFO" | "WARN" | "ERROR" (rerun TextLog levels)
    source: str  # entity-ish origin, e.g. "train1/unit2/ecu", "bus1", "radio1-2", "plant"
    text: str


class SampleTable:
    """Growable table of float rows (time first): appends go to a flat C array, O(1) and allocation-light.

    ``array`` materialises an (n, width) read-only numpy view, cached until the next append."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._buf = array("d")
        self._cache: np.ndarray | None = None

    def append(self, row) -> None:
        if len(row) != self.width:
            raise ValueError(f"row of {len(row)} values, table has {self.width} columns")
        if isinstance(row, np.ndarray):
            self._buf.frombytes(row.astype(float, copy=False).tobytes())
        else:
            self._buf.extend(row)
        self._cache = None

    def extend_bytes(self, rows: bytes) -> None:
        """Append whole rows given as native float64 bytes (how the frame engine hands over its statistics)."""
        if len(rows) % (8 * self.width):
            raise ValueError(f"{len(rows)} bytes are not whole rows of {self.width} float64 values")
        if rows:
            self._buf.frombytes(rows)
            self._cache = None

    def __len__(self) -> int:
        return len(self._buf) // self.width

    def last(self, column: int = 0) -> float:
        """Value of ``column`` in the last row (NaN when empty), without materialising the table."""
        return self._buf[len(self._buf) - self.width + column] if self._buf else float("nan")

    @property
    def array(self) -> np.ndarray:
        """A read-only (n, width) array of the rows so far."""
        if self._cache is None:
            self._cache = np.frombuffer(self._buf.tobytes(), dtype=float).reshape(-1, self.width)
        return self._cache


@dataclass
class BusLog:
    """Per-bus statistics: load per window and the latency of every frame."""

    name: str  # "bus1" ... (1-based train number)
    bitrate: int
    load: SampleTable = field(default_factory=lambda: SampleTable(2))  # (t_window_end, load 0..1)
    # (t_end, frame_id, latency_s = end of transmission - enqueue time, queueing_s)
    frames: SampleTable = field(default_factory=lambda: SampleTable(4))
    frames_sent: int = 0
    frames_dropped: int = 0  # TX-queue overflow or injected drop


@dataclass
class RunLog:
    """Everything a run produced, for metrics and recording."""

    layout: TrainLayout
    # per sample: t, x_r, v_r, then x[n], v[n], a[n], force_cmd[n], force_applied[n]
    signals: SampleTable = field(init=False)
    buses: list[BusLog] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    reference_change_times: list[float] = field(default_factory=list)
    radio_stats: dict[str, dict[str, int]] = field(default_factory=dict)  # link name -> counters
    codec_saturations: dict[str, int] = field(default_factory=dict)  # "Message.Signal" -> count
    e2e: dict[str, dict[str, int]] = field(default_factory=dict)  # ECU name -> E2E status -> count
    frames_lost: int = 0
    interrupted: bool = False  # stopped early (Ctrl-C): everything up to sim_time_s is valid
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0

    def __post_init__(self) -> None:
        self.signals = SampleTable(3 + 5 * self.layout.n_units)

    def add_sample(self, t: float, x_r: float, v_r: float, x: np.ndarray, v: np.ndarray, a: np.ndarray,
                   force_cmd: np.ndarray, force_applied: np.ndarray) -> None:
        self.signals.append(np.concatenate(((t, x_r, v_r), x, v, a, force_cmd, force_applied)))

    def event(self, t: float, level: str, source: str, text: str) -> None:
        self.events.append(Event(t, level, source, text))

    # ---- views on the sampled signals (each (k,) or (k, n))
    def _block(self, i: int) -> np.ndarray:
        n = self.layout.n_units
        return self.signals.array[:, 3 + i * n : 3 + (i + 1) * n]

    @property
    def t(self) -> np.ndarray:
        return self.signals.array[:, 0]

    @property
    def x_ref(self) -> np.ndarray:
        return self.signals.array[:, 1]

    @property
    def v_ref(self) -> np.ndarray:
        return self.signals.array[:, 2]

    @property
    def x(self) -> np.ndarray:
        return self._block(0)

    @property
    def v(self) -> np.ndarray:
        return self._block(1)

    @property
    def a(self) -> np.ndarray:
        return self._block(2)

    @property
    def force_cmd(self) -> np.ndarray:
        return self._block(3)

    @property
    def force_applied(self) -> np.ndarray:
        return self._block(4)

    @property
    def position_error(self) -> np.ndarray:
        """x - x* with x* = x_r - offset."""
        return self.x - (self.x_ref[:, None] - self.layout.offset_m[None, :])

    @property
    def speed_error(self) -> np.ndarray:
        return self.v - self.v_ref[:, None]

    @property
    def couplers(self) -> np.ndarray:
        """(k, n_couplers) coupler displacement e (> 0 stretched)."""
        p = self.layout.coupler_pairs()
        x = self.x
        if len(p) == 0:
            return np.zeros((len(x), 0))
        return x[:, p[:, 0]] - x[:, p[:, 1]] - self.layout.length_m[p[:, 0]][None, :]

    @property
    def gaps(self) -> np.ndarray:
        """(k, n_trains-1) gap between consecutive trains."""
        L = self.layout
        tails, heads = L.tails(), L.heads()
        x = self.x
        return (x[:, tails[:-1]] - L.length_m[tails[:-1]][None, :]) - x[:, heads[1:]]

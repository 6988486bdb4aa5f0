"""CAN timing analysis of one train bus: its frame set, each frame's worst-case response time, the load.

Builds the periodic message set a train's bus carries (from the DBC and the scenario's periods), runs the
Davis et al. (2007) analysis of :mod:`hil.can.wcrt` on it, and sets measured latencies beside the bounds.

What a train bus carries (the virtual rig's wiring, ``hil/runtime/virtual.py``):

* ``Reference`` and ``ReferenceAux`` from the wayside, every ``reference_period_s``;
* per unit slot ``u`` in 1..units: ``Sensor_Uu`` from the plant every ``sensor_period_s``, and
  ``TractionCmd_Uu``, ``AgentState_Uu``, ``AgentAux_Uu`` from the ECU every ``cycle_s``;
* radio frames forwarded by the gateway: ``RadioAheadState``/``Aux`` if a train runs ahead (its tail's
  ``AgentState``/``AgentAux``), ``RadioBehindState``/``Aux`` if one runs behind (its head's); the ``Aux``
  frames only with ``forward_aux``. They repeat at their source's period, with a release jitter.

With a DBC that packs frames into CAN FD containers (``dbc/train_fd.dbc``), every container whose parts are all
in the set replaces them (``pack_messages``): the common case, each sender's frames of one instant in one frame.
A cycle in which a container is incomplete (an ECU with a stale sensor sends its TractionCmd alone) sends its
parts as themselves; those frames are not in the analysed set.

A forwarded frame is released on this bus when its source frame has ended on the other bus plus the radio's
delay, so its release jitter is bounded by the spread of the source's response time there (WCRT - best case)
plus the radio's own jitter (the constant latency shifts the phase only; the rate cap and losses only remove
frames). :func:`forwarded_jitter` computes that bound as a fixed point over the train's buses.

Assumptions of the bounds (Davis et al.): priority-ordered TX queues (``can.queue_policy = "priority"``;
a FIFO queue breaks them), no TX-queue overflow, an error-free bus, and worst-case phasing of all senders.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ecu_sim.codec import MessageCodec, TrainDb
from hil.can.wcrt import BusRates, as_rates
from hil.can.wcrt import CanMessage, response_times
from hil.scenario.model import Scenario

_MAX_JITTER_ITERATIONS = 100
_LIST_MAX = 6  # frames named in the table's footer lines


class CanAnalysisError(ValueError):
    """A user error in a CAN analysis request: the message names the bad option, field or value."""


# --------------------------------------------------------------------------- the frame set


def _message(codec: MessageCodec, period_s: float | None, extended: bool, jitter_s: float = 0.0) -> CanMessage:
    """A CanMessage of one DBC message: the given period, else the DBC's GenMsgCycleTime."""
    period = codec.cycle_time_s if period_s is None else period_s
    return CanMessage(codec.name, codec.frame_id, period, codec.dlc, extended=extended, jitter_s=jitter_s)


def _forwarded(codec: MessageCodec, source: MessageCodec, cycle_s: float | None, extended: bool,
               jitter_s: float) -> CanMessage:
    """A radio frame: its own ID and DLC, its source's period (cycle_s, else the source's DBC cycle)."""
    period = source.cycle_time_s if cycle_s is None else cycle_s
    return CanMessage(codec.name, codec.frame_id, period, codec.dlc, extended=extended, jitter_s=jitter_s)


def train_bus_messages(db: TrainDb, units: int, cycle_s: float | None = None, sensor_period_s: float | None = None,
                       reference_period_s: float | None = None, radio_ahead: bool = True, radio_behind: bool = True,
                       forward_aux: bool = True, radio_jitter_s: float | tuple[float, float] = 0.0,
                       extended: bool = False) -> list[CanMessage]:
    """Every periodic frame on the bus of a train with ``units`` power units (see the module docstring).

    Periods not given come from the DBC's GenMsgCycleTime; radio frames repeat at their source's period
    (``cycle_s``, else the source AgentState/AgentAux's DBC cycle) with release jitter ``radio_jitter_s``:
    one value for both directions, or (ahead, behind).
    """
    if isinstance(units, bool) or not isinstance(units, int) or not 1 <= units <= db.max_units:
        raise CanAnalysisError(f"units={units!r} must be an integer in 1..{db.max_units} (the DBC's unit slots)")
    msgs = [_message(db.reference, reference_period_s, extended), _message(db.reference_aux, reference_period_s, extended)]
    for u in range(units):
        msgs.append(_message(db.sensor(u), sensor_period_s, extended))
        msgs += [_message(c, cycle_s, extended) for c in (db.traction_cmd(u), db.agent_state(u), db.agent_aux(u))]
    j_ahead, j_behind = radio_jitter_s if isinstance(radio_jitter_s, tuple) else (radio_jitter_s, radio_jitter_s)
    sides = []
    if radio_ahead:  # the train ahead's tail, forwarded
        sides.append((db.radio_ahead_state, db.radio_ahead_aux, units - 1, j_ahead))
    if radio_behind:  # the train behind's head, forwarded
        sides.append((db.radio_behind_state, db.radio_behind_aux, 0, j_behind))
    for state, aux, src, jitter in sides:
        msgs.append(_forwarded(state, db.agent_state(src), cycle_s, extended, jitter))
        if forward_aux:
            msgs.append(_forwarded(aux, db.agent_aux(src), cycle_s, extended, jitter))
    return pack_messages(msgs, db, units)


def pack_messages(msgs: list[CanMessage], db: TrainDb, units: int) -> list[CanMessage]:
    """The frame set as sent with the DBC's CAN FD containers: each container whose parts are all in ``msgs``, at
    one period and jitter, replaces them (unchanged without containers)."""
    by_name = {m.name: m for m in msgs}
    for c in db.containers_for(units):
        parts = [by_name.get(p.name) for p in c.parts]
        if None in parts or len({(m.period_s, m.jitter_s) for m in parts}) != 1:  # type: ignore[union-attr]
            continue
        first = parts[0]
        for p in c.parts:
            del by_name[p.name]
        by_name[c.name] = CanMessage(c.name, c.frame_id, first.period_s, c.length, extended=first.extended,  # type: ignore[union-attr]
                                     jitter_s=first.jitter_s)  # type: ignore[union-attr]
    return list(by_name.values())


def carrier(db: TrainDb, units: int, codec: MessageCodec, msgs: Sequence[CanMessage]) -> str:
    """The frame of ``msgs`` that carries ``codec``'s message: itself, or the container it is packed in."""
    names = {m.name for m in msgs}
    if codec.name in names:
        return codec.name
    return next((c.name for c in db.carriers(codec.frame_id, units) if c.name in names), codec.name)


# --------------------------------------------------------------------------- one train's buses


@dataclass(frozen=True)
class TrainBusSetup:
    """What fixes the frame set and timing of one train's bus; None periods mean the DBC's cycle times."""

    units: int
    bitrate: int
    cycle_s: float | None = None
    sensor_period_s: float | None = None
    reference_period_s: float | None = None
    n_trains: int | None = None  # None: unknown, analyse a middle train's bus (radio both ways)
    bus_index: int = 0  # 0-based train/bus index; only used when n_trains is known
    forward_aux: bool = True
    radio_link_jitter_s: float = 0.0  # the radio's own spread of delivery times (a bound)
    extended: bool = False
    queue_policy: str = "priority"
    fd: bool = False  # CAN FD frames
    data_bitrate: int | None = None  # CAN FD with BRS: the data phase's bitrate
    brs: bool = True

    def __post_init__(self) -> None:
        try:
            self.rates
        except ValueError as exc:
            raise CanAnalysisError(f"bitrate: {exc}") from None
        if self.n_trains is not None and not 0 <= self.bus_index < self.n_trains:
            raise CanAnalysisError(f"bus{self.bus_index + 1}: the train has buses bus1..bus{self.n_trains}")
        if not (math.isfinite(self.radio_link_jitter_s) and self.radio_link_jitter_s >= 0):
            raise CanAnalysisError(f"radio jitter {self.radio_link_jitter_s!r} s must be finite and >= 0")

    @property
    def rates(self) -> BusRates:
        """The bus's bit timing (classical, or CAN FD with its data phase)."""
        return BusRates(self.bitrate, self.data_bitrate if self.fd else None, self.fd, self.brs)

    @classmethod
    def from_scenario(cls, sc: Scenario, bus_index: int = 0) -> "TrainBusSetup":
        """Units, periods, bitrate and radio of a scenario, for bus ``bus_index`` (0-based)."""
        radio = sc.radio
        if radio.jitter_s > 0 and radio.jitter_distribution != "uniform":
            raise CanAnalysisError(
                f"scenario {sc.name}: radio.jitter_distribution = {radio.jitter_distribution!r} has no upper bound, "
                "so forwarded radio frames have no bounded release jitter (use 'uniform' for the analysis)"
            )
        return cls(units=sc.trains.units, bitrate=sc.can.bitrate, cycle_s=sc.ecu.cycle_s,
                   sensor_period_s=sc.can.sensor_period_s, reference_period_s=sc.reference.period_s,
                   n_trains=sc.trains.count, bus_index=bus_index, forward_aux=radio.forward_aux,
                   radio_link_jitter_s=radio.jitter_s, extended=sc.can.extended_ids, queue_policy=sc.can.queue_policy,
                   fd=sc.can.fd, data_bitrate=sc.can.data_rate if sc.can.fd else None, brs=sc.can.brs)

    def radio_sides(self, bus_index: int | None = None) -> tuple[bool, bool]:
        """(has a train ahead, has one behind) for a bus: bus1 has none ahead, the last none behind."""
        if self.n_trains is None:
            return True, True
        k = self.bus_index if bus_index is None else bus_index
        return k > 0, k < self.n_trains - 1

    def messages(self, db: TrainDb, radio_jitter_s: float | tuple[float, float],
                 bus_index: int | None = None) -> list[CanMessage]:
        """The frame set of this setup's bus (or of ``bus_index``), forwarded frames with the given jitter."""
        if db.containers and not self.fd:
            raise CanAnalysisError(f"DBC {db.path.name} packs frames into CAN FD containers: analyse it on a CAN FD bus "
                                   "(--scenario NAME --set can.fd=true --set can.data_bitrate=B)")
        ahead, behind = self.radio_sides(bus_index)
        return train_bus_messages(db, self.units, self.cycle_s, self.sensor_period_s, self.reference_period_s,
                                  ahead, behind, self.forward_aux, radio_jitter_s, self.extended)


def _source_bounds(db: TrainDb, setup: TrainBusSetup, jitter: tuple[float, float]) -> tuple[float, float]:
    """(tail, head) sources' largest response-time spread, WCRT - best case, over the train's buses.

    A bus's tail AgentState/AgentAux becomes RadioAhead* on the bus behind; its head's becomes RadioBehind*
    on the bus ahead. ``jitter`` is that of the forwarded frames on every bus.
    """
    tail, head = setup.units - 1, 0
    rates = setup.rates
    worst = [0.0, 0.0]
    for k in ([None] if setup.n_trains is None else range(setup.n_trains)):
        ahead, behind = setup.radio_sides(k)
        if not (ahead or behind):
            continue
        msgs = setup.messages(db, jitter, k)
        bounds, by_name = response_times(msgs, rates), {m.name: m for m in msgs}
        for side, unit, feeds in ((0, tail, behind), (1, head, ahead)):
            if feeds:
                codecs = [db.agent_state(unit)] + ([db.agent_aux(unit)] if setup.forward_aux else [])
                frames = [by_name[carrier(db, setup.units, c, msgs)] for c in codecs]
                spread = (bounds[m.name].r_s - rates.best_case_ns(m.dlc, setup.extended) * 1e-9 for m in frames)
                worst[side] = max(worst[side], *spread)
    return worst[0], worst[1]


def forwarded_jitter(db: TrainDb, setup: TrainBusSetup) -> tuple[float, float]:
    """Release-jitter bounds (RadioAhead*, RadioBehind*) on every bus of the train (inf if unbounded).

    A source frame is queued at its ECU's tick and ends between its best case and its WCRT later; the
    radio then adds its latency (a constant: phase only) and up to its jitter. So J = radio jitter +
    max over the sources (on any bus) of WCRT - best case. The sources' WCRT depends on J only if
    forwarded frames outrank them (not with the DBC's IDs, 0x180.. after 0x100..); the least fixed point
    is found by iteration from J = 0. If any source is unbounded, both bounds are inf (with the DBC's IDs
    every radio frame is then in an overloaded priority level anyway).
    """
    link = setup.radio_link_jitter_s
    jitter = (0.0, 0.0)
    for _ in range(_MAX_JITTER_ITERATIONS):
        new = tuple(round(link + b, 9) for b in _source_bounds(db, setup, jitter))  # whole ns
        if not all(map(math.isfinite, new)):
            return math.inf, math.inf
        if [round(x * 1e9) for x in new] == [round(x * 1e9) for x in jitter]:
            return new  # type: ignore[return-value]
        jitter = new  # type: ignore[assignment]
    raise RuntimeError(f"forwarded-frame jitter did not converge in {_MAX_JITTER_ITERATIONS} iterations")


# --------------------------------------------------------------------------- the analysis


@dataclass(frozen=True)
class FrameTiming:
    """One frame's timing on the bus: worst-case length, C, period, WCRT, and the measured max if known."""

    name: str
    can_id: int
    dlc: int
    extended: bool
    bits: int  # worst-case stuffed length incl. the 3-bit intermission
    c_s: float
    period_s: float
    jitter_s: float
    deadline_s: float
    wcrt_s: float  # inf when the frame's priority level is overloaded
    schedulable: bool
    measured_s: float | None = None  # the run's largest latency of this ID (queued -> end of frame)

    @property
    def utilisation(self) -> float:
        """This frame's share of the bus, C / T."""
        return self.c_s / self.period_s

    @property
    def ratio(self) -> float | None:
        """measured / WCRT bound (None without a measurement)."""
        if self.measured_s is None:
            return None
        return self.measured_s / self.wcrt_s if self.wcrt_s > 0 else math.inf

    @property
    def exceeds(self) -> bool:
        """True when the measured latency is above the bound (the analysis or the emulator is wrong)."""
        return self.measured_s is not None and self.measured_s > self.wcrt_s


def analyse(messages: Sequence[CanMessage], bitrate: int | BusRates,
            measured: Mapping[int, float] | None = None) -> list[FrameTiming]:
    """Timing of every frame, highest priority (lowest ID) first; ``measured``: frame ID -> max latency (s)."""
    rates = as_rates(bitrate)
    bounds = response_times(list(messages), rates)
    measured = measured or {}
    out = []
    for m in sorted(messages, key=lambda m: m.can_id):
        r = bounds[m.name]
        bits = sum(rates.worst_case_bits(m.dlc, m.extended))
        out.append(FrameTiming(m.name, m.can_id, m.dlc, m.extended, bits, rates.worst_case_ns(m.dlc, m.extended) * 1e-9,
                               m.period_s, m.jitter_s, m.deadline, r.r_s, r.schedulable, measured.get(m.can_id)))
    return out


def utilisation(timings: Sequence[FrameTiming]) -> float:
    """Bus utilisation, the sum of C / T over the frames."""
    return sum(t.utilisation for t in timings)


def analyse_train_bus(db: TrainDb, setup: TrainBusSetup, measured: Mapping[int, float] | None = None) -> list[FrameTiming]:
    """Analyse the setup's bus, forwarded frames with the :func:`forwarded_jitter` bound.

    Where that bound is infinite (a source frame's level is overloaded), the forwarded frames and every
    frame of lower priority are reported unbounded and unschedulable.
    """
    jitter = forwarded_jitter(db, setup)
    if all(map(math.isfinite, jitter)):
        return analyse(setup.messages(db, jitter), setup.rates, measured)
    timings = analyse(setup.messages(db, 0.0), setup.rates, measured)
    radio = {c.frame_id for c in (db.radio_ahead_state, db.radio_ahead_aux, db.radio_behind_state, db.radio_behind_aux)}
    first = min((t.can_id for t in timings if t.can_id in radio), default=None)
    if first is None:
        return timings
    # a frame with unbounded release jitter makes its own WCRT and every lower-priority frame's unbounded
    return [dataclasses.replace(t, wcrt_s=math.inf, schedulable=False, jitter_s=math.inf if t.can_id in radio else t.jitter_s)
            if t.can_id >= first else t for t in timings]


# --------------------------------------------------------------------------- the table


def _ms(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    return "inf" if math.isinf(seconds) else f"{seconds * 1e3:.3f}"


def _row(t: FrameTiming, with_measured: bool) -> list[str]:
    width = 8 if t.extended else 3
    row = [t.name, f"0x{t.can_id:0{width}X}", str(t.dlc), str(t.bits), _ms(t.c_s), _ms(t.period_s), _ms(t.jitter_s),
           _ms(t.wcrt_s), _ms(t.deadline_s), f"{100 * t.utilisation:.2f}", "yes" if t.schedulable else "NO"]
    if with_measured:
        ratio = t.ratio
        row += [_ms(t.measured_s), "-" if ratio is None else f"{ratio:.3f}", "EXCEEDS BOUND" if t.exceeds else ""]
    return row


HEADER = ["frame", "ID", "DLC", "bits", "C ms", "T ms", "J ms", "WCRT ms", "D ms", "U %", "sched"]
MEASURED_HEADER = ["measured ms", "meas/WCRT", "flag"]


def format_table(timings: Sequence[FrameTiming], bitrate: int | BusRates | None = None) -> str:
    """Aligned text table (IDs in hex, times in ms), the measured columns if any frame has a measurement,
    then the bus utilisation and a count of unschedulable frames and of measurements above their bound."""
    with_measured = any(t.measured_s is not None for t in timings)
    rows = [HEADER + (MEASURED_HEADER if with_measured else [])] + [_row(t, with_measured) for t in timings]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = []
    for r in rows:
        cells = [r[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(r[1:], widths[1:])]
        if with_measured:
            cells[-1] = r[-1].ljust(widths[-1])
        lines.append("  ".join(cells).rstrip())
    rate = f" at {as_rates(bitrate)}" if bitrate else ""
    lines.append(f"bus utilisation{rate}: {100 * utilisation(timings):.2f} % "
                 f"(sum of C/T over {len(timings)} frames, worst-case frame lengths)")
    bad = [t.name for t in timings if not t.schedulable]
    shown = ", ".join(bad[:_LIST_MAX]) + (f", ... ({len(bad) - _LIST_MAX} more)" if len(bad) > _LIST_MAX else "")
    lines.append(f"unschedulable frames: {f'{len(bad)}: {shown}' if bad else 'none'}")
    if with_measured:
        over = [f"{t.name} (0x{t.can_id:03X})" for t in timings if t.exceeds]
        lines.append(f"measured above bound: {', '.join(over) if over else 'none'}")
    return "\n".join(lines)

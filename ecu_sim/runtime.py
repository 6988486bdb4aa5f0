"""The ECU runtime: the firmware loop around one control law.

Each cycle it reads the latest frame of every input stream (own sensor, neighbours' AgentState and
AgentAux, the wayside reference), checks each with the E2E CRC and alive counter, judges freshness by
age, builds the controller's :class:`~ecu_sim.view.LocalView`, runs the law, and encodes its outputs
(TractionCmd, AgentState, AgentAux). It is clock-agnostic: the virtual-time runtime and a real-time
process call ``on_frame`` when a frame arrives and ``cycle`` on the ECU's timer. The rig's runtimes call
``cycle_outputs`` instead when a program keeps the standard ``cycle`` (``encodes_in_engine``): the same outputs,
not yet encoded, which the engine encodes and sends in one call.

Sample alignment: the plant samples every unit's sensors at the same instants and numbers them with the
Sensor frame's alive counter. An ECU sends its AgentState/AgentAux with that same counter (so the counter
means "sample k"; a repeated sample is REPEATED at the receivers), and keeps its own last samples by
counter. A neighbour's state is then compared with our own state *at the same sample*: at 90 m/s one
cycle of skew would otherwise read as 0.9 m of coupler displacement, nine times the seed-000 band.

Degraded modes: a neighbour whose last good frame is older than ``neighbour_timeout_s`` is left out
of the law; a stale own sensor or (for pinned units) a stale reference commands the service brake;
losing the train ahead for longer than ``radio_contact_timeout_s`` after contact commands the
emergency brake; a controller that raises or returns a non-finite force stops the ECU (it falls
silent, and the plant's fail-safe takes over), as a crashed ECU would.

Every freshness check counts a TIMEOUT in the stream's E2E statistics when a stream that had been fresh goes
stale. ``monitors`` run after every cycle (``ecu_sim.diagnostics``: diagnostic events, sensor and traction
plausibility); a monitor that judges the own sensor implausible sets ``sensor_fault``, which gives the same
degraded mode as a stale sensor (service brake, no AgentState/AgentAux).
"""
from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal, NoReturn, Protocol

from trainhil_engine import Mailbox

from ecu_sim.codec import MessageCodec, TrainDb
from ecu_sim.controllers.base import Controller
from ecu_sim.e2e import E2EStatus
from ecu_sim.view import AgentInfo, BrakeMode, Command, LocalView, NeighbourView, ReferenceView

INF = float("inf")
_EMERGENCY = BrakeMode.EMERGENCY
_SERVICE = BrakeMode.SERVICE


ECU_STOPPED = "ECU stopped"  # the words that end every firmware-failure event (the rig's ecu_failure verdict)
RESTARTED = "restarted with a reset controller"  # the start of every restart event (the same verdict)


@contextlib.contextmanager
def os_exit_stops_the_firmware() -> Iterator[None]:
    """While firmware runs in the rig's own process (virtual time), ``os._exit`` raises SystemExit instead, which
    stops the calling ECU like any failure (``guarded_cycle``) rather than ending the run with nothing written."""
    real = os._exit

    def refuse(code: int) -> NoReturn:
        raise SystemExit(f"os._exit({code}) called by the firmware")

    os._exit = refuse  # type: ignore[assignment]
    try:
        yield
    finally:
        os._exit = real


Output = tuple[MessageCodec, tuple[float, ...], int]  # one frame of a cycle, not yet encoded: (message, values, counter)


def guarded_cycle(ecu: "Ecu", t: float) -> list[tuple[int, bytes]]:
    """``ecu.cycle(t)``, with a program that raises (or calls sys.exit) stopped like a failed law, not the run."""
    return _guarded(ecu, t, ecu.cycle)


def _guarded(ecu: "Ecu", t: float, cycle):
    """``cycle(t)`` of a live ECU; a program that raises stops the ECU and sends nothing."""
    if not ecu.alive:
        return []
    try:
        return cycle(t)
    except (Exception, SystemExit) as exc:
        ecu.stop(t, f"ECU program failed: {exc!r}")
        return []


def cycle_and_send(ecu: "Ecu", t: float, key, send_outputs: Callable[[Any, list[Output]], None],
                   send_frames: Callable[[Any, list[tuple[int, bytes]]], None]) -> None:
    """One guarded cycle of ``ecu`` at ``t``, what it produced sent to ``key`` (a runtime's node or bus): its outputs
    unencoded through ``send_outputs`` (the engine encodes and sends them in one call) when its program keeps the
    standard ``cycle`` (``encodes_in_engine``), else its frames through ``send_frames``. A value the codec refuses
    (NaN) stops the ECU as ``guarded_cycle`` does when ``cycle`` encodes it."""
    if not encodes_in_engine(ecu):
        if frames := guarded_cycle(ecu, t):
            send_frames(key, frames)
        return
    if outputs := _guarded(ecu, t, ecu.cycle_outputs):
        try:
            send_outputs(key, outputs)
        except ValueError as exc:
            ecu.stop(t, f"ECU program failed: {exc!r}")


def encode_outputs(outputs: list[Output]) -> list[tuple[int, bytes]]:
    """A cycle's outputs as frames (id, data), encoded here: where no engine call sends them (python-can)."""
    return [(codec.frame_id, codec.encode(values, counter)) for codec, values, counter in outputs]


def encodes_in_engine(ecu: "Ecu") -> bool:
    """Whether the ECU's program keeps the standard ``cycle``, so a runtime may take its outputs unencoded
    (``cycle_outputs``) and have the engine encode and send them in one call; a program that overrides ``cycle``
    (in a subclass, or on the instance, as a factory may) is called as it is."""
    return getattr(ecu.cycle, "__func__", None) is Ecu.cycle


class EcuSettings(Protocol):
    """What the firmware reads of its configuration (the rig passes its scenario's ``[ecu]`` section)."""

    cycle_s: float  # control period
    neighbour_timeout_s: float  # older neighbour data is dropped
    reference_timeout_s: float  # older reference: service brake
    radio_contact_timeout_s: float  # no train ahead for this long: emergency brake


class SlotChecker:
    """The E2E statistics of one mailbox slot, read from the engine (counts indexed by E2EStatus)."""

    __slots__ = ("_mb", "_i")

    def __init__(self, mailbox: Mailbox, index: int) -> None:
        self._mb, self._i = mailbox, index

    @property
    def counts(self) -> list[int]:
        return [self._mb.count(self._i, s) for s in E2EStatus]

    @property
    def lost(self) -> int:
        return self._mb.summary(self._i).get("LOST", 0)

    @property
    def timeouts(self) -> int:
        return self._mb.summary(self._i).get("TIMEOUT", 0)

    def summary(self) -> dict[str, int]:
        """Non-zero counts by status name, plus the lost frames and the timeouts."""
        return self._mb.summary(self._i)


class InputSlot:
    """One input stream of an ECU: its codec and its mailbox slot in the engine (the last raw frame, and the
    last frame that passed the E2E check, read once per cycle)."""

    __slots__ = ("codec", "index", "checker", "_mb")

    def __init__(self, mailbox: Mailbox, index: int, codec: MessageCodec) -> None:
        self._mb, self.index, self.codec = mailbox, index, codec
        self.checker = SlotChecker(mailbox, index)

    @property
    def values(self) -> tuple[float, ...]:
        """Decoded values of the last good frame (empty before any)."""
        return self._mb.values(self.index)

    @property
    def counter(self) -> int:
        """Alive counter of the last good frame (-1 before any)."""
        return self._mb.counter(self.index)

    @property
    def t_good(self) -> float:
        """Reception time of the last good frame (-inf before any)."""
        return self._mb.t_good(self.index)

    def age(self, t: float) -> float:
        return t - self.t_good


@dataclass(frozen=True, slots=True)
class NeighbourLink:
    """Where one neighbour's state arrives from."""

    state_id: int
    aux_id: int | None
    link: Literal["intra", "inter"]
    side: Literal["ahead", "behind"]
    offset_m: float


class EcuCounters:
    """What an ECU counts: cycles and controller failures here, bad frames in its mailboxes."""

    __slots__ = ("cycles", "controller_errors", "_mb")

    def __init__(self, mailbox: Mailbox) -> None:
        self.cycles = 0
        self.controller_errors = 0
        self._mb = mailbox

    @property
    def unknown_frames(self) -> int:
        """Frames with an ID this ECU has no input for (a receiver without acceptance filter)."""
        return self._mb.unknown_frames

    @property
    def malformed_frames(self) -> int:
        """Frames of a known ID whose length is not the DBC's DLC: dropped, never decoded."""
        return self._mb.malformed_frames


class Ecu:
    """One power unit's onboard controller."""

    def __init__(self, name: str, agent: AgentInfo, controller: Controller, db: TrainDb,
                 neighbours: list[NeighbourLink], cfg: EcuSettings, sample_period_s: float = 0.01) -> None:
        self.name = name
        self.agent = agent
        self.controller = controller
        self.cfg = cfg
        self.alive = True
        self.events: list[tuple[float, str, str]] = []  # (t, level, text), drained by the runtime
        self.mailbox = Mailbox()  # the input mailboxes (engine): the rig delivers into it, cycle() reads it
        self.counters = EcuCounters(self.mailbox)
        u = agent.unit
        self._out_cmd = db.traction_cmd(u)
        self._out_state = db.agent_state(u)
        self._out_aux = db.agent_aux(u)
        self._cmd_counter = 0
        self._samples: list[tuple[float, float, float] | None] = [None] * 16  # own (x, v, t_rx) by sample counter
        self._align_window_s = 8 * sample_period_s  # half the counter's wrap: older matches would be ambiguous
        # A mailbox read once per cycle sees the counter advance by cycle/sample period; allow twice that
        # (one jittered cycle) before a jump counts as a wrong sequence.
        self._max_delta = min(14, 2 * max(1, round(cfg.cycle_s / sample_period_s)))
        self.slots: dict[int, InputSlot] = {}
        self._sensor = self._slot(db.sensor(u))
        self._ref = self._slot(db.reference) if agent.has_reference else None
        self._ref_aux = self._slot(db.reference_aux) if agent.has_reference else None
        self._links = [(nl, self._slot(db.by_id[nl.state_id]), self._slot(db.by_id[nl.aux_id]) if nl.aux_id is not None else None)
                       for nl in neighbours]
        self.view = LocalView(t=0.0, dt=cfg.cycle_s, x=math.nan, v=math.nan,
                              neighbours=[NeighbourView(nl.link, nl.side, nl.offset_m) for nl in neighbours],
                              ref=ReferenceView())
        self._flags: dict[str, bool] = {}
        self._sensor_counter = -1  # alive counter (sample number) of the own sensor frame read this cycle
        self._link_t_good = [-INF] * len(self._links)  # reception time of each neighbour's last good state
        # per cycle: (view, state slot, aux slot or -1) of each neighbour, and which one is the train ahead
        self._neighbour_io = [(nv, state.index, aux.index if aux is not None else -1)
                              for nv, (_, state, aux) in zip(self.view.neighbours, self._links)]
        self._ahead = next((k for k, (nl, _, _) in enumerate(self._links) if nl.link == "inter" and nl.side == "ahead"), None)
        self._timeouts = (float(cfg.neighbour_timeout_s), float(cfg.reference_timeout_s), float(cfg.radio_contact_timeout_s))
        self.sensor_fault = False  # own sensor judged implausible (stuck, noisy) by a monitor: service brake
        self.monitors: list = []  # callables monitor(ecu, t) run after every cycle (ecu_sim.diagnostics)
        self.last_command: Command | None = None  # what the last cycle commanded (None: the ECU stopped)

    def _slot(self, codec: MessageCodec) -> InputSlot:
        slot = InputSlot(self.mailbox, self.mailbox.add_slot(codec, self._max_delta), codec)
        self.slots[codec.frame_id] = slot
        return slot

    def e2e_summary(self) -> dict[str, int]:
        """E2E verdicts summed over every input stream (status name -> count)."""
        totals: dict[str, int] = {}
        for slot in self.slots.values():
            for status, n in self.mailbox.summary(slot.index).items():
                totals[status] = totals.get(status, 0) + n
        for key, n in (("UNKNOWN_ID", self.counters.unknown_frames), ("WRONG_LENGTH", self.counters.malformed_frames)):
            if n:
                totals[key] = n  # bad input seen before any E2E check (absent when zero: results unchanged)
        return totals

    @property
    def rx_ids(self) -> set[int]:
        """Acceptance filter: the IDs this ECU listens to."""
        return set(self.slots)

    # ---- called by the runtime
    def on_frame(self, frame_id: int, data: bytes, t: float) -> None:
        """Mailbox write: keep the latest frame of each stream (checked at the next cycle). The virtual-time
        engine delivers into ``mailbox`` itself; real-time nodes call this per received frame."""
        if self.mailbox.put(frame_id, data, t) == 2:
            self._report_malformed()

    def _report_malformed(self) -> None:
        """The first wrong-length frame is an event; further ones are only counted."""
        first = self.mailbox.take_first_malformed()
        if first is not None:
            t, index, length = first
            codec = next(s.codec for s in self.slots.values() if s.index == index)
            self.events.append((t, "WARN", f"{codec.name}: frame of {length} bytes, DLC is {codec.dlc}: dropped "
                                           "(further ones are counted)"))

    def cycle(self, t: float) -> list[tuple[int, bytes]]:
        """Run one control cycle at time t; return the frames to send (id, data)."""
        return encode_outputs(self.cycle_outputs(t))

    def sent_messages(self) -> tuple[MessageCodec, ...]:
        """The messages its standard cycle sends (TractionCmd, AgentState, AgentAux)."""
        return self._out_cmd, self._out_state, self._out_aux

    def cycle_outputs(self, t: float) -> list[Output]:
        """Run one control cycle at time t; return its frames not yet encoded: (message, values, alive counter)."""
        if not self.alive:
            return []
        self.counters.cycles += 1
        if self.mailbox.refresh():  # some wrong-length frames: the first is reported once
            self._report_malformed()
        cmd = self.last_command = self._control(t)
        frames = [] if cmd is None else self._outputs(cmd)
        for monitor in self.monitors:
            monitor(self, t)
        return frames

    def stop(self, t: float, why: str) -> None:
        """The firmware failed: the ECU falls silent (the plant's fail-safe takes over), an ERROR event says why."""
        self.alive = False
        self.counters.controller_errors += 1
        self.events.append((t, "ERROR", f"{why}; {ECU_STOPPED}"))

    def restart(self) -> None:
        """Power-cycle: clear the controller's memory and the mailboxes, start sending again."""
        self.controller.reset()
        self.mailbox.reset()
        self._samples = [None] * 16
        self.sensor_fault = False
        self.alive = True

    # ---- internals
    def _control(self, t: float) -> Command | None:
        view = self.view
        view.t = t
        sensor_ok, _, values, counter, t_good = self.mailbox.read(self._sensor.index, t, self._timeouts[0])
        self._sensor_counter = counter
        if self._flags.get("sensor_stale", False) is sensor_ok:  # changed: log it
            self._flag(t, "sensor_stale", not sensor_ok, "WARN", "own sensor data stale: service brake")
        if not sensor_ok or self.sensor_fault:
            return Command(0.0, _SERVICE, 0.0)
        view.x, view.v = values
        self._samples[counter] = (view.x, view.v, t_good)
        self._fill_neighbours(t)
        ref_ok = self._fill_reference(t)
        try:
            cmd = self.controller.step(view)
            if not math.isfinite(cmd.force_n):
                raise ValueError(f"controller returned a non-finite force {cmd.force_n}")
        except (Exception, SystemExit) as exc:  # the firmware crashed (sys.exit too): fall silent, fail-safe
            self.stop(t, f"controller {type(self.controller).__name__} failed: {exc!r}")
            return None
        if self.agent.has_reference:
            self._flag(t, "ref_stale", not ref_ok, "WARN", "reference stale: service brake")
            if not ref_ok:
                cmd = Command(0.0, _SERVICE, 0.0)
        if self._ahead is not None and self._lost_train_ahead(t):
            cmd = Command(0.0, _EMERGENCY, 0.0)
        if cmd.mode == _EMERGENCY:
            self._flag(t, "emergency", True, "ERROR", "emergency brake commanded")
        return cmd

    def _fill_neighbours(self, t: float) -> None:
        timeout, read, t_goods, nan = self._timeouts[0], self.mailbox.read, self._link_t_good, math.nan
        for k, (nv, state, aux) in enumerate(self._neighbour_io):
            nv.valid, nv.age_s, values, counter, t_good = read(state, t, timeout)
            t_goods[k] = t_good
            if not nv.valid:
                continue
            nv.x, nv.v = values
            self._align(nv, counter, t_good)
            if aux >= 0:
                aux_ok, _, aux_values, _, _ = read(aux, t, timeout)  # (never fresh before its first frame)
                if aux_ok and aux_values:
                    nv.a, nv.u = aux_values
                    continue
            nv.a = nv.u = nan

    def _align(self, nv: NeighbourView, counter: int, t_good: float) -> None:
        """Shift a neighbour's sample k by our own motion since our sample k (same-instant comparison)."""
        own = self._samples[counter]
        if own is None:
            return
        x_k, v_k, t_k = own
        if 0.0 <= t_good - t_k < self._align_window_s:
            nv.x += self.view.x - x_k
            nv.v += self.view.v - v_k

    def _fill_reference(self, t: float) -> bool:
        if self._ref is None:
            return True
        ref = self.view.ref
        ref.valid, ref.age_s, values, _, _ = self.mailbox.read(self._ref.index, t, self._timeouts[1])
        if ref.valid:
            ref.x, ref.v = values
            aux = self.mailbox.values(self._ref_aux.index) if self._ref_aux else ()
            ref.a = aux[0] if aux else 0.0
        return ref.valid

    def _lost_train_ahead(self, t: float) -> bool:
        """Head of a following train: contact with the train ahead lost for too long after it was made."""
        t_good = self._link_t_good[self._ahead]  # type: ignore[index]
        if t_good == -INF:
            return False
        lost = t - t_good > self._timeouts[2]
        self._flag(t, "radio_lost", lost, "ERROR", "lost contact with the train ahead: emergency brake")
        return lost

    def _flag(self, t: float, key: str, on: bool, level: str, text: str) -> None:
        """Log a condition when it starts and when it clears (not every cycle)."""
        if self._flags.get(key, False) != on:
            self._flags[key] = on
            self.events.append((t, level if on else "INFO", text if on else f"cleared: {text}"))

    def _outputs(self, cmd: Command) -> list[Output]:
        """TractionCmd always; AgentState/AgentAux only with a fresh own sample, numbered by that sample."""
        self._cmd_counter = (self._cmd_counter + 1) & 0xF
        frames: list[Output] = [(self._out_cmd, (int(cmd.mode), cmd.force_n), self._cmd_counter)]
        if self._flags.get("sensor_stale") or self.sensor_fault or self._sensor_counter < 0:
            return frames
        v, k = self.view, self._sensor_counter
        accel = cmd.accel_mps2 if math.isfinite(cmd.accel_mps2) else cmd.force_n / self.agent.mass_kg
        frames.append((self._out_state, (v.x, v.v), k))
        frames.append((self._out_aux, (accel, cmd.force_n), k))
        return frames

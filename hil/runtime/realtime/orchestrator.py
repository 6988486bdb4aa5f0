"""The real-time (HIL) run: bus servers (with the radio), plant and ECU processes, started, paced, stopped, merged.

``run_realtime(scenario, out_dir, pace=...)`` is the real-time twin of ``hil.session.run_scenario``: it writes
the same ``run.rrd`` and ``metrics.json`` (same keys, ``runtime = "realtime"``) plus the timing figures of the
real-time rig. Steps:

1. One bus server per train bus, paced by ``pace``: the engine's ``NativeBusServer`` (a native thread each,
   outside the interpreter lock, CAN errors and bus faults included). Sleep-only (``spin_us = 0``). The ECU
   and plant nodes are lazy readers: a server hands them their frames at their read times, with a SYNC
   (``hil/runtime/realtime/protocol.py``), and wakes at frame ends only for eager nodes (python-can) and for the
   frames the radio takes. The radio is in the servers (``EngineRadio``): each forwards the routed frames that end
   on its bus to the next train's server itself, with no process or Python per frame.
2. Node processes (same Python): the plant + wayside, the ECUs (``ecus_per_process``
   units per process; by default ``default_ecus_per_process``: one ECU process per core the rest of the rig
   leaves, and faster than real time one train's units at most in each), and on SocketCAN the radio bridge. Each prints "ready"; once all have (or ``READY_TIMEOUT_S`` passes: an error naming the
   node) and, with external units on the emulated buses, once their buses have a client of their own
   (``external.wait_for_connections``), every node gets "go <T0>" with T0 a little in the future, and
   sim_t = (wall - T0) * pace everywhere.
3. The nodes stop by themselves at the simulated duration. An ECU process that exits early is an ERROR event
   ("ECU process train1/unit2 exited with code -9") and the run goes on: the plant's fail-safe takes over.
   One whose cycles stopped (a law that never returns) is killed as hung (``hang_watch``), the same way; a hung
   plant is killed and stops the run.
   With ``ecu.restart_after_s`` the watchdog starts it again (``hil.runtime.realtime.faults``). A plant or radio
   process that dies ends the run early (recorded as an event).
4. Ctrl-C / SIGTERM: every node is told "stop", finishes its loop and writes its results; stragglers are
   terminated, then killed, after a grace period. What was recorded is written, ``interrupted`` is set.
   Nodes run in their own sessions (a terminal's Ctrl-C reaches only the orchestrator), and a node whose stdin
   closes (the orchestrator died, even by SIGKILL) stops by itself: no orphans either way.
5. Merge: the plant's signals and events, the ECUs' events/E2E/lateness, the radio counters and the bus logs
   (shifted to simulated time) into a ``RunLog``; ``compute_metrics`` as in virtual time, plus
   ``cycle_lateness_p50/p99/max_s`` (worst ECU, wall seconds), ``cycle_deadline_misses`` (all ECUs),
   ``plant_lateness_p99_s``, ``plant_deadline_misses`` and ``e2e_latency_p50/p99/max_s`` (simulated seconds,
   see ``plant_node``). ``deadline_misses`` keeps its virtual-time meaning (CAN frames later than their period).
"""
from __future__ import annotations

import collections
import math
import os
import queue
import re
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import trainhil_engine as engine

from ecu_sim.codec import TrainDb
from ecu_sim.references import USER_PATH_ENV
from hil.scenario.layout import TrainLayout
from hil.faults.schedule import needs_fault_machinery
from hil.runtime.realtime.bus_server import BusServer, turns_given_up, turns_let_go_text
from hil.runtime.realtime.turns import TURNS_MODES, TurnsMode, takes_turns, turns_text
from hil.runtime.realtime.bus_spool import BusSpool
from hil.runtime.realtime.idle_latency import IdleLatencySetting, check_setting, hold_for_run
from hil.runtime.realtime.cpu_layout import (CPU_LAYOUT_MODES, CpuLayout, CpuLayoutMode, choose_cpu_layout, format_cores,
                                             pin)
from hil.runtime.realtime.scheduling import SchedulingMode, choose_scheduling
from hil.runtime.realtime.merge import merge_nodes, open_recording, write_rest
from hil.runtime.realtime.engine_radio import EngineRadio
from hil.runtime.realtime.native_server import PUMP_S, NativeBusServer
from hil.runtime.realtime.external import JOIN_LINE, ExternalUnitMissing, JoinWait, wait_for_connections
from hil.runtime.realtime.hang_watch import HangWatch, hung_after_s
from hil.runtime.realtime.pacing import ALIVE_LINE
from hil.runtime.realtime.live_tail import LiveTail
from hil.runtime.realtime.sockets import remove_run_dir, remove_stale_run_dirs, validate_name
from hil.runtime.realtime.socketcan import check_channels
from hil.record.canlog import frame_listener, log_format, log_path, open_can_log
from hil.record.live import LiveTarget
from hil.record.diskspace import DiskFullError
from hil.record.integrity import mark_failed, mark_running, write_json_atomic
from hil.record.out_dir import disk_full_outcome, write_metrics_when_full
from hil.record.metrics import run_metrics
from hil.record.runlog import BusLog, Event, RunLog, RunResult
from hil.record.safety import record_violations
from hil.runtime.errors import RigDidNotStart
from hil.runtime.firmware import import_roots
from hil.runtime.train_db import bus_packing, load_train_db
from hil.scenario.model import Scenario

READY_TIMEOUT_S = 60.0  # importing numpy/scipy/cantools in many processes on a loaded 2-core machine is slow
GO_MARGIN_S = 0.3  # wall seconds between "go" and T0, so every node has the message before sim time 0
BUS_WARNINGS_MAX = 100  # a bus's warnings recorded as the run's events, at most (record_bus_warnings)
STOP_GRACE_S = 10.0  # after the end (or a stop), how long nodes get to write their results
KILL_GRACE_S = 3.0
# wall seconds between the supervising loop's turns at most (exits, stop requests, spool, pumps, live view); each
# turn wakes Python cold, some 200 µs of CPU here (docs/realtime-performance.md)
SUPERVISE_S = 0.25
FAULT_TICK_S = 0.01  # ... while faults are injected (their schedule is polled at each turn)
END_POLL_S = 0.05  # ... once the run's time is over, while the nodes write their results and exit


SIGNAL_NAMES = ("SIGINT", "SIGTERM", "SIGHUP")  # stop reasons that are a user's request, not a failure
RUN_FILE = "run.json"  # in the nodes directory: the run's name, T0, pace, duration and seed
RUNNING_NOTE = ("a real-time run writes run.rrd and these metrics when it ends; if the rig was killed, "
                "`hil recover {out}` rebuilds both from what the nodes recorded")


# The first words of the lines a node prints for the orchestrator: "ready" (pacing.handshake), the plant's
# "joined" (an external unit, JoinWait) and "fault" lines (hil/runtime/realtime/faults.py); anything else is the node's
# own code printing. An ECU or plant process's "alive" (pacing.Heartbeat) only stamps ``Node.last_alive``
# (hang_watch.py).
PROTOCOL_WORDS = frozenset({"ready", JOIN_LINE, "fault"})
PRINTED_TAIL_LINES = 20


class NodeError(RigDidNotStart):
    """A node failed to start or to become ready."""


@dataclass
class Node:
    """One node process and what it said."""

    name: str
    kind: str  # "plant" | "radio" | "ecu"
    proc: subprocess.Popen
    stderr_path: Path
    lines: "queue.Queue[str]" = field(default_factory=queue.Queue)
    ready: bool = False
    reported: bool = False
    #: the last lines the node's own code printed (a law's print calls), kept bounded: a chatty law costs no memory
    printed: "collections.deque[str]" = field(default_factory=lambda: collections.deque(maxlen=PRINTED_TAIL_LINES))
    printed_count: int = 0
    last_alive: float = field(default_factory=time.time)  # epoch s of its last "ready" or "alive" line
    held: bool = False  # stopped on purpose (an injected ecu_hang): the hang watch leaves it alone

    def start_reader(self) -> None:
        """Drain the node's stdout for as long as it lives: protocol lines ("ready") to ``lines``, heartbeats to
        ``last_alive``, the rest to the bounded ``printed`` tail (never left in the pipe, where a full pipe would
        block the node)."""
        stdout = self.proc.stdout
        assert stdout is not None  # started with stdout=PIPE

        def read() -> None:
            for line in stdout:
                line = line.strip()
                if line == ALIVE_LINE or line == "ready":
                    self.last_alive = time.time()
                    if line == ALIVE_LINE:
                        continue
                if line.partition(" ")[0] in PROTOCOL_WORDS:
                    self.lines.put(line)
                else:
                    self.printed.append(line)
                    self.printed_count += 1

        threading.Thread(target=read, name=f"stdout {self.name}", daemon=True).start()

    def tell(self, text: str) -> None:
        stdin = self.proc.stdin
        if stdin is None:
            return
        try:
            stdin.write(text + "\n")
            stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            pass

    def stderr_tail(self, lines: int = 30) -> str:
        """The last ``lines`` whole lines the node wrote on stderr (a traceback's end names the error)."""
        try:
            text = self.stderr_path.read_text(errors="replace").strip()
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


class _StopRequest:
    """SIGINT/SIGTERM/SIGHUP while running: remember it (the main loop polls) instead of raising mid-cleanup."""

    def __init__(self) -> None:
        self.requested: str | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> "_StopRequest":
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum: int, _frame) -> None:
        self.requested = signal.Signals(signum).name

    def __exit__(self, *exc) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h)


def run_name(scenario_name: str) -> str:
    """A fresh run name (its directory holds the bus sockets): the scenario's name, the pid and a random tag."""
    base = re.sub(r"[^A-Za-z0-9_.-]", "_", scenario_name).lstrip(".-")[:40] or "run"
    return f"{base}-{os.getpid()}-{secrets.token_hex(2)}"


def _run_result(log: RunLog, metrics: dict, out_dir: Path, files: list[Path]) -> RunResult:
    return RunResult(log, metrics, out_dir, files)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_ecus_per_process(n_ecus: int, cores: int | None = None, units_per_train: int | None = None,
                             pace: float = 1.0) -> int:
    """ECUs per process when the user does not say: one ECU process per core left after the bus servers (with
    the radio in them) and the plant take one, so the ECUs of a process share its wake-ups and no more Python
    processes start than the cores can run. Faster than real time (``pace`` > 1), no process hosts units of two
    trains (``units_per_train``): their units share their deadlines, and with a tenth of the wall time per cycle
    the processes' parallelism matters more than sharing wake-ups.

    Measured on 2 cores under SCHED_FIFO, alternated (``bench/bench_realtime_scale.py --ecus N --per-process ...``;
    docs/realtime-performance.md, "The default process layout"). Before the CPUs' idle latency was held: seed000's
    12 units in one process cost 0.13-0.16 CPU-s per simulated second against 0.18-0.19 for one process per train,
    ECU p99 0.51-0.68 ms against 0.65-0.74. With it held, one process against two: 32 and 48 ECUs (30 s) p99
    0.28-0.38 ms against 0.27-0.59, at less CPU; 64 ECUs (5 min) 0.48 (with 64 misses in a machine stall) to 1.38
    ms, median 0.79, in seven runs against 0.76 to 1.15, median 0.79, in five, at 0.32-0.37 CPU-s against 0.42-0.46;
    96 ECUs (30 s) 1.85 and 1.13 against 2.02 and 1.72; only 128 ECUs (30 s) did better in two (1.49 to 2.33 ms
    against 2.59 and 2.95). At pace 10 (``hil run seed000 --realtime --pace 10 --duration 300``, three pairs) one
    process missed more: 32-41 late plant publications of 30,000 against 23-35, ECU misses 35-159 against 1-52."""
    ecu_processes = max(1, (usable_cores() if cores is None else cores) - 1)
    per_process = max(1, math.ceil(n_ecus / ecu_processes))
    if pace <= 1.0 or units_per_train is None:
        return per_process
    return max(1, min(per_process, units_per_train))


def run_realtime(scenario: Scenario, out_dir: Path, *, pace: float = 1.0, duration_s: float | None = None,
                 seed: int | None = None, ecus_per_process: int | None = None, record: bool = True, progress: bool = False,
                 plant_spin_us: float = 200.0, on_start: Callable[[float], None] | None = None,
                 can_log: str | bool | None = None,
                 run: str | None = None, on_channels: Callable[[list[Channel]], None] | None = None,
                 live: LiveTarget | None = None, overrides: dict | None = None, source: str | None = None,
                 keep_signals: bool = True, radio_in_servers: bool = True, scheduling: SchedulingMode = "auto",
                 idle_latency_us: IdleLatencySetting = "auto", cpu_layout: CpuLayoutMode = "auto",
                 turns: TurnsMode = "auto"):
    """Run ``scenario`` on the real-time rig (see the module docstring); returns a ``hil.session.RunResult``.

    ``plant_spin_us``: on SocketCAN, the plant polls this long before each publication (0: sleep only); on the
    emulated buses it waits for its servers' SYNC instead. ``on_start(t0)`` is
    called with the epoch time of simulated t = 0 once every node is ready (tools, tests). ``can_log``: write
    ``<bus>.<asc|blf|mf4>`` per bus, frames stamped in simulated seconds as in a virtual-time run. ``run``: the run name
    (the python-can channel prefix; default: a fresh one); ``on_channels(channels)`` is called once the buses are
    up, before the nodes start, so that an external device can join (``ecu.external``). ``keep_signals=False``
    (``hil run``): the merge lets the signals and the bus rows go chunk by chunk once written, so
    ``result.log`` holds the last of them only. ``live``: stream the
    recording to a viewer as the run goes (hil/runtime/realtime/live_tail.py). ``radio_in_servers=False``: the
    radio as a node process on the emulated buses too, as before it moved into the servers (benchmarks compare).
    ``scheduling``: "auto" runs the serving thread and the nodes under SCHED_FIFO where the host permits it,
    "fifo" insists (SchedulingRefused otherwise), "normal" never does (hil/runtime/realtime/scheduling.py).
    ``idle_latency_us``: "auto" holds the CPUs' wake-up latency limit at 0 µs for a run at pace <= 1 where the host
    permits it (else the host's stays, said in the events), "host" leaves it, a number holds that many µs
    (IdleLatencyRefused where the host does not permit it; hil/runtime/realtime/idle_latency.py).
    ``cpu_layout``: "auto" keeps the serving thread and the plant on the first core the rig may use and the ECU
    processes on the others, at pace 1 or slower where it may use two or more; "none" leaves placement to the kernel
    (hil/runtime/realtime/cpu_layout.py). ``turns``: "on" makes each ECU cycle and plant publication the node's turn
    on the emulated buses (``frame_io.EngineFrames.read_every``): its frames go on the bus at its instant, the bus
    waiting for them up to ``TURN_HOLD_MAX_S`` of wall time; "off": when the node sends them; "auto" (the default):
    on faster than real time, off otherwise (``takes_turns``)."""
    if turns not in TURNS_MODES:
        raise ValueError(f"turns={turns!r} must be one of {', '.join(TURNS_MODES)}")
    if not (isinstance(pace, (int, float)) and 0 < pace < float("inf")):
        raise ValueError(f"pace={pace!r} must be a positive number (1.0 = wall clock)")
    if ecus_per_process is not None and ecus_per_process < 1:
        raise ValueError(f"ecus_per_process={ecus_per_process!r} must be >= 1")
    check_setting(idle_latency_us)  # a bad value: before anything runs
    if cpu_layout not in CPU_LAYOUT_MODES:
        raise ValueError(f"cpu_layout={cpu_layout!r} must be one of {', '.join(CPU_LAYOUT_MODES)}")
    idle = None  # IdleLatencyHold, while the run holds the CPUs' wake-up latency limit
    socketcan = scenario.can.transport == "socketcan"
    took_turns = takes_turns(turns, pace, socketcan)
    fmt = log_format(can_log)
    db = load_train_db(scenario)  # the DBC fits the scenario, before any process starts
    if socketcan:  # configuration only: every node opens the host's interfaces; no bus servers
        check_channels(scenario.can.socketcan_channels, scenario.trains.count)
        if fmt is not None:
            raise ValueError("can_log needs the emulated transport (with socketcan, use python -m can.logger -i socketcan)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    duration = scenario.duration_s if duration_s is None else float(duration_s)
    seed = scenario.seed if seed is None else seed
    layout = TrainLayout.from_config(scenario.trains)
    nodes_dir = out_dir / "nodes"
    shutil.rmtree(nodes_dir, ignore_errors=True)
    nodes_dir.mkdir()
    (nodes_dir / "scenario.json").write_text(scenario.model_dump_json())
    mark_running(out_dir / "metrics.json", scenario.name, "realtime",  # replaced by the metrics when the run ends
                 note=RUNNING_NOTE.format(out=out_dir))
    remove_stale_run_dirs()  # left by a rig that was killed (kill -9): its sockets accept no one
    run = run_name(scenario.name) if run is None else validate_name(run, "run")
    external = [layout.unit_index(name) for name in scenario.ecu.external]
    join = None  # JoinWait, while external units are expected
    sc_ = scenario.can
    servers: list[BusServer] = []
    radio = None  # EngineRadio: the radio in the bus servers (emulated buses, two trains or more)
    radio_stats = None  # its links' counters at the end
    sched = None  # Scheduling: what the serving thread and the nodes run under
    cpus = None  # CpuLayout: which cores the serving thread, the plant and the ECU processes run on (None: any)
    nodes: list[Node] = []
    events: list[Event] = []
    wall0 = time.perf_counter()
    t0 = None
    run_wall = 0.0
    stop_reason = None
    clock = {"t0": math.inf}  # epoch of simulated t = 0, once known (the CAN logs' time origin)
    faults = None  # hil.runtime.realtime.faults.RealtimeFaults when the scenario has faults or a restart policy
    tail = None  # LiveTail, with a live target once the run has started
    spool = None  # BusSpool, once the servers are up
    asc: list = []
    try:
        with _StopRequest() as stop:
            if not socketcan and layout.n_trains > 1 and radio_in_servers:
                radio = EngineRadio(scenario, db, seed, pace, bus_packing(scenario, db), save_to=nodes_dir)
            serving = None if socketcan else engine.ServingThread()  # every bus on one thread: shared wake-ups
            sched = choose_scheduling(scheduling, None if serving is None else serving.native_id)
            events.append(Event(0.0, "INFO", "rig", f"scheduling: {sched.describe()}"))
            cpus = place_serving_thread(choose_cpu_layout(cpu_layout, pace=pace), serving, events)
            idle, said = hold_for_run(idle_latency_us, pace)
            events.append(Event(0.0, "INFO", "rig", said))
            events.append(Event(0.0, "INFO", "rig", f"turns: {turns_text(turns, pace, socketcan)}"))
            for i in range(0 if socketcan else layout.n_trains):
                server = NativeBusServer(run, f"bus{i + 1}", sc_.bitrate, sc_.queue_policy, sc_.tx_queue_depth,
                                    extended=sc_.extended_ids, spin_us=0, pace=pace, log=BusLog(f"bus{i + 1}", sc_.bitrate),
                                    fd=sc_.fd, data_bitrate=sc_.data_rate if sc_.fd else None,
                                    radio=radio.port(i) if radio is not None else None, serving_thread=serving)
                if fmt is not None:
                    asc.append(_attach_can_log(server, i, out_dir, clock, pace, fmt))
                record_bus_warnings(server, events, f"bus{i + 1}", clock, pace)
                servers.append(server.start(pump_thread=False))  # pumped by the supervising loop
            faults = _faults(scenario, layout, servers, seed, db, radio)
            spool = BusSpool(servers, nodes_dir, pace)  # the servers' frame rows to files as the run goes
            if on_channels is not None:
                on_channels(channels(run, scenario))
            env = node_environment(scenario)
            node_args = _node_arguments(run, nodes_dir, seed, duration, pace, sched.policy == "fifo", took_turns)
            nodes = _start_nodes(layout, nodes_dir, node_args, planned_ecu_processes(scenario, ecus_per_process, pace),
                                 plant_spin_us, env, radio_node=radio is None, cpus=cpus)
            say = (lambda text: print(f"real-time rig {run}: {text}", file=sys.stderr)) if progress else None
            if say is not None:
                say(f"{len(nodes)} node processes, pace {pace:g}, {sched.describe()}; {said}; "
                    f"{cpus.describe() if cpus is not None else 'CPU layout: none'}; "
                    f"turns {turns_text(turns, pace, socketcan)}" + (
                    f"; waiting up to {scenario.ecu.join_timeout_s:g} s for external unit(s) "
                    f"{', '.join(scenario.ecu.external)}" if external else ""))
            _wait_ready(nodes, stop)
            if external:
                ready = time.time()
                join = JoinWait(layout, external, scenario.ecu.join_timeout_s, nodes[0].lines, ready, say)
                if servers:  # the emulated buses: t = 0 once the external units' buses have their clients
                    wait_for_connections(servers, layout, external, sum(n.kind == "radio" for n in nodes),
                                         ready + scenario.ecu.join_timeout_s, lambda: stop.requested is not None, say)
            if not stop.requested:
                t0 = clock["t0"] = time.time() + GO_MARGIN_S
                for bus_server in servers:  # their load windows end where virtual time's do: t = k x the window
                    bus_server.align_load_windows(t0)
                write_json_atomic(nodes_dir / RUN_FILE, {  # what hil recover needs
                    "run": run, "t0": t0, "pace": pace, "duration_s": duration, "seed": seed,
                    "buses": {s.log.name: {"epoch0": s.epoch0, "bitrate": s.log.bitrate} for s in servers}})
                for n in nodes:
                    n.tell(f"go {t0!r}")
                if on_start is not None:
                    on_start(t0)
                if faults is not None:
                    faults.go(t0, pace, nodes, _respawn(nodes_dir, node_args, layout, env, cpus))
                if live is not None:
                    tail = LiveTail(live, scenario, layout, nodes_dir, (t0, pace), run)
                    if say is not None:
                        say(live.describe())
                ticks = [f for f in (faults.tick if faults is not None else None, tail.poll if tail else None,
                                     _pumps(servers), spool.tick) if f]
                hangs = HangWatch(hung_after_s(max(scenario.ecu.cycle_s, scenario.can.sensor_period_s), pace), t0)
                stop_reason = _supervise(nodes, t0, pace, duration, stop, events, progress,
                                         _all_of(ticks) if ticks else None, join,
                                         FAULT_TICK_S if faults is not None else min(SUPERVISE_S, spool.every_wall_s),
                                         hangs)
                run_wall = time.time() - t0  # from simulated t = 0 to the end (realtime_factor ~ pace)
            else:
                stop_reason = stop.requested
            if faults is not None:
                faults.release()
            _stop_nodes(nodes)
    except RigDidNotStart as exc:  # the rig never ran: say so, not "running" (which would point to hil recover)
        mark_failed(out_dir / "metrics.json", scenario.name, "realtime", str(exc))
        raise
    finally:
        if idle is not None:
            idle.close()
        _kill_all(nodes)
        final_stats = [s.stats for s in servers]
        server_stats = {s.log.name: st.as_dict(t0, pace) for s, st in zip(servers, final_stats)}
        if spool is not None:
            spool.close()
        for s in servers:
            s.close()
        if radio is not None:
            radio_stats = _close_radio(radio, events)
        for w in asc:
            w.stop()
        remove_run_dir(run)
    wall = run_wall if t0 is not None else time.perf_counter() - wall0
    let_go = turns_let_go_text(final_stats)
    given_up = turns_given_up(final_stats, t0, pace) if t0 is not None else None
    if spool is not None and spool.lost:
        events.append(Event(0.0, "ERROR", "rig", f"bus rows spooled only until the disk filled ({spool.lost})"))
    full = None  # a DiskFullError from writing the recording: the metrics are still merged and written
    rrd, log = None, None
    files = [log_path(out_dir, f"bus{i + 1}", fmt) for i in range(len(asc))] if fmt else []
    try:
        rrd = open_recording(scenario, layout, out_dir / "run.rrd", None if t0 is None else (t0, pace),
                             [s.log.name for s in servers]) if record else None
        sinks = ([(rrd, 0)] if rrd is not None else []) + ([(tail.writer, tail.sent)] if tail is not None else [])
        log, extra = merge_nodes(scenario, layout, nodes_dir, servers, events, t0, pace, duration, wall, stop_reason,
                                 sinks, keep_rows=keep_signals, radio_stats=radio_stats)
        _finish_log(log, faults, t0, pace, scenario, let_go, given_up)
        for writer, _ in sinks:  # the rest to the recording and the viewer: events, timing
            write_rest(writer, log, nodes_dir)
    except DiskFullError as exc:  # run.rrd filled the disk (its writer cuts it): the metrics are merged all the same
        full = exc
        if log is None:  # it filled during the merge: again, without the recording
            log, extra = merge_nodes(scenario, layout, nodes_dir, servers, events, t0, pace, duration, wall,
                                     stop_reason, [], keep_rows=False, radio_stats=radio_stats)
            _finish_log(log, faults, t0, pace, scenario, let_go, given_up)
        log.events.append(Event(log.sim_time_s, "ERROR", "rig", f"run.rrd cut: {exc.strerror}"))
    extra["realtime"]["bus_servers"] = server_stats
    if sched is not None:
        extra["realtime"]["scheduling"] = sched.as_dict()
    extra["realtime"]["idle_latency_us"] = None if idle is None else idle.limit_us  # None: the host's
    extra["realtime"]["cpu_layout"] = None if cpus is None else cpus.as_dict()  # None: the kernel placed everything
    extra["realtime"]["turns"] = took_turns
    if rrd is not None:
        rrd.close()
        files.append(out_dir / "run.rrd")
    if tail is not None:
        tail.close()
    metrics = run_metrics(log, scenario, "realtime", seed, pace=float(pace), overrides=overrides, source=source)
    metrics.update(extra)
    if stop_reason and stop_reason not in SIGNAL_NAMES:
        metrics["stopped_early"] = stop_reason  # a node died or hung: the run could not go on (hil run: exit 1)
    missing = join.missing() if join is not None and join.waiting and not stop.requested else None
    if missing is not None:
        metrics["error"] = f"ExternalUnitMissing: {stop_reason or missing}"
    if full is not None:
        metrics["error"] = f"DiskFullError: {full.strerror}"
        raise disk_full_outcome(out_dir, write_metrics_when_full(out_dir / "metrics.json", metrics), log.sim_time_s)
    write_json_atomic(out_dir / "metrics.json", metrics)
    files.append(out_dir / "metrics.json")
    if missing is not None:
        raise ExternalUnitMissing(f"{stop_reason or missing} (what ran is in {out_dir}): start the external program "
                                  "once the rig has printed its channels, or raise ecu.join_timeout_s")
    return _run_result(log, metrics, out_dir, files)


def _all_of(ticks: list[Callable[[float], None]]) -> Callable[[float], None]:
    """One tick that runs every one of ``ticks``."""
    def tick(t: float) -> None:
        for f in ticks:
            f(t)

    return tick


def _pumps(servers: list[BusServer]) -> Callable[[float], None]:
    """One tick that pumps every server (started without a pump thread) every ``PUMP_S`` of wall time: one wake-up
    of the supervising loop does what a thread per bus did."""
    due = [0.0]

    def tick(_sim_now: float) -> None:
        if (now := time.monotonic()) >= due[0]:
            due[0] = now + PUMP_S
            for s in servers:
                s.pump()

    return tick


def _finish_log(log: RunLog, faults, t0: float | None, pace: float, scenario: Scenario,
                let_go: str | None = None, given_up: tuple[float, str] | None = None) -> None:
    """The merged log's fault report, the turns let go (``let_go``, at the end), when they were given up
    (``given_up``: its time and text) and its safety violations on the timeline."""
    if faults is not None:
        faults.finish(log, t0, pace)
    if given_up is not None:
        log.events.append(Event(given_up[0], "WARN", "rig", given_up[1]))
    if let_go:
        log.events.append(Event(log.sim_time_s, "WARN", "rig", let_go))
    record_violations(log, scenario.plant.coupler_band_m)


@dataclass(frozen=True)
class Channel:
    """Where a python-can program joins one train's bus: ``can.Bus(interface=..., channel=...)``."""

    bus: str  # "bus1"
    train: int  # 1-based
    interface: str  # "trainhil" or "socketcan"
    channel: str  # "<run>/bus1", or the host interface ("vcan0")

    def line(self) -> str:
        """The ``key=value`` line ``hil run --realtime`` prints on stdout for scripts."""
        return f"channel bus={self.bus} train={self.train} interface={self.interface} channel={self.channel}"


def channels(run: str, sc: Scenario) -> list[Channel]:
    """The python-can channels of a run's train buses."""
    if sc.can.transport == "socketcan":
        return [Channel(f"bus{i + 1}", i + 1, "socketcan", ch) for i, ch in enumerate(sc.can.socketcan_channels)]
    return [Channel(f"bus{i + 1}", i + 1, "trainhil", f"{run}/bus{i + 1}") for i in range(sc.trains.count)]


def node_environment(sc: Scenario) -> dict[str, str]:
    """The node processes' environment: ours, with the folders the scenario's ``module:QualName`` references are
    imported from in ``TRAINHIL_USER_PATH``, which a node searches *after* its ``sys.path`` (each node resolves the
    references itself). Not on ``PYTHONPATH``: a folder there comes before the installed packages, so any module
    in it would shadow them."""
    env = dict(os.environ)
    roots = [str(r) for r in import_roots(sc)]
    if roots:
        env[USER_PATH_ENV] = os.pathsep.join([*roots, *filter(None, [env.get(USER_PATH_ENV)])])
    return env


def record_bus_warnings(server: NativeBusServer, events: list[Event], bus: str, clock: dict, pace: float,
                        limit: int = BUS_WARNINGS_MAX) -> None:
    """Make the server's warnings the run's WARN events from ``bus``: a node that left with frames in its TX queue
    (how many were lost), a frame the bus cannot carry, bad input. Each is timed when it happened (the engine stamps
    it; one before t = 0 at 0), though reported up to a pump period later. The first ``limit`` are recorded, then one
    that says the rest are not (a client that reconnects again and again cannot fill memory; the server's counters
    still count everything)."""
    said = [0]
    to_seconds = sim_seconds(server, clock, pace)

    def on_message(level: str, text: str, t_ns: int) -> None:
        if level != "WARNING" or said[0] > limit:
            return
        said[0] += 1
        t = max(0.0, to_seconds(t_ns)) if math.isfinite(clock["t0"]) else 0.0
        if said[0] > limit:
            text = f"more than {limit} warnings from this bus: the rest are not recorded (its counters have them)"
        events.append(Event(t, "WARN", bus, re.sub(r"^bus \S+: ", "", text)))  # the source names the bus

    server.on_message = on_message


def sim_seconds(server: BusServer, clock: dict, pace: float) -> Callable[[int], float]:
    """The run's simulated seconds of a time the server stamps (ns since its zero): it happened at wall time
    ``epoch0 + t_ns / pace``, and the run's simulated time is (wall - t0) x pace (t0: ``clock["t0"]``, read at each
    call, as it is set when the run goes)."""
    epoch0 = server.epoch0

    def to_seconds(t_ns: int) -> float:
        return (epoch0 + t_ns * 1e-9 / pace - clock["t0"]) * pace

    return to_seconds


def _attach_can_log(server: BusServer, i: int, out_dir: Path, clock: dict, pace: float, fmt: str):
    """Log every frame of ``server`` to ``bus<i+1>.<fmt>`` in simulated seconds (written by the server's thread)."""
    writer = open_can_log(out_dir, f"bus{i + 1}", i, "real time", fmt)
    server.frame_listeners.append(frame_listener(writer, i, sim_seconds(server, clock, pace)))
    return writer


# --------------------------------------------------------------------------- processes


def _close_radio(radio: EngineRadio, events: list[Event]) -> dict[str, dict[str, int]]:
    """The engine's radio stops; its links' counters, for the merge (and in ``radio.json`` if the disk allows)."""
    radio.close()
    radio.save()
    if radio.starved:
        events.append(Event(0.0, "ERROR", "radio", f"{radio.starved} radio frames dropped: the links' random "
                                                   "numbers were not topped up in time"))
    return radio.stats()


def _faults(scenario: Scenario, layout: TrainLayout, servers: list[BusServer], seed: int, db: TrainDb,
            radio: EngineRadio | None = None):
    """The run's fault machinery (hil/runtime/realtime/faults.py), or None without faults and restart policy."""
    from hil.runtime.realtime.faults import RealtimeFaults
    from hil.faults.schedule import BUS_KINDS

    if not needs_fault_machinery(scenario):
        return None
    if not servers and any(f.train for f in scenario.faults if f.kind in BUS_KINDS):
        raise ValueError("bus faults need the emulated transport (can.transport = \"emulated\")")

    return RealtimeFaults(scenario, layout, servers, seed, db, radio)


def _node_arguments(run: str, nodes_dir: Path, seed: int, duration: float, pace: float, fifo: bool,
                    turns: bool = False) -> list[str]:
    """The arguments every node process of a run takes (``hil.runtime.realtime.node.node_parser``)."""
    return ["--run", run, "--scenario-json", str(nodes_dir / "scenario.json"), "--seed", str(seed),
            "--duration", repr(duration), "--pace", repr(pace), "--out", str(nodes_dir), *(["--fifo"] if fifo else []),
            *(["--turns"] if turns else [])]


def _respawn(nodes_dir: Path, common: list[str], layout: TrainLayout, env: dict[str, str],
             cpus: CpuLayout | None = None):
    """spawn(unit): a late-joining ECU process for a restarted unit, started as every node is (``launch_node``)."""
    serial = iter(range(1, 1 << 30))

    def spawn(u: int) -> Node:
        argv = ["hil.runtime.realtime.ecu_node", *common, *_cpu_arguments(cpus, "ecu"), "--unit", str(u), "--join-late"]
        return launch_node(layout.unit_name(u), "ecu", argv, nodes_dir / f"ecu_restart_{next(serial)}.stderr", env)

    return spawn


def place_serving_thread(cpus: CpuLayout | None, serving, events: list[Event]) -> CpuLayout | None:
    """Put the serving thread (None on SocketCAN) on the layout's rig cores and say the layout in the run's events;
    the layout the nodes follow (None when there is none, or the serving thread could not be placed)."""
    if cpus is None:
        events.append(Event(0.0, "INFO", "rig", "CPU layout: none (the kernel places every process)"))
        return None
    if serving is not None and (why := pin(cpus.rig, serving.native_id)) is not None:
        events.append(Event(0.0, "WARN", "rig", f"CPU layout not applied: the serving thread cannot run on "
                                                f"{format_cores(cpus.rig)} ({why})"))
        return None
    events.append(Event(0.0, "INFO", "rig", cpus.describe()))
    return cpus


def _cpu_arguments(cpus: CpuLayout | None, kind: str) -> list[str]:
    """A node's ``--cpus`` for its kind in the run's CPU layout (none without one)."""
    return [] if cpus is None else ["--cpus", format_cores(cpus.cores_for(kind))]


def _start_nodes(layout: TrainLayout, nodes_dir: Path, common: list[str], ecu_processes: list[list[int]],
                 spin_us: float, env: dict[str, str] | None = None, radio_node: bool = False,
                 cpus: CpuLayout | None = None) -> list[Node]:
    """The plant first (``nodes[0]``), the radio (``radio_node``: on SocketCAN; on the emulated buses the radio is
    in the bus servers), then one ECU process for each of ``ecu_processes`` (its flat units:
    ``planned_ecu_processes``). ``common``: ``_node_arguments``; ``cpus``: the run's CPU layout (each node is told
    its cores)."""
    specs = [("plant", "plant", ["hil.runtime.realtime.plant_node", "--spin-us", repr(spin_us)])]
    if radio_node and layout.n_trains > 1:
        specs.append(("radio", "radio", ["hil.runtime.realtime.radio_node"]))
    for group in ecu_processes:
        names = ",".join(layout.unit_name(u) for u in group)
        specs.append((names, "ecu", ["hil.runtime.realtime.ecu_node", *[a for u in group for a in ("--unit", str(u))]]))
    return [launch_node(name, kind, [argv[0], *common, *_cpu_arguments(cpus, kind), *argv[1:]],
                        nodes_dir / f"{kind}_{i}.stderr", env)
            for i, (name, kind, argv) in enumerate(specs)]


def ecu_process_units(layout: TrainLayout, per_process: int, solo=(), external=()) -> list[list[int]]:
    """The flat units of each ECU process: ``per_process`` at a time, front to back; a unit with an ECU fault
    (``solo``) in a process of its own (the fault kills or stops that process); an ``external`` unit in none."""
    units = [u for u in range(layout.n_units) if u not in solo and u not in external]
    return [units[k:k + per_process] for k in range(0, len(units), per_process)] + [[u] for u in sorted(solo)]


def planned_ecu_processes(scenario: Scenario, ecus_per_process: int | None = None,
                          pace: float = 1.0) -> list[list[int]]:
    """The flat units of each ECU process a real-time run of ``scenario`` starts (``hil run --realtime`` builds
    each group's firmware together before the run: ``check_firmware``)."""
    from hil.runtime.realtime.faults import solo_units

    layout = TrainLayout.from_config(scenario.trains)
    external = [layout.unit_index(name) for name in scenario.ecu.external]
    per_process = ecus_per_process or default_ecus_per_process(layout.n_units - len(external),
                                                               units_per_train=scenario.trains.units, pace=pace)
    return ecu_process_units(layout, per_process, solo_units(scenario, layout), external)


def launch_node(name: str, kind: str, argv: list[str], stderr_path: Path, env: dict[str, str] | None) -> Node:
    """Start one node process (``argv``: its module and arguments) with its stdout drained and its stderr to a file.

    Through ``node_start``, which imports python-can without asammdf (a node writes no CAN log). ``python -P``:
    the working folder is not put on the node's ``sys.path``, so a module planted there (a ``cantools.py``) is
    never imported in place of the real one; the user's own modules are found by the documented rule
    (``ecu_sim.references``: after ``sys.path``). Its own session: a terminal's Ctrl-C reaches only the
    orchestrator, which stops the nodes."""
    command = [sys.executable, "-P", "-m", "hil.runtime.realtime.node_start", *argv]
    with open(stderr_path, "w") as fh:
        proc = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=fh, text=True,
                                bufsize=1, env=env, start_new_session=True)
    node = Node(name, kind, proc, stderr_path)
    node.start_reader()
    return node


def _wait_ready(nodes: list[Node], stop: _StopRequest) -> None:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while not all(n.ready for n in nodes) and not stop.requested:
        for n in nodes:
            while not n.lines.empty():
                if n.lines.get() == "ready":
                    n.ready = True
            if not n.ready and n.proc.poll() is not None:
                if stop.requested:
                    return
                raise NodeError(f"{n.kind} node {n.name} exited with code {n.proc.returncode} before it was ready:\n"
                                + _indent(n.stderr_tail() or "(nothing on its stderr)"))
        if time.monotonic() > deadline:
            late = ", ".join(f"{n.kind} {n.name}" for n in nodes if not n.ready)
            raise NodeError(f"nodes not ready after {READY_TIMEOUT_S:.0f} s: {late}")
        time.sleep(0.02)


def _indent(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())


def _supervise(nodes: list[Node], t0: float, pace: float, duration: float, stop: _StopRequest,
               events: list[Event], progress: bool, on_tick: Callable[[float], None] | None = None,
               join: JoinWait | None = None, every_s: float = SUPERVISE_S,
               hangs: HangWatch | None = None) -> str | None:
    """Wait for the end of the run; report early exits. Returns why the run stopped early (None: completed).
    The loop turns every ``every_s`` wall seconds (FAULT_TICK_S with fault injection, else SUPERVISE_S or a spool
    period, the shorter: the rig's processes share two cores with it), every END_POLL_S once the run's time is
    over; ``on_tick(sim_now)`` runs every turn; ``join`` stops the run when an external unit has not joined in
    time; ``hangs`` kills the ECU and plant processes whose events stopped (a hung plant stops the run)."""
    end_wall = t0 + duration / pace
    bar = _progress_bar(duration) if progress else None
    try:
        while True:
            now = time.time()
            sim_now = max((now - t0) * pace, 0.0)
            if bar is not None:
                bar.update(round(min(sim_now, duration), 1) - bar.n)  # drawn at most every mininterval
            if stop.requested:
                return stop.requested
            if join is not None and (why := join.poll(now)):
                events.append(Event(sim_now, "ERROR", "rig", f"run stopped: {why}"))
                return why
            for n in nodes:
                code = n.proc.poll()
                if code is not None and not n.reported and (code != 0 or now < end_wall - 0.5):
                    n.reported = True
                    tail = n.stderr_tail(10)
                    # an ECU process's every unit stopped: one event each (the safety verdict counts units)
                    for name in n.name.split(",") if n.kind == "ecu" else [n.name]:
                        text = f"{'ECU' if n.kind == 'ecu' else n.kind} process {name} exited with code {code}"
                        events.append(Event(sim_now, "ERROR", "rig", text + (f": {tail}" if tail and code > 0 else "")))
                    if n.kind != "ecu":
                        return f"{n.kind} node exited"
            if hangs is not None and now < end_wall and (why := hangs.check(nodes, now, sim_now, events)):
                return why
            if all(n.proc.poll() is not None for n in nodes):
                return None
            if on_tick is not None:
                on_tick(sim_now)
            if now > end_wall + STOP_GRACE_S:
                late = ", ".join(f"{n.kind} {n.name}" for n in nodes if n.proc.poll() is None)
                return f"nodes did not finish: {late}"
            time.sleep(every_s if now < end_wall else min(every_s, END_POLL_S))
    finally:
        if bar is not None:
            bar.close()


def _stop_nodes(nodes: list[Node]) -> None:
    """Ask every live node to stop and give it time to write its results."""
    for n in nodes:
        if n.proc.poll() is None:
            n.tell("stop")
    deadline = time.monotonic() + STOP_GRACE_S
    for n in nodes:
        try:
            n.proc.wait(max(deadline - time.monotonic(), 0.01))
        except subprocess.TimeoutExpired:
            pass


def _kill_all(nodes: list[Node]) -> None:
    """Terminate, then kill, whatever still runs; close the pipes. No orphans."""
    live = [n for n in nodes if n.proc.poll() is None]
    for n in live:
        n.tell("stop")
        n.proc.terminate()
    deadline = time.monotonic() + KILL_GRACE_S
    for n in live:
        try:
            n.proc.wait(max(deadline - time.monotonic(), 0.01))
        except subprocess.TimeoutExpired:
            n.proc.kill()
            n.proc.wait()
    for n in nodes:
        for f in (n.proc.stdin, n.proc.stdout):
            try:
                if f is not None:
                    f.close()
            except (OSError, ValueError):
                pass


def _progress_bar(total: float):
    from tqdm import tqdm

    # a terminal redraws in place; a file or pipe gets a line per redraw, so fewer of them there
    return tqdm(total=total, unit="s", desc="real time (sim s)", mininterval=0.1 if sys.stderr.isatty() else 5.0,
                bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}]")


# --------------------------------------------------------------------------- merging

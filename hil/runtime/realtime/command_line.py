"""Command line of the real-time rig's pieces: ``hil bus-server`` (also ``python -m hil.runtime.realtime.bus_server``).

``add_bus_server_parser(subparsers)`` registers the sub-command on the ``hil`` parser; ``bus_server_main`` is the
standalone entry. The server runs until SIGINT/SIGTERM (or ``--duration``), then prints its statistics and,
with ``--stats-json``, writes them. It prints ``ready <socket path>`` once nodes can connect.
"""
from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from pathlib import Path

from hil.cli_values import positive_int, positive_number, positive_seconds
from hil.runtime.realtime.bus_server import DEFAULT_SPIN_US
from hil.runtime.realtime.cpu_layout import CPU_LAYOUT_MODES
from hil.runtime.realtime.idle_latency import latency_us
from hil.runtime.realtime.native_server import NativeBusServer
from hil.runtime.realtime.scheduling import PRIORITIES, SCHEDULING_MODES, SchedulingRefused, choose_server_scheduling
from hil.runtime.realtime.sockets import BusServerError, remove_run_dir
from hil.runtime.realtime.turns import TURNS_MODES

DESCRIPTION = ("Serve one emulated CAN bus in wall-clock time. python-can nodes join it with "
               "can.Bus(interface='trainhil', channel='<run>/<bus>').")


def _fifo_priority(text: str) -> int:
    """A SCHED_FIFO priority: a whole number from 1 to 99."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= 99:
        raise argparse.ArgumentTypeError(f"{text!r} is not a SCHED_FIFO priority (a whole number from 1 to 99)")
    return value


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", required=True, help="run name: the socket is <runtime root>/<run>/<bus>.sock")
    p.add_argument("--bus", required=True, help="bus name, e.g. bus1 (python-can channel \"<run>/<bus>\")")
    p.add_argument("--bitrate", type=positive_int, default=500_000, help="bit/s (default 500000)")
    p.add_argument("--fd", action="store_true", help="a CAN FD bus: nodes send classical and CAN FD frames (python-can fd=True)")
    p.add_argument("--data-bitrate", type=positive_int, metavar="BIT/S",
                   help="with --fd: the data phase's bitrate of frames with BRS (default: --bitrate)")
    p.add_argument("--policy", choices=("priority", "fifo"), default="priority", help="TX queue policy per node")
    p.add_argument("--depth", type=positive_int, default=64, help="TX queue depth per node (default 64)")
    p.add_argument("--scheduling", choices=SCHEDULING_MODES, default="auto",
                   help="auto (default): serve under SCHED_FIFO where the host permits it, else under the normal "
                        "scheduler; fifo: insist (exit 1 where refused); normal: never")
    p.add_argument("--fifo", type=_fifo_priority, metavar="PRIORITY",
                   help=f"the SCHED_FIFO priority (1-99, default {PRIORITIES['bus servers']}); a refusal is "
                        "warned about")
    p.add_argument("--spin-us", type=float, default=None,
                   help="spin the last microseconds before a frame ends (default: 0 under SCHED_FIFO, which wakes "
                        f"on time; {DEFAULT_SPIN_US} under the normal scheduler; 0: never spin)")
    p.add_argument("--pace", type=positive_number, default=1.0,
                   help="model seconds per wall second (default 1.0; 0.5: frames last twice as long in wall time)")
    p.add_argument("--duration", type=positive_seconds, help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--stats-json", help="write the final statistics to this JSON file")
    p.add_argument("--verbose", action="store_true", help="log nodes joining and leaving")
    p.add_argument("--tcp", action="store_true",
                   help="also listen on loopback TCP; host, port and the run's token go to <run dir>/<bus>.tcp (mode 0600)")
    p.add_argument("--tcp-host", default="127.0.0.1", help="with --tcp: 127.0.0.1 (default) or ::1; nothing else")


def add_bus_server_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``hil bus-server`` on the ``hil`` parser's sub-parsers; returns the new parser."""
    p = subparsers.add_parser("bus-server", help="serve one emulated CAN bus in real time (python-can: trainhil)",
                              description=DESCRIPTION)
    _add_arguments(p)
    p.set_defaults(func=cmd_bus_server)
    return p


def _print_stats(stats: dict) -> None:
    def fmt(v):
        return "-" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)

    print(f"bus {stats['channel']} ({stats['bitrate']} bit/s): " + ", ".join(
        f"{k}={fmt(v)}" for k, v in stats.items() if k not in ("channel", "bitrate")))


def cmd_bus_server(args: argparse.Namespace, server_cls=NativeBusServer) -> int:
    """Serve until a signal or the duration; exit 2 with one message on bad arguments or a taken socket.
    ``server_cls``: the engine's server; the tests' oracle server runs through here too."""
    if args.verbose:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.data_bitrate is not None and not args.fd:
        print("hil bus-server: error: --data-bitrate is for CAN FD buses: add --fd", file=sys.stderr)
        return 2
    if args.fifo is not None and args.scheduling == "normal":
        print("hil bus-server: error: --fifo PRIORITY with --scheduling normal: choose one", file=sys.stderr)
        return 2
    try:  # before the serving thread starts: it inherits it
        sched = choose_server_scheduling(args.scheduling, PRIORITIES["bus servers"] if args.fifo is None else args.fifo)
    except (SchedulingRefused, ValueError) as exc:
        print(f"hil bus-server: error: {exc}", file=sys.stderr)
        return 1 if isinstance(exc, SchedulingRefused) else 2
    if args.fifo is not None and sched.policy == "normal":
        print(f"hil bus-server: warning: {sched.why_normal}; running under the normal scheduler", file=sys.stderr)
    spin_us = args.spin_us if args.spin_us is not None else 0 if sched.policy == "fifo" else DEFAULT_SPIN_US
    try:
        server = server_cls(args.run, args.bus, args.bitrate, args.policy, args.depth, spin_us=spin_us,
                            keep_log=False, pace=args.pace, tcp=args.tcp, tcp_host=args.tcp_host, fd=args.fd,
                            data_bitrate=args.data_bitrate)
    except (ValueError, OSError, BusServerError) as exc:
        print(f"hil bus-server: error: {exc}", file=sys.stderr)
        return 2
    previous = {s: signal.signal(s, lambda *_: server.shutdown(wait=False)) for s in (signal.SIGINT, signal.SIGTERM)}
    timer = threading.Timer(args.duration, server.shutdown) if args.duration else None
    try:
        print(f"ready {server.path}" + (f" tcp {server.tcp_address[0]}:{server.tcp_address[1]} token-file "
                                        f"{server.token_file}" if args.tcp else ""), flush=True)
        if timer:
            timer.daemon = True
            timer.start()
        server.serve_forever()
    finally:
        if timer:
            timer.cancel()
        for s, h in previous.items():
            signal.signal(s, h)
        stats = {**server.stats.as_dict(), "scheduling": sched.policy, "spin_us": spin_us}
        server.close()
        remove_run_dir(args.run)  # if no other server of the run is left in it
    _print_stats(stats)
    if args.stats_json:
        Path(args.stats_json).write_text(json.dumps(stats, indent=1))
    return 0


def add_realtime_arguments(run: argparse.ArgumentParser) -> None:
    """Add ``--realtime`` and its options (``--pace``, ``--ecus-per-process``, ``--scheduling`` ...) to ``hil run``."""
    g = run.add_argument_group("real time (HIL)")
    g.add_argument("--realtime", action="store_true",
                   help="run on the real-time rig: bus servers, radio, plant and ECU processes paced to the wall clock")
    g.add_argument("--pace", type=positive_number, default=None,
                   help="with --realtime: simulated seconds per wall second (default 1.0 = wall clock; 0.5 slower, 10 faster)")
    g.add_argument("--ecus-per-process", type=positive_int, default=None, metavar="N",
                   help="with --realtime: host N ECUs per process (default: one ECU process per core left after "
                        "the bus servers, plant and radio; faster than real time one train's units at most in each)")
    g.add_argument("--scheduling", choices=SCHEDULING_MODES, default=None,
                   help="with --realtime: auto (the default) runs the bus servers, plant and ECU processes under "
                        "SCHED_FIFO where the host permits it, else under the normal scheduler; fifo: SCHED_FIFO or "
                        "exit 1; normal: never")
    g.add_argument("--idle-latency-us", type=latency_us, default=None, metavar="US",
                   help="with --realtime: the CPUs' wake-up latency limit for the run (/dev/cpu_dma_latency, as "
                        "cyclictest holds it). auto (the default) holds 0 at pace 1 or slower where the host permits it "
                        "(root), so idle CPUs poll instead of halting: wake-ups cost less, but the CPUs never rest; "
                        "host leaves the host's; a number of microseconds holds that or exits 1")
    g.add_argument("--cpu-layout", choices=CPU_LAYOUT_MODES, default=None,
                   help="with --realtime: auto (the default) keeps the bus servers and the plant on the first core the "
                        "rig may use and the ECU processes on the others (at pace 1 or slower, where it may use two "
                        "or more); none: the kernel places every process")
    g.add_argument("--turns", choices=TURNS_MODES, default=None,
                   help="with --realtime: on: each ECU cycle and plant publication is a turn, whose frames go on the "
                        "bus at its instant however long the node's Python takes (the bus waits up to 2 ms of wall "
                        "time for it), so the loop is virtual time's while the nodes keep up; off: frames go on the "
                        "bus when the node sends them, after its work; auto (the default): on faster than real time "
                        "(--pace above 1), off otherwise")
    g.add_argument("--external", action="append", default=[], metavar="UNIT",
                   help="with --realtime: leave UNIT (e.g. train2/unit3) without an emulated ECU, for an external "
                        "program or device on the bus (adds to ecu.external; repeatable)")
    g.add_argument("--run", dest="run_name", metavar="NAME",
                   help="with --realtime: the run name, i.e. the python-can channel prefix NAME/bus1 (default: fresh)")


def check_realtime_args(args: argparse.Namespace, scenario) -> None:
    """ScenarioError (``hil`` prints it, exit 2) naming a ``hil run --realtime`` option that does not combine with it
    or with the scenario: checked before the output folder is touched, so a bad option loses no previous run."""
    from hil.runtime.realtime.socketcan import SocketCanUnavailable, check_channels
    from hil.scenario import ScenarioError

    if getattr(args, "ideal", False):
        raise ScenarioError("--ideal cannot be combined with --realtime (the ideal loop has no network to run in real time)")
    if scenario.can.transport == "socketcan":
        if getattr(args, "can_log", False):
            raise ScenarioError("--can-log needs can.transport = 'emulated' (on SocketCAN: python -m can.logger -i socketcan)")
        try:
            check_channels(scenario.can.socketcan_channels, scenario.trains.count)
        except SocketCanUnavailable as exc:
            raise ScenarioError(str(exc)) from None
    if args.run_name is not None:
        from hil.runtime.realtime.sockets import validate_name

        try:
            validate_name(args.run_name, "--run")
        except ValueError as exc:
            raise ScenarioError(str(exc)) from None


def run_realtime_from_args(args: argparse.Namespace, scenario, out: Path, live=None, overrides: dict | None = None):
    """``hil run --realtime`` with options that ``check_realtime_args`` passed: the RunResult of a real-time run."""
    from hil.runtime.realtime.orchestrator import run_realtime

    with WarningLines():
        return run_realtime(scenario, out, pace=1.0 if args.pace is None else args.pace, duration_s=args.duration,
                            ecus_per_process=args.ecus_per_process, record=not args.no_record,
                            progress=not args.quiet, can_log=getattr(args, "can_log", False), run=args.run_name,
                            on_channels=print_channels, live=live, overrides=overrides, source=str(args.scenario),
                            keep_signals=False, scheduling=args.scheduling or "auto",
                            idle_latency_us="auto" if args.idle_latency_us is None else args.idle_latency_us,
                            cpu_layout=args.cpu_layout or "auto", turns=args.turns or "auto")


class WarningLines(logging.Handler):
    """For a ``hil run --realtime``: the rig's logged warnings (its bus servers': a node's first frame dropped, a
    leave that lost frames, bad input from a client) as ``hil: warning:`` lines on stderr, written above the
    progress bar as they come; they are the run's WARN events as well. Without it Python would print them bare."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)

    def emit(self, record: logging.LogRecord) -> None:
        line = f"hil: warning: {record.getMessage()}"
        if sys.stderr.isatty():  # above the bar, which a terminal redraws in place
            from tqdm import tqdm

            tqdm.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)

    def __enter__(self) -> "WarningLines":
        logging.getLogger("hil").addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        logging.getLogger("hil").removeHandler(self)


def print_channels(channels) -> None:
    """One ``channel bus=... train=... interface=... channel=...`` line per bus on stdout (also under --quiet):
    what a script needs to start its python-can program on the run's buses."""
    for ch in channels:
        print(ch.line())
    sys.stdout.flush()


def bus_server_main(argv: list[str] | None = None, server_cls=NativeBusServer) -> int:
    p = argparse.ArgumentParser(prog="python -m hil.runtime.realtime.bus_server", description=DESCRIPTION)
    _add_arguments(p)
    return cmd_bus_server(p.parse_args(argv), server_cls)

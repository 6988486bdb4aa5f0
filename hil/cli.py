"""The ``hil`` command line: run scenarios, list them.

User errors (a bad scenario file, an unknown name) print one clear message and exit 2, no traceback.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ecu_sim.references import ReferenceLoadError
from hil.cli_values import positive_seconds
from hil.record.canlog import CanLogUnavailable
from hil.record.diskspace import DiskFullError
from hil.record.out_dir import (OutputDirError, ensure_writable_dir, free_reserve, hold_folder, release_folder,
                                reserve_space)
from hil.scenario import ScenarioError, load_scenario, packaged_scenarios
from hil.scenario.loader import parse_assignment

EXIT_FAILED, EXIT_USAGE, EXIT_UNSAFE, EXIT_INTERRUPTED = 1, 2, 3, 130  # documented in RUN_DESCRIPTION, docs/cli.md


def _cmd_scenarios(args: argparse.Namespace) -> int:
    for name, path in packaged_scenarios().items():
        try:
            desc = load_scenario(path).description
        except ScenarioError as exc:
            desc = f"(invalid: {exc})"
        print(f"{name:24s} {desc}")
    return 0


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


SUMMARY_KEYS = [
    ("settling_time_s", "settling time (s, 0.5 km/h band)"),
    ("speed_overshoot_max_mps", "max speed overshoot (m/s)"),
    ("speed_error_max_after_settling_mps", "max |v - v_r| after settling (m/s)"),
    ("coupler_max_abs_m", "max |coupler displacement| (m)"),
    ("coupler_out_of_band_s", "time any coupler out of band (s)"),
    ("gap_min_m", "min gap per train pair (m)"),
    ("gap_final_m", "final gap per train pair (m)"),
    ("frames_sent", "frames sent"),
    ("frames_lost", "frames lost"),
    ("reader_samples_skipped", "samples skipped at readers (not lost)"),
    ("reader_samples_repeated", "samples repeated at readers"),
    ("bus_load_max", "max bus load"),
    ("frame_latency_p99_s", "frame latency p99 (s)"),
    ("cycle_lateness_p99_s", "ECU cycle lateness p99 (s, real time)"),
    ("cycle_deadline_misses", "ECU cycle deadline misses"),
    ("e2e_latency_p99_s", "sensor-to-actuator latency p99 (s)"),
    ("sim_time_s", "simulated time (s)"),
    ("wall_time_s", "wall time (s)"),
    ("realtime_factor", "x real time"),
]


def print_summary(metrics: dict, out: Path) -> None:
    title = f"{metrics.get('scenario')} ({metrics.get('runtime')})"
    if metrics.get("interrupted"):
        title += "  INTERRUPTED: partial results"
    print(title)
    for key, label in SUMMARY_KEYS:
        if key in metrics:
            print(f"  {label:38s} {_fmt(metrics[key])}")
    sat = metrics.get("codec_saturations") or {}
    if sat:
        print(f"  {'signals saturated (count)':38s} " + ", ".join(f"{k}: {v}" for k, v in sat.items()))
    for line in (_drop_lines(metrics.get("per_bus")) + _safety_lines(metrics.get("safety")) + _fault_lines(metrics.get("faults"))
                 + _turn_lines(metrics.get("realtime"))):
        print(f"  {line}")
    written = [name for name in ("run.rrd", "metrics.json") if (out / name).exists()]
    print(f"  written to {out}/ ({', '.join(written)})")


def _drop_lines(per_bus: dict | None) -> list[str]:
    """Which nodes dropped frames (a full TX queue, bus-off, frames queued when they left), by bus; none: no line."""
    from hil.record.metrics import dropped_by_node  # here: commands other than run start without the metrics

    drops = dropped_by_node(per_bus)
    return [f"{'frames dropped, by node':38s} " + ", ".join(f"{name} {n}" for name, n in drops.items())] if drops else []


def _safety_lines(safety: dict | None) -> list[str]:
    """One line per safety verdict that was violated (first time, count, total time), or 'safe'."""
    if not safety:
        return []
    from hil.record.safety import ECU_FAILURE, violated

    verdicts = {k: v for k, v in safety.items() if isinstance(v, dict) and "violated" in v}
    bad = [f"{k}: {v['count']}x from t = {v['first_s']:.1f} s " + (
           f"({v['violations'][0]['where']}: {v['violations'][0]['text']})" if k == ECU_FAILURE
           else f"({v['total_s']:.1f} s summed over units)") for k, v in violated(safety).items()]
    return [f"{'safety verdicts':38s} " + ("; ".join(bad) if bad else "safe (" + ", ".join(verdicts) + ": none)")]


def _turn_lines(realtime: dict | None) -> list[str]:
    """With turns: how many the buses waited for, how many they let go (where the loop left virtual time's), and on
    how many buses they were given up (the machine did not keep up with them)."""
    if not realtime or not realtime.get("turns"):
        return []
    servers = realtime.get("bus_servers", {}).values()
    held, let_go = sum(b["turns_held"] for b in servers), sum(b["turn_overruns"] for b in servers)
    given_up = sum(b.get("turns_given_up_s") is not None for b in servers)
    return [f"{'turns waited for, let go':38s} {held}, {let_go}"
            + (f"; given up on {given_up} of {len(servers)} buses" if given_up else "")]


def _fault_lines(faults: dict | None) -> list[str]:
    """Injected vs detected faults, with each undetected one named."""
    if not faults or not faults.get("scheduled"):
        return []
    missed = [f"{f['kind']} on {f['target']}" for f in faults.get("faults", []) if f.get("injected") and not f.get("detected")]
    text = f"{faults['injected']} injected, {faults['detected']} detected"
    return [f"{'faults':38s} " + text + (f" (missed: {', '.join(missed)})" if missed else "")]


def _check_run_options(args: argparse.Namespace) -> None:
    """Options that do nothing in the chosen runtime are errors, not silently ignored."""
    if not args.realtime:
        given = [name for name, value in (("--pace", args.pace), ("--ecus-per-process", args.ecus_per_process),
                                          ("--run", args.run_name), ("--scheduling", args.scheduling),
                                          ("--idle-latency-us", args.idle_latency_us), ("--cpu-layout", args.cpu_layout),
                                          ("--turns", args.turns))
                 if value is not None]
        if given:
            verb = "applies" if len(given) == 1 else "apply"
            raise ScenarioError(f"{' and '.join(given)} only {verb} with --realtime (virtual time runs as fast as it can)")
    if args.ideal and args.can_log:
        raise ScenarioError("--can-log has no effect with --ideal: the ideal loop has no CAN bus to log")


def _cmd_run(args: argparse.Namespace) -> int:
    _check_run_options(args)
    overrides = dict(parse_assignment(a) for a in args.set)
    if args.seed is not None:
        overrides["seed"] = args.seed
    scenario = load_scenario(args.scenario, overrides)
    if args.external:  # added to the scenario's own, validated like them
        scenario = load_scenario(args.scenario, {**overrides, "ecu.external": [*scenario.ecu.external, *args.external]})
    silkit = _silkit_options(args)
    if silkit is not None:
        try:
            silkit.check_buses([f"bus{i + 1}" for i in range(scenario.trains.count)])  # the rig's bus names
        except ValueError as exc:
            raise ScenarioError(str(exc)) from None
    if not args.realtime and args.silkit is None:  # before anything is written
        from hil.runtime.firmware import refuse_external_units

        refuse_external_units(scenario, "the ideal loop" if args.ideal else "virtual time")
    from hil.runtime.assembly import check_firmware

    processes = None  # virtual time: every unit in one process
    if args.realtime and silkit is None and not args.ideal:
        from hil.runtime.realtime.orchestrator import planned_ecu_processes

        processes = planned_ecu_processes(scenario, args.ecus_per_process, args.pace or 1.0)
    # a law or program that cannot be built (in the process that will run it): exit 2, nothing written
    check_firmware(scenario, ecus=not args.ideal, processes=processes)
    live = live_target(args)
    if args.realtime and silkit is None:
        from hil.runtime.realtime.command_line import check_realtime_args

        check_realtime_args(args, scenario)
    out = Path(args.out) if args.out else default_output_dir(scenario.name, args)
    check_output_dir(out, args.overwrite)  # from here on, --overwrite has removed the previous run's files
    try:
        return _run_in(out, scenario, args, overrides, live, silkit)
    finally:
        free_reserve(out)
        release_folder(out)


def _silkit_options(args: argparse.Namespace):
    """--silkit and its companions as SilKitOptions (None without --silkit); a value that cannot work is exit 2."""
    if args.silkit is None:
        given = [o for o, v in (("--silkit-step", args.silkit_step), ("--silkit-config", args.silkit_config),
                                ("--silkit-network", args.silkit_network or None),
                                ("--silkit-no-system-controller", args.silkit_no_system_controller or None))
                 if v is not None]
        if given:
            raise ScenarioError(f"{' and '.join(given)} only with --silkit")
        return None
    if args.ideal:
        raise ScenarioError("--silkit runs the rig, not the ideal loop: not with --ideal")
    if args.realtime and any(v is not None for v in (args.ecus_per_process, args.run_name, args.scheduling,
                                                     args.idle_latency_us, args.cpu_layout, args.turns)):
        raise ScenarioError("--realtime --silkit runs the virtual rig paced by SIL Kit: --ecus-per-process, --run, "
                            "--scheduling, --idle-latency-us, --cpu-layout and --turns are for the process rig "
                            "(without --silkit)")
    from hil.silkit.options import SilKitOptions

    try:
        config = Path(args.silkit_config).read_text() if args.silkit_config else ""
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"--silkit-config {args.silkit_config}: cannot read it ({exc})") from None
    try:
        return SilKitOptions(uri=args.silkit, step_s=0.001 if args.silkit_step is None else args.silkit_step,
                             pace=(1.0 if args.pace is None else args.pace) if args.realtime else None,
                             system_controller=not args.silkit_no_system_controller, config=config,
                             networks=_network_names(args.silkit_network))
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None


def _network_names(pairs: list[str]) -> dict[str, str]:
    """--silkit-network BUS=NAME (repeatable) as {bus: SIL Kit network}."""
    names: dict[str, str] = {}
    for pair in pairs:
        bus, sep, name = pair.partition("=")
        if not sep or not bus.strip() or not name.strip():
            raise ValueError(f"--silkit-network {pair!r}: expected BUS=NETWORK, e.g. bus1=CAN1")
        names[bus.strip()] = name.strip()
    if len(set(names.values())) < len(names):
        raise ValueError(f"--silkit-network: two buses on one SIL Kit network ({pairs})")
    return names


def _run_in(out: Path, scenario, args: argparse.Namespace, overrides: dict, live=None, silkit=None) -> int:
    """The run itself, into ``out`` (checked and held), with every option already checked."""
    from hil.faults.schedule import late_faults

    for warning in late_faults(scenario, scenario.duration_s if args.duration is None else args.duration):
        print(f"hil: warning: {warning}", file=sys.stderr)
    if scenario.can.transport == "socketcan" and not (args.realtime or args.ideal):
        print("hil: warning: can.transport = 'socketcan' is for real-time runs (--realtime); this run is in virtual "
              "time, on the rig's emulated buses", file=sys.stderr)
    if live is not None and not args.quiet:
        print(f"hil: {live.describe()}", file=sys.stderr)
    if args.realtime and silkit is None:
        from hil.runtime.realtime.command_line import run_realtime_from_args

        result = run_realtime_from_args(args, scenario, out, live, _given(args, overrides))
    else:
        from hil.session import run_scenario  # virtual time (and the ideal loop): not a real-time orchestrator's

        result = run_scenario(scenario, out, duration_s=args.duration, can_log=args.can_log, ideal=args.ideal,
                              record=not args.no_record, progress=not args.quiet, live=live,
                              overrides=_given(args, overrides), source=str(args.scenario), keep_signals=False,
                              silkit=silkit)
    print_summary(result.metrics, out)
    if result.metrics.get("stopped_early"):  # a plant or radio process died: not the Ctrl-C code
        print(f"hil: error: the run stopped early: {result.metrics['stopped_early']} (what ran is in {out})",
              file=sys.stderr)
        return EXIT_FAILED
    code = EXIT_INTERRUPTED if result.log.interrupted else unsafe_exit(result.metrics) if args.check else 0
    if live is not None and live.port is not None and code != EXIT_INTERRUPTED:
        _keep_serving(live)
    return code


RUN_FILES = ("run.rrd", "metrics.json", "bus*.asc", "bus*.blf", "bus*.mf4")


def default_output_dir(name: str, args: argparse.Namespace) -> Path:
    """runs/<name>, runs/<name>-ideal or runs/<name>-realtime: one runtime's run never refuses another's."""
    return Path("runs") / (name + ("-ideal" if args.ideal else "-realtime" if args.realtime else ""))


def check_output_dir(out: Path, overwrite: bool) -> None:
    """A directory that holds a previous run is refused (exit 2), unless ``--overwrite``: then its run files go
    first, so nothing of the old run is mistaken for the new one. A directory that a live run holds is refused
    even with ``--overwrite``; from here this process holds it (``hil.record.folder_lock``)."""
    ensure_writable_dir(out)
    hold_folder(out)  # before anything of an old run goes: a run still writing there keeps its folder
    reserve_space(out)  # room for metrics.json should the recording fill the disk (given back at the end)
    old = [f for pattern in RUN_FILES for f in out.glob(pattern)] if out.is_dir() else []
    if not old:
        return
    if not overwrite:
        import datetime

        when = datetime.datetime.fromtimestamp(max(f.stat().st_mtime for f in old)).strftime("%Y-%m-%d %H:%M")
        raise ScenarioError(f"{out} holds a previous run (written {when}): pass --overwrite to replace it, or "
                            "--out another directory")
    import shutil

    for f in old:
        f.unlink()
    shutil.rmtree(out / "nodes", ignore_errors=True)


def _given(args: argparse.Namespace, overrides: dict) -> dict:
    """Every override the command line made, as dotted keys (for the run's provenance)."""
    given = dict(overrides)
    if args.external:
        given["ecu.external"] = list(args.external)
    if args.duration is not None:
        given["duration_s"] = args.duration
    return given


def live_target(args: argparse.Namespace):
    """The --connect / --serve target, or None; both at once is a usage error."""
    from hil.record.live import LiveTarget

    if args.connect is not None and args.serve is not None:
        raise ScenarioError("--connect and --serve exclude each other: stream to a viewer, or serve one")
    try:
        if args.connect is not None:
            return LiveTarget(url=args.connect)
        if args.serve is not None:
            return LiveTarget(port=args.serve)
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None
    return None


def _keep_serving(live) -> None:
    """--serve: the run is over; viewers can still connect until Ctrl-C."""
    import time

    print(f"hil: the run is over; still {live.describe()}; Ctrl-C to stop", file=sys.stderr)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass


def unsafe_exit(metrics: dict) -> int:
    """``--check``: EXIT_UNSAFE, with the violated verdicts named on stderr, when the run was not safe; else 0."""
    from hil.record.safety import violated

    bad = [f"{k} ({v['count']}x, first at t = {v['first_s']:.1f} s)"
           for k, v in violated(metrics.get("safety")).items()]
    if not bad:
        return 0
    print(f"hil: unsafe: {'; '.join(bad)}", file=sys.stderr)
    return EXIT_UNSAFE


RUN_DESCRIPTION = """Run one scenario and write run.rrd (the rerun recording) and metrics.json, then print a summary.

By default the run is in virtual time, as fast as the machine allows and reproducible bit for bit; --realtime
runs the same firmware, plant and buses as processes paced to the wall clock; --ideal runs the network-free
reference loop. --check makes an unsafe run fail, for CI.

Exit codes: 0 done (with --check: and safe); 1 the run could not go on (a real-time node failed to start or
died, an external unit never joined, the plant diverged, the disk is full); 2 bad input (scenario, --set, options);
3 unsafe: --check and a safety verdict was violated (named on stderr); 130 interrupted (Ctrl-C, SIGTERM)."""

RUN_EXAMPLES = """examples:
  hil run seed000                                        the main demo (800 s simulated, about a minute)
  hil run seed000 --duration 60 --seed 3 --can-log       one ASC log per bus beside the recording
  hil run seed000 --set radio.latency_s=0.3 --set can.bitrate=250000 --out runs/seed000-slow-radio
  hil run my_scenario.toml --ideal                       the ideal loop of your own scenario
  hil run seed000 --realtime --pace 1 --duration 20 --ecus-per-process 12
  hil run seed000 --duration 60 --check                  exit 3 if any safety verdict is violated
  hil run cruise.toml --set controller.law=mylaw:PDSpacing   your law, from ./mylaw.py
  hil run cruise.toml --realtime --external train2/unit3 --run dut   then start your ECU on dut/bus2"""


def _version() -> str:
    import trainhil_engine

    from hil import __version__

    return f"hil (trainhil) {__version__}, frame engine {trainhil_engine.VERSION}"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hil", description="trainhil: CAN emulation rig for cooperative train control")
    p.add_argument("--version", action="version", version=_version())
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run one scenario (virtual time, or --realtime) and record it",
                         description=RUN_DESCRIPTION, epilog=RUN_EXAMPLES,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    run.add_argument("scenario", help="packaged scenario name (see `hil scenarios`) or path to a .toml file")
    run.add_argument("--out", help="output directory (default: runs/<scenario name>, with -ideal or -realtime "
                                   "appended for those runtimes)")
    run.add_argument("--overwrite", action="store_true",
                     help="replace a previous run in the output directory (default: refuse, exit 2)")
    run.add_argument("--duration", type=positive_seconds, help="simulated seconds (default: the scenario's duration_s)")
    run.add_argument("--seed", type=int, help="random seed (default: the scenario's seed)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scenario field, e.g. --set radio.latency_s=0.2 --set can.bitrate=250000 (repeatable)")
    run.add_argument("--can-log", nargs="?", const="asc", choices=("asc", "blf", "mf4"), metavar="FORMAT",
                     help="write one CAN log per bus: asc (the default), blf or mf4 (needs asammdf); python-can reads "
                          "each, bus1 on channel 0 (channel 1 in the ASC/BLF files)")
    run.add_argument("--ideal", action="store_true", help="run the ideal network-free reference loop instead")
    run.add_argument("--silkit", nargs="?", const="", default=None, metavar="URI",
                     help="virtual time in lockstep with Vector SIL Kit, the rig simulating its CAN buses for SIL Kit "
                          "participants; ecu.external units are participants named after them (train1/unit2). URI: "
                          "the registry (default: one of the run's own on 127.0.0.1, printed on stdout). With "
                          "--realtime: SIL Kit's time coupled to the wall clock at --pace (its AnimationFactor)")
    run.add_argument("--silkit-step", type=float, default=None, metavar="S",
                     help="--silkit: the participants' time step, s (default 0.001; the rig steps at half of it); a "
                          "frame is seen at the first step after its end, and each step costs SIL Kit's synchronisation")
    run.add_argument("--silkit-config", metavar="FILE",
                     help="--silkit: a SIL Kit participant configuration (YAML/JSON, as SIL Kit's tools take with "
                          "--configuration) for the rig's participant: logging, middleware (acceptors, domain sockets)")
    run.add_argument("--silkit-network", action="append", default=[], metavar="BUS=NETWORK",
                     help="--silkit: the SIL Kit network simulating BUS (default: the bus's name, bus1 ...), e.g. "
                          "bus1=CAN1 (repeatable)")
    run.add_argument("--silkit-no-system-controller", action="store_true",
                     help="--silkit: another participant starts the simulation (Vector's sil-kit-system-controller "
                          "trainhil train1/unit2 ..., CANoe); by default the rig does, once the external units joined")
    run.add_argument("--no-record", action="store_true", help="skip the rerun recording (metrics only)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    from hil.record.live import DEFAULT_PORT, DEFAULT_URL

    run.add_argument("--connect", nargs="?", const=DEFAULT_URL, metavar="URL",
                     help=f"stream the recording live to a running rerun viewer (default URL {DEFAULT_URL})")
    run.add_argument("--serve", nargs="?", type=int, const=DEFAULT_PORT, metavar="PORT",
                     help=f"serve the recording live on loopback (default port {DEFAULT_PORT}) for "
                          "`rerun --connect rerun+http://127.0.0.1:PORT/proxy`; keeps serving after the run until Ctrl-C")
    run.add_argument("--check", action="store_true",
                     help=f"exit {EXIT_UNSAFE} if the run's safety verdict is unsafe, naming the violated verdicts (for CI)")
    from hil.runtime.realtime.command_line import add_realtime_arguments

    add_realtime_arguments(run)
    run.set_defaults(func=_cmd_run)

    sc = sub.add_parser("scenarios", help="list the packaged scenarios")
    sc.set_defaults(func=_cmd_scenarios)

    from hil.commands.can_analysis import add_can_analysis_parser
    from hil.runtime.realtime.command_line import add_bus_server_parser
    from hil.commands.sweep import add_sweep_parser, add_sweeps_list_parser

    add_sweep_parser(sub)
    add_sweeps_list_parser(sub)
    from hil.commands.compare import add_compare_parser

    add_compare_parser(sub)
    add_can_analysis_parser(sub)
    from hil.commands.fmu import add_fmu_parser
    from hil.commands.silkit import add_silkit_parser

    add_fmu_parser(sub)
    add_silkit_parser(sub)
    add_bus_server_parser(sub)
    from hil.commands.recover import add_recover_parser

    add_recover_parser(sub)
    from hil.viewer import add_view_parser

    add_view_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    from hil.record.live import exit_now_if_abandoned

    args = build_parser().parse_args(argv)
    code = _dispatch(args)
    exit_now_if_abandoned(code)  # a dropped live viewer: rerun would wait for it at exit, maybe forever
    return code


def _dispatch(args: argparse.Namespace) -> int:
    """Run the command; user errors become one line on stderr and their documented exit code."""
    try:
        return args.func(args)
    except (ScenarioError, CanLogUnavailable, OutputDirError) as exc:
        print(f"hil: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (FileNotFoundError, ReferenceLoadError) as exc:  # ReferenceLoadError: user code named in the scenario
        print(f"hil: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except DiskFullError as exc:  # the files written before the disk filled stay readable
        print(f"hil: error: {exc.strerror}", file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(EXIT_FAILED)  # not through the interpreter's exit hooks: rerun's would wait forever for its dead file writer
    except RuntimeError as exc:  # a real-time node that failed to start (NodeError), named in the message
        print(f"hil: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except BrokenPipeError:  # `hil ... | head`: the reader left; stop quietly (Python docs' recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:  # before or after the run loop (the run loop itself stops cleanly on its own)
        print("hil: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())

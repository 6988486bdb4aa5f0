"""``hil can-analysis``: every frame of a train bus with its worst-case length, WCRT and the bus load.

With ``--scenario`` the bus is that scenario's (units, periods, bitrate, radio; ``--bus`` picks which train's
bus, so bus1 has no radio frames from a train ahead and the last bus none from behind). Without it the bus
is a middle train's (radio frames both ways) with ``--units`` slots (default: all the DBC's) and the DBC's
GenMsgCycleTime. Explicit ``--bitrate``/``--units``/``--cycle`` override the scenario. ``--measured RUN_DIR``
sets the run's largest latency of each frame ID beside its bound. User errors print one line, exit 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path

from ecu_sim.codec import DbcMismatchError, TrainDb, default_dbc_path
from hil.cli_values import positive_int, positive_seconds
from hil.can.analysis import CanAnalysisError, TrainBusSetup, analyse_train_bus, forwarded_jitter, format_table
from hil.scenario import ScenarioError, load_scenario
from hil.scenario.loader import parse_assignment
from hil.scenario.model import Scenario

MEASURED_KEY = "latency_max_by_id"
DESCRIPTION = ("Every frame of a train bus: worst-case length, WCRT (Davis et al. 2007) and bus utilisation; "
               "with --measured, a run's largest latency of each frame beside its bound.")


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dbc", nargs="?", help="train DBC file (default: the packaged dbc/train.dbc)")
    p.add_argument("--bitrate", type=positive_int, help="bit/s (required without --scenario)")
    p.add_argument("--units", type=positive_int, help="power units per train (default: the scenario's, else every DBC slot)")
    p.add_argument("--cycle", type=positive_seconds, metavar="S",
                   help="period in s of every frame: ECU cycle, sensor and reference (default: the scenario's, else the DBC's)")
    p.add_argument("--scenario", metavar="NAME|PATH", help="take units, periods, bitrate and radio from this scenario")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="with --scenario: override one of its fields, e.g. --set can.fd=true --set can.data_bitrate=5000000")
    p.add_argument("--bus", default="bus1", help="which train's bus, busK (default bus1); also where --measured reads")
    p.add_argument("--measured", metavar="RUN_DIR", help=f"a `hil run` output dir: per_bus[bus].{MEASURED_KEY} of its metrics.json")


def add_can_analysis_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``can-analysis`` on a ``hil`` subparsers object; its func returns the exit code."""
    p = subparsers.add_parser("can-analysis", help="worst-case response time of every frame of a train bus",
                              description=DESCRIPTION)
    _add_arguments(p)
    p.set_defaults(func=run_can_analysis)
    return p


def parse_bus(text: str) -> int:
    """``busK`` (or ``K``) -> 0-based index K - 1."""
    m = re.fullmatch(r"(?:bus)?([0-9]+)", text.strip(), re.IGNORECASE)
    if not m or int(m.group(1)) < 1:
        raise CanAnalysisError(f"--bus {text!r}: expected bus1, bus2, ...")
    return int(m.group(1)) - 1


def read_measured(run_dir: Path, bus: str) -> tuple[dict[int, float], dict]:
    """(frame ID -> measured max latency in s, the whole metrics) of ``bus`` from RUN_DIR/metrics.json."""
    path = Path(run_dir) / "metrics.json"
    if not path.is_file():
        raise CanAnalysisError(f"--measured: {path} not found (give the output directory of a `hil run`)")
    try:
        metrics = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CanAnalysisError(f"--measured: {path} is not readable JSON ({exc})") from None
    per_bus = metrics.get("per_bus") if isinstance(metrics, dict) else None
    if not isinstance(per_bus, dict) or bus not in per_bus:
        have = ", ".join(per_bus) if isinstance(per_bus, dict) else "no per_bus section"
        raise CanAnalysisError(f"--measured: {path} has no per_bus[{bus!r}] ({have})")
    by_id = per_bus[bus].get(MEASURED_KEY)
    if not isinstance(by_id, dict):
        raise CanAnalysisError(f"--measured: {path} has no per_bus[{bus!r}][{MEASURED_KEY!r}]: it was written before "
                               "per-frame latencies were recorded; run the scenario again to get them")
    out = {}
    for key, value in by_id.items():
        try:
            can_id = int(key, 16)
        except (TypeError, ValueError):
            raise CanAnalysisError(f"--measured: {path}: per_bus[{bus!r}][{MEASURED_KEY!r}] key {key!r} is not a hex ID") from None
        if value is not None:
            out[can_id] = float(value)
    return out, metrics


def db_path(sc: Scenario | None) -> Path:
    """The DBC analysed without an explicit one: the scenario's, else the packaged train.dbc."""
    return sc.can.dbc_path if sc is not None else default_dbc_path()


def check_measured_run(run_dir: Path, metrics: dict, sc: Scenario | None, dbc: Path) -> None:
    """The measured run must be a run of the analysed scenario on the analysed DBC (its provenance says): another
    scenario's latencies say nothing about these bounds."""
    from hil.record.provenance import file_hash

    prov = metrics.get("provenance")
    if not isinstance(prov, dict):
        raise CanAnalysisError(f"--measured {run_dir}: its metrics.json has no provenance, so nothing says which "
                               "scenario and DBC it ran: run the scenario again with `hil run`")
    if sc is not None and prov.get("scenario") != sc.name:
        raise CanAnalysisError(f"--measured {run_dir}: a run of scenario {prov.get('scenario')!r}, not of "
                               f"{sc.name!r}: its latencies do not belong to this analysis")
    if prov.get("dbc_sha256") not in (None, file_hash(dbc)):
        raise CanAnalysisError(f"--measured {run_dir}: the run used another DBC ({prov.get('dbc')!r}, sha256 "
                               f"{prov['dbc_sha256'][:12]}...) than the one analysed ({dbc})")


def _scenario(args: argparse.Namespace) -> Scenario | None:
    """The scenario given with --scenario, with its --set overrides (None without one)."""
    if args.set and not args.scenario:
        raise CanAnalysisError("--set overrides a scenario's fields: give the scenario with --scenario")
    return load_scenario(args.scenario, dict(parse_assignment(a) for a in args.set)) if args.scenario else None


def _setup(args: argparse.Namespace, bus_index: int, db: TrainDb, sc: Scenario | None) -> tuple[TrainBusSetup, str]:
    """The bus to analyse, and a one-line description of where it came from."""
    if sc is not None:
        setup = TrainBusSetup.from_scenario(sc, bus_index)
        where = f"bus{bus_index + 1} of scenario {sc.name} ({sc.trains.count} trains)"
    else:
        if args.bitrate is None:
            raise CanAnalysisError("--bitrate is required without --scenario")
        setup = TrainBusSetup(units=db.max_units, bitrate=args.bitrate)
        where = "a middle train's bus (radio frames ahead and behind; --scenario for the first or last bus)"
    overrides = {}
    if args.bitrate is not None:
        overrides["bitrate"] = args.bitrate
    if args.cycle is not None:
        overrides.update(cycle_s=args.cycle, sensor_period_s=args.cycle, reference_period_s=args.cycle)
    if args.units is not None:
        overrides["units"] = args.units
    return dataclasses.replace(setup, **overrides), where


def _period(value: float | None) -> str:
    return "DBC" if value is None else f"{value * 1e3:g} ms"


def _analyse(args: argparse.Namespace) -> None:
    if args.dbc and Path(args.dbc).suffix.lower() == ".toml":
        raise CanAnalysisError(f"{args.dbc} looks like a scenario file; the positional argument is a DBC file. "
                               f"Analyse a scenario's bus with --scenario {args.dbc}")
    sc = _scenario(args)
    db = TrainDb.load(Path(args.dbc) if args.dbc else db_path(sc))
    bus_index = parse_bus(args.bus)
    setup, where = _setup(args, bus_index, db, sc)
    measured, metrics = read_measured(Path(args.measured), f"bus{bus_index + 1}") if args.measured else ({}, {})
    if args.measured:
        check_measured_run(Path(args.measured), metrics, sc, Path(args.dbc) if args.dbc else db_path(sc))
    timings = analyse_train_bus(db, setup, measured)
    ahead, behind = forwarded_jitter(db, setup)
    print(f"DBC {db.path}: {where}")
    print(f"  {setup.units} units, {setup.rates}, periods: ECU {_period(setup.cycle_s)}, "
          f"sensor {_period(setup.sensor_period_s)}, reference {_period(setup.reference_period_s)}")
    print(f"  forwarded-frame release jitter bound: ahead {ahead * 1e3:.3f} ms, behind {behind * 1e3:.3f} ms "
          f"(source WCRT - best case + radio jitter {setup.radio_link_jitter_s * 1e3:g} ms)")
    if setup.queue_policy != "priority":
        print(f"  WARNING: can.queue_policy = {setup.queue_policy!r}: the bounds assume priority-ordered TX queues "
              "and do not hold for this bus")
    if args.measured:
        ran = metrics.get("scenario")
        print(f"  measured: {Path(args.measured) / 'metrics.json'} (run of {ran or 'an unnamed scenario'}), bus{bus_index + 1}")
    print()
    print(format_table(timings, setup.rates))
    extra = sorted(set(measured) - {t.can_id for t in timings})
    if extra:
        print("measured IDs not on the analysed bus: " + ", ".join(f"0x{i:03X}" for i in extra))


def run_can_analysis(args: argparse.Namespace) -> int:
    """The command: print the analysis, exit 0; a user error prints ``hil: error: ...`` and returns 2."""
    try:
        _analyse(args)
    except (CanAnalysisError, ScenarioError, DbcMismatchError, FileNotFoundError) as exc:
        print(f"hil: error: {exc}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.commands.can_analysis ...``, the same as ``hil can-analysis ...``."""
    p = argparse.ArgumentParser(prog="hil can-analysis", description=DESCRIPTION)
    _add_arguments(p)
    return run_can_analysis(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

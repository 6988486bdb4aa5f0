"""``hil compare SCENARIO... [--set k=v] [--duration S] [--out DIR]``: several runs side by side.

Every scenario runs in virtual time over CAN (``--ideal``: the ideal network-free loop instead), with the
same ``--set`` overrides; a metric family (:mod:`hil.compare.report`) judges each run. The table is printed
and written to OUT/compare.md, compare.csv and compare.json, with OUT/speed_error.png and the recorded speed
errors in OUT/traces.npz (default OUT: runs/compare-<names>).
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from hil.record.out_dir import ensure_writable_dir

from hil.scenario import ScenarioError, load_scenario


def add_compare_parser(sub) -> None:
    p = sub.add_parser("compare", help="run several scenarios and compare them in one table and plot")
    p.add_argument("scenarios", nargs="+", metavar="SCENARIO", help="packaged scenario names or .toml paths")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field in every scenario, e.g. --set ecu.cycle_s=0.01 (repeatable)")
    p.add_argument("--duration", type=float, help="simulated seconds (default: each scenario's duration_s)")
    p.add_argument("--out", help="output directory (default: runs/compare-<names>)")
    p.add_argument("--ideal", action="store_true", help="run the ideal network-free loops instead")
    p.add_argument("--family", help="metric family (default: the first that applies to every scenario)")
    p.add_argument("--workers", type=int, default=None,
                   help="parallel runs (local processes; default: the number of CPUs, as hil sweep)")
    p.set_defaults(func=_cmd_compare)


def _cmd_compare(args: argparse.Namespace) -> int:
    from hil.scenario.loader import parse_assignment
    from hil.compare.report import choose_family, table_rows, text_table, write_outputs
    from hil.compare.runner import CompareItem, run_items

    overrides = dict(parse_assignment(a) for a in args.set)
    if args.duration is not None and not args.duration > 0:
        raise ScenarioError(f"--duration must be > 0, got {args.duration}")
    scenarios = [load_scenario(name, overrides) for name in args.scenarios]
    try:
        family = choose_family(scenarios, args.family)
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None
    labels = _unique([sc.name for sc in scenarios])
    items = [CompareItem(label, sc, family.name, args.ideal, args.duration) for label, sc in zip(labels, scenarios)]
    out = Path(args.out) if args.out else Path("runs") / ("compare-" + "-".join(labels))[:120]
    ensure_writable_dir(out)  # before any run
    wall0 = time.perf_counter()
    workers = (os.cpu_count() or 1) if args.workers is None else args.workers
    if workers < 1:
        raise ScenarioError(f"--workers must be >= 1, got {args.workers}")
    runs = run_items(items, workers, progress=lambda label: print(f"  done: {label}", flush=True))
    title = "hil compare " + " ".join(args.scenarios) + "".join(f" --set {a}" for a in args.set) + (" --ideal" if args.ideal else "")
    paths = write_outputs(runs, family, out, title)
    header, rows = table_rows(runs, family)
    print(text_table(header, rows))
    print(f"  {len(runs)} runs in {time.perf_counter() - wall0:.1f} s wall; written to {out}/ "
          f"({', '.join(p.name for p in paths.values())})")
    return 0


def _unique(names: list[str]) -> list[str]:
    """Labels for the table: the scenario names, numbered when one appears twice."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if names.count(n) == 1 else f"{n}#{seen[n]}")
    return out

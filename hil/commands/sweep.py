"""``hil sweep`` and ``hil sweeps``: run a sweep file's grid, write results.csv and plots; list packaged sweeps.

Exit codes: 0 when every point has finished (failed runs are results: they are counted, listed and kept in
``runs/<id>/error.txt``), 130 after Ctrl-C (run the same command again to resume). Bad sweep files raise
SweepError (a ScenarioError), which ``hil``'s main turns into one message and exit code 2.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from hil.record.out_dir import ensure_writable_dir

from hil.cli_values import positive_seconds
from hil.sweep.spec import SweepError, SweepSpec, load_sweep, packaged_sweeps


def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``hil sweep SWEEP --out DIR [--set K=V] [--duration S] [--workers N] [--dask ADDRESS|local] [--no-plots]``."""
    p = subparsers.add_parser("sweep", help="run a grid of scenario variants in parallel, write results.csv and plots")
    p.add_argument("sweep", help="packaged sweep name (see `hil sweeps`) or path to a sweep .toml file")
    p.add_argument("--out", help="output directory (default: runs/sweep-<name>); rerun with the same --out to resume")
    p.add_argument("--workers", type=int, help="parallel runs (default: the number of CPUs); with --dask local: the "
                                               "LocalCluster's workers; ignored with a tcp:// scheduler")
    p.add_argument("--dask", metavar="ADDRESS", help="run on a Dask cluster: tcp://host:port of a scheduler, or `local` "
                                                     "for a LocalCluster on this machine")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="set a scenario field in every run, as hil run --set (joins the file's [overrides]; repeatable)")
    p.add_argument("--duration", type=positive_seconds, help="simulated seconds of every run (replaces the file's)")
    p.add_argument("--no-plots", action="store_true", help="write results.csv only")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_sweep)
    return p


def add_sweeps_list_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``hil sweeps``: the packaged sweeps with their size and description."""
    p = subparsers.add_parser("sweeps", help="list the packaged sweeps")
    p.set_defaults(func=cmd_sweeps)
    return p


def cmd_sweeps(args: argparse.Namespace) -> int:
    for name, path in packaged_sweeps().items():
        try:
            spec = load_sweep(path)
            desc = f"{len(spec.points):4d} runs  {spec.description}"
        except SweepError as exc:
            desc = f"(invalid: {exc})"
        print(f"{name:24s} {desc}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from hil.sweep.runner import run_sweep

    if args.workers is not None and args.workers < 1:
        raise SweepError(f"--workers must be >= 1, got {args.workers}")
    from hil.scenario.loader import parse_assignment

    spec = load_sweep(args.sweep, dict(parse_assignment(a) for a in args.set), args.duration)
    out = Path(args.out) if args.out else Path("runs") / f"sweep-{spec.name}"
    ensure_writable_dir(out)  # before any run
    result = run_sweep(spec, out, workers=args.workers, dask=args.dask, progress=not args.quiet)
    plots = [] if args.no_plots or not result.rows else _plots(spec, result.rows, out)
    _summary(spec, result, plots)
    return 130 if result.interrupted else 0


def _plots(spec: SweepSpec, rows: list[dict], out: Path) -> list[Path]:
    try:
        from hil.sweep.plots import make_plots
    except ModuleNotFoundError as exc:
        if exc.name != "hil.sweep.plots":
            raise
        print("plots skipped: hil.sweep.plots is not available")
        return []
    return make_plots(spec, rows, out)


def _summary(spec: SweepSpec, result, plots: list[Path]) -> None:
    head = f"{spec.name}: {result.ok} ok, {result.failed} failed"
    if result.pending:
        head += f", {result.pending} not run"
    head += f" of {result.total} runs ({result.reused} reused from an earlier invocation)"
    if result.interrupted:
        head += "  INTERRUPTED: run the same command again to resume"
    print(head)
    for run_id in result.failures[:10]:
        print(f"  failed: {result.out_dir / 'runs' / run_id / 'error.txt'}")
    if len(result.failures) > 10:
        print(f"  ... and {len(result.failures) - 10} more failures (status column of results.csv)")
    print(f"  results: {result.csv_path}")
    for p in plots:
        print(f"  plot: {p}")

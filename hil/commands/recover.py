"""``hil recover RUN_DIR``: the command's parser and handler; the recovery itself is
hil/runtime/realtime/recover.py, imported only when the command runs (it imports the orchestrator and the plant)."""
from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = ("Rebuild run.rrd and metrics.json of a real-time run whose rig was killed (kill -9, an "
               "out-of-memory kill), from the files its node processes left in RUN_DIR/nodes. What lived only in the "
               "orchestrator is gone and is said so: its own events, the TX-queue drop counts, and the bus rows of "
               "the last second. The result is marked \"recovered\": true and \"interrupted\": true.")


def add_recover_parser(subparsers) -> None:
    """``hil recover RUN_DIR``."""
    p = subparsers.add_parser("recover", description=DESCRIPTION,
                              help="rebuild run.rrd and metrics.json of a real-time run whose rig was killed")
    p.add_argument("run_dir", help="the run's output directory (hil run --out)")
    p.set_defaults(func=_cmd_recover)


def _cmd_recover(args: argparse.Namespace) -> int:
    from hil.runtime.realtime.recover import RecoverError, recover
    from hil.scenario import ScenarioError

    try:
        metrics = recover(Path(args.run_dir))
    except RecoverError as exc:
        raise ScenarioError(str(exc)) from None
    print(f"recovered {args.run_dir}: {metrics['sim_time_s']:.1f} s simulated; run.rrd and metrics.json written "
          f"(bus tables lost with the rig)")
    return 0

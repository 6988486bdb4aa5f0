"""Seeds 002 and 003: run every scenario of docs/multi_train.md, then write its tables and figures.

    nice -n 10 python docs/make_multi_train.py run [--workers 2] [--only NAME ...]   # full durations, over CAN and radio
    python docs/make_multi_train.py report                                         # tables (stdout) + docs/figures/*.png

``run`` saves every run's signals to runs/multi_train/<run>.npz (resumable: existing files are kept unless
--force). The 6000 s seed-002 runs take 2-4 min each on this 2-core machine, the 600 s seed-003 runs 1-2 min.
``report`` reads those files only. Run names: the scenario name, ``+limits`` for seed 002's realistic
traction limits applied to another law's scenario, ``@ideal`` for the network-free loop.
"""
from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "runs" / "multi_train"
FIGURES = Path(__file__).resolve().parent / "figures"

SEED002 = ["seed002", "seed002-fixed-a1", "seed002-fixed-a3", "seed002-fixed-a5", "seed002-bai", "seed002-lyg"]
SEED003 = ["seed003-p1", "seed003-p2", "seed003-p3"]
LIMITS_FROM = "seed002-limits"  # its [plant.limits] is applied to every seed-002 law for the "+limits" runs


def all_runs() -> list[str]:
    """Every run of the report: network runs, the same with limits (seed 002), and the ideal loops."""
    runs = list(SEED002) + [f"{n}+limits" for n in SEED002] + list(SEED003)
    return runs + [f"{n}@ideal" for n in SEED002 + SEED003]


def scenario_of(run: str):
    """The scenario of a run name (``+limits`` copies seed002-limits' plant.limits onto the law's scenario)."""
    from hil.scenario import load_scenario

    name = run.split("@")[0]
    if name.endswith("+limits"):
        limits = load_scenario(LIMITS_FROM).plant.limits.model_dump()
        return load_scenario(name.removesuffix("+limits"), {"plant.limits": limits, "name": name})
    return load_scenario(name)


def save_log(path: Path, log, scenario_name: str) -> None:
    """The signals and counters of a RunLog, enough to rebuild it with :func:`load_log`."""
    extra = {"events": [(e.t, e.level, e.source, e.text) for e in log.events], "radio": log.radio_stats,
             "saturations": log.codec_saturations, "frames_lost": log.frames_lost, "wall_time_s": log.wall_time_s}
    np.savez_compressed(path, signals=log.signals.array, changes=np.array(log.reference_change_times, dtype=float),
                        scenario=scenario_name, extra=json.dumps(extra))


def load_log(path: Path):
    """(RunLog, scenario, extra dict) from a file written by :func:`save_log`."""
    from hil.scenario.layout import TrainLayout
    from hil.record.runlog import RunLog

    data = np.load(path, allow_pickle=False)
    run = str(data["scenario"])
    sc = scenario_of(run)
    log = RunLog(TrainLayout.from_config(sc.trains))
    log.signals._buf.frombytes(np.ascontiguousarray(data["signals"], dtype=float).tobytes())
    log.reference_change_times = data["changes"].tolist()
    extra = json.loads(str(data["extra"]))
    log.sim_time_s = float(log.t[-1]) if len(log.t) else 0.0
    return log, sc, extra


def run_one(run: str, force: bool = False) -> str:
    """Run one scenario (network rig, or the ideal loop for ``@ideal``) and save it."""
    from hil.runtime.ideal import IdealLoop
    from hil.runtime.virtual import VirtualRig

    RUNS.mkdir(parents=True, exist_ok=True)
    out = RUNS / f"{run}.npz"
    if out.exists() and not force:
        return f"{run}: kept {out.name}"
    sc = scenario_of(run)
    log = IdealLoop(sc).run() if run.endswith("@ideal") else VirtualRig(sc).run()
    save_log(out, log, run)
    return f"{run}: {log.sim_time_s:.0f} s simulated in {log.wall_time_s:.0f} s"


def cmd_run(args: argparse.Namespace) -> int:
    runs = args.only or all_runs()
    unknown = sorted(set(runs) - set(all_runs()))
    if unknown:
        print(f"unknown run(s): {unknown}; known: {all_runs()}", file=sys.stderr)
        return 2
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for line in pool.map(run_one, runs, [args.force] * len(runs)):
            print(line, flush=True)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from hil.compare import multi_train as mt

    FIGURES.mkdir(exist_ok=True)
    logs = {p.stem: load_log(p) for p in sorted(RUNS.glob("*.npz"))}
    missing = [r for r in all_runs() if r not in logs]
    if missing:
        print(f"note: not run yet: {', '.join(missing)}", file=sys.stderr)
    print(mt.report_markdown({k: (log, sc) for k, (log, sc, _) in logs.items()}, {k: extra for k, (_, _, extra) in logs.items()}))
    for group, names in (("seed002", SEED002), ("seed002-limits", [f"{n}+limits" for n in SEED002]),
                         ("seed002-ideal", [f"{n}@ideal" for n in SEED002])):
        have = {n: logs[n][0] for n in names if n in logs}
        if have:
            path = FIGURES / f"{group}-spacing.png"
            mt.plot_spacing(have, path, title=f"{group}: head-to-head spacing d per pair (d_r = 7.4 km)")
            print(f"wrote {path}", file=sys.stderr)
    have = {n: logs[n][0] for n in SEED003 if n in logs}
    if have:
        for what in ("tracking", "speed"):
            path = FIGURES / f"seed003-{what}.png"
            mt.plot_seed003(have, path, what, speed_limit_mps=mt.speed_limit_of(logs[SEED003[-1]][1]) if SEED003[-1] in logs else None)
            print(f"wrote {path}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run the scenarios (saved to runs/multi_train/)")
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--only", nargs="*", help="run names (default: all)")
    r.add_argument("--force", action="store_true", help="rerun even if the file exists")
    r.set_defaults(func=cmd_run)
    rep = sub.add_parser("report", help="tables and figures from the saved runs")
    rep.set_defaults(func=cmd_report)
    args = p.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

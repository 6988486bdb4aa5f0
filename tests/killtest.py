"""Kill runs at random moments and check what they leave: the random-kill test and the reliability benchmark.

``kill_run`` starts ``hil run ...`` as a subprocess, waits until the run has started (its metrics.json stub
appears; in real time the plant's first save, ``nodes/plant.json``, a few seconds after sim t = 0), waits
``delay_s`` more, sends ``sig`` to it (or, with
``child``, SIGKILL to one of its node processes), waits for the end and judges the run directory with
``check_run_dir``. ``random_kills`` does it ``n`` times with seeded random delays and signals.

    python -m tests.killtest --n 10 --seed 1 --out runs/kills            # virtual time, 10 kills
    python -m tests.killtest --n 3 --realtime --out runs/kills-rt        # hil run --realtime
    python -m tests.killtest --n 3 --realtime --child --out runs/kills-c # SIGKILL a random node process

A kill counts as intact when metrics.json parses and says incomplete (or complete, if the run finished first),
run.rrd opens with rerun's Python API, the two agree, and nothing printed a traceback.
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

from hil.record.integrity import IntegrityReport, check_run_dir

SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
REALTIME_SIGNALS = (signal.SIGTERM, signal.SIGINT)  # the orchestrator handles these two (SIGHUP: not yet)
NODE_MODULES = ("hil.runtime.realtime.plant_node", "hil.runtime.realtime.radio_node", "hil.runtime.realtime.ecu_node")


@dataclass
class KillOutcome:
    """One kill: when, how, what the process did, and the verdict on its run directory."""

    out_dir: str
    delay_s: float
    signal: str
    target: str  # "run" or the node module killed
    returncode: int | None
    finished_first: bool  # the run ended before the kill could be sent
    traceback: bool
    report: IntegrityReport
    stderr_tail: str = ""  # the end of what the run printed on stderr (why it failed, when it did)

    @property
    def intact(self) -> bool:
        expected_incomplete = not self.finished_first and self.target == "run"
        return (self.report.ok and not self.traceback and self.returncode is not None
                and (self.report.complete is False or not expected_incomplete))

    def as_dict(self) -> dict:
        d = asdict(self)
        d["intact"] = self.intact
        return d


def hil_run_argv(out_dir: Path, scenario: str = "seed000", duration_s: float = 600.0, realtime: bool = False,
                 extra: tuple[str, ...] = ()) -> list[str]:
    """``hil run`` (as ``python -m hil``) of a run long enough not to finish before the kill."""
    argv = [sys.executable, "-m", "hil", "run", scenario, "--duration", repr(duration_s), "--out", str(out_dir),
            "--quiet", *extra]
    if realtime:
        argv += ["--realtime", "--ecus-per-process", "6"]
    return argv


def _stamps(out_dir: Path, started_file: str | None = None) -> tuple:
    """What marks a run's start: its metrics.json stub (virtual) or nodes/scenario.json (real time) being written.

    The content counts too: a file replaced in the same clock tick may reuse the inode number it replaced."""
    out = []
    files = [out_dir / started_file] if started_file else [out_dir / "metrics.json", out_dir / "nodes" / "scenario.json"]
    for f in files:
        try:
            st = f.stat()
            out.append((st.st_ino, st.st_mtime_ns, zlib.crc32(f.read_bytes())))
        except FileNotFoundError:
            out.append(None)
    return tuple(out)


def _started(out_dir: Path, before: tuple, started_file: str | None = None) -> bool:
    """A start marker appeared or was rewritten since ``before`` (files of an earlier run do not count)."""
    return any(now is not None and now != old for now, old in zip(_stamps(out_dir, started_file), before))


def _node_processes(pid: int) -> list:
    import psutil

    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    out = []
    for p in kids:
        try:
            cmd = p.cmdline()
        except psutil.Error:
            continue
        mod = next((m for m in NODE_MODULES if m in cmd), None)
        if mod is not None:
            out.append((mod, p))
    return out


def kill_run(argv: list[str], out_dir: Path, delay_s: float, sig: int = signal.SIGTERM, *, child: bool = False,
             rng: random.Random | None = None, started_file: str | None = None, start_timeout_s: float = 180.0,
             end_timeout_s: float = 180.0) -> KillOutcome:
    """Start ``argv`` (a run writing to ``out_dir``), kill it ``delay_s`` after it started, check what it left.

    The start is the first write of the run's metrics.json stub or nodes/scenario.json, or, with
    ``started_file`` (e.g. "nodes/plant.json": the real-time plant's first save, after sim t = 0), of that file."""
    out_dir = Path(out_dir)
    before = _stamps(out_dir, started_file)
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    target, finished_first = "run", False
    try:
        deadline = time.monotonic() + start_timeout_s
        while not _started(out_dir, before, started_file) and proc.poll() is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{out_dir}: the run did not start within {start_timeout_s:.0f} s")
            time.sleep(0.02)
        time.sleep(delay_s)
        if proc.poll() is not None:
            finished_first = True
        elif child:
            nodes = _node_processes(proc.pid)
            if nodes:
                target, victim = (rng or random).choice(nodes)
                victim.send_signal(signal.SIGKILL)
                sig = signal.SIGKILL
            else:
                proc.send_signal(sig)
        else:
            proc.send_signal(sig)
        _, err = proc.communicate(timeout=end_timeout_s)
    except BaseException:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
        raise
    report = check_run_dir(out_dir)
    return KillOutcome(str(out_dir), delay_s, signal.Signals(sig).name, target, proc.returncode, finished_first,
                       "Traceback" in err, report, err[-2000:])


def random_kills(n: int, out_root: Path, seed: int = 0, max_delay_s: float = 5.0, realtime: bool = False,
                 child: bool = False, scenario: str = "seed000", duration_s: float | None = None) -> list[KillOutcome]:
    """``n`` runs killed after seeded random delays in [0, max_delay_s] with seeded random stop signals."""
    rng = random.Random(seed)
    duration = duration_s if duration_s is not None else (30.0 if child else 600.0)
    outcomes = []
    for k in range(n):
        out = Path(out_root) / f"kill{k:03d}"
        argv = hil_run_argv(out, scenario, duration, realtime)
        sig = rng.choice(REALTIME_SIGNALS if realtime else SIGNALS)
        outcomes.append(kill_run(argv, out, rng.uniform(0.0, max_delay_s), sig, child=child, rng=rng,
                                 started_file="nodes/plant.json" if realtime else None))
    return outcomes


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.killtest", description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=10, help="number of runs to kill")
    p.add_argument("--seed", type=int, default=0, help="seed of the random delays and signals")
    p.add_argument("--max-delay", type=float, default=5.0, help="kill within this many wall seconds after the start")
    p.add_argument("--realtime", action="store_true", help="hil run --realtime instead of virtual time")
    p.add_argument("--child", action="store_true", help="SIGKILL a random node process (real time) instead of the run")
    p.add_argument("--scenario", default="seed000")
    p.add_argument("--out", required=True, help="directory for the killed runs (one sub-directory each)")
    args = p.parse_args(argv)
    outcomes = random_kills(args.n, Path(args.out), args.seed, args.max_delay, args.realtime, args.child, args.scenario)
    for o in outcomes:
        r = o.report
        print(f"{Path(o.out_dir).name}: {o.target} {o.signal} after {o.delay_s:.2f} s -> exit {o.returncode}, "
              f"{'intact' if o.intact else 'NOT INTACT'} (complete={r.complete}, sim_time_s={r.sim_time_s}, "
              f"recorded to {r.rrd_last_time_s}, {r.rrd_chunks} chunks){'; ' + '; '.join(r.problems) if r.problems else ''}")
    good = sum(o.intact for o in outcomes)
    print(f"recordings intact after {len(outcomes)} random kills: {good} of {len(outcomes)}")
    return 0 if good == len(outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())

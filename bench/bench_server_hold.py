"""Benchmark: the frames a real-time run loses when the host holds one of its processes still for a while.

On a virtual machine the host now and then takes a virtual CPU for milliseconds; whatever runs there stops. This
bench stops one of the rig's processes on purpose (``bench/process_hold.py``: SIGSTOP, then SIGCONT) a few times
in a run and prints, per run, the holds as measured, the frames each bus dropped by node, and the plant's
publications that missed their deadline and those skipped. The nodes go on meanwhile, and what they sent waits in
their sockets until the servers read it.

    python bench/bench_server_hold.py [--hold serving plant ecus] [--hold-ms 100] [--pace 10] [--holds 4]
                                      [--firmware standard null] [--scenario seed000]

``--hold serving``: the orchestrator, whose native thread serves every bus; ``serving,plant``: both at once, as
when they share the CPU the host holds. ``--firmware null``: the ECUs run
``bench.null_firmware`` (as in ``bench/bench_realtime_scale.py``). One hold every 1.5 s of wall time from 1 s; the
run lasts until 2 s after the last. The rig's default settings otherwise.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_realtime_scale import FIRMWARES, scenario_for  # noqa: E402
from bench.process_hold import KINDS  # noqa: E402
from hil.runtime.realtime.orchestrator import run_realtime  # noqa: E402
from hil.scenario.loader import ScenarioError  # noqa: E402

FIRST_HOLD_S, HOLD_EVERY_S = 1.0, 1.5  # wall seconds after simulated t = 0


def run_held(sc, which: str, hold_ms: float, pace: float, holds: int) -> tuple[dict, list, list[float]]:
    """Run ``sc`` at ``pace`` with ``which`` held ``holds`` times for ``hold_ms``: (its metrics, its buses' logs,
    the holds' measured lengths in ms). The holder is ended with the run, whatever happens."""
    offsets = [FIRST_HOLD_S + k * HOLD_EVERY_S for k in range(holds)]
    holder: list[subprocess.Popen] = []

    def on_start(go: float) -> None:
        holder.append(subprocess.Popen(
            [sys.executable, str(ROOT / "bench" / "process_hold.py"), str(os.getpid()), which, repr(hold_ms),
             repr(go), *map(repr, offsets)], stdout=subprocess.PIPE, text=True))

    try:
        with tempfile.TemporaryDirectory() as tmp:
            res = run_realtime(sc, Path(tmp) / "run", pace=pace, duration_s=(offsets[-1] + 2.0) * pace, record=False,
                               on_start=on_start)
    finally:
        for p in holder:
            p.terminate()
    out, _ = holder[0].communicate(timeout=30) if holder else ("", None)
    lengths = [1e3 * (float(b) - float(a)) for a, b in (line.split() for line in out.splitlines())]
    return res.metrics, res.log.buses, lengths


def report(which: str, firmware: str, metrics: dict, buses: list, lengths: list[float]) -> str:
    """One run's line: what was held and how long, the frames lost by bus and node, the plant's late and skipped
    publications."""
    by_bus = "; ".join(f"{b.name} " + (", ".join(f"{n} {k}" for n, k in sorted(b.dropped_by_node.items())) or "none")
                       for b in buses)
    held = ", ".join(f"{x:.1f}" for x in lengths) or "none (the run ended first)"
    skipped = metrics["realtime"]["plant"]["cycles_skipped"]
    return (f"{which:8s} {firmware:8s} held {held} ms: {metrics['frames_lost']} frames lost ({by_bus}); "
            f"{metrics['plant_deadline_misses']} plant publications late, {skipped} skipped (the latest due sent)")


def hold_kinds(text: str) -> str:
    """``--hold``'s value: one of process_hold's KINDS, or several comma-separated."""
    if not text or not set(text.split(",")) <= set(KINDS):
        raise argparse.ArgumentTypeError(f"{text!r}: not {', '.join(KINDS)}, or several of them comma-separated")
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hold", nargs="+", type=hold_kinds, default=["serving", "plant", "ecus"],
                    help="serving, plant or ecus; several comma-separated (serving,plant): held together")
    ap.add_argument("--hold-ms", type=float, default=100.0)
    ap.add_argument("--pace", type=float, default=10.0)
    ap.add_argument("--holds", type=int, default=4)
    ap.add_argument("--firmware", nargs="+", choices=sorted(FIRMWARES), default=["standard", "null"])
    ap.add_argument("--scenario", default="seed000")
    args = ap.parse_args()
    if args.hold_ms <= 0 or args.hold_ms >= 1e3 * HOLD_EVERY_S - 500 or args.holds < 1 or args.pace <= 0:
        raise SystemExit(f"--hold-ms must be in (0, {1e3 * HOLD_EVERY_S - 500:g}), --holds at least 1, --pace above 0")
    try:
        scenarios = {fw: scenario_for(0, args.scenario, fw) for fw in args.firmware}
    except ScenarioError as exc:
        raise SystemExit(f"--scenario: {exc}") from None
    print(f"{os.cpu_count()} CPUs; {args.scenario} at pace {args.pace:g}, {args.holds} holds of {args.hold_ms:g} ms "
          f"({args.hold_ms * args.pace:g} simulated ms), one every {HOLD_EVERY_S:g} s of wall time", flush=True)
    for which in args.hold:
        for fw, sc in scenarios.items():
            print(report(which, fw, *run_held(sc, which, args.hold_ms, args.pace, args.holds)), flush=True)


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        print("bench_server_hold: interrupted", file=sys.stderr)
        raise SystemExit(130) from None

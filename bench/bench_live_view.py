"""What live viewing costs a virtual-time run: seed000 recorded to run.rrd only, and to run.rrd plus a live stream
to a listening viewer (``--connect``), side by side and alternated in one process, so the machine's drift hits both.

The viewer is rerun's headless proxy (``rerun --bind 127.0.0.1 --port P --save FILE``, analytics off), on
loopback. Prints simulated seconds per wall second of each and the ratio. Target: the live stream does not slow
the run noticeably (a few per cent).
    python bench/bench_live_view.py [--sim 200] [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from hil.record.live import LiveTarget
from hil.scenario import load_scenario
from hil.session import run_scenario


def start_proxy(work: Path) -> tuple[subprocess.Popen, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (work / "cfg" / "rerun").mkdir(parents=True)
    (work / "cfg" / "rerun" / "analytics.json").write_text(json.dumps({"analytics_enabled": False}))
    env = {**os.environ, "XDG_CONFIG_HOME": str(work / "cfg"), "XDG_DATA_HOME": str(work / "data")}
    proc = subprocess.Popen(["rerun", "--bind", "127.0.0.1", "--port", str(port), "--save", str(work / "live.rrd")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                            start_new_session=True)  # `rerun` is a launcher: its viewer binary is a child
    for _ in range(300):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            break
        except OSError:
            time.sleep(0.1)
    return proc, f"rerun+http://127.0.0.1:{port}/proxy"


def one(sc, out: Path, sim: float, live: LiveTarget | None) -> float:
    t0 = time.perf_counter()
    run_scenario(sc, out, duration_s=sim, live=live)
    return sim / (time.perf_counter() - t0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sim", type=float, default=200.0)
    p.add_argument("--repeat", type=int, default=3)
    args = p.parse_args()
    sc = load_scenario("seed000")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        proxy, url = start_proxy(work)
        try:
            file_only, live = [], []
            for k in range(args.repeat):
                file_only.append(one(sc, work / f"f{k}", args.sim, None))
                live.append(one(sc, work / f"l{k}", args.sim, LiveTarget(url=url)))
        finally:
            os.killpg(proxy.pid, signal.SIGTERM)  # the launcher and the binary it started
            proxy.wait(10)
    a, b = statistics.median(file_only), statistics.median(live)
    print(f"seed000, {args.sim:g} s simulated, median of {args.repeat}:")
    print(f"  run.rrd only          {a:6.1f}x real time   ({', '.join(f'{x:.1f}' for x in file_only)})")
    print(f"  run.rrd + --connect   {b:6.1f}x real time   ({', '.join(f'{x:.1f}' for x in live)})")
    print(f"  live view costs {100 * (a / b - 1):+.1f} % wall time")


if __name__ == "__main__":
    main()

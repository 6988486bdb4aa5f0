"""Cost of recording a run to .rrd: the writer on a finished seed000 log, and per-frame rows (recording.frames).

    python bench/bench_recording.py [--sim 60] [--ideal-sim 800]

Prints the wall time of writing everything (signals, 2D track, bus load and latency, events) in one go, for the
ideal loop's log (--ideal-sim simulated seconds: signals only) and the network run's (--sim: signals and every
frame's latency), the file sizes, and the cost per CAN frame of the per-frame text rows.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from hil.record.frames import FrameRecorder
from hil.record.rerun_writer import RerunWriter
from hil.runtime.ideal import IdealLoop
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario
from hil.session import IncrementalRecorder


def write(log, sc, path: Path, frames: FrameRecorder | None = None) -> float:
    t0 = time.perf_counter()
    with RerunWriter(path, log.layout, sc.name, sc.plant.coupler_band_m, sc.trains.spacing_m,
                     sc.trains.emergency_gap_m, frames=frames is not None) as w:
        rec = IncrementalRecorder(w)
        rec.frames = frames
        rec(log)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=60.0, help="simulated seconds of the network run")
    ap.add_argument("--ideal-sim", type=float, default=800.0, help="simulated seconds of the ideal loop")
    ap.add_argument("--scenario", default="seed000")
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    out = Path(tempfile.mkdtemp(prefix="bench-recording-"))
    ideal = IdealLoop(sc).run(args.ideal_sim)
    rig = VirtualRig(sc)
    frames = FrameRecorder(rig.buses, rig.db)
    net = rig.run(args.sim)
    n_frames = sum(b.frames_sent for b in net.buses)
    for name, log in ((f"ideal loop {args.ideal_sim:g} s", ideal), (f"network {args.sim:g} s", net)):
        times = [write(log, sc, out / "a.rrd") for _ in range(3)]
        print(f"{name:18s}: {len(log.signals)} samples, write {min(times):.3f}-{max(times):.3f} s, "
              f"{(out / 'a.rrd').stat().st_size / 1e6:.1f} MB")
    t = write(net, sc, out / "frames.rrd", frames)
    base = min(write(net, sc, out / "a.rrd") for _ in range(2))
    print(f"with frame rows   : {n_frames} frames, write {t:.2f} s ({(t - base) / n_frames * 1e6:.1f} us per frame), "
          f"{(out / 'frames.rrd').stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()

"""Seed 001 period study: STSMCA at 1, 5 and 10 ms ECU periods, as written and with the remedy, side by side.

    python docs/seed001_period_study.py [--duration 200] [--workers 1]

Every run is the packaged ``seed001`` scenario (start-up, the ramp, the pulse on car 1 at 100-130 s) with
the ECU, Sensor and Reference periods all set to P. Variants:

- exchange schedule over CAN: front to back (``ecu.stagger_s`` = 0.5 ms, the scenario's: each car has the car
  ahead's acceleration of the same period, a Gauss-Seidel sweep) or the rig's default 0.1 ms stagger (every
  car uses its neighbours' values of the previous period, a Jacobi sweep, as the ideal loop does);
- the law as written (``accel_gain`` = 1) or the remedy, the under-relaxed neighbour feed-forward
  ``accel_gain`` = 0.8, and for contrast the 2-sample mean filter (``accel_exchange = "mean2"``);
- 1 ms runs only in the ideal loop: 26 frames per cycle need 3.2 ms of a 1 Mbit/s classical CAN bus;
- step sensitivity: two CAN runs again with half the plant step (0.5 ms).

Writes docs/figures/seed001-period-study.png and .json (the table's numbers), prints a markdown table.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from hil.compare.report import CompareRun, families
from hil.compare.runner import CompareItem, run_items
from hil.scenario import load_scenario

FIG = Path(__file__).resolve().parent / "figures"
GS, JACOBI = 0.0005, 0.0001


def variants() -> list[tuple[str, float, bool, dict]]:
    """(label, period, ideal, extra overrides) of every run of the study."""
    kappa = {"controller.params.accel_gain": 0.8}
    mean2 = {"controller.params.accel_exchange": "mean2"}
    out = [("1 ms ideal, as written", 0.001, True, {}), ("1 ms ideal, kappa 0.8", 0.001, True, kappa)]
    for p in (0.005, 0.01):
        ms = f"{p * 1e3:g} ms"
        out += [
            (f"{ms} CAN front-to-back, as written", p, False, {"ecu.stagger_s": GS}),
            (f"{ms} CAN front-to-back, kappa 0.8", p, False, {"ecu.stagger_s": GS, **kappa}),
            (f"{ms} CAN front-to-back, mean2", p, False, {"ecu.stagger_s": GS, **mean2}),
            (f"{ms} CAN 0.1 ms stagger, as written", p, False, {"ecu.stagger_s": JACOBI}),
            (f"{ms} CAN 0.1 ms stagger, kappa 0.8", p, False, {"ecu.stagger_s": JACOBI, **kappa}),
            (f"{ms} ideal, as written", p, True, {}),
            (f"{ms} ideal, kappa 0.8", p, True, kappa),
        ]
    half = {"plant.step_s": 0.0005}  # step sensitivity: the same runs with half the plant step
    out += [("5 ms CAN front-to-back, as written, plant step 0.5 ms", 0.005, False, {"ecu.stagger_s": GS, **half}),
            ("10 ms CAN front-to-back, kappa 0.8, plant step 0.5 ms", 0.01, False, {"ecu.stagger_s": GS, **kappa, **half})]
    return out


def items(duration: float) -> list[CompareItem]:
    out = []
    for label, p, ideal, extra in variants():
        sc = load_scenario("seed001", {"ecu.cycle_s": p, "can.sensor_period_s": p, "reference.period_s": p, **extra})
        out.append(CompareItem(label, sc, "single_train", ideal, duration))
    return out


COLUMNS = [("spacing_time_s", "spacing within 1 cm after (s)", "{:.2f}"),
           ("speed_err_min_mps", "v - v_r min after 10 s (m/s)", "{:.2e}"),
           ("speed_err_max_mps", "v - v_r max after 10 s (m/s)", "{:.2e}"),
           ("adjacent_dv_max_mps", "max |v_j - v_j+1| after 10 s (m/s)", "{:.2e}"),
           ("spacing_min_m", "spacing min (m)", "{:.4f}"),
           ("spacing_max_m", "spacing max (m)", "{:.4f}"),
           ("peak_force_kn", "peak |F| (kN)", "{:.0f}"),
           ("chattering_kn_per_s", "TV(F) after 10 s (kN/s per car)", "{:.4g}"),
           ("bus_load_max", "bus load max", "{:.2f}")]


def table(runs: list[CompareRun]) -> str:
    head = "| run | " + " | ".join(c[1] for c in COLUMNS) + " |\n|---|" + "---|" * len(COLUMNS) + "\n"
    rows = []
    for r in runs:
        cells = []
        for key, _, fmt in COLUMNS:
            v = r.metrics.get(key)
            cells.append("–" if v is None else fmt.format(v))
        rows.append(f"| {r.label} | " + " | ".join(cells) + " |")
    return head + "\n".join(rows)


def plot(runs: list[CompareRun], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pick = ["1 ms ideal, as written", "5 ms CAN front-to-back, as written", "10 ms CAN front-to-back, as written",
            "10 ms CAN 0.1 ms stagger, as written", "10 ms CAN front-to-back, kappa 0.8", "10 ms CAN front-to-back, mean2"]
    by = {r.label: r for r in runs}
    fig = Figure(figsize=(11, 8))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    for i, label in enumerate(pick):
        r = by.get(label)
        if r is None:
            continue
        worst = np.max(np.abs(r.speed_error), axis=1)
        per = max(1, int(round(1.0 / np.median(np.diff(r.t)))))  # samples per second
        n = len(worst) // per
        env = worst[: n * per].reshape(n, per).max(axis=1)  # 1 s envelope of the recorded samples
        ax1.semilogy(r.t[: n * per : per] + 0.5, np.maximum(env, 1e-5), lw=1.2, color=f"C{i}", label=label)
        k = np.searchsorted(r.t, 20.0)
        idx = np.argmax(np.abs(r.speed_error[:k]), axis=1)
        ax2.plot(r.t[:k], r.speed_error[np.arange(k), idx], lw=0.8, color=f"C{i}")
    ax1.axhspan(1e-5, 1.1e-3, color="0.85", zorder=0, label="paper's band (|e| <= 1.1e-3 m/s)")
    ax1.set_ylabel("max over cars |v - v_r|, 1 s envelope (m/s)")
    ax1.set_xlabel("t (s)  (pulse disturbance on car 1 at 100-130 s)")
    ax1.legend(fontsize=7.5, loc="upper right", ncol=2)
    ax1.grid(True, which="both", alpha=0.3)
    ax2.set_ylabel("v - v_r, worst car (m/s)")
    ax2.set_xlabel("t (s), start-up")
    ax2.set_ylim(-0.6, 0.6)
    ax2.grid(True, alpha=0.3)
    fig.suptitle("seed 001 STSMCA: ECU period and neighbour-acceleration exchange (recorded every 50 ms)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=200.0)
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    families()
    runs = run_items(items(args.duration), args.workers, progress=lambda s: print("done:", s, file=sys.stderr, flush=True))
    FIG.mkdir(exist_ok=True)
    plot(runs, FIG / "seed001-period-study.png")
    (FIG / "seed001-period-study.json").write_text(json.dumps(
        {"command": f"python docs/seed001_period_study.py --duration {args.duration:g}",
         "runs": [{"run": r.label, "runtime": r.runtime, "metrics": r.metrics} for r in runs]}, indent=1))
    print(table(runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())

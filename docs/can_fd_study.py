"""Which bus does each law need? Seed 001 at 1 ms and seed 004 at 0.2 ms (kN fractional) and 1.4 ms (kN PID) over
classical CAN and CAN FD, beside the ideal loop.

    python docs/can_fd_study.py [--duration-001 200] [--duration-004 200] [--workers 2]

Every run is a packaged scenario with the ECU and Sensor periods set to the law's (seed 001: Reference too, as in
its period study) and the bus set to one of: classical CAN at 1 Mbit/s, or CAN FD at 1 Mbit/s nominal with the
bit-rate switch to 2, 5 or 8 Mbit/s. Two frame sets: dbc/train.dbc's (Sensor, AgentState, AgentAux and
TractionCmd per unit, Reference and ReferenceAux), sent as FD frames on the FD buses; and on the FD buses also
dbc/train_fd.dbc's ("packed": each ECU's three frames of a cycle in one 20-byte container, the plant's sensor
frames in one container per 8 units, Reference and ReferenceAux in one 12-byte container; every part keeps its
E2E header). Nothing else changes.

Writes docs/figures/can-fd-study.json (every figure of the tables) and prints the markdown tables: the runs
(bus load, latency, drops, the papers' metrics) and the response-time analysis (worst-case utilisation and the
shortest period every frame meets, for both frame sets).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

from ecu_sim.codec import TrainDb, default_dbc_path
from hil.can.analysis import TrainBusSetup, analyse_train_bus
from hil.can.wcrt import BusRates
from hil.compare.report import CompareRun, families
from hil.compare.runner import CompareItem, run_items
from hil.scenario import load_scenario

FIG = Path(__file__).resolve().parent / "figures"
NOMINAL = 1_000_000
BUSES = [("ideal loop", None), ("classical 1M", {}), ("FD 1M/2M", {"can.fd": True, "can.data_bitrate": 2_000_000}),
         ("FD 1M/5M", {"can.fd": True, "can.data_bitrate": 5_000_000}),
         ("FD 1M/8M", {"can.fd": True, "can.data_bitrate": 8_000_000})]
PACKED = {"can.dbc": "train_fd.dbc"}
BUSES += [(f"{bus} packed", {**extra, **PACKED}) for bus, extra in BUSES if extra and extra.get("can.fd")]
# (scenario, the law's period, whether the reference follows the period, which seed)
LAWS = [("seed001", 0.001, True, "001"), ("seed001-smca", 0.001, True, "001"), ("seed001-pidca", 0.001, True, "001"),
        ("seed001-cca", 0.001, True, "001"), ("seed004-kn", 0.0002, False, "004"), ("seed004-kn-pid", 0.0014, False, "004")]


def period_overrides(period_s: float, with_reference: bool) -> dict:
    out = {"ecu.cycle_s": period_s, "can.sensor_period_s": period_s, "can.bitrate": NOMINAL}
    if with_reference:
        out["reference.period_s"] = period_s
    return out


def items(durations: dict[str, float]) -> list[CompareItem]:
    out = []
    for name, period, with_ref, seed in LAWS:
        for bus, extra in BUSES:
            sc = load_scenario(name, {**period_overrides(period, with_ref), **(extra or {})})
            out.append(CompareItem(f"{name} {period * 1e3:g} ms, {bus}", sc, "single_train", extra is None, durations[seed]))
    return out


COLUMNS = [("bus_load_max", "bus load max", "{:.2f}"),
           ("latency_to_period_max", "worst latency / period", "{:.2f}"),
           ("frame_latency_max_s", "worst latency (ms)", "ms"),
           ("frames_dropped", "frames dropped", "{:d}"),
           ("spacing_time_s", "spacing within 1 cm after (s)", "{:.2f}"),
           ("speed_err_worst_after_mps", "worst |v - v_r| after 10 s (m/s)", "{:.3g}"),
           ("speed_err_worst_mps", "worst |v - v_r| (m/s)", "{:.3g}"),
           ("spacing_min_m", "spacing min (m)", "{:.3f}"),
           ("spacing_max_m", "spacing max (m)", "{:.3f}"),
           ("peak_force_kn", "peak |F| (kN)", "{:.0f}")]


def _cell(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value * 1e3:.3g}" if fmt == "ms" else fmt.format(value)


def run_table(runs: list[CompareRun]) -> str:
    head = "| run | " + " | ".join(c[1] for c in COLUMNS) + " |\n|---|" + "---|" * len(COLUMNS) + "\n"
    return head + "\n".join(f"| {r.label} | " + " | ".join(_cell(r.metrics.get(k), f) for k, _, f in COLUMNS) + " |"
                            for r in runs)


# ------------------------------------------------------------------------------------------ the analysis


def _rates(extra: dict) -> BusRates:
    return BusRates(NOMINAL, extra.get("can.data_bitrate"), fd=bool(extra.get("can.fd")))


def shortest_period(fits, lo: float = 1e-5, hi: float = 0.05) -> float | None:
    """The shortest period (to 1 us) at which ``fits(period)`` holds, by bisection (None if not even at ``hi``)."""
    if not fits(hi):
        return None
    while hi - lo > 1e-6:
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    return hi


def dbc_frame_set_fits(db: TrainDb, name: str, rates: BusRates, units: int | None = None):
    """fits(period): every frame of the scenario's bus meets its deadline at that ECU, Sensor and Reference period."""
    units = load_scenario(name).trains.units if units is None else units  # one train: no radio frames
    base = TrainBusSetup(units=units, bitrate=NOMINAL, n_trains=1, fd=rates.fd, data_bitrate=rates.data)

    def fits(period: float) -> bool:
        setup = dataclasses.replace(base, cycle_s=period, sensor_period_s=period, reference_period_s=period)
        return all(t.schedulable for t in analyse_train_bus(db, setup))
    return fits


def _dbs() -> tuple[TrainDb, TrainDb]:
    """The two frame sets: dbc/train.dbc's and the packed dbc/train_fd.dbc's."""
    return TrainDb.load(), TrainDb.load(default_dbc_path("train_fd.dbc"))


def _unpacked_buses() -> list[tuple[str, dict]]:
    return [(bus, extra) for bus, extra in BUSES[1:] if "can.dbc" not in extra]


def analysis_rows() -> list[dict]:
    db, packed = _dbs()
    out = []
    for units, label in ((6, "seed 001 (6 cars)"), (8, "seed 004 (8 cars)")):
        name = "seed001" if units == 6 else "seed004-kn"
        for bus, extra in _unpacked_buses():
            rates = _rates(extra)
            out.append({"train": label, "bus": bus,
                        "dbc_shortest_period_s": shortest_period(dbc_frame_set_fits(db, name, rates)),
                        "packed_shortest_period_s": shortest_period(dbc_frame_set_fits(packed, name, rates))
                        if rates.fd else None})
    return out


def most_units(fits_for_units, period: float, limit: int = 16) -> int:
    """The most cars per bus whose frames all meet their deadlines at ``period`` (0: not even one)."""
    best = 0
    for n in range(1, limit + 1):
        if not fits_for_units(n)(period):
            break
        best = n
    return best


def capacity_rows() -> list[dict]:
    """For each law's period: how many cars one bus carries, DBC frame set and packed (CAN FD only)."""
    db, packed = _dbs()
    out = []
    for label, name, period in (("seed 001 at 1 ms", "seed001", 0.001), ("seed 004 kN at 0.2 ms", "seed004-kn", 0.0002),
                                ("seed 004 kN PID at 1.4 ms", "seed004-kn-pid", 0.0014)):
        for bus, extra in _unpacked_buses():
            rates = _rates(extra)
            out.append({"law": label, "bus": bus,
                        "dbc_units": most_units(lambda n: dbc_frame_set_fits(db, name, rates, n), period),
                        "packed_units": most_units(lambda n: dbc_frame_set_fits(packed, name, rates, n), period)
                        if rates.fd else None})
    return out


def capacity_table(rows: list[dict]) -> str:
    head = "| law and period | bus | cars per bus, DBC frame set | cars per bus, packed frame set (train_fd.dbc) |\n|---|---|---|---|\n"
    return head + "\n".join(f"| {r['law']} | {r['bus']} | {r['dbc_units']} | "
                            f"{'–' if r['packed_units'] is None else r['packed_units']} |" for r in rows)


def analysis_table(rows: list[dict]) -> str:
    ms = lambda v: "–" if v is None else f"{v * 1e3:.3f}"  # noqa: E731
    head = ("| train | bus | shortest period, DBC frame set (ms) | shortest period, packed frame set, train_fd.dbc (ms) |\n"
            "|---|---|---|---|\n")
    return head + "\n".join(f"| {r['train']} | {r['bus']} | {ms(r['dbc_shortest_period_s'])} | "
                            f"{ms(r['packed_shortest_period_s'])} |" for r in rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration-001", type=float, default=200.0, help="simulated seconds of each seed 001 run")
    ap.add_argument("--duration-004", type=float, default=200.0, help="simulated seconds of each seed 004 run")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--analysis-only", action="store_true", help="only the response-time analysis (seconds)")
    args = ap.parse_args(argv)
    rows, capacity = analysis_rows(), capacity_rows()
    print(analysis_table(rows), end="\n\n")
    print(capacity_table(capacity), end="\n\n")
    runs: list[CompareRun] = []
    if not args.analysis_only:
        families()
        runs = run_items(items({"001": args.duration_001, "004": args.duration_004}), args.workers,
                         progress=lambda s: print("done:", s, file=sys.stderr, flush=True))
        print(run_table(runs))
    FIG.mkdir(exist_ok=True)
    command = "python docs/can_fd_study.py" + ("" if args.analysis_only else
                                                f" --duration-001 {args.duration_001:g} --duration-004 {args.duration_004:g}")
    out = {"command": command, "analysis": rows, "capacity": capacity,
           "runs": [{"run": r.label, "runtime": r.runtime, "metrics": r.metrics} for r in runs]}
    target = FIG / ("can-fd-analysis.json" if args.analysis_only else "can-fd-study.json")
    target.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Reliability benchmark: faults injected vs detected, frames corrupted vs rejected, recordings intact
after N random kills.

    python bench/bench_reliability.py                                   # every part with the defaults
    python bench/bench_reliability.py --scenario-s 60 --realtime-s 0 --campaign 2 --frames 5000 --kills 3

Parts (each can be skipped with 0):

1. ``--scenario-s``: the packaged ``faults`` scenario in virtual time (ECU crash and restart, babbling node,
   corruption burst, 20 s tunnel blackout): injected vs detected, detection latencies, CAN errors, safety verdicts.
2. ``--realtime-s``: the same on the real-time rig (pace 1).
3. ``--campaign``: runs of a small group (2 trains x 2 units, consensus law) with every one of the 13 fault kinds
   at seeded random times, targets and parameters: injected vs detected per kind, detection latency.
4. ``--frames``: random CAN frames with 1..8 random bit errors through the receiver's bit-level checks
   (the oracle tests/oracle/bus_errors.py, the engine's model): corrupted vs rejected per number of flipped bits (CAN's residual error rate).
5. ``--kills``: ``hil run faults`` killed at random moments (``tests/killtest.py``'s ``random_kills``): recordings intact.

Results go to ``--out``/results.json and are printed as tables; docs/faults.md quotes them.
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.oracle.bus_errors import corrupt, receive, wire_bits  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402
from hil.scenario.loader import read_scenario_data, resolve, scenario_from_dict  # noqa: E402
from hil.scenario.model import FAULT_KINDS  # noqa: E402

SLOT_S = 12.0  # one fault per slot in a campaign run


# --------------------------------------------------------------------------- 1, 2: the packaged scenario


def packaged(duration: float, out: Path, realtime: bool) -> dict:
    from hil.session import run_scenario

    sc = load_scenario("faults")
    t = time.perf_counter()
    if realtime:
        from hil.runtime.realtime.orchestrator import run_realtime

        res = run_realtime(sc, out, pace=1.0, duration_s=duration)
    else:
        res = run_scenario(sc, out, duration_s=duration)
    m = res.metrics
    f, s = m["faults"], m["safety"]
    return {"runtime": m["runtime"], "sim_s": m["sim_time_s"], "wall_s": round(time.perf_counter() - t, 1),
            "injected": f["injected"], "detected": f["detected"],
            "faults": [{k: r[k] for k in ("kind", "target", "start_s", "end_s", "detected_s", "detection_latency_s",
                                          "detected_by", "detectors")} for r in f["faults"]],
            "can_errors": {k: f["can_errors"][k] for k in ("corrupted", "rejected", "undetected", "undetected_caught_by_e2e",
                                                           "undetected_unknown_id", "undetected_accepted", "error_frames")},
            "bus_off": {n: c["bus_off"] for b in f["can_errors"]["buses"].values() for n, c in b["nodes"].items()},
            "ecu_restarts": f["ecu_restarts"],
            "gap_min_m": m["gap_min_m"], "gap_below_le": s["gap_below_le"]["violated"],
            "collision": s["collision"]["violated"], "coupler_out_of_band_s": s["coupler_out_of_band"]["total_s"],
            "overspeed_s": s["overspeed"]["total_s"]}


# --------------------------------------------------------------------------- 3: a campaign


def small_scenario(faults: list[dict], duration: float, seed: int):
    data = read_scenario_data(resolve("seed000-consensus"))
    data.update(name="campaign", duration_s=duration, seed=seed, faults=faults)
    data["trains"].update(count=2, units=2, head_positions_m=[109000.0, 105840.0], speeds_kmh=[316.0, 316.0])
    return scenario_from_dict(data, "campaign")


def random_fault(kind: str, start: float, rng: random.Random) -> dict:
    """One fault of ``kind`` at ``start`` with random target and parameters (2 trains x 2 units)."""
    # the force balance judges 2 s windows and wants two in a row: actuator faults last long enough for it
    long = kind in ("actuator_degradation", "traction_loss")
    f: dict = {"kind": kind, "at_s": round(start, 3), "duration_s": round(rng.uniform(5.0, 7.0) if long else rng.uniform(2.0, 4.0), 3)}
    if kind in ("ecu_crash", "ecu_hang", "sensor_stuck", "sensor_noise", "actuator_degradation", "traction_loss"):
        f.update(train=rng.randint(1, 2), unit=rng.randint(1, 2))
    elif kind.startswith("radio"):
        f["pair"] = 1
    else:
        f["train"] = rng.randint(1, 2)
    if kind == "sensor_noise":
        f["position_noise_m"] = round(rng.uniform(0.2, 3.0), 2)
    elif kind == "actuator_degradation":
        f["health"] = round(rng.uniform(0.0, 0.6), 2)
    elif kind == "bus_corruption":
        f.update(bits=rng.randint(1, 5), probability=round(rng.uniform(0.05, 1.0), 2))
    elif kind in ("bus_error_frames", "frame_drop"):
        f["probability"] = round(rng.uniform(0.05, 1.0), 2)
    elif kind == "radio_burst_loss":
        f["probability"] = round(rng.uniform(0.3, 1.0), 2)
    elif kind == "radio_latency":
        f["latency_s"] = round(rng.uniform(0.02, 0.5), 3)
    return f


def campaign(runs: int, seed: int) -> dict:
    from hil.runtime.virtual import VirtualRig

    rng = random.Random(seed)
    per_kind = {k: {"injected": 0, "detected": 0, "latencies": [], "missed": []} for k in FAULT_KINDS}
    can = dict.fromkeys(("corrupted", "rejected", "undetected", "undetected_caught_by_e2e", "undetected_unknown_id",
                         "undetected_accepted"), 0)
    wall = 0.0
    for r in range(runs):
        kinds = list(FAULT_KINDS)
        rng.shuffle(kinds)
        faults = [random_fault(k, i * SLOT_S + rng.uniform(1.0, 3.0), rng) for i, k in enumerate(kinds)]
        sc = small_scenario(faults, len(kinds) * SLOT_S, seed * 1000 + r)
        t = time.perf_counter()
        log = VirtualRig(sc).run()
        wall += time.perf_counter() - t
        rep = log.fault_report
        for spec, row in zip(faults, rep["faults"]):
            c = per_kind[row["kind"]]
            c["injected"] += row["injected"]
            c["detected"] += row["detected"]
            if row["detected"]:
                c["latencies"].append(row["detection_latency_s"])
            else:
                c["missed"].append({k: v for k, v in spec.items() if k not in ("kind", "at_s")})
        for k in can:
            can[k] += rep["can_errors"][k]
    table = {}
    for k, c in per_kind.items():
        lat = np.array(c["latencies"])
        table[k] = {"injected": c["injected"], "detected": c["detected"],
                    "latency_p50_s": float(np.median(lat)) if lat.size else None,
                    "latency_max_s": float(lat.max()) if lat.size else None, "missed": c["missed"]}
    return {"runs": runs, "seed": seed, "sim_s_per_run": len(FAULT_KINDS) * SLOT_S, "wall_s": round(wall, 1),
            "injected": sum(c["injected"] for c in table.values()), "detected": sum(c["detected"] for c in table.values()),
            "by_kind": table, "can_errors": can}


# --------------------------------------------------------------------------- 4: bit errors


def bit_errors(frames: int, seed: int, max_bits: int = 8) -> dict:
    rng = random.Random(seed)
    out = {}
    for bits in range(1, max_bits + 1):
        by = {"corrupted": 0, "rejected": 0, "undetected": 0, "stuff": 0, "form": 0, "crc": 0}
        for _ in range(frames):
            ext = rng.random() < 0.2
            cid = rng.randrange(1 << (29 if ext else 11))
            data = bytes(rng.randrange(256) for _ in range(rng.randint(0, 8)))
            wire = wire_bits(cid, data, ext)
            seen = receive(corrupt(wire, rng.sample(range(1, len(wire) - 9), bits)))
            by["corrupted"] += 1
            if seen.error is None:
                by["undetected"] += 1
            else:
                by["rejected"] += 1
                by[seen.error] += 1
        out[str(bits)] = by
    return out


# --------------------------------------------------------------------------- 5: kills


def kills(n: int, out: Path, seed: int) -> dict:
    try:
        from tests.killtest import random_kills
    except ImportError:  # the robustness half's helper is not there
        return {"n": n, "skipped": "tests/killtest.py not available"}
    outcomes = random_kills(n, out, seed=seed, max_delay_s=8.0, scenario="faults", duration_s=300.0)
    return {"n": n, "intact": sum(o.intact for o in outcomes),
            "kills": [{"delay_s": round(o.delay_s, 2), "signal": o.signal, "intact": o.intact,
                       "sim_time_s": o.report.sim_time_s, "problems": o.report.problems} for o in outcomes]}


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario-s", type=float, default=300.0, help="virtual run of the faults scenario (0: skip)")
    p.add_argument("--realtime-s", type=float, default=45.0, help="real-time run of the faults scenario (0: skip)")
    p.add_argument("--campaign", type=int, default=4, help="campaign runs of 13 faults each (0: skip)")
    p.add_argument("--frames", type=int, default=20000, help="random frames per number of bit errors (0: skip)")
    p.add_argument("--kills", type=int, default=5, help="random kills of hil run faults (0: skip)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-reliability")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    if args.scenario_s > 0:
        results["virtual"] = r = packaged(args.scenario_s, args.out / "virtual", False)
        _print_packaged(r)
    if args.realtime_s > 0:
        results["realtime"] = r = packaged(args.realtime_s, args.out / "realtime", True)
        _print_packaged(r)
    if args.campaign > 0:
        results["campaign"] = r = campaign(args.campaign, args.seed)
        print(f"\ncampaign: {r['runs']} runs x {len(FAULT_KINDS)} faults ({r['sim_s_per_run']:g} s each, "
              f"{r['wall_s']} s wall): detected {r['detected']} of {r['injected']}")
        print(f"  {'kind':22s} {'injected':>8s} {'detected':>8s} {'latency p50':>12s} {'max':>8s}")
        for k, c in r["by_kind"].items():
            p50 = "-" if c["latency_p50_s"] is None else f"{c['latency_p50_s']:.3f} s"
            mx = "-" if c["latency_max_s"] is None else f"{c['latency_max_s']:.3f} s"
            print(f"  {k:22s} {c['injected']:8d} {c['detected']:8d} {p50:>12s} {mx:>8s}"
                  + (f"   missed: {c['missed']}" if c["missed"] else ""))
        c = r["can_errors"]
        print(f"  frames corrupted {c['corrupted']}: rejected by the CAN receivers {c['rejected']}, let through "
              f"{c['undetected']} (of which caught by the E2E CRC {c['undetected_caught_by_e2e']}, dropped as an "
              f"unknown ID {c['undetected_unknown_id']}, accepted {c['undetected_accepted']})")
    if args.frames > 0:
        results["bit_errors"] = r = bit_errors(args.frames, args.seed)
        print(f"\nCAN receivers against random bit errors ({args.frames} random frames per row)")
        print(f"  {'bits':>4s} {'corrupted':>9s} {'rejected':>9s} {'undetected':>10s}  stuff/form/crc")
        for bits, c in r.items():
            print(f"  {bits:>4s} {c['corrupted']:9d} {c['rejected']:9d} {c['undetected']:10d}  "
                  f"{c['stuff']}/{c['form']}/{c['crc']}")
    if args.kills > 0:
        results["kills"] = r = kills(args.kills, args.out / "kills", args.seed)
        if "skipped" in r:
            print(f"\nrandom kills: skipped ({r['skipped']})")
        else:
            print(f"\nrecordings intact after {r['n']} random kills of `hil run faults`: {r['intact']} of {r['n']}")
    (args.out / "results.json").write_text(json.dumps(results, indent=1, default=str) + "\n")
    print(f"\nwritten to {args.out / 'results.json'}")
    return 0


def _print_packaged(r: dict) -> None:
    print(f"\nfaults scenario, {r['runtime']}, {r['sim_s']:g} simulated s ({r['wall_s']} s wall): "
          f"detected {r['detected']} of {r['injected']} injected faults, {r['ecu_restarts']} ECU restart(s)")
    for f in r["faults"]:
        if f["start_s"] is None:  # a run shorter than the schedule
            print(f"  {f['kind']:16s} {f['target']:18s} not started")
            continue
        lat = "-" if f["detection_latency_s"] is None else f"{f['detection_latency_s']:.3f} s"
        print(f"  {f['kind']:16s} {f['target']:18s} start {f['start_s']:8.3f} s  detected after {lat:>9s} by "
              f"{f['detected_by']}")
    c = r["can_errors"]
    print(f"  frames corrupted {c['corrupted']}, rejected {c['rejected']}, undetected {c['undetected']}; "
          f"bus-off episodes {sum(r['bus_off'].values())}")
    print(f"  min gap {r['gap_min_m']} m, gap below l_e: {r['gap_below_le']}, collision: {r['collision']}, "
          f"coupler out of band {r['coupler_out_of_band_s']:.1f} s, overspeed {r['overspeed_s']:.1f} s (unit-seconds)")


if __name__ == "__main__":
    sys.exit(main())

"""Seed 004's results: run the scenarios, then print the tables of docs/seed004.md and draw its figure.

    python docs/seed004_report.py run [KEY ...]     # one run per key (default: all), saved as runs/seed004-report/KEY.npz
    python docs/seed004_report.py table             # tables (markdown) from the saved runs
    python docs/seed004_report.py figure            # docs/figures/seed004-errors.png

Each run is a full scenario (1250 s) unless its key says otherwise, over CAN (VirtualRig) or in the ideal loop,
with the plant step and ECU period of its scenario or of the overrides listed in RUNS. The slowest are the kN
runs in the ideal loop at 0.2 ms (about 15-40 min each on the 2-core dev machine, depending on its load).
Band metrics use the recorded samples (every 10 ms), all cars together (the worst car at each sample).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from hil.plant import PlantDiverged
from hil.runtime.ideal import IdealLoop
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario

OUT = Path("runs/seed004-report")
FIG = Path(__file__).parent / "figures" / "seed004-errors.png"
BAND_E, BAND_V = 0.012, 0.0025  # the paper's bands: m, m/s
FAST = {"ecu.cycle_s": 0.0002, "can.sensor_period_s": 0.0002}  # the kN laws' period in the ideal loop
HALF = {"plant.step_s": 0.0001, "ecu.cycle_s": 0.0001, "can.sensor_period_s": 0.0001, "recording.period_s": 0.01}
FAULTS = {150.0: "car 2 h 0.7", 350.0: "car 5 h -> 0.5 (20 s), -1 kN", 620.0: "car 6 h 0.6"}
REALISTIC_N = 60e3  # ~ a CRH5A motor car's share of the train's ~300 kN starting effort (order of magnitude)

# key: (scenario, runtime, overrides, duration or None for the scenario's)
RUNS: dict[str, tuple[str, str, dict, float | None]] = {
    "frac-N-can": ("seed004", "can", {}, None),
    "frac-N-ideal": ("seed004", "ideal", {}, None),
    "pid-N-can": ("seed004-pid", "can", {}, None),
    "pid-N-ideal": ("seed004-pid", "ideal", {}, None),
    "frac-kN-can": ("seed004-kn", "can", {}, None),
    "pid-kN-can": ("seed004-kn-pid", "can", {}, None),
    "frac-kN-ideal": ("seed004-kn", "ideal", FAST, None),
    "pid-kN-ideal": ("seed004-kn-pid", "ideal", FAST, None),
    "ours-can": ("seed004-ours", "can", {}, None),
    # the ECU phase of seeds 000-002 (2 ms + 0.1 ms per unit): car 8 reads its sensor one period older than x_r
    "ours-can-phase2.7ms": ("seed004-ours", "can", {"ecu.phase_s": 0.002, "ecu.stagger_s": 0.0001}, None),
    "ours-ideal": ("seed004-ours", "ideal", {}, None),
    # halving the plant step, the ECU period, or both (0.2 ms ideal runs), over the first 400 s (two traction
    # phases, the first cruise, the faults on cars 2 and 5): compared with the first 400 s of the base run
    "frac-N-can-step0.1ms-400s": ("seed004", "can", {"plant.step_s": 0.0001}, 400.0),
    "ours-can-step0.1ms-400s": ("seed004-ours", "can", {"plant.step_s": 0.0001}, 400.0),
    "ours-can-ecu5ms-400s": ("seed004-ours", "can", {"ecu.cycle_s": 0.005, "can.sensor_period_s": 0.005, "ecu.phase_s": 0.0025,
                                                     "reference.period_s": 0.005, "can.bitrate": 1000000}, 400.0),
    "frac-kN-ideal-0.1ms-400s": ("seed004-kn", "ideal", HALF, 400.0),
    "pid-kN-ideal-0.1ms-400s": ("seed004-kn-pid", "ideal", HALF, 400.0),
    # what the RBF / adaptive term does (ideal loop, against frac-N-ideal)
    "frac-N-ideal-c2=0": ("seed004", "ideal", {"controller.params.c2": 0.0}, None),
    "frac-N-ideal-rbfstart": ("seed004", "ideal", {"controller.params.rbf_origin": "start"}, None),
}


# ---------------------------------------------------------------------- running


def run(key: str) -> Path:
    name, runtime, overrides, duration = RUNS[key]
    sc = load_scenario(name, dict(overrides))
    wall = time.perf_counter()
    rig = VirtualRig(sc) if runtime == "can" else IdealLoop(sc)
    peak, tv = _track_every_step(rig.parts.plant)
    diverged = None
    try:
        log = rig.run(duration)
    except PlantDiverged as exc:  # keep what was run (the ideal loop has no codec saturating the forces)
        log, diverged = rig.log, str(exc)[:300]
    wall = time.perf_counter() - wall
    e, de = log.position_error, log.speed_error
    stats = [getattr(c, "stats", {}) | {"rho_hat": getattr(c, "rho_hat", None)} for c in rig.parts.controllers]
    meta = {"key": key, "scenario": name, "runtime": runtime, "overrides": overrides, "wall_s": wall, "diverged": diverged,
            "plant_step_s": sc.plant.step_s, "ecu_cycle_s": sc.ecu.cycle_s,
            "changes": [float(c) for c in rig.parts.reference.change_times],
            "saturations": {k: int(v) for k, v in log.codec_saturations.items()},
            "bus_load_max": max((float(b.load.array[:, 1].max()) for b in log.buses if len(b.load)), default=None),
            "controllers": stats, "events": [(ev.t, ev.level, ev.source, ev.text) for ev in log.events[:50]],
            "masses": rig.parts.plant.layout.effective_mass_kg.tolist(), "distribution": rig.parts.plant.units.distribution.tolist(),
            "slope": rig.parts.plant.units.slope.tolist()}
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"{key}.npz"
    np.savez_compressed(path, t=log.t, e=e.astype(np.float32), de=de.astype(np.float32),
                        e_max=np.abs(e).max(axis=1), de_max=np.abs(de).max(axis=1),
                        f_applied=log.force_applied.astype(np.float32), f_cmd=log.force_cmd.astype(np.float32),
                        f_peak_step=peak, f_tv_step=tv,
                        meta=json.dumps(meta, default=float))
    print(f"{key}: {log.t[-1]:.0f} s simulated in {wall:.0f} s -> {path}", flush=True)
    return path


def _track_every_step(plant) -> tuple[np.ndarray, np.ndarray]:
    """Peak |applied force| and its total variation per unit at every plant step (the recording's 10 ms samples
    alias a chatter at the 0.2 ms ECU period and miss one-period impulses). Returns live arrays."""
    n = plant.layout.n_units
    peak, tv, last = np.zeros(n), np.zeros(n), np.zeros(n)
    step, force = plant.step, plant.force_applied

    def tracked() -> None:
        step()
        np.maximum(peak, np.abs(force), out=peak)
        tv.__iadd__(np.abs(force - last))
        last[:] = force

    plant.step = tracked
    return peak, tv


# ---------------------------------------------------------------------- metrics


def load(key: str) -> dict | None:
    path = OUT / f"{key}.npz"
    if not path.exists():
        return None
    z = np.load(path)
    out = {k: z[k] for k in z.files if k != "meta"}
    out["meta"] = json.loads(str(z["meta"]))
    return out


def entry(t: np.ndarray, err: np.ndarray, band: float) -> tuple[float | None, float | None, float]:
    """(first time inside, time from which it stays inside, time outside after the first entry)."""
    inside = err <= band
    if not inside.any():
        return None, None, float(t[-1] - t[0])
    first = int(np.argmax(inside))
    bad = np.flatnonzero(~inside[first:])
    stays = float(t[first + bad[-1] + 1]) if len(bad) and first + bad[-1] + 1 < len(t) else (float(t[first]) if not len(bad) else None)
    dt = np.diff(t, append=t[-1])
    return float(t[first]), stays, float(np.sum(dt[first:][~inside[first:]]))


def window_max(t: np.ndarray, x: np.ndarray, start: float, width: float = 20.0) -> float:
    sel = (t >= start) & (t < start + width)
    return float(x[sel].max()) if sel.any() else math.nan


def fmt(x: float | None, unit: str = "", nd: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "never" if unit == "s" else "–"
    return f"{x:.{nd}g}{(' ' + unit) if unit else ''}"


def summary(r: dict) -> dict:
    t, em, vm = r["t"], r["e_max"], r["de_max"]
    te = entry(t, em, BAND_E)
    tv = entry(t, vm, BAND_V)
    after = t >= 10.0
    stepwise = "f_peak_step" in r  # tracked at every plant step, else from the 10 ms recording
    f = r["f_peak_step"] if stepwise else np.abs(r["f_applied"]).max(axis=0)
    tv_sum = r["f_tv_step"] if stepwise else np.abs(np.diff(r["f_applied"].astype(float), axis=0)).sum(axis=0)
    tvar = tv_sum / max(t[-1] - t[0], 1e-9)
    dt = np.diff(t, append=t[-1])
    out_e10, out_v10 = float(np.sum(dt[after & (em > BAND_E)])), float(np.sum(dt[after & (vm > BAND_V)]))
    return {"enter_e": te[0], "stay_e": te[1], "out_e": out_e10, "enter_v": tv[0], "stay_v": tv[1], "out_v": out_v10,
            "max_e": float(em.max()), "max_v": float(vm.max()), "max_e_10": float(em[after].max()), "max_v_10": float(vm[after].max()),
            "f_peak": f, "tv": tvar, "tv_mean": float(tvar.mean()), "stepwise": stepwise, "sat": sum(v for k, v in r["meta"]["saturations"].items() if "TractionCmd" in k)}


# ---------------------------------------------------------------------- tables and figure

ROWS = [("frac-N-can", "fractional, N (as written), CAN 10 ms"), ("pid-N-can", "PID, N, CAN 10 ms"),
        ("frac-N-ideal", "fractional, N, ideal 10 ms"), ("pid-N-ideal", "PID, N, ideal 10 ms"),
        ("frac-kN-can", "fractional, kN, CAN 5 ms / 1 Mbit/s"), ("pid-kN-can", "PID, kN, CAN 5 ms / 1 Mbit/s"),
        ("frac-kN-ideal", "fractional, kN, ideal 0.2 ms"), ("pid-kN-ideal", "PID, kN, ideal 0.2 ms"),
        ("ours-can", "OURS: fractional + feed-forward, x20, CAN 10 ms"), ("ours-ideal", "OURS, ideal 10 ms"),
        ("ours-can-phase2.7ms", "OURS, CAN 10 ms, ECU phase 2 ms + 0.1 ms per car (car 8 reads its sensor late)")]


def table_main(results: dict) -> list[str]:
    lines = ["| run | both bands held from | time outside after 10 s: E / dE | "
             "max abs E / abs dE after 10 s | peak applied force (car) | Force signal saturations |",
             "|---|---|---|---|---|---|"]
    for key, label in ROWS:
        r = results.get(key)
        if r is None:
            continue
        s = summary(r)
        car = int(np.argmax(s["f_peak"]))
        held = None if s["stay_e"] is None or s["stay_v"] is None else max(s["stay_e"], s["stay_v"])
        note = " (diverged: PlantDiverged)" if r["meta"].get("diverged") else ""
        lines.append(f"| {label} (`{key}`){note} | {fmt(held, 's')} | "
                     f"{fmt(s['out_e'], 's')} / {fmt(s['out_v'], 's')} | {fmt(s['max_e_10'], 'm')} / {fmt(s['max_v_10'], 'm/s')} | "
                     f"{s['f_peak'][car] / 1e3:.4g} kN ({car + 1}) | {s['sat']} |")
    return lines


def table_transitions(results: dict) -> list[str]:
    shown = ("frac-N-can", "pid-N-can", "frac-kN-can", "frac-kN-ideal", "pid-kN-ideal", "ours-can")
    keys = [k for k in shown if k in results]
    if not keys:
        return []
    changes = results[keys[0]]["meta"]["changes"]
    events = sorted([(c, "mode change") for c in changes] + [(t, "fault: " + d) for t, d in FAULTS.items()])
    head = "| t (s) | event | " + " | ".join(f"`{k}` E / dE" for k in keys) + " |"
    lines = [head, "|---|---|" + "---|" * len(keys)]
    for t0, what in events:
        cells = []
        for k in keys:
            r = results[k]
            cells.append(f"{fmt(window_max(r['t'], r['e_max'], t0), nd=2)} / {fmt(window_max(r['t'], r['de_max'], t0), nd=2)}")
        lines.append(f"| {t0:g} | {what} | " + " | ".join(cells) + " |")
    return lines


def table_halving(results: dict) -> list[str]:
    """The reported errors (max after 10 s, time outside the bands) of a run and of its halved twin, same window."""
    pairs = [("frac-N-can", "frac-N-can-step0.1ms-400s", "plant step 0.2 -> 0.1 ms"),
             ("ours-can", "ours-can-step0.1ms-400s", "plant step 0.2 -> 0.1 ms"),
             ("ours-can", "ours-can-ecu5ms-400s", "ECU period 10 -> 5 ms (1 Mbit/s)"),
             ("frac-kN-ideal", "frac-kN-ideal-0.1ms-400s", "step and ECU period 0.2 -> 0.1 ms"),
             ("pid-kN-ideal", "pid-kN-ideal-0.1ms-400s", "step and ECU period 0.2 -> 0.1 ms")]
    lines = ["| run | halved | max abs E after 10 s: base / halved | max abs dE after 10 s: base / halved | "
             "time outside the bands after 10 s (E / dE): base / halved | largest sample-by-sample change of the worst car's abs E / abs dE |",
             "|---|---|---|---|---|---|"]
    for base, half, what in pairs:
        a, b = results.get(base), results.get(half)
        if a is None or b is None:
            continue
        n = min(len(a["t"]), len(b["t"]))
        w = [{k: r[k][:n] for k in ("t", "e_max", "de_max")} | {"f_applied": r["f_applied"][:n], "meta": r["meta"]} for r in (a, b)]
        sa, sb = summary(w[0]), summary(w[1])
        de = np.abs(w[0]["e_max"] - w[1]["e_max"]).max()
        dv = np.abs(w[0]["de_max"] - w[1]["de_max"]).max()
        lines.append(f"| `{base}`, first {a['t'][n - 1]:.0f} s | {what} (`{half}`) | {sa['max_e_10']:.3g} / {sb['max_e_10']:.3g} m | "
                     f"{sa['max_v_10']:.3g} / {sb['max_v_10']:.3g} m/s | {sa['out_e']:.3g} s, {sa['out_v']:.3g} s / "
                     f"{sb['out_e']:.3g} s, {sb['out_v']:.3g} s | {de:.2g} m / {dv:.2g} m/s |")
    return lines


def table_rbf(results: dict) -> list[str]:
    lines = ["| run | Phi max (any car) | k / c1 max | rho^ at the end (car 1) | max abs E after 10 s | max abs dE after 10 s |", "|---|---|---|---|---|---|"]
    for key in ("frac-N-ideal", "frac-N-ideal-c2=0", "frac-N-ideal-rbfstart", "frac-N-can", "frac-kN-ideal", "ours-can"):
        r = results.get(key)
        if r is None:
            continue
        st = r["meta"]["controllers"]
        s = summary(r)
        lines.append(f"| `{key}` | {max(c.get('phi_max', 0) for c in st):.3g} | {max(c.get('k_over_c1_max', 1) for c in st):.6g} | "
                     f"{fmt(st[0].get('rho_hat'))} | {s['max_e_10']:.4g} m | {s['max_v_10']:.4g} m/s |")
    return lines


def table_forces(results: dict) -> list[str]:
    lines = ["| run | " + " | ".join(f"car {i}" for i in range(1, 9)) + " | chattering: total variation of the applied force, mean over cars |",
             "|---|" + "---|" * 9]
    for key, _ in ROWS:
        r = results.get(key)
        if r is not None:
            s = summary(r)
            how = "every plant step" if s["stepwise"] else "10 ms samples"
            lines.append(f"| `{key}` ({how}) | " + " | ".join(f"{f / 1e3:.4g}" for f in s["f_peak"]) +
                         f" | {s['tv_mean'] / 1e3:.4g} kN/s |")
    return lines


def tables() -> None:
    results = {k: r for k in RUNS if (r := load(k)) is not None}
    missing = [k for k in RUNS if k not in results]
    for title, lines in (("Bands (worst car at each sample)", table_main(results)),
                         ("Worst abs E (m) / abs dE (m/s) in the 20 s after each mode change and fault", table_transitions(results)),
                         ("Peak applied force per car (kN; realistic: ~60 kN per motor car)", table_forces(results)),
                         ("Halving the step", table_halving(results)), ("The RBF / adaptive term", table_rbf(results))):
        print(f"\n### {title}\n")
        print("\n".join(lines))
    if missing:
        print(f"\n(not run yet: {', '.join(missing)})", file=sys.stderr)


def figure() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    show = [("frac-N-can", "fractional, N, CAN"), ("pid-N-can", "PID, N, CAN"), ("frac-kN-can", "fractional, kN, CAN 5 ms"),
            ("frac-kN-ideal", "fractional, kN, ideal 0.2 ms"), ("pid-kN-ideal", "PID, kN, ideal 0.2 ms"), ("ours-can", "ours, CAN")]
    fig, axes = plt.subplots(2, 2, figsize=(15, 8), gridspec_kw={"width_ratios": [3, 1]})
    for key, label in show:
        r = load(key)
        if r is None:
            continue
        for row, (sig, band) in enumerate((("e_max", BAND_E), ("de_max", BAND_V))):
            for col, lim in enumerate((None, (0, 30))):
                ax = axes[row, col]
                ax.semilogy(r["t"], np.maximum(r[sig], 1e-7), lw=0.6, label=label)
                ax.axhline(band, color="k", ls=":", lw=1)
                if lim:
                    ax.set_xlim(*lim)
    changes = (load("frac-N-can") or {"meta": {"changes": []}})["meta"]["changes"]
    for ax in axes[:, 0]:
        for c in changes:
            ax.axvline(c, color="0.8", lw=0.6, zorder=0)
        for t0 in FAULTS:
            ax.axvline(t0, color="r", lw=0.6, ls="--", zorder=0)
    axes[0, 0].set(title="seed 004: worst car's |E| (m); grey: mode changes, red: faults; dotted: the paper's band", ylabel="|E| (m)")
    axes[1, 0].set(title="worst car's |dE| (m/s)", ylabel="|dE| (m/s)", xlabel="t (s)")
    axes[0, 1].set(title="first 30 s")
    axes[1, 1].set(xlabel="t (s)")
    for ax in axes.ravel():
        ax.set_ylim(1e-6, 1e3)
    axes[0, 0].legend(loc="upper right", fontsize=8, ncol=3)
    fig.tight_layout()
    FIG.parent.mkdir(exist_ok=True)
    fig.savefig(FIG, dpi=90)
    print(f"wrote {FIG}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["run", "table", "figure"])
    ap.add_argument("keys", nargs="*", help=f"runs (default: all): {', '.join(RUNS)}")
    args = ap.parse_args()
    if args.what == "run":
        for key in args.keys or list(RUNS):
            if key not in RUNS:
                raise SystemExit(f"unknown run {key!r}; known: {', '.join(RUNS)}")
            run(key)
    elif args.what == "table":
        tables()
    else:
        figure()


if __name__ == "__main__":
    main()

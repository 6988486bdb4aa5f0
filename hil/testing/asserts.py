"""Assertion helpers for rig runs whose failure says which signal (unit, coupler, gap, bus), when, and by how much.

Signals are selected by entity path or shell pattern (``/trains/*/units/*/speed_error_kmh``) and checked over a
time window; values between samples are held (zero-order hold), as in the metrics. A failure raises
:class:`HilAssertionError` (an AssertionError) listing the failing signals, worst first, then the run.
"""
from __future__ import annotations

import fnmatch
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from hil.testing.results import HilRun, Series

MAX_LINES = 8
E2E_ERRORS = ("CRC_ERROR", "WRONG_SEQUENCE", "REPEATED")
UNIT_FAMILIES = ("TractionCmd", "Sensor", "AgentState", "AgentAux")
_SUFFIX_UNITS = (("_kmh", "km/h"), ("_mps", "m/s"), ("_ms", "ms"), ("_kn", "kN"), ("_km", "km"), ("_m", "m"),
                 ("_s", "s"))
LEVELS = {"DEBUG": 0, "INFO": 1, "WARN": 2, "ERROR": 3}


class HilAssertionError(AssertionError):
    """A rig check failed; the message names the signals, times and margins."""


# --------------------------------------------------------------------------- helpers


def unit_of(path: str) -> str:
    """The physical unit a path's suffix names ("" when none, e.g. bus load as a fraction)."""
    for suffix, unit in _SUFFIX_UNITS:
        if path.endswith(suffix):
            return unit
    return ""


def _num(x: float) -> str:
    return f"{x:.4g}"


def _window(s: Series, after: float, until: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, v, hold) of the samples in [after, until]; hold = how long each sample holds inside the window."""
    end = s.t[-1] if until is None and len(s.t) else (until if until is not None else after)
    keep = (s.t >= after) & (s.t <= end)
    t, v = s.t[keep], s.v[keep]
    nxt = np.append(t[1:], end) if len(t) else t
    return t, v, np.maximum(nxt - t, 0.0)


def _select(run: HilRun, pattern: str) -> dict[str, Series]:
    return run.signals.match(pattern) if any(c in pattern for c in "*?[") else {pattern: run.signals[pattern]}


def _fail(check: str, failures: list[tuple[float, str]], total: int, what: str, run: HilRun) -> None:
    """Raise with the failures sorted worst first (severity = first element), at most MAX_LINES of them."""
    __tracebackhide__ = True
    if not failures:
        return
    failures.sort(key=lambda f: -f[0] if math.isfinite(f[0]) else -math.inf)
    lines = [f"HIL check failed: {check}", f"  {len(failures)} of {total} {what} fail{'s' if len(failures) == 1 else ''}:"]
    lines += [f"  - {text}" for _, text in failures[:MAX_LINES]]
    if len(failures) > MAX_LINES:
        lines.append(f"  ... and {len(failures) - MAX_LINES} more")
    lines.append(f"  {run.describe()}")
    raise HilAssertionError("\n".join(lines))


def _no_samples(path: str, after: float, until: float | None) -> tuple[float, str]:
    return math.inf, f"{path}: no samples between t = {_num(after)} s and {'the end' if until is None else _num(until) + ' s'}"


def _window_text(after: float, until: float | None) -> str:
    if until is None:
        return f"from t = {_num(after)} s" if after > 0 else "throughout"
    return f"between t = {_num(after)} s and {_num(until)} s"


# --------------------------------------------------------------------------- value checks


def assert_within(run: HilRun, pattern: str, lo: float, hi: float, *, after: float = 0.0,
                  until: float | None = None) -> None:
    """Every matching signal stays within [lo, hi] for t in [after, until] (until: the end of the run)."""
    __tracebackhide__ = True
    if not lo <= hi:
        raise ValueError(f"lo = {lo} is above hi = {hi}")
    selected = _select(run, pattern)
    failures = []
    for path, s in selected.items():
        t, v, hold = _window(s, after, until)
        if not len(t):
            failures.append(_no_samples(path, after, until))
            continue
        excess = np.maximum(lo - v, v - hi)
        excess[~np.isfinite(v)] = np.inf
        out = excess > 0
        if out.any():
            u = unit_of(path)
            i0, iw = int(np.argmax(out)), int(np.argmax(excess))
            side = "above" if v[i0] > hi else "below"
            failures.append((float(excess[iw]), (
                f"{path}: left [{_num(lo)}, {_num(hi)}] {u} at t = {t[i0]:.3f} s ({_num(v[i0])} {u}, "
                f"{_num(excess[i0])} {side}); worst {_num(v[iw])} {u} at t = {t[iw]:.3f} s ({_num(excess[iw])} beyond); "
                f"outside for {_num(hold[out].sum())} s in total")))
    u = unit_of(next(iter(selected)))
    _fail(f"{pattern} within [{_num(lo)}, {_num(hi)}] {u} {_window_text(after, until)}", failures, len(selected),
          "signals", run)


def _never(run: HilRun, pattern: str, limit: float, after: float, until: float | None, below: bool) -> None:
    __tracebackhide__ = True
    selected = _select(run, pattern)
    failures = []
    word = "below" if below else "above"
    for path, s in selected.items():
        t, v, hold = _window(s, after, until)
        if not len(t):
            failures.append(_no_samples(path, after, until))
            continue
        excess = (limit - v) if below else (v - limit)
        excess = np.where(np.isfinite(v), excess, np.inf)
        out = excess > 0
        if out.any():
            u = unit_of(path)
            i0, iw = int(np.argmax(out)), int(np.argmax(excess))
            failures.append((float(excess[iw]), (
                f"{path}: {word} {_num(limit)} {u} from t = {t[i0]:.3f} s ({_num(v[i0])} {u}); "
                f"{'minimum' if below else 'maximum'} {_num(v[iw])} {u} at t = {t[iw]:.3f} s "
                f"({_num(excess[iw])} {u} {word} the limit); {word} for {_num(hold[out].sum())} s in total")))
    u = unit_of(next(iter(selected)))
    _fail(f"{pattern} never {word} {_num(limit)} {u} {_window_text(after, until)}", failures, len(selected),
          "signals", run)


def assert_never_below(run: HilRun, pattern: str, limit: float, *, after: float = 0.0,
                       until: float | None = None) -> None:
    """Every matching signal stays at or above ``limit`` (e.g. gaps above l_e)."""
    __tracebackhide__ = True
    _never(run, pattern, limit, after, until, below=True)


def assert_never_above(run: HilRun, pattern: str, limit: float, *, after: float = 0.0,
                       until: float | None = None) -> None:
    """Every matching signal stays at or below ``limit``."""
    __tracebackhide__ = True
    _never(run, pattern, limit, after, until, below=False)


def assert_settles(run: HilRun, pattern: str, *, within: float, tol: float, target: float = 0.0) -> None:
    """Every matching signal enters [target - tol, target + tol] no later than t = ``within`` and stays there to the
    end of the run. The settling time is the first sample of the final stretch inside the band."""
    __tracebackhide__ = True
    if not tol > 0:
        raise ValueError(f"tol = {tol} must be > 0")
    if run.duration_s <= within:
        raise ValueError(f"the run lasts {run.duration_s:g} s: it cannot show settling within {within:g} s "
                         f"(run it for longer than {within:g} s)")
    selected = _select(run, pattern)
    failures = []
    for path, s in selected.items():
        t, v = s.t, s.v
        if not len(t):
            failures.append(_no_samples(path, 0.0, None))
            continue
        dev = np.abs(v - target)
        dev[~np.isfinite(v)] = np.inf
        out = dev > tol
        if not out.any():
            continue
        u, last = unit_of(path), int(len(out) - 1 - np.argmax(out[::-1]))
        band = f"{_num(target)} ± {_num(tol)} {u}"
        if last == len(t) - 1:
            failures.append((math.inf, f"{path}: never settles in {band}: still {_num(v[last])} {u} at the end "
                                       f"(t = {t[last]:.3f} s, {_num(dev[last] - tol)} {u} outside)"))
            continue
        settled = float(t[last + 1])
        if settled > within:
            late = t >= within
            iw = int(np.argmax(np.where(late, dev, -np.inf)))
            failures.append((settled - within, (
                f"{path}: settles in {band} at t = {settled:.3f} s, {_num(settled - within)} s later than "
                f"{_num(within)} s; last outside at t = {t[last]:.3f} s ({_num(v[last])} {u}); worst after "
                f"{_num(within)} s: {_num(v[iw])} {u} at t = {t[iw]:.3f} s ({_num(dev[iw] - tol)} {u} outside)")))
    u = unit_of(next(iter(selected)))
    _fail(f"{pattern} settles in {_num(target)} ± {_num(tol)} {u} within {_num(within)} s", failures,
          len(selected), "signals", run)


# --------------------------------------------------------------------------- CAN checks


@lru_cache(maxsize=4)
def _db(path: Path):
    from ecu_sim.codec import TrainDb

    return TrainDb.load(path)


def _frames(run: HilRun, frame: str | int) -> list[tuple[int, str, bool]]:
    """(ID, name, explicit) of the frames meant: an ID, a name in the run's DBC (a message or a CAN FD container),
    or a shell pattern over those names."""
    db = _db(run.scenario.can.dbc_path)
    names = {**{n: c.frame_id for n, c in db.by_name.items()}, **{c.name: c.frame_id for c in db.containers}}
    if isinstance(frame, int):
        codec = db.by_id.get(frame) or db.container_by_id.get(frame)
        return [(frame, codec.name if codec else f"0x{frame:03X}", True)]
    if any(c in frame for c in "*?["):
        found = [(fid, name, False) for name, fid in names.items() if fnmatch.fnmatchcase(name, frame)]
        if not found:
            raise KeyError(f"no DBC message matches {frame!r} (e.g. TractionCmd_U01, Sensor_U*, Reference)")
        return sorted(found)
    if frame not in names:
        raise KeyError(f"no DBC message {frame!r} (e.g. TractionCmd_U01, AgentState_U02, Reference, RadioAheadState)")
    return [(names[frame], frame, True)]


def _arrivals(run: HilRun, frame_id: int, bus: str) -> np.ndarray:
    """When a message reached the bus's receivers: as itself, or inside a CAN FD container that carries it."""
    carriers = [c.frame_id for c in _db(run.scenario.can.dbc_path).carriers(frame_id, run.log.layout.units_per_train)]
    if not carriers:
        return run.frame_times(frame_id, bus)
    return np.sort(np.concatenate([run.frame_times(i, bus) for i in (frame_id, *carriers)]))


def _expected_on_every_bus(run: HilRun, name: str) -> bool:
    """Frames every train bus carries: the wayside's Reference frames and the frames of units the trains have."""
    if name.startswith("Reference"):
        return True
    family, _, unit = name.rpartition("_U")
    return family in UNIT_FAMILIES and unit.isdigit() and int(unit) <= run.log.layout.units_per_train


def assert_frame_period(run: HilRun, frame: str | int, max_gap_ms: float, *, bus: str | None = None,
                        after: float = 0.0, until: float | None = None) -> None:
    """The frame (a DBC name, a pattern such as ``TractionCmd_U*``, or an ID) is received at least every
    ``max_gap_ms`` between ``after`` and ``until`` (default: the end of the run), on ``bus`` or on every bus that
    should carry it. Silence at either end of the window counts: an ECU that stops sending fails."""
    __tracebackhide__ = True
    if not max_gap_ms > 0:
        raise ValueError(f"max_gap_ms = {max_gap_ms} must be > 0")
    end = run.duration_s if until is None else float(until)
    buses = [run._bus(bus).name] if bus is not None else [b.name for b in run.log.buses]
    limit = max_gap_ms * 1e-3
    failures, checked = [], 0
    for frame_id, name, explicit in _frames(run, frame):
        for b in buses:
            times = _arrivals(run, frame_id, b)
            if not len(times) and not (explicit and bus is not None) and not _expected_on_every_bus(run, name):
                continue  # e.g. RadioAheadState on the first train's bus: nobody sends it there
            checked += 1
            times = times[(times >= after) & (times <= end)]
            label = f"{name} (0x{frame_id:03X}) on {b}"
            if not len(times):
                failures.append((math.inf, f"{label}: no frame between t = {_num(after)} s and {_num(end)} s"))
                continue
            edges = np.concatenate(([after], times, [end]))
            gaps = np.diff(edges)
            over = gaps > limit + 1e-12
            if over.any():
                iw, i0 = int(np.argmax(gaps)), int(np.argmax(over))
                failures.append((float(gaps[iw] - limit), (
                    f"{label}: {int(over.sum())} gap{'s' if over.sum() > 1 else ''} longer than {_num(max_gap_ms)} ms; "
                    f"first from t = {edges[i0]:.4f} s to {edges[i0 + 1]:.4f} s; longest {_num(gaps[iw] * 1e3)} ms "
                    f"({_num((gaps[iw] - limit) * 1e3)} ms over) from t = {edges[iw]:.4f} s to {edges[iw + 1]:.4f} s"
                    f"{' (the end of the window: no frame since)' if iw == len(gaps) - 1 else ''}")))
    if not checked:
        raise HilAssertionError(f"HIL check failed: no frame matching {frame!r} was ever sent on "
                                f"{bus or 'any bus'}\n  {run.describe()}")
    _fail(f"{frame} received at least every {_num(max_gap_ms)} ms {_window_text(after, until)}", failures, checked,
          "frame streams", run)


def assert_no_e2e_errors(run: HilRun, statuses: tuple[str, ...] = E2E_ERRORS) -> None:
    """No ECU saw a frame with one of these E2E verdicts (default: CRC errors, wrong sequences, repeated counters;
    add "OK_SOME_LOST" (or the counts "LOST", "TIMEOUT") to also forbid lost frames and input timeouts)."""
    __tracebackhide__ = True
    failures = []
    for ecu, counts in sorted(run.log.e2e.items()):
        bad = {s: n for s, n in counts.items() if s in statuses and n}
        if bad:
            total = sum(n for s, n in counts.items() if s not in ("LOST", "TIMEOUT"))  # those are not verdicts
            failures.append((float(sum(bad.values())), f"{ecu}: " + ", ".join(f"{n} {s}" for s, n in bad.items())
                             + f" (of {total} checked frames)"))
    _fail(f"no E2E errors ({', '.join(statuses)})", failures, len(run.log.e2e), "ECUs", run)


def assert_no_events(run: HilRun, level: str = "ERROR", *, source: str | None = None) -> None:
    """No event at ``level`` or above (DEBUG < INFO < WARN < ERROR), optionally only from sources matching a pattern."""
    __tracebackhide__ = True
    if level not in LEVELS:
        raise ValueError(f"level {level!r}: one of {', '.join(LEVELS)}")
    bad = [e for e in run.events if LEVELS.get(e.level, 3) >= LEVELS[level]
           and (source is None or fnmatch.fnmatchcase(e.source, source))]
    failures = [(-e.t, f"t = {e.t:.3f} s {e.level} {e.source}: {e.text}") for e in bad]
    _fail(f"no {level} events{'' if source is None else ' from ' + source}", failures, len(run.events), "events", run)

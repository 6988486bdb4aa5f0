"""Scenario checks beyond pydantic's field constraints: value kinds, and rules across fields and sections.

Type checks pydantic's lax mode would skip: a TOML string, boolean or number of the wrong kind is an error.

pydantic (lax) turns ``count = "3"`` into 3, ``enabled = "no"`` into False and ``unit_mass_kg = true`` into
1.0. In a scenario file each of these is a typo or a misunderstanding, so ``wrong_kind`` reports it instead
(the caller raises, naming the field). Only the scalar kinds are judged here (str, bool, number), also inside
lists and tuples; everything else is left to pydantic. ``non_finite`` finds NaN/inf in free-form values
(controller parameters), which ``allow_inf_nan=False`` does not reach.

``scenario_inconsistency`` holds the cross-field rules a Scenario validator applies (each message names its
dotted field): a usable name and seed, a duration of at least one period, finite controller parameters, a
coupler band around 0, non-empty and non-overlapping track segments, non-empty blackouts, v_r > 0 on a
position profile, disturbances on trains and units that exist.
"""
from __future__ import annotations

import enum
import math
import re
import types
import typing
from typing import Any

_STR, _BOOL, _NUM, _OTHER = "a string", "a boolean", "a number", "other"


def _kinds(annotation: Any) -> set[str] | None:
    """The scalar kinds an annotation admits (None: anything, do not judge)."""
    if annotation is Any or annotation is object:
        return None
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _kinds(typing.get_args(annotation)[0])
    if origin is typing.Union or origin is types.UnionType:
        out: set[str] = set()
        for arg in typing.get_args(annotation):
            if arg is type(None):
                continue
            k = _kinds(arg)
            if k is None:
                return None
            out |= k
        return out
    if origin is typing.Literal:
        return {_BOOL if isinstance(v, bool) else _STR if isinstance(v, str) else _NUM if isinstance(v, (int, float))
                else _OTHER for v in typing.get_args(annotation)}
    if annotation is bool:
        return {_BOOL}
    if annotation in (int, float):
        return {_NUM}
    if annotation is str:
        return {_STR}
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return None  # enums take their values' kinds; pydantic checks them
    return {_OTHER}


def _kind_of(value: Any) -> str:
    if isinstance(value, bool):
        return _BOOL
    if isinstance(value, str):
        return _STR
    if isinstance(value, (int, float)):
        return _NUM
    return _OTHER


def _items(annotation: Any, value: Any) -> list[tuple[int, Any, Any]]:
    """(index, item annotation, item) of a list/tuple value under a list/tuple annotation (else [])."""
    if not isinstance(value, (list, tuple)):
        return []
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Union or origin is types.UnionType:
        seqs = [a for a in args if typing.get_origin(a) in (list, tuple)]
        return _items(seqs[0], value) if len(seqs) == 1 else []
    if origin is list and args:
        return [(i, args[0], v) for i, v in enumerate(value)]
    if origin is tuple and args:
        if len(args) == 2 and args[1] is Ellipsis:
            return [(i, args[0], v) for i, v in enumerate(value)]
        return [(i, a, v) for i, (a, v) in enumerate(zip(args, value))]
    return []


def wrong_kind(annotation: Any, value: Any) -> str | None:
    """Why ``value`` must not be coerced to ``annotation`` (e.g. "expected a number, got a string '3'"), or None."""
    kinds = _kinds(annotation)
    got = _kind_of(value)
    if kinds is not None and got != _OTHER and got not in kinds and kinds & {_STR, _BOOL, _NUM}:
        if not (got == _NUM and _OTHER in kinds):  # a number for a list field: pydantic's own error is clearer
            wanted = " or ".join(sorted(kinds & {_STR, _BOOL, _NUM}))
            return f"expected {wanted}, got {got} {value!r} (write it without quotes, or fix the value)" \
                if got == _STR and _NUM in kinds else f"expected {wanted}, got {got} {value!r}"
    for i, item_annotation, item in _items(annotation, value):
        why = wrong_kind(item_annotation, item)
        if why is not None:
            return f"item {i}: {why}"
    return None


def non_finite(value: Any, path: str = "") -> str | None:
    """The dotted path of the first NaN/inf inside a nested dict/list value, or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return path or "(value)"
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for k, v in items:
        found = non_finite(v, f"{path}.{k}" if path else str(k))
        if found is not None:
            return found
    return None


# --------------------------------------------------------------------------- cross-field checks of a whole scenario


def _segment_errors(where: str, segments: list, start: str, end: str, overlap: bool) -> str | None:
    """Empty segments (end <= start) and, if ``overlap`` is forbidden, overlapping ones."""
    for i, seg in enumerate(segments):
        if not getattr(seg, end) > getattr(seg, start):
            return f"{where}.{i}: {end} ({getattr(seg, end)}) must be after {start} ({getattr(seg, start)})"
    if overlap:
        order = sorted(range(len(segments)), key=lambda i: getattr(segments[i], start))
        for a, b in zip(order, order[1:]):
            if getattr(segments[b], start) < getattr(segments[a], end):
                return (f"{where}.{b} [{getattr(segments[b], start)}, {getattr(segments[b], end)}) overlaps "
                        f"{where}.{a} [{getattr(segments[a], start)}, {getattr(segments[a], end)})")
    return None


UNIT_NAME = re.compile(r"train(\d+)/unit(\d+)")


def unit_name_error(name: str, n_trains: int, units_per_train: int) -> str | None:
    """Why ``name`` is not the ``train<t>/unit<k>`` name of a unit of this group (1-based), or None."""
    m = UNIT_NAME.fullmatch(str(name).strip())
    if m is None:
        return f"{name!r} is not a unit name: expected 'train<t>/unit<k>', e.g. 'train1/unit2' (1-based)"
    train, unit = int(m.group(1)), int(m.group(2))
    if not 1 <= train <= n_trains:
        return f"{name!r}: there is no train {train} (trains.count = {n_trains})"
    if not 1 <= unit <= units_per_train:
        return f"{name!r}: a train has no unit {unit} (trains.units = {units_per_train})"
    return None


MAX_NAME_CHARS = 100


def _name_error(name: str) -> str | None:
    """The scenario name names the output directory (runs/<name>): no path separators, not empty."""
    if len(name) > MAX_NAME_CHARS:
        return f"name = {name[:40]!r}...: {len(name)} characters, at most {MAX_NAME_CHARS} (it names the run directory)"
    if any(not c.isprintable() for c in name):
        return f"name = {name!r}: control characters (newlines, tabs) are not allowed (it names the run directory)"
    if not name.strip() or name in (".", "..") or any(c in name for c in "/\\\0"):
        return f"name = {name!r}: must be a non-empty name without '/', '\\\\' or NUL (it names the run directory)"
    return None


def scenario_inconsistency(sc: Any) -> str | None:
    """The first cross-field error of a validated Scenario (each names its dotted field), or None.

    Rules that involve more than one section, or that the runtime would otherwise only hit mid-run (a track
    segment overlap, a position profile with v_r <= 0, a disturbance on a train that does not exist)."""
    checks = (
        _name_error(sc.name),
        None if sc.seed >= 0 else f"seed = {sc.seed}: must be >= 0 (numpy seeds are non-negative)",
        _duration_error(sc),
        _params_error(sc.controller.params),
        _band_error(sc.plant.coupler_band_m),
        _segment_errors("track.grades", sc.track.grades, "start_m", "end_m", overlap=True),
        _segment_errors("track.curves", sc.track.curves, "start_m", "end_m", overlap=True),
        _segment_errors("radio.blackouts", sc.radio.blackouts, "start_m", "end_m", overlap=False),
        _reference_error(sc.reference),
        _disturbance_error(sc.plant.disturbances, sc.trains.count, sc.trains.units),
        _firmware_units_error(sc.ecu, sc.trains.count, sc.trains.units),
    )
    return next((why for why in checks if why is not None), None)


def _firmware_units_error(ecu: Any, n_trains: int, n_units: int) -> str | None:
    """ecu.units and ecu.external name units that exist, each at most once, and not both."""
    seen: dict[str, str] = {}
    for where, name in [*((f"ecu.units.{i}.unit", o.unit) for i, o in enumerate(ecu.units)),
                        *((f"ecu.external.{i}", n) for i, n in enumerate(ecu.external))]:
        why = unit_name_error(name, n_trains, n_units)
        if why is not None:
            return f"{where}: {why}"
        key = str(name).strip()
        if key in seen:
            return f"{where} = {key!r}: already given in {seen[key]}"
        seen[key] = where
    for i, o in enumerate(ecu.units):
        if o.params is not None:
            bad = non_finite(o.params)
            if bad is not None:
                return f"ecu.units.{i}.params.{bad}: must be a finite number (got NaN or inf)"
    return None


def _duration_error(sc: Any) -> str | None:
    periods = {"ecu.cycle_s": sc.ecu.cycle_s, "can.sensor_period_s": sc.can.sensor_period_s,
               "recording.period_s": sc.recording.period_s, "reference.period_s": sc.reference.period_s}
    field, longest = max(periods.items(), key=lambda kv: kv[1])
    if sc.duration_s < longest:
        return f"duration_s = {sc.duration_s} is shorter than {field} = {longest}: the run would not complete one period"
    return None


def _params_error(params: dict) -> str | None:
    where = non_finite(params)
    return None if where is None else f"controller.params.{where}: must be a finite number (got NaN or inf)"


def _band_error(band: tuple[float, float]) -> str | None:
    lo, hi = band
    if not lo < 0 < hi:
        return f"plant.coupler_band_m = {list(band)}: must be (max compression < 0, max stretch > 0)"
    return None


def _reference_error(ref: Any) -> str | None:
    if ref.by == "position":
        for i, seg in enumerate(ref.segments):
            if seg.end > ref.x0_m and seg.speed <= 0:
                return (f"reference.segments.{i}: speed {seg.speed} m/s: a position profile needs v_r > 0 on every "
                        "segment ahead of x0_m (x_r would never reach the next one)")
    return None


def _disturbance_error(disturbances: list, n_trains: int, n_units: int) -> str | None:
    for i, d in enumerate(disturbances):
        if d.train is not None and d.train > n_trains:
            return f"plant.disturbances.{i}.train = {d.train}: there are only {n_trains} trains (trains.count)"
        if d.unit is not None and d.unit > n_units:
            return f"plant.disturbances.{i}.unit = {d.unit}: a train has only {n_units} units (trains.units)"
    return None

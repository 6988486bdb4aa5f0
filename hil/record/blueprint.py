"""The default rerun blueprint, so `rerun run.rrd` (or `hil view DIR`) opens on tabs of useful plots.

The tabs follow the kind of run (one blueprint per scenario type):

- always: an overview (the 2D track view with every unit along the line and the gaps coloured by safety margin,
  all speeds against the reference, the gaps with l_s and l_e, the event log), speeds and speed errors per train,
  position errors, traction (commanded and applied), CAN buses (load, frame latency), events;
- couplers (with the band) only when trains have more than one unit; gaps only with more than one train;
- frames (every CAN frame as a text row: ID, decoded signals, latency) when ``recording.frames = true``;
- timing (ECU cycle and plant lateness, sensor-to-actuator latency) for real-time runs, whose recording also has a
  ``wall_time`` timeline beside ``sim_time``.

Entity paths come from :mod:`hil.record.paths`, as the writer's, so the views always match the data. Rerun view
queries only support a trailing `/**` wildcard, hence the explicit per-entity contents.
"""
from __future__ import annotations

import rerun.blueprint as rrb

from hil.scenario.layout import TrainLayout
from hil.record.paths import (
    EVENTS, LIMIT_COUPLER_MAX, LIMIT_COUPLER_MIN, LIMIT_EMERGENCY, LIMIT_SPACING, REF_POSITION, REF_SPEED, TIMING,
    TRACK, bus_path, coupler_path, gap_path, unit_path,
)


def _unit_view(layout: TrainLayout, train: int, signals: tuple[str, ...], extra: tuple[str, ...], title: str) -> rrb.TimeSeriesView:
    contents = [unit_path(train, j, s) for j in range(layout.units_per_train) for s in signals] + list(extra)
    return rrb.TimeSeriesView(origin="/", contents=contents, name=f"{title}: train {train + 1}")


def _per_train(layout: TrainLayout, signals: tuple[str, ...], title: str, extra: tuple[str, ...] = ()) -> rrb.Grid:
    views = [_unit_view(layout, i, signals, extra, title) for i in range(layout.n_trains)]
    return rrb.Grid(*views, name=title)


def _couplers(layout: TrainLayout) -> rrb.Grid:
    limits = [LIMIT_COUPLER_MIN, LIMIT_COUPLER_MAX]
    views = [rrb.TimeSeriesView(origin="/", name=f"Couplers: train {i + 1}",
                                contents=[coupler_path(i, j) for j in range(layout.units_per_train - 1)] + limits)
             for i in range(layout.n_trains)]
    return rrb.Grid(*views, name="Couplers")


def _gaps(layout: TrainLayout) -> rrb.Vertical:
    contents = [gap_path(i) for i in range(1, layout.n_trains)] + [LIMIT_SPACING, LIMIT_EMERGENCY]
    gaps = rrb.TimeSeriesView(origin="/", contents=contents, name="Gaps to the train ahead (m)")
    where = rrb.TimeSeriesView(origin="/", contents=[REF_POSITION], name="Reference position (km)")
    return rrb.Vertical(gaps, where, row_shares=[3, 1], name="Gaps")


def _buses(bus_names: list[str]) -> rrb.Vertical:
    load = rrb.TimeSeriesView(origin="/", contents=[bus_path(b, "load") for b in bus_names], name="Bus load")
    latency = rrb.TimeSeriesView(origin="/", contents=[bus_path(b, "frame_latency_ms") for b in bus_names],
                                 name="Frame latency (ms)")
    return rrb.Vertical(load, latency, name="CAN buses")


def track_view() -> rrb.Spatial2DView:
    """Every unit as a box at its position along the line (m, direction of travel to the right), the gaps between
    trains as bars coloured by safety margin (green at l_s, red at l_e), and each train's slot on the reference."""
    return rrb.Spatial2DView(origin=TRACK, name="Track: units, gaps (green at l_s, red at l_e), slots")


def _overview(layout: TrainLayout) -> rrb.Vertical:
    speeds = rrb.TimeSeriesView(origin="/", name="Speeds (km/h), all units",
                                contents=[unit_path(i, j, "speed_kmh") for i in range(layout.n_trains)
                                          for j in range(layout.units_per_train)] + [REF_SPEED])
    middle = [speeds]
    if layout.n_trains > 1:
        middle.append(rrb.TimeSeriesView(origin="/", name="Gaps (m) with l_s and l_e",
                                         contents=[gap_path(i) for i in range(1, layout.n_trains)]
                                         + [LIMIT_SPACING, LIMIT_EMERGENCY]))
    events = rrb.TextLogView(origin=EVENTS, name="Event log")
    return rrb.Vertical(track_view(), rrb.Horizontal(*middle), events, row_shares=[2, 3, 1], name="Overview")


def _frames(bus_names: list[str]) -> rrb.Tabs:
    views = [rrb.TextLogView(origin=f"/buses/{b}/frames", name=f"Frames on {b}") for b in bus_names]
    return rrb.Tabs(*views, name="Frames")


def _timing() -> rrb.Vertical:
    ecus = rrb.TimeSeriesView(origin=TIMING, name="ECU cycle and plant lateness (ms)")
    e2e = rrb.TimeSeriesView(origin="/", contents=[TIMING + "/e2e_latency_ms"], name="Sensor-to-actuator latency (ms)")
    return rrb.Vertical(ecus, e2e, name="Timing (real time)")


def default_blueprint(layout: TrainLayout, bus_names: list[str] | None = None, *, frames: bool = False,
                      realtime: bool = False) -> rrb.Blueprint:
    """The tabs for this kind of run (see the module docstring). Bus names default to one per train: bus1, bus2, ...

    ``frames``: add the per-frame text tab; ``realtime``: add the timing tab. The time panel opens on sim_time."""
    buses = bus_names if bus_names is not None else [f"bus{i + 1}" for i in range(layout.n_trains)]
    tabs: list = [
        _overview(layout),
        _per_train(layout, ("speed_kmh",), "Speeds (km/h)", (REF_SPEED,)),
        _per_train(layout, ("speed_error_kmh",), "Speed errors (km/h)"),
        _per_train(layout, ("position_error_m",), "Position errors (m)"),
    ]
    if layout.units_per_train > 1:
        tabs.append(_couplers(layout))
    if layout.n_trains > 1:
        tabs.append(_gaps(layout))
    tabs += [_per_train(layout, ("traction_kn", "applied_kn"), "Traction (kN)"), _buses(buses)]
    if frames:
        tabs.append(_frames(buses))
    if realtime:
        tabs.append(_timing())
    tabs.append(rrb.TextLogView(origin=EVENTS, name="Events"))
    return rrb.Blueprint(rrb.Tabs(*tabs), rrb.TimePanel(timeline="sim_time"), collapse_panels=False)

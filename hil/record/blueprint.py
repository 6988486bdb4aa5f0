"""The default rerun blueprint, so `rerun run.rrd` opens on tabs of useful plots.

Entity paths are built here and by the writer from the same helpers, so the views always match the data.
Rerun view queries only support a trailing `/**` wildcard, hence the explicit per-entity contents.
"""
from __future__ import annotations

import rerun.blueprint as rrb

from hil.layout import TrainLayout

LIMIT_COUPLER_MAX = "/limits/coupler_max_m"
LIMIT_COUPLER_MIN = "/limits/coupler_min_m"
LIMIT_SPACING = "/limits/spacing_m"
LIMIT_EMERGENCY = "/limits/emergency_gap_m"
REF_SPEED = "/reference/speed_kmh"
REF_POSITION = "/reference/position_km"


def unit_path(train: int, unit: int, signal: str) -> str:
    """Entity path of a unit signal; train and unit are 0-based here, 1-based in the path."""
    return f"/trains/{train + 1}/units/{unit + 1}/{signal}"


def coupler_path(train: int, coupler: int) -> str:
    """Coupler `coupler` joins unit `coupler` and `coupler + 1` (0-based here, 1-based in the path)."""
    return f"/trains/{train + 1}/couplers/{coupler + 1}/displacement_m"


def gap_path(train: int) -> str:
    """Gap from train `train` (0-based, >= 1) to the train ahead."""
    return f"/trains/{train + 1}/gap_ahead_m"


def bus_path(name: str, signal: str) -> str:
    return f"/buses/{name}/{signal}"


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


def default_blueprint(layout: TrainLayout, bus_names: list[str] | None = None) -> rrb.Blueprint:
    """Tabs: speeds (with reference), speed errors, position errors, couplers (with band), gaps (with l_s, l_e)
    and the reference position, traction (commanded and applied), CAN buses, events. Bus names default to one per train: bus1, bus2, ..."""
    buses = bus_names if bus_names is not None else [f"bus{i + 1}" for i in range(layout.n_trains)]
    tabs = rrb.Tabs(
        _per_train(layout, ("speed_kmh",), "Speeds (km/h)", (REF_SPEED,)),
        _per_train(layout, ("speed_error_kmh",), "Speed errors (km/h)"),
        _per_train(layout, ("position_error_m",), "Position errors (m)"),
        _couplers(layout),
        _gaps(layout),
        _per_train(layout, ("traction_kn", "applied_kn"), "Traction (kN)"),
        _buses(buses),
        rrb.TextLogView(origin="/events", name="Events"),
    )
    return rrb.Blueprint(tabs, collapse_panels=False)

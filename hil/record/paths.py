"""Entity paths of a recording: one place, so the writer, the blueprint and the tests' signals always agree.

Trains, units, couplers and buses are 1-based in paths (``/trains/2/units/1/speed_kmh``), 0-based in the helpers'
arguments. No rerun import here: the pytest plugin uses these paths without loading the rerun SDK.
"""
from __future__ import annotations

LIMIT_COUPLER_MAX = "/limits/coupler_max_m"
LIMIT_COUPLER_MIN = "/limits/coupler_min_m"
LIMIT_SPACING = "/limits/spacing_m"
LIMIT_EMERGENCY = "/limits/emergency_gap_m"
REF_SPEED = "/reference/speed_kmh"
REF_POSITION = "/reference/position_km"
EVENTS = "/events"
TRACK = "/track"
TRACK_UNITS = "/track/units"
TRACK_GAPS = "/track/gaps"
TRACK_SLOTS = "/track/slots"
TIMING = "/timing"  # real-time runs: ECU and plant lateness, sensor-to-actuator latency (hil.runtime.realtime.orchestrator)


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


def frames_path(bus: str, frame_id: int, name: str) -> str:
    """Per-frame text rows of one frame ID on one bus, e.g. /buses/bus1/frames/0C1_Sensor_U02."""
    return f"/buses/{bus}/frames/{frame_id:03X}_{name}"

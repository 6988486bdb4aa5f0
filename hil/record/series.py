"""The recorded signals of a run as (entity path -> values) columns: one definition for the .rrd and for tests.

The rerun writer sends these columns and the pytest plugin (``hil.testing``) hands them to tests, so a path in a
test's assertion is the path of the same curve in the recording. numpy only (no rerun import): cheap to load.

Units are in the path's suffix: ``speed_kmh``, ``traction_kn``, ``displacement_m``, ``gap_ahead_m``, ...
The track geometry (:func:`track_geometry`) is what the 2D track view draws: unit boxes along the line and the
gaps between trains, each gap with its safety margin (s - l_e) / (l_s - l_e): 1 at l_s, 0 at l_e, < 0 below l_e.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.scenario.layout import TrainLayout
from hil.record import paths as bp

MPS_TO_KMH = 3.6


def signal_columns(layout: TrainLayout, rows: np.ndarray) -> dict[str, np.ndarray]:
    """Entity path -> values (one per row) of every sampled scalar, from RunLog signal rows (t, x_r, v_r, x, v, a,
    F_cmd, F_applied). Per unit: speed, speed error, position error, traction command and applied force; per coupler
    its displacement; per train after the first its gap to the train ahead; the reference speed and position."""
    L, n = layout, layout.n_units
    x_r, v_r = rows[:, 1], rows[:, 2]
    x, v = rows[:, 3 : 3 + n], rows[:, 3 + n : 3 + 2 * n]
    f_cmd, f_app = rows[:, 3 + 3 * n : 3 + 4 * n], rows[:, 3 + 4 * n : 3 + 5 * n]
    per_unit = {
        "speed_kmh": v * MPS_TO_KMH,
        "speed_error_kmh": (v - v_r[:, None]) * MPS_TO_KMH,
        "position_error_m": x - (x_r[:, None] - L.offset_m[None, :]),
        "traction_kn": f_cmd / 1000.0,
        "applied_kn": f_app / 1000.0,
    }
    out: dict[str, np.ndarray] = {}
    for u in range(n):
        i, j = L.train_unit(u)
        for signal, values in per_unit.items():
            out[bp.unit_path(i, j, signal)] = values[:, u]
    pairs = L.coupler_pairs()
    if len(pairs):
        e = x[:, pairs[:, 0]] - x[:, pairs[:, 1]] - L.length_m[pairs[:, 0]][None, :]
        for c, front in enumerate(pairs[:, 0]):
            i, j = L.train_unit(int(front))
            out[bp.coupler_path(i, j)] = e[:, c]
    gaps = gaps_of(L, x)
    for k in range(L.n_trains - 1):
        out[bp.gap_path(k + 1)] = gaps[:, k]
    out[bp.REF_SPEED] = v_r * MPS_TO_KMH
    out[bp.REF_POSITION] = x_r / 1000.0
    return out


def gaps_of(layout: TrainLayout, x: np.ndarray) -> np.ndarray:
    """(k, n_trains - 1) gap from each train's rear end to the front of the train behind it."""
    tails, heads = layout.tails(), layout.heads()
    return (x[:, tails[:-1]] - layout.length_m[tails[:-1]][None, :]) - x[:, heads[1:]]


def limit_values(coupler_band: tuple[float, float], spacing_m: float, emergency_gap_m: float) -> dict[str, float]:
    """The constant reference lines drawn beside couplers and gaps (band edges, l_s, l_e)."""
    return {bp.LIMIT_COUPLER_MIN: float(coupler_band[0]), bp.LIMIT_COUPLER_MAX: float(coupler_band[1]),
            bp.LIMIT_SPACING: float(spacing_m), bp.LIMIT_EMERGENCY: float(emergency_gap_m)}


@dataclass
class TrackGeometry:
    """What the 2D track view shows at each sample (k samples, n units, g = n_trains - 1 gaps), in metres."""

    unit_centers: np.ndarray  # (k, n, 2): (middle of the unit along the line, 0)
    gap_strips: np.ndarray  # (k, g, 2, 2): from the front of the train behind to the rear of the train ahead
    gap_m: np.ndarray  # (k, g)
    gap_margin: np.ndarray  # (k, g): (s - l_e) / (l_s - l_e)
    slots: np.ndarray  # (k, n_trains, 2): where each head unit should be (x_r - its slot offset)


def track_geometry(layout: TrainLayout, rows: np.ndarray) -> TrackGeometry:
    """Unit positions along the line (y = 0; x = position in m, increasing in the direction of travel) and the gaps."""
    L, n = layout, layout.n_units
    k = len(rows)
    x_r, x = rows[:, 1], rows[:, 3 : 3 + n]
    centers = np.zeros((k, n, 2))
    centers[:, :, 0] = x - 0.5 * L.length_m[None, :]
    tails, heads = L.tails(), L.heads()
    g = L.n_trains - 1
    strips = np.zeros((k, g, 2, 2))
    strips[:, :, 0, 0] = x[:, heads[1:]]
    strips[:, :, 1, 0] = x[:, tails[:-1]] - L.length_m[tails[:-1]][None, :]
    gap = strips[:, :, 1, 0] - strips[:, :, 0, 0]
    margin = (gap - L.emergency_gap_m) / (L.spacing_m - L.emergency_gap_m)
    slots = np.zeros((k, L.n_trains, 2))
    slots[:, :, 0] = x_r[:, None] - L.offset_m[heads][None, :]
    return TrackGeometry(centers, strips, gap, margin, slots)


def margin_colors(margin: np.ndarray) -> np.ndarray:
    """RGBA (uint8) per gap: green at or above l_s (margin >= 1), through amber, to red at l_e (margin <= 0)."""
    m = np.clip(np.asarray(margin, dtype=float), 0.0, 1.0)
    red = np.where(m < 0.5, 220, np.round(220 - (m - 0.5) * 2 * 190)).astype(np.uint8)
    green = np.where(m < 0.5, np.round(40 + m * 2 * 150), 190).astype(np.uint8)
    out = np.empty(m.shape + (4,), dtype=np.uint8)
    out[..., 0], out[..., 1], out[..., 2], out[..., 3] = red, green, 40, 255
    below = np.asarray(margin) <= 0.0
    out[below] = (200, 0, 0, 255)
    return out

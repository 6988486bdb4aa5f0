"""The firmware's line database: grade and curve resistance per kg at a position, for feed-forward.

A real onboard unit knows the line's gradient and curve profile from its track database; here it is
configured from a ``TrackConfig`` (usually the scenario's own ``[track]``, copied into the law's parameters).
The tables are ``ecu_sim.track.TrackProfile``'s, as the plant's (one format, one set of segment checks); the
lookup is a scalar ``bisect`` because a law asks for one position per cycle.
"""
from __future__ import annotations

import bisect

from ecu_sim.track import TrackConfig, TrackProfile


class LineMap:
    """Grade + curve resistance per kg (N/kg, + = resists forward motion) at a front-end position."""

    def __init__(self, track: TrackConfig) -> None:
        profile = TrackProfile(track)
        self._edges = profile.breakpoints.tolist()
        self._grade = profile.grade_per_kg.tolist()
        self._curve = profile.curve_per_kg.tolist()
        self.flat = profile.flat

    def resistance_per_kg(self, x: float, v: float) -> float:
        """g grade/1000 + curve resistance (curve opposes motion: counted for v >= 0 as the plant does for v > 0)."""
        if self.flat:
            return 0.0
        k = bisect.bisect_right(self._edges, x)
        curve = self._curve[k] if v >= 0.0 else -self._curve[k]
        return self._grade[k] + curve

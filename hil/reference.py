"""The virtual leader: x_r(t), v_r(t) from a scenario's reference profile.

Position profiles (seed 000) give v_r as a function of x_r, so x_r(t) solves dx_r/dt = v_r(x_r):
piecewise linear with a breakpoint whenever x_r crosses a segment boundary. Time profiles give
v_r(t) directly. Steps in v_r are steps (a_r = 0 between them), as in the papers.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

from hil.scenario.model import ReferenceConfig


@dataclass(frozen=True)
class ReferenceProfile:
    """Piecewise-constant v_r with exact x_r: breakpoints t_k, x_k, v_k (v_k holds on [t_k, t_{k+1}))."""

    times: tuple[float, ...]
    positions: tuple[float, ...]
    speeds: tuple[float, ...]

    @classmethod
    def from_config(cls, cfg: ReferenceConfig) -> "ReferenceProfile":
        if cfg.by == "time":
            return cls._from_time_segments(cfg)
        return cls._from_position_segments(cfg)

    @classmethod
    def _from_time_segments(cls, cfg: ReferenceConfig) -> "ReferenceProfile":
        times, positions, speeds = [], [], []
        x = cfg.x0_m
        for seg in cfg.segments:
            times.append(seg.start)
            positions.append(x)
            speeds.append(seg.speed)
            x += seg.speed * (seg.end - seg.start)
        return cls(tuple(times), tuple(positions), tuple(speeds))

    @classmethod
    def _from_position_segments(cls, cfg: ReferenceConfig) -> "ReferenceProfile":
        times, positions, speeds = [], [], []
        t, x = 0.0, cfg.x0_m
        for seg in cfg.segments:
            if seg.end <= x:
                continue  # segments behind the start position
            if seg.speed <= 0:
                raise ValueError(f"reference segment starting at {seg.start} m has speed {seg.speed}: a position profile needs v_r > 0")
            times.append(t)
            positions.append(x)
            speeds.append(seg.speed)
            t += (seg.end - x) / seg.speed
            x = seg.end
        return cls(tuple(times), tuple(positions), tuple(speeds))

    @property
    def change_times(self) -> list[float]:
        """Times at which v_r steps (after t = 0)."""
        return [t for t in self.times[1:]]

    def at(self, t: float) -> tuple[float, float]:
        """(x_r, v_r) at time t; the last speed holds beyond the profile's end."""
        k = bisect.bisect_right(self.times, t) - 1
        k = max(k, 0)
        return self.positions[k] + self.speeds[k] * (t - self.times[k]), self.speeds[k]

"""The virtual leader: x_r(t), v_r(t), a_r(t) from a scenario's reference profile.

Position profiles (seed 000) give v_r as a function of x_r, so x_r(t) solves dx_r/dt = v_r(x_r):
piecewise linear with a breakpoint whenever x_r crosses a segment boundary. Time profiles give
v_r(t) directly: a constant segment holds its speed (a step at its start, a_r = 0, as in the papers);
a ramp segment (``to_speed_*``) moves v_r linearly from ``speed`` to ``to_speed`` over [start, end)
with constant a_r, and x_r is the exact integral (x_k + v_k dt + a_k dt^2 / 2). After the last
segment the reference holds the last segment's end speed with a_r = 0.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

from hil.scenario.model import ReferenceConfig


@dataclass(frozen=True)
class ReferenceProfile:
    """Piecewise v_r with exact x_r: breakpoints t_k, x_k, v_k, a_k (v = v_k + a_k (t - t_k) on [t_k, t_{k+1})).

    ``accels`` empty means every a_k = 0 (piecewise-constant v_r).
    """

    times: tuple[float, ...]
    positions: tuple[float, ...]
    speeds: tuple[float, ...]
    accels: tuple[float, ...] = ()

    @classmethod
    def from_config(cls, cfg: ReferenceConfig) -> "ReferenceProfile":
        if cfg.by == "time":
            return cls._from_time_segments(cfg)
        return cls._from_position_segments(cfg)

    @classmethod
    def _from_time_segments(cls, cfg: ReferenceConfig) -> "ReferenceProfile":
        times, positions, speeds, accels = [], [], [], []
        x = cfg.x0_m
        for seg in cfg.segments:
            dt = seg.end - seg.start
            v0, v1 = seg.speed, seg.to_speed
            a = (v1 - v0) / dt if seg.is_ramp else 0.0
            times.append(seg.start)
            positions.append(x)
            speeds.append(v0)
            accels.append(a)
            x += v0 * dt + 0.5 * a * dt * dt if seg.is_ramp else seg.speed * dt
        last = cfg.segments[-1]
        if last.is_ramp:  # hold the ramp's end speed afterwards instead of ramping on forever
            times.append(last.end)
            positions.append(x)
            speeds.append(last.to_speed)
            accels.append(0.0)
        if not any(accels):
            return cls(tuple(times), tuple(positions), tuple(speeds))
        return cls(tuple(times), tuple(positions), tuple(speeds), tuple(accels))

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
        """Times at which v_r steps or its slope changes (after t = 0)."""
        return [t for t in self.times[1:]]

    def at(self, t: float) -> tuple[float, float]:
        """(x_r, v_r) at time t; the last speed holds beyond the profile's end."""
        x, v, _ = self.state(t)
        return x, v

    def state(self, t: float) -> tuple[float, float, float]:
        """(x_r, v_r, a_r) at time t; before the first breakpoint the first segment extends backwards."""
        k = bisect.bisect_right(self.times, t) - 1
        k = max(k, 0)
        dt = t - self.times[k]
        a = self.accels[k] if self.accels else 0.0
        if a == 0.0:  # piecewise-constant: exactly the historical formula (bit-identical runs)
            return self.positions[k] + self.speeds[k] * dt, self.speeds[k], 0.0
        return self.positions[k] + (self.speeds[k] + 0.5 * a * dt) * dt, self.speeds[k] + a * dt, a

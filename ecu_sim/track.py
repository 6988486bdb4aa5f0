"""The line's description: grade and curve segments, and their resistance per kg as piecewise-constant tables.

One description serves both sides: the firmware's line database (``ecu_sim.line_map``) and the plant's physics
(``hil.plant.dynamics``); the scenario's ``[track]`` section is a ``TrackConfig``. Segments are looked up for all
units at once with one ``np.searchsorted`` on the sorted breakpoints of all segments; outside every segment
grade and curvature are 0.
"""
from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

G = 9.81  # m/s^2
MAX_SEGMENTS = 10_000  # segments per list (a bound, so that a hostile file cannot exhaust memory)


class _Strict(BaseModel):
    """Unknown keys and values of the wrong kind are errors; immutable; no NaN or infinity."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class GradeSegment(_Strict):
    start_m: float
    end_m: float
    grade_permille: float = Field(description="+ = uphill")


class CurveSegment(_Strict):
    start_m: float
    end_m: float
    radius_m: float = Field(gt=0)


class TrackConfig(_Strict):
    grades: list[GradeSegment] = Field(default=[], max_length=MAX_SEGMENTS)
    curves: list[CurveSegment] = Field(default=[], max_length=MAX_SEGMENTS)
    curve_coefficient: float = Field(default=600.0, description="curve resistance per kg = g * coefficient / R / 1000")


def _check_segments(name: str, segments: list) -> None:
    """Reject empty or overlapping segments of one kind (the profile would be ambiguous)."""
    for i, seg in enumerate(segments):
        if not seg.end_m > seg.start_m:
            raise ValueError(f"track.{name}[{i}]: end_m ({seg.end_m}) must be after start_m ({seg.start_m})")
    order = sorted(range(len(segments)), key=lambda i: segments[i].start_m)
    for a, b in zip(order, order[1:]):
        if segments[b].start_m < segments[a].end_m:
            raise ValueError(
                f"track.{name}[{a}] [{segments[a].start_m}, {segments[a].end_m}) overlaps "
                f"track.{name}[{b}] [{segments[b].start_m}, {segments[b].end_m})"
            )


class TrackProfile:
    """Grade force per kg (signed, + uphill) and curve resistance per kg (>= 0) by position."""

    def __init__(self, track: TrackConfig) -> None:
        _check_segments("grades", track.grades)
        _check_segments("curves", track.curves)
        edges = sorted({s.start_m for s in track.grades + track.curves} | {s.end_m for s in track.grades + track.curves})
        self.breakpoints = np.array(edges, dtype=float)
        # interval k (searchsorted side="right") is [edges[k-1], edges[k]); 0 and len(edges) lie outside
        mids = np.concatenate(([-np.inf], (self.breakpoints[:-1] + self.breakpoints[1:]) / 2, [np.inf]))
        self.grade_per_kg = np.zeros(len(edges) + 1)  # g * grade / 1000, N/kg, + = uphill
        self.curve_per_kg = np.zeros(len(edges) + 1)  # g * coefficient / R / 1000, N/kg
        for seg in track.grades:
            inside = (mids >= seg.start_m) & (mids < seg.end_m)
            self.grade_per_kg[inside] = G * seg.grade_permille / 1000.0
        for seg in track.curves:
            inside = (mids >= seg.start_m) & (mids < seg.end_m)
            self.curve_per_kg[inside] = G * track.curve_coefficient / seg.radius_m / 1000.0

    @property
    def flat(self) -> bool:
        """True when there is no segment at all (the plant then skips the lookup)."""
        return len(self.breakpoints) == 0

    def lookup(self, x: np.ndarray, grade_out: np.ndarray, curve_out: np.ndarray) -> None:
        """Write grade and curve resistance per kg at positions ``x`` into the two output arrays."""
        k = np.searchsorted(self.breakpoints, x, side="right")
        np.take(self.grade_per_kg, k, out=grade_out)
        np.take(self.curve_per_kg, k, out=curve_out)

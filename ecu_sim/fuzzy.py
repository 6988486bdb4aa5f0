"""A small two-input Mamdani fuzzy inference in numpy: seed 002's tuner of the potential weight a.

Mamdani with min implication, max aggregation and centroid defuzzification. Both inputs and the
output live on normalised universes [0, 1], each with seven triangular levels NB NM NS ZO PS PM PB
centred evenly at 0, 1/6, ..., 1 (half-width 1/6, so two neighbouring levels always sum to 1). The
end levels are full triangles cut by the universe: an input outside [0, 1] is clipped to it, so NB
and PB act as shoulders. The seed gives neither membership functions nor universes: these are ours
(CONTROLLERS.md asks for "triangular on normalised universes, documented").

The aggregated output set is piecewise linear, so its centroid is computed exactly, by integrating
each linear piece between its kinks (:func:`centroid`), not on a sampled universe.
tests/test_fuzzy.py checks it against scikit-fuzzy and against an independent brute-force
computation. At most two levels of each input fire, so at most four rules are evaluated per call.

Cost: about 10 us per call, in plain floats (the laws call it every cycle for every neighbour).
"""
from __future__ import annotations

import numpy as np

LEVELS = ("NB", "NM", "NS", "ZO", "PS", "PM", "PB")
N_LEVELS = len(LEVELS)
CENTRES = np.linspace(0.0, 1.0, N_LEVELS)  # NB at 0 ... PB at 1
HALF_WIDTH = 1.0 / (N_LEVELS - 1)

#: Seed 002, Table 1: output level of the weight a; rows = input 1 (|d - d_r|), columns = input 2 (|dv_r/dt|).
SEED002_RULES: tuple[tuple[str, ...], ...] = (
    ("ZO", "PS", "PS", "PM", "PM", "PB", "PB"),  # NB
    ("NS", "ZO", "ZO", "PS", "PM", "PM", "PB"),  # NM
    ("NS", "NS", "ZO", "ZO", "PS", "PS", "PM"),  # NS
    ("NM", "NS", "NS", "ZO", "PS", "PS", "PM"),  # ZO
    ("NM", "NM", "NS", "NS", "ZO", "PS", "PS"),  # PS
    ("NB", "NM", "NM", "NS", "ZO", "ZO", "PS"),  # PM
    ("NB", "NB", "NM", "NM", "NS", "ZO", "ZO"),  # PB
)


def triangular(x: float | np.ndarray, centres: np.ndarray = CENTRES, half_width: float = HALF_WIDTH) -> np.ndarray:
    """Membership of x in each triangular level: max(0, 1 - |x - c| / w); shape (levels,) or (levels, len(x))."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        return np.maximum(0.0, 1.0 - np.abs(x - centres) / half_width)
    return np.maximum(0.0, 1.0 - np.abs(x[..., None] - centres) / half_width).T


def rule_indices(table: tuple[tuple[str, ...], ...]) -> np.ndarray:
    """A rule table of level names as a (7, 7) array of output level indices; bad names are errors."""
    if len(table) != N_LEVELS or any(len(row) != N_LEVELS for row in table):
        raise ValueError(f"a rule table needs {N_LEVELS} x {N_LEVELS} entries")
    try:
        return np.array([[LEVELS.index(name) for name in row] for row in table], dtype=int)
    except ValueError:
        bad = sorted({name for row in table for name in row} - set(LEVELS))
        raise ValueError(f"unknown level name(s) {bad} in rule table (levels: {', '.join(LEVELS)})") from None


class Mamdani2:
    """Two inputs in [0, 1] -> one output in [0, 1] through a 7 x 7 rule table (see the module docstring)."""

    def __init__(self, table: tuple[tuple[str, ...], ...] = SEED002_RULES) -> None:
        self.rules = rule_indices(table)
        self._rules = self.rules.tolist()

    def strengths(self, x1: float, x2: float) -> list[float]:
        """Firing strength of each output level: max over its rules of min(mu1, mu2) (a new list)."""
        s = [0.0] * N_LEVELS
        rules = self._rules
        for i, m1 in _active(x1):
            for j, m2 in _active(x2):
                k = rules[i][j]
                w = m1 if m1 < m2 else m2
                if w > s[k]:
                    s[k] = w
        return s

    def __call__(self, x1: float, x2: float) -> float:
        """Crisp output (exact centroid of the aggregated set) for inputs x1, x2 (clipped to [0, 1])."""
        return centroid(self.strengths(x1, x2))


def _active(x: float) -> list[tuple[int, float]]:
    """The (level, membership) pairs with non-zero membership of x clipped to [0, 1] (one or two levels)."""
    x = min(max(float(x), 0.0), 1.0)
    pos = x / HALF_WIDTH
    j = min(int(pos), N_LEVELS - 2)
    t = pos - j  # in [0, 1]: membership 1 - t in level j, t in level j + 1
    out = [(j, 1.0 - t)] if t < 1.0 else []
    if t > 0.0:
        out.append((j + 1, t))
    return out


def centroid(strength) -> float:
    """Exact centroid of max_k min(strength_k, triangle_k(y)) on [0, 1] for the seven evenly spaced levels.

    Between two centres c_j, c_j+1 (local t in [0, 1]) only levels j and j+1 are non-zero, and
    mu(t) = max(min(s_j, 1 - t), min(s_j+1, t)) is linear between the kinks t in {0, 1, 1 - s_j, s_j+1,
    s_j, 1 - s_j+1, 1/2}. Evaluating mu there and integrating each linear piece exactly gives the
    area and the first moment with no discretisation error. Plain floats: intervals where both levels
    are off are skipped, so a call costs a few microseconds.
    """
    s = [float(v) for v in strength]
    if len(s) != N_LEVELS or min(s) < 0.0 or max(s) <= 0.0:
        raise ValueError(f"strengths must be {N_LEVELS} non-negative values, not all zero, got {strength!r}")
    area = moment = 0.0
    for j in range(N_LEVELS - 1):
        a, b = s[j], s[j + 1]
        if a == 0.0 and b == 0.0:
            continue
        c = j * HALF_WIDTH
        knots = sorted({0.0, 1.0, 0.5, min(max(1.0 - a, 0.0), 1.0), min(max(b, 0.0), 1.0),
                        min(max(a, 0.0), 1.0), min(max(1.0 - b, 0.0), 1.0)})
        t0 = knots[0]
        m0 = max(min(a, 1.0 - t0), min(b, t0))
        for t1 in knots[1:]:
            m1 = max(min(a, 1.0 - t1), min(b, t1))
            h = (t1 - t0) * HALF_WIDTH
            y0, y1 = c + t0 * HALF_WIDTH, c + t1 * HALF_WIDTH
            area += h * (m0 + m1) / 2.0
            moment += h * (y0 * (2.0 * m0 + m1) + y1 * (m0 + 2.0 * m1)) / 6.0
            t0, m0 = t1, m1
    return moment / area

"""Seed 002: multi-train tracking with an adaptive artificial potential whose weight a is fuzzy-tuned.

Each train (one mass, one ECU) hears the train ahead and the train behind over radio and the wayside
reference. The law, per kg (the ECU sends the force m u^):

    u^ = k1 u1 + k2 u2 + R(v) + grade/curve(x)
    u1 = F_p(g_ahead; a_ahead) - F_p(g_behind; a_behind)                      (potential, eq. 5)
    u2 = -alpha (v - v_r) + sum_j (v_j - v)                                    (speed consensus, eq. 6)
    F_p(g; a) = sign(g) (exp(a |g| / L) - 1) / (exp(a) - 1),   L = 3 km         (eq. 4)

with g = d - d_r the error of a gap (d head to head, d_r = 7.4 km), seen the same way by both trains of
the pair: a long gap pulls the follower forward and holds the leader back, a short one pushes them apart,
and F_p(0) = 0: the only equilibrium of the potential is every gap at d_r.

Reconstructions (the seed's formulas are garbled; CONTROLLERS.md section 002 and docs/multi_train.md):
- (4): the printed exponent "3^{1a (d - d_r)}" is read as a |d - d_r| / 3 km (CONTROLLERS.md's reading,
  consistent with the figures: F_p(+-3 km) = +-1 for every a). With this reading a larger a makes the
  potential *weaker* below 3 km (slope at d_r: a / (L (e^a - 1)), 0.58/L at a = 1, 0.16/L at 3, 0.034/L at 5).
- (5): sgn((i - j)(d_r - d_ij)) with the leading minus gives +F_p for the train ahead (j = i - 1) and
  -F_p for the train behind (j = i + 1), i.e. the symmetric pair force above.
- (6): printed with +sum a_ij (v_i - v_j), which is unstable for small alpha: we use -sum (v_i - v_j).
- units: (8) adds k1 u1 (dimensionless F_p) to k2 u2 (a force, m (...)). We read every term per kg:
  F_p in m/s^2 (1 m/s^2 at a 3 km gap error), u2 in m/s^2, k1 = 1, k2 = 0.05 (1/s). alpha is not
  given: alpha = 1 (the check in CONTROLLERS.md found the paper's 80 s only near alpha = 1; we take
  it as the natural unit value, not fitted).
- (7): resistance, grade and curve compensation at the own speed and position; the grade and curve
  come from the firmware's line map (``line_map``), Davis from the nominal plant info.
- fuzzy tuning (Table 1): two inputs |d - d_r| / ``gap_scale_m`` and |dv_r/dt| / ``dvr_scale_mps2``,
  both clipped to [0, 1], seven triangular levels each (ecu_sim/fuzzy.py); the output level maps
  linearly to a in [``a_min``, ``a_max``] = [1, 5] (NB -> 1, ZO -> 3, PB -> 5: the paper's own
  fixed values). One a per gap (the pair's error), so both trains of a pair use the same a.
  |dv_r/dt| is the larger of the wayside's a_r and the received v_r's change over the last cycle
  (a stepped v_r has a_r = 0: the step shows for one cycle only).
- ``tuning = "fixed"`` uses ``a_fixed`` for every gap (the paper's a = 1, 3, 5 variants).
Safety: with ``emergency_rule`` the follower brakes at the emergency rate when the gap ahead falls below
l_e (rig rule, not in the seed). Neighbours not heard (``valid = False``) are left out of both sums.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from ecu_sim.controllers.base import PlantInfo, register
from ecu_sim.controllers.common import check_own_state, emergency_command, train_ahead_too_close
from ecu_sim.controllers.multi_train import MultiTrainLaw, MultiTrainParams, gap_terms
from ecu_sim.fuzzy import Mamdani2
from ecu_sim.view import AgentInfo, Command, LocalView


def potential_force(g: float, a: float, scale_m: float) -> float:
    """F_p(g; a) = sign(g) (exp(a |g| / scale) - 1) / (exp(a) - 1): 0 at g = 0, +-1 at g = +-scale."""
    if g == 0.0:
        return 0.0
    return math.copysign(math.expm1(a * abs(g) / scale_m) / math.expm1(a), g)


class PotentialParams(MultiTrainParams):
    """Seed 002's parameters (k1, k2, d_r through the scenario's l_s) and our readings of the missing ones."""

    k1: float = Field(default=1.0, ge=0, description="potential gain (m/s^2 per unit of F_p)")
    k2: float = Field(default=0.05, ge=0, description="speed-consensus gain (1/s)")
    alpha: float = Field(default=1.0, ge=0, description="weight of the own speed error in u2 (not given by the seed: ours)")
    scale_m: float = Field(default=3000.0, gt=0, description="L: gap error at which F_p = 1 (the 3 km of the reading of (4))")
    tuning: Literal["fuzzy", "fixed"] = "fuzzy"
    a_fixed: float = Field(default=3.0, gt=0, description="a for tuning = 'fixed'")
    a_min: float = Field(default=1.0, gt=0, description="a at the fuzzy output's NB centre")
    a_max: float = Field(default=5.0, gt=0, description="a at the fuzzy output's PB centre")
    gap_scale_m: float = Field(default=3000.0, gt=0, description="fuzzy input 1 = |d - d_r| / this, clipped to 1")
    dvr_scale_mps2: float = Field(default=1.0, gt=0, description="fuzzy input 2 = |dv_r/dt| / this, clipped to 1")

    @model_validator(mode="after")
    def _check_range(self) -> "PotentialParams":
        if not self.a_min < self.a_max:
            raise ValueError(f"a_min ({self.a_min}) must be below a_max ({self.a_max})")
        return self


@register
class FuzzyPotential(MultiTrainLaw):
    """Seed 002's law for one train: fuzzy-tuned (or fixed-a) artificial potential + speed consensus."""

    name = "potential"
    Params = PotentialParams

    def __init__(self, params: PotentialParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self._fuzzy = Mamdani2() if params.tuning == "fuzzy" else None
        self._last_vr: float | None = None
        self.last_weights: dict[str, float] = {}  # a per side of the last cycle (for tests and inspection)

    def reset(self) -> None:
        self._last_vr = None
        self.last_weights = {}

    def weight(self, g: float, dvr_dt: float) -> float:
        """The potential weight a for a gap error g (m) and a reference acceleration magnitude (m/s^2)."""
        p = self.params
        if self._fuzzy is None:
            return p.a_fixed
        y = self._fuzzy(abs(g) / p.gap_scale_m, abs(dvr_dt) / p.dvr_scale_mps2)
        return p.a_min + (p.a_max - p.a_min) * y

    def _reference_rate(self, view: LocalView) -> float:
        """|dv_r/dt|: the wayside's a_r, or the received v_r's step over the last cycle if larger."""
        ref = view.ref
        rate = abs(ref.a) if math.isfinite(ref.a) else 0.0
        if self._last_vr is not None and view.dt > 0:
            rate = max(rate, abs(ref.v - self._last_vr) / view.dt)
        self._last_vr = ref.v
        return rate

    def step(self, view: LocalView) -> Command:
        agent, p = self.agent, self.params
        check_own_state(view)
        if p.emergency_rule and train_ahead_too_close(view, agent, self.plant_info):
            return emergency_command(agent, self.plant_info)
        ref = view.ref
        pinned = agent.has_reference and ref.valid
        dvr = self._reference_rate(view) if pinned else 0.0
        v = view.v
        u1 = u2 = 0.0
        for nb, g, dv in gap_terms(view, agent.offset_m):
            a = self.weight(g, dvr)
            self.last_weights[nb.side] = a
            f = nb.weight * potential_force(g, a, p.scale_m)
            u1 += f if nb.side == "ahead" else -f
            u2 += nb.weight * dv
        if pinned:
            u2 -= p.alpha * (v - ref.v)
        u = p.k1 * u1 + p.k2 * u2 + self.feed_forward(view.x, v)
        if not math.isfinite(u):
            raise ValueError(f"command is not finite (v = {v!r}, v_r = {ref.v!r})")
        return Command(force_n=agent.mass_kg * u, accel_mps2=u)

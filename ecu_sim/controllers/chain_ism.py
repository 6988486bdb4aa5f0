"""Seed 003 (patent): chain cooperative control of a train group under matched and mismatched disturbances.

Agents are single-mass trains, dx/dt = v + d2 (mismatched, position channel), dv/dt = u + d1 (matched),
after the running, grade and curve resistance are cancelled by feed-forward. They form a chain
1-2-...-N over radio; the virtual leader (the wayside reference x_r, v_r) is heard by the trains listed
in ``leaders`` (default: train 1 only, b_1 = 1), so the others follow it through the chain. With the
slot errors x~ = x - (x_r - offset), v~ = v - v_r, a neighbour's Delta_j = x~_j - x~ and dv_j = v_j - v, and
sig(z)^a = |z|^a sign(z), alpha2 = 2 alpha1 / (alpha1 + 1):

Protocol 1 (finite-time, designed without disturbances; the patent's first protocol):
    u0 = k1 sum_j sig(Delta_j)^a1 + k2 sum_j sig(dv_j)^a2 - b [k1 sig(x~)^a1 + k2 sig(v~)^a2 - a_r]
Protocol 2 (protocol 1 on tracking errors with a differential term, gains ku, kd):
    the same with Delta_j -> Delta_j + ku dDelta_j/dt, dv_j -> dv_j + kd d(dv_j)/dt, x~ -> x~ + ku dx~/dt,
    v~ -> v~ + kd dv~/dt; the derivatives are first-order filtered differences (time constant
    ``tau_d``) of what the ECU receives: dx/dt of a measured position includes d2, which is what the
    term is for. dx~/dt = dx/dt - v_r and dv~/dt = dv/dt - a_r, so a step of v_r is not differentiated.
Protocol 3 (composite integral sliding mode + disturbance-observer feed-forward + speed saturation):
    ESOs (ecu_sim/observers.py) estimate d1 (from v and the own command), d2 (from x and v) and, per
    neighbour, d2_j - d2 (from Delta_j and dv_j). With the effective speeds xi = v + d2^ (the observer's
    estimate of dx/dt), the nominal u0 is protocol 1 on (Delta_j, dxi_j, x~, xi~). The integral sliding
    variable s = xi - xi(0) - int_0^t u0 dtau (zero from the start: no reaching phase) and
        u = u0 - d1^ - d(d2^)/dt - k0 sat(s / phi)
    give ds/dt = (d1 - d1^) + (d2' - d2^') - k0 sat(s/phi): on s = 0, d(xi)/dt = u0 and dx/dt = xi + (d2 - d2^),
    so the train group follows the disturbance-free protocol-1 dynamics in (x, xi). Speed saturation:
        u <- min(u, k_v (v_max - margin - v) - d1^)
    keeps v below v_max (up to the observer error over k_v); while it binds, s is re-anchored to 0
    (integral anti-windup).

Reconstructions: the patent's formulas are images missing from the text (CONTROLLERS.md section 003), so
everything above is our design, in the patent's words: (2) "the tracking error augmented with a
differential term, gains ku and kd, using the follower's first derivatives of position and speed";
(3) "k0, k1, k2 > 0, the disturbance observer's estimates of the system speed and of the disturbance,
s_j the integral sliding surface, a saturation operator on the speed". The gains are not given: the
defaults are ours, chosen by one rule and not fitted (k1 = omega^2, k2 = 2 omega with omega = 0.1 rad/s:
a critically damped linearisation; alpha1 = 0.9 as seed 000; ku = 5 s, kd = 2 s keep the differential
loop gain k2 kd = 0.4 below 1; ESO bandwidths 2 and 1 rad/s; k0 = 0.1 m/s^2, phi = 0.05 m/s;
k_v = 0.5 1/s, margin 0.5 m/s). Every law adds the resistance feed-forward R(v) + grade/curve(x).
"""
from __future__ import annotations

import math

from pydantic import Field

from ecu_sim.controllers.base import PlantInfo, register
from ecu_sim.controllers.common import check_own_state, emergency_command, sig, train_ahead_too_close, usable_neighbours
from ecu_sim.controllers.multi_train import MultiTrainLaw, MultiTrainParams
from ecu_sim.observers import Eso
from ecu_sim.view import AgentInfo, Command, LocalView


class ChainParams(MultiTrainParams):
    """Protocol 1's gains and the leader set (ours: the patent gives no numbers)."""

    k1: float = Field(default=0.01, gt=0, description="position gain (m^(1-a1)/s^2)")
    k2: float = Field(default=0.2, gt=0, description="speed gain (m^(1-a2)/s^(2-a2))")
    alpha1: float = Field(default=0.9, gt=0, le=1, description="position exponent (0 < a1 < 1; 1 = linear)")
    leaders: list[int] = Field(default=[1], description="1-based trains that hear the virtual leader (b_i = 1)")


class DifferentialParams(ChainParams):
    """Protocol 2: the differential term's gains and filter."""

    ku: float = Field(default=5.0, ge=0, description="differential gain on the position errors (s)")
    kd: float = Field(default=2.0, ge=0, description="differential gain on the speed errors (s)")
    tau_d: float = Field(default=0.2, gt=0, description="time constant of the derivative filter (s)")


class IsmParams(ChainParams):
    """Protocol 3: sliding mode, observers and speed saturation."""

    k0: float = Field(default=0.1, ge=0, description="sliding-mode switching gain (m/s^2)")
    phi: float = Field(default=0.05, gt=0, description="boundary layer of sat(s / phi) (m/s)")
    omega_d1: float = Field(default=2.0, gt=0, description="bandwidth of the speed-channel observer (rad/s)")
    omega_d2: float = Field(default=1.0, gt=0, description="bandwidth of the position-channel observers (rad/s)")
    speed_limit_mps: float | None = Field(default=None, gt=0, description="v_max of the saturation (None: no saturation)")
    speed_margin_mps: float = Field(default=0.5, ge=0, description="the governor aims this far below v_max")
    k_speed: float = Field(default=0.5, gt=0, description="gain of the speed governor (1/s)")


class _ChainBase(MultiTrainLaw):
    """Shared: pinning, protocol 1's nominal term, feed-forward, safety rule."""

    def __init__(self, params: ChainParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self._a1, self._a2 = params.alpha1, 2.0 * params.alpha1 / (params.alpha1 + 1.0)
        self.leader = (agent.train + 1) in params.leaders

    def nominal(self, pairs: list[tuple[float, float]], own: tuple[float, float] | None, a_r: float) -> float:
        """Protocol 1's u0 from (position, speed) differences to neighbours and the own errors if pinned."""
        p, a1, a2 = self.params, self._a1, self._a2
        u = 0.0
        for dx, dv in pairs:
            u += p.k1 * sig(dx, a1) + p.k2 * sig(dv, a2)
        if own is not None:
            u -= p.k1 * sig(own[0], a1) + p.k2 * sig(own[1], a2) - a_r
        return u

    def pinned(self, view: LocalView) -> bool:
        return self.leader and self.agent.has_reference and view.ref.valid

    def command(self, view: LocalView, u: float) -> Command:
        """Add the feed-forward and build the force command from a net acceleration u."""
        total = u + self.feed_forward(view.x, view.v)
        if not math.isfinite(total):
            raise ValueError(f"command is not finite (x = {view.x!r}, v = {view.v!r}, v_r = {view.ref.v!r})")
        return Command(force_n=self.agent.mass_kg * total, accel_mps2=total)

    def unsafe(self, view: LocalView) -> Command | None:
        check_own_state(view)
        if self.params.emergency_rule and train_ahead_too_close(view, self.agent, self.plant_info):
            return emergency_command(self.agent, self.plant_info)
        return None


@register
class ChainFiniteTime(_ChainBase):
    """Protocol 1: finite-time chain consensus with leader pinning."""

    name = "chain_p1"
    Params = ChainParams

    def step(self, view: LocalView) -> Command:
        brake = self.unsafe(view)
        if brake is not None:
            return brake
        off, ref = self.agent.offset_m, view.ref
        pairs = [(d, dv) for _, d, dv in usable_neighbours(view, off)]
        own = (view.x - (ref.x - off), view.v - ref.v) if self.pinned(view) else None
        return self.command(view, self.nominal(pairs, own, ref.a if own is not None else 0.0))


class _FilteredDerivative:
    """First-order filtered difference quotient of a sampled signal."""

    __slots__ = ("tau", "last", "value")

    def __init__(self, tau: float) -> None:
        self.tau, self.last, self.value = tau, None, 0.0

    def update(self, z: float, dt: float) -> float:
        if self.last is not None and dt > 0:
            beta = dt / (self.tau + dt)
            self.value += beta * ((z - self.last) / dt - self.value)
        self.last = z
        return self.value


@register
class ChainDifferential(_ChainBase):
    """Protocol 2: protocol 1 on tracking errors augmented with a filtered differential term."""

    name = "chain_p2"
    Params = DifferentialParams

    def __init__(self, params: DifferentialParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.reset()

    def reset(self) -> None:
        tau = self.params.tau_d
        self._d: dict[str, _FilteredDerivative] = {k: _FilteredDerivative(tau) for k in ("x", "v", "ahead_x", "ahead_v", "behind_x", "behind_v")}
        self._t: float | None = None

    def step(self, view: LocalView) -> Command:
        brake = self.unsafe(view)
        if brake is not None:
            return brake
        p, off, ref = self.params, self.agent.offset_m, view.ref
        dt = view.t - self._t if self._t is not None else 0.0
        self._t = view.t
        D = self._d
        xdot, vdot = D["x"].update(view.x, dt), D["v"].update(view.v, dt)
        pairs = []
        for nb, d, dv in usable_neighbours(view, off):
            dd, ddv = D[nb.side + "_x"].update(d, dt), D[nb.side + "_v"].update(dv, dt)
            pairs.append((d + p.ku * dd, dv + p.kd * ddv))
        own = None
        if self.pinned(view):
            own = (view.x - (ref.x - off) + p.ku * (xdot - ref.v), view.v - ref.v + p.kd * (vdot - ref.a))
        return self.command(view, self.nominal(pairs, own, ref.a if own is not None else 0.0))


@register
class ChainIsm(_ChainBase):
    """Protocol 3: integral sliding mode on protocol 1, observer feed-forward of d1 and d2, speed saturation."""

    name = "chain_p3"
    Params = IsmParams

    def __init__(self, params: IsmParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.reset()

    def reset(self) -> None:
        p = self.params
        self.eso_d1, self.eso_d2 = Eso(p.omega_d1), Eso(p.omega_d2)
        self.eso_pair = {side: Eso(p.omega_d2) for side in ("ahead", "behind")}
        self.s = 0.0  # integral sliding variable
        self.saturated = False  # the speed governor bound in the last cycle
        self._t: float | None = None
        self._xi: float | None = None
        self._u_net = 0.0  # last net acceleration command (the speed observer's input)
        self._u0 = 0.0  # last nominal term (integrated into s)

    def step(self, view: LocalView) -> Command:
        brake = self.unsafe(view)
        if brake is not None:
            self._u_net = 0.0
            return brake
        p, off, ref = self.params, self.agent.offset_m, view.ref
        dt = view.t - self._t if self._t is not None else 0.0
        self._t = view.t
        d1 = self.eso_d1.update(view.v, self._u_net, dt)
        d2 = self.eso_d2.update(view.x, view.v, dt)
        xi = view.v + d2  # effective speed: the observer's estimate of dx/dt
        pairs = []
        for nb, d, dv in usable_neighbours(view, off):
            w = self.eso_pair[nb.side].update(d, dv, dt)  # estimate of d2_j - d2
            pairs.append((d, dv + w))
        own = (view.x - (ref.x - off), xi - ref.v) if self.pinned(view) else None
        u0 = self.nominal(pairs, own, ref.a if own is not None else 0.0)
        if self._xi is not None:
            self.s += (xi - self._xi) - self._u0 * dt
        self._xi, self._u0 = xi, u0
        u = u0 - d1 - self.eso_d2.rate - p.k0 * max(-1.0, min(1.0, self.s / p.phi))
        self.saturated = False
        if p.speed_limit_mps is not None:
            cap = p.k_speed * (p.speed_limit_mps - p.speed_margin_mps - view.v) - d1
            if u > cap:
                u, self.saturated, self.s = cap, True, 0.0
        self._u_net = u
        return self.command(view, u)

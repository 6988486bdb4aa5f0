"""Longitudinal dynamics of every unit of every train, advanced by a fixed step.

Per unit u (flat index, front to back), x = front-end position, v = speed:

    m_eff a = F_act + coupler forces - m (c0 sgn v + c1 v + c2 v|v|) - m g (grade/1000)
              - m g (coef / R / 1000) sgn v + disturbance

Couplers join adjacent units of the same train: e = x_front - x_rear - l_front, f = k e + d de/dt
pulls the front unit back (-f) and the rear unit forward (+f). Curve resistance is a friction,
so (unlike grade) it opposes motion like c0 and vanishes at standstill.

Integrator. The coupler chain is a nearly undamped oscillator (k = 1.6e5 N/m, d = 600 N s/m,
80 t: omega ~ 1..2.8 rad/s, damping ratio ~ 0.002..0.005), and an integrator that pumps or bleeds
energy changes the very coupler oscillation the controllers are judged on. The linear part
(couplers k, d and the Davis c1 term) is discretised exactly: with z = [q; v], z' = A z + B w,
one augmented ``scipy.linalg.expm([[A, B], [0, 0]] dt)`` per distinct train gives Phi = e^{A dt}
and Gamma = int_0^dt e^{As} ds B once per step size, and z_{k+1} = Phi z_k + Gamma w_k is the exact
flow for a w held constant over the step: no numerical damping or pumping at any dt. Measured on a
free 4-unit chain over 1000 s: relative energy drift 7e-11 at 1 ms and 1.5e-12 at 10 ms (roundoff);
RK4 gives -1.1e-7 at 10 ms.

Positions are integrated as q = x - base, base = (train origin) - (lengths ahead in the train),
so q_front - q_rear = e and the rest lengths drop out of the linear map (they are equivalent to
the constant input Gamma K base). This matters for roundoff: with absolute x and the rest lengths
as a constant input term, e is rounded to ulp(x) every step (1.5e-11 m at 100 km) and the free
chain's energy random-walks by 5e-7 over 1000 s at 1 ms (5.6e-8 even at x ~ 200 m). The origin
moves to the head every REBASE_EVERY steps by a multiple of 1/ORIGIN_GRID m (exact in floating
point); x = base + q is refreshed after every step.

The remaining forces w (actuator, c0, c2 v|v|, grade, curve, disturbance) are evaluated at the
step start and held over the step (zero-order hold): first order for them, the held force lags by
dt/2. They are small and slowly varying next to the coupler forces, and the commands are ZOH
anyway (the ECUs send them every 10 ms). Measured: one unit at 60 m/s under 30 kN with the default
Davis terms differs from solve_ivp (rtol 1e-10) by 3e-5 m/s and 3.7 mm after 200 s at 1 ms.
Grade and curve changes take effect at the first step after a unit front crosses a breakpoint.
A position-channel (mismatched) disturbance d2 (seed 003: dx/dt = v + d2) is evaluated at the step
start like the forces and added to q as d2 dt after the exact step; it never enters v.
The explicit brake fade near standstill (time constant V_STOP / a_brake ~ 0.08 s) and c0 sgn v
(chatter of c0 dt ~ 1e-5 m/s at rest) are stable for dt well above the 1 ms default.

One step is one matrix-vector product on the buffer [q; v; w] (extra rows give the mean
acceleration over the step and a sum that detects non-finite inputs) plus about 15 in-place vector
operations: 7-14 us at 12 units on the 2-core dev machine (tests/test_plant.py::test_step_cost).
Groups above DENSE_MAX_UNITS units use per-train blocks in one batched matmul instead of one
dense matrix (at 512 units: ~30 us instead of ~280 us).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm

from hil.scenario.layout import TrainLayout
from hil.plant.actuators import Actuators
from hil.plant.disturbances import Disturbances
from ecu_sim.track import TrackProfile
from hil.plant.units import unit_params
from hil.scenario.model import PlantConfig, TrackConfig

DENSE_MAX_UNITS = 64  # above this a batched per-train block product is cheaper than one dense matvec
ORIGIN_GRID = 1024.0  # train origins move in multiples of 1/1024 m, so origin updates are exact
REBASE_EVERY = 1024  # steps between origin moves (|q| stays below ~100 m at 90 m/s and 1 ms)


class PlantDiverged(RuntimeError):
    """The plant state or a force became non-finite (the message names the units and t)."""


def train_block(m_eff: np.ndarray, m: np.ndarray, k: float, d: float, c1: float, dt: float) -> np.ndarray:
    """Exact step map of one train in rest-relative coordinates q (q_front - q_rear = e).

    Rows [q'; v'; a_mean], columns [q; v; w]: shape (3u, 3u). w is held over the step.
    """
    u = len(m_eff)
    lap = np.zeros((u, u))  # path-graph Laplacian of the coupler chain
    for j in range(u - 1):
        lap[j : j + 2, j : j + 2] += [[1.0, -1.0], [-1.0, 1.0]]
    minv = np.diag(1.0 / m_eff)
    aug = np.zeros((3 * u, 3 * u))  # d/dt [q; v; w] with w held constant
    aug[:u, u : 2 * u] = np.eye(u)
    aug[u : 2 * u, :u] = -minv @ (k * lap)
    aug[u : 2 * u, u : 2 * u] = -minv @ (d * lap + np.diag(m * c1))
    aug[u : 2 * u, 2 * u :] = minv
    step = expm(aug * dt)[: 2 * u]  # [Phi | Gamma]
    accel = step[u:].copy()
    accel[:, u : 2 * u] -= np.eye(u)
    return np.vstack([step, accel / dt])


class _Propagator:
    """Applies the exact linear step to the buffer [q; v; w], writing [q'; v'; a; check]."""

    def __init__(self, layout: TrainLayout, plant: PlantConfig, dt: float, c1: float | np.ndarray | None = None) -> None:
        n, nt, u = layout.n_units, layout.n_trains, layout.units_per_train
        blocks = self._blocks(layout, plant, dt, c1)
        units = np.arange(n).reshape(nt, u)
        self._cols = np.hstack([units, n + units, 2 * n + units])  # (nt, 3u) inputs of each train
        self.dense = n <= DENSE_MAX_UNITS
        if self.dense:
            self._m = np.zeros((3 * n + 1, 3 * n))
            for i in range(nt):
                self._m[np.ix_(self._cols[i], self._cols[i])] = blocks[i]
            self._m[3 * n] = 1.0  # finite check: the sum of all inputs
        else:
            self._blocks_ = blocks
            self._buf = np.empty((nt, 3 * u))
            self._res = np.empty((nt, 3 * u, 1))
            self._inv = np.argsort(self._cols.ravel())  # output position -> flat index into the block results

    @staticmethod
    def _blocks(layout: TrainLayout, plant: PlantConfig, dt: float, c1_units: float | np.ndarray | None = None) -> np.ndarray:
        """Per-train step maps, computed once per distinct train (they are usually all equal).

        ``c1_units``: per-unit Davis c1 (hil/plant/units.py), else ``plant.davis_c1`` for every unit."""
        k, d, c1 = plant.coupler_stiffness_n_per_m, plant.coupler_damping_ns_per_m, plant.davis_c1
        cache: dict[bytes, np.ndarray] = {}
        out = []
        for i in range(layout.n_trains):
            sl = slice(layout.index(i, 0), layout.index(i, 0) + layout.units_per_train)
            c1_i = c1_units[sl] if isinstance(c1_units, np.ndarray) else (c1 if c1_units is None else c1_units)
            params = (layout.effective_mass_kg[sl], layout.mass_kg[sl])
            key = b"".join(np.ascontiguousarray(p, dtype=float).tobytes() for p in (*params, c1_i))
            if key not in cache:
                cache[key] = train_block(*params, k, d, c1_i, dt)
            out.append(cache[key])
        return np.array(out)

    def apply(self, zw: np.ndarray, zn: np.ndarray) -> bool:
        """zn[:3n] <- step map of zw; returns False when an input was non-finite."""
        if self.dense:
            np.dot(self._m, zw, out=zn)
            return math.isfinite(zn[-1])
        np.take(zw, self._cols, out=self._buf)
        np.matmul(self._blocks_, self._buf[:, :, None], out=self._res)
        np.take(self._res.ravel(), self._inv, out=zn[:-1])
        zn[-1] = np.add.reduce(zw)
        return math.isfinite(zn[-1])


class Plant:
    """The train group's true state, advanced by :meth:`step`; commands in, sensor values out.

    Per-unit masses, rotating-mass factors and Davis coefficients ([plant.units]) and the actuator chain
    ([plant.actuator], health faults) come from hil/plant/units.py and hil/plant/actuators.py; ``self.layout``
    holds the true per-unit masses, while the firmware's AgentInfo keeps the nominal ones of [trains].
    """

    def __init__(
        self,
        plant: PlantConfig,
        track: TrackConfig,
        layout: TrainLayout,
        x0: np.ndarray,
        v0: np.ndarray,
        rng: np.random.Generator,
        dt: float | None = None,
    ) -> None:
        n, u = layout.n_units, layout.units_per_train
        self.units = unit_params(layout, plant)  # per-unit masses, Davis, lambda, rho ([plant.units], [plant.actuator])
        layout = self.units.layout  # the true masses (the firmware keeps the nominal ones of [trains])
        self.layout, self.config, self.rng = layout, plant, rng
        self.dt = float(plant.step_s if dt is None else dt)
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"plant step dt must be a positive number, got {dt!r}")
        self._zw = np.zeros(3 * n)  # [q; v; w]: rest-relative positions, speeds, held forces
        self._zn = np.zeros(3 * n + 1)  # [q'; v'; a; check]
        self._q, self._v, self._w = self._zw[:n], self._zw[n : 2 * n], self._zw[2 * n :]
        self.a = self._zn[2 * n : 3 * n]  # mean acceleration over the last step (view, updated in place)
        # x = base + q, base = train origin - lengths ahead in the train (q_front - q_rear = e)
        self._ahead = np.concatenate([np.concatenate(([0.0], np.cumsum(ls)[:-1])) for ls in layout.length_m.reshape(-1, u)])
        x0 = _state_array("x0", x0, n)
        self._origin = np.round(x0[layout.heads()] * ORIGIN_GRID) / ORIGIN_GRID
        self._base = np.repeat(self._origin, u) - self._ahead
        self._x = np.empty(n)
        self.x, self.v = x0, _state_array("v0", v0, n)
        self._prop = _Propagator(layout, plant, self.dt, self.units.c1)
        self._act = Actuators(plant, layout, self.dt, units=self.units)
        self.force_cmd, self.mode_cmd = self._act.force_cmd, self._act.mode_cmd
        self.force_applied, self.last_cmd_t = self._act.force_applied, self._act.last_cmd_t
        self.events = self._act.events
        self._track = TrackProfile(track)
        self._dist = Disturbances(plant.disturbances, layout, rng, self.dt)
        self._d2 = np.zeros(n) if self._dist.has_position else None  # position-channel disturbance (m/s)
        m = layout.mass_kg
        c0, c2 = self.units.c0, self.units.c2  # floats unless given per unit
        self._neg_m, self._neg_mc0, self._neg_mc2 = -m, -m * c0, -m * c2
        self._c0, self._c2 = c0, c2
        if self.units.configured:
            self.events.append((0.0, "INFO", self.units.describe(plant.units.seed)))
        self._r, self._s = np.empty(n), np.empty(n)
        self._grade, self._curve = np.empty(n), np.empty(n)
        self._steps = 0
        self.t = 0.0

    def close(self) -> None:
        """The run is over. The built-in plant holds nothing to give back; the FMU plant returns its instance."""

    # ------------------------------------------------------------------ state

    @property
    def x(self) -> np.ndarray:
        """True front-end positions (m), refreshed in place after each step: copy it to keep a snapshot.

        Set positions by assigning ``plant.x = array``: the state is the rest-relative q, so editing
        the returned array in place changes nothing and is overwritten by the next step.
        """
        return self._x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        self._x[:] = value
        np.subtract(self._x, self._base, out=self._q)

    @property
    def v(self) -> np.ndarray:
        """True speeds (m/s), a live array updated in place each step: copy it to keep a snapshot."""
        return self._v

    @v.setter
    def v(self, value: np.ndarray) -> None:
        self._v[:] = value

    def coupler_displacements(self) -> np.ndarray:
        """e (m, > 0 stretched) of every coupler, from the rest-relative positions (no ulp(x) rounding)."""
        p = self.layout.coupler_pairs()
        if len(p) == 0:
            return np.zeros(0)
        return self._q[p[:, 0]] - self._q[p[:, 1]]

    def _rebase(self) -> None:
        """Move each train's origin to its head (by a multiple of 1/ORIGIN_GRID m) to keep |q| small."""
        shift = np.round(self._q[self.layout.heads()] * ORIGIN_GRID) / ORIGIN_GRID
        self._origin += shift
        self._q -= np.repeat(shift, self.layout.units_per_train)
        np.subtract(np.repeat(self._origin, self.layout.units_per_train), self._ahead, out=self._base)

    # ------------------------------------------------------------------ inputs and outputs

    def command(self, u: int, force_n: float, mode: int, t: float) -> None:
        """Hold force_n (N) and mode (BrakeMode) for unit u from now on; t = arrival time (s)."""
        if not 0 <= u < self.layout.n_units:
            raise IndexError(f"unit index {u} out of range 0..{self.layout.n_units - 1}")
        if not math.isfinite(force_n):
            raise PlantDiverged(f"non-finite force command {force_n!r} N for {self._act.unit_name(u)} at t = {t:.6f} s")
        self._act.command(u, force_n, mode, t)

    def set_health(self, u: int, health: float, at_s: float | None = None, ramp_s: float = 0.0) -> None:
        """Actuator fault API: unit u's health h goes to ``health`` (in [0, 1]) at ``at_s`` (default: now),
        linearly over ``ramp_s`` from its value then. h scales the unit's shaped traction/brake force
        (hil/plant/actuators.py); the ECU never sees it. A later call for the same unit replaces the schedule
        after its start. Degradation to 60 % over 10 s at t = 300 s: ``set_health(u, 0.6, 300.0, 10.0)``;
        total traction loss of a car at t = 500 s: ``set_health(u, 0.0, 500.0)``. Logged when it takes effect.
        """
        self._act.set_health(u, health, self.t if at_s is None else at_s, ramp_s)

    def set_fault_offset(self, u: int, offset_n: float, at_s: float | None = None, ramp_s: float = 0.0) -> None:
        """Actuator fault API: unit u's bounded fault offset nu (N, scaled by its distribution share) from ``at_s``."""
        self._act.set_fault_offset(u, offset_n, self.t if at_s is None else at_s, ramp_s)

    @property
    def health(self) -> np.ndarray:
        """Actuator health h per unit at the last step (a live array: copy it to keep a snapshot)."""
        return self._act.health

    def measure(self) -> tuple[np.ndarray, np.ndarray]:
        """Sensor positions and speeds: new arrays (the caller may keep them), with configured noise."""
        x, v = self._x.copy(), self._v.copy()
        sensor = self.config.sensor
        if sensor.position_noise_m > 0:
            x += self.rng.normal(0.0, sensor.position_noise_m, x.shape)
        if sensor.speed_noise_mps > 0:
            v += self.rng.normal(0.0, sensor.speed_noise_mps, v.shape)
        return x, v

    def energy(self) -> float:
        """Kinetic (m_eff v^2 / 2) plus coupler spring (k e^2 / 2) energy, J."""
        e = self.coupler_displacements()
        kinetic = 0.5 * float(np.dot(self.layout.effective_mass_kg * self._v, self._v))
        return kinetic + 0.5 * self.config.coupler_stiffness_n_per_m * float(np.dot(e, e))

    # ------------------------------------------------------------------ integration

    def step(self) -> None:
        """Advance by dt: held forces from the state at t, exact linear coupler/c1 dynamics."""
        t, v, w, r, s = self.t, self._v, self._w, self._r, self._s
        force = self._act.apply(t, v)
        np.multiply(v, v, out=r)
        np.sign(v, out=s)
        if self._track.flat:  # w = -m (c0 + c2 v^2) sgn v + F
            np.multiply(r, self._neg_mc2, out=r)
            np.add(r, self._neg_mc0, out=r)
            np.multiply(r, s, out=r)
        else:  # w = -m ((c0 + curve + c2 v^2) sgn v + grade) + F
            self._track.lookup(self._x, self._grade, self._curve)
            np.multiply(r, self._c2, out=r)
            np.add(r, self._curve, out=r)
            np.add(r, self._c0, out=r)
            np.multiply(r, s, out=r)
            np.add(r, self._grade, out=r)
            np.multiply(r, self._neg_m, out=r)
        np.add(r, force, out=w)
        if self._dist:
            self._dist.add(t, w)
        if not self._prop.apply(self._zw, self._zn):
            self._diverged(t)
        n2 = 2 * self.layout.n_units
        self._zw[:n2] = self._zn[:n2]
        if self._d2 is not None:  # mismatched disturbance dx/dt = v + d2 (held over the step), v unchanged
            self._d2.fill(0.0)
            self._dist.add_position(t, self._d2)
            self._q += self._d2 * self.dt
        self._steps += 1
        if self._steps % REBASE_EVERY == 0:
            self._rebase()
        np.add(self._base, self._q, out=self._x)
        self.t = self._steps * self.dt

    def _diverged(self, t: float) -> None:
        """Name the units whose state or held force is non-finite and raise PlantDiverged."""
        bad_state = ~(np.isfinite(self._x) & np.isfinite(self._v))
        if bad_state.any():
            what, units = "state (x, v)", np.flatnonzero(bad_state)
        else:
            what, units = "force", np.flatnonzero(~np.isfinite(self._w))
        detail = "; ".join(
            f"{self._act.unit_name(int(u))}: x = {self._x[u]:.6g} m, v = {self._v[u]:.6g} m/s, "
            f"force = {self._w[u]:.6g} N (command {self.force_cmd[u]:.6g} N)"
            for u in units[:8]
        )
        raise PlantDiverged(f"plant diverged at t = {t:.6f} s: non-finite {what} on {detail}")


def _state_array(name: str, value: np.ndarray, n: int) -> np.ndarray:
    """Check an initial state vector: shape (n,) and finite."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,):
        raise ValueError(f"{name} has shape {arr.shape}, expected ({n},) (one value per unit)")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} has non-finite values at units {np.flatnonzero(~np.isfinite(arr)).tolist()}")
    return arr

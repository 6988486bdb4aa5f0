"""The scenario file's schema: every section of a scenario TOML as a validated pydantic model.

Units are SI in field names' suffixes (``_m``, ``_s``, ``_n``, ``_mps``); speeds may also be
written in km/h where the field name says ``_kmh``. Unknown keys are errors, so a typo in a
scenario file is reported with its dotted path instead of being silently ignored.
"""
from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

KMH = 1.0 / 3.6


class Section(BaseModel):
    """Base of every scenario section: strict about unknown keys, immutable once loaded."""

    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------- trains


class TrainsConfig(Section):
    """The train group: N trains of n identical units, and their initial state."""

    count: int = Field(ge=1, le=32)
    units: int = Field(ge=1, le=16, description="power units (ECUs) per train")
    unit_mass_kg: float = Field(gt=0)
    unit_length_m: float = Field(gt=0)
    rotating_mass_factor: float = Field(default=0.0, ge=0, le=0.5)
    head_positions_m: list[float] = Field(description="front-end position of each train's head unit")
    speeds_mps: list[float] | None = None
    speeds_kmh: list[float] | None = None
    spacing_m: float = Field(gt=0, description="l_s: desired gap rear-of-train to front-of-next")
    emergency_gap_m: float = Field(gt=0, description="l_e: emergency-braking trigger gap")

    @model_validator(mode="after")
    def _check(self) -> "TrainsConfig":
        if (self.speeds_mps is None) == (self.speeds_kmh is None):
            raise ValueError("give exactly one of speeds_mps or speeds_kmh")
        for name in ("head_positions_m", "speeds_mps", "speeds_kmh"):
            values = getattr(self, name)
            if values is not None and len(values) != self.count:
                raise ValueError(f"{name} has {len(values)} values, expected count = {self.count}")
        if self.emergency_gap_m >= self.spacing_m:
            raise ValueError("emergency_gap_m must be below spacing_m")
        pos = self.head_positions_m
        for i in range(1, len(pos)):
            rear = pos[i - 1] - self.units * self.unit_length_m
            if pos[i] >= rear:
                raise ValueError(f"train {i + 1} starts overlapping train {i} (head at {pos[i]} m, rear of train {i} at {rear} m)")
        return self

    @property
    def initial_speeds_mps(self) -> list[float]:
        if self.speeds_mps is not None:
            return list(self.speeds_mps)
        return [v * KMH for v in self.speeds_kmh or []]


# --------------------------------------------------------------------------- plant


class TractionLimits(Section):
    """Actuator envelope. ``enabled = false`` reproduces the papers' unconstrained setting."""

    enabled: bool = True
    max_traction_n: float = Field(default=300e3, gt=0, description="per unit, at low speed")
    max_power_w: float = Field(default=2.4e6, gt=0, description="per unit: traction <= P / v above the base speed")
    max_brake_n: float = Field(default=300e3, gt=0, description="per unit, service + electric brake")
    rate_limit_n_per_s: float = Field(default=200e3, gt=0, description="|dF/dt| per unit")


class FailSafe(Section):
    """What the plant does when traction commands stop arriving for a unit."""

    hold_s: float = Field(default=0.1, ge=0, description="keep the last command this long")
    service_brake_mps2: float = Field(default=0.8, gt=0)
    emergency_after_s: float = Field(default=2.0, ge=0, description="service brake, then emergency after this")
    emergency_brake_mps2: float = Field(default=1.2, gt=0)


class Disturbance(Section):
    """An additive force on some units over a time window."""

    kind: Literal["pulse", "step", "sine", "random"]
    train: int | None = Field(default=None, ge=1, description="1-based; omit for all trains")
    unit: int | None = Field(default=None, ge=1, description="1-based; omit for all units")
    start_s: float = Field(ge=0)
    end_s: float
    amplitude_n: float
    frequency_hz: float = Field(default=0.0, ge=0, description="sine frequency")
    correlation_s: float = Field(default=1.0, gt=0, description="random: correlation time")

    @model_validator(mode="after")
    def _check(self) -> "Disturbance":
        if self.end_s <= self.start_s:
            raise ValueError(f"end_s ({self.end_s}) must be after start_s ({self.start_s})")
        if self.kind == "sine" and self.frequency_hz <= 0:
            raise ValueError("a sine disturbance needs frequency_hz > 0")
        return self


class SensorConfig(Section):
    """Sensor imperfections on top of the DBC quantisation."""

    position_noise_m: float = Field(default=0.0, ge=0)
    speed_noise_mps: float = Field(default=0.0, ge=0)


class PlantConfig(Section):
    """Longitudinal dynamics of every unit of every train."""

    step_s: float = Field(default=0.001, gt=0, le=0.1)
    davis_c0: float = Field(default=0.01176, ge=0, description="N/kg")
    davis_c1: float = Field(default=0.00077616, ge=0, description="N*s/(m*kg)")
    davis_c2: float = Field(default=1.6e-5, ge=0, description="N*s^2/(m^2*kg)")
    coupler_stiffness_n_per_m: float = Field(default=1.6e5, ge=0)
    coupler_damping_ns_per_m: float = Field(default=600.0, ge=0)
    coupler_band_m: tuple[float, float] = Field(default=(-0.1, 0.1), description="(max compression, max stretch)")
    limits: TractionLimits = TractionLimits()
    failsafe: FailSafe = FailSafe()
    sensor: SensorConfig = SensorConfig()
    disturbances: list[Disturbance] = []


# --------------------------------------------------------------------------- track & reference


class GradeSegment(Section):
    start_m: float
    end_m: float
    grade_permille: float = Field(description="+ = uphill")


class CurveSegment(Section):
    start_m: float
    end_m: float
    radius_m: float = Field(gt=0)


class TrackConfig(Section):
    grades: list[GradeSegment] = []
    curves: list[CurveSegment] = []
    curve_coefficient: float = Field(default=600.0, description="curve resistance per kg = g * coefficient / R / 1000")


class SpeedSegment(Section):
    """The reference speed over one stretch (position-based) or one interval (time-based)."""

    start: float = Field(description="m for position profiles, s for time profiles")
    end: float
    speed_mps: float | None = None
    speed_kmh: float | None = None

    @model_validator(mode="after")
    def _check(self) -> "SpeedSegment":
        if (self.speed_mps is None) == (self.speed_kmh is None):
            raise ValueError("give exactly one of speed_mps or speed_kmh")
        if self.end <= self.start:
            raise ValueError(f"end ({self.end}) must be after start ({self.start})")
        return self

    @property
    def speed(self) -> float:
        return self.speed_mps if self.speed_mps is not None else self.speed_kmh * KMH  # type: ignore[operator]


class ReferenceConfig(Section):
    """The virtual leader: v_r as a function of x_r (position-based) or of t, x_r = integral of v_r."""

    by: Literal["position", "time"] = "position"
    x0_m: float
    segments: list[SpeedSegment] = Field(min_length=1)
    period_s: float = Field(default=0.01, gt=0, description="wayside Reference frame period")

    @model_validator(mode="after")
    def _check(self) -> "ReferenceConfig":
        segs = self.segments
        for a, b in zip(segs, segs[1:]):
            if abs(a.end - b.start) > 1e-9:
                raise ValueError(f"segments must be contiguous: one ends at {a.end}, the next starts at {b.start}")
        if self.by == "position" and not (segs[0].start <= self.x0_m < segs[-1].end):
            raise ValueError(f"x0_m = {self.x0_m} lies outside the segments [{segs[0].start}, {segs[-1].end})")
        return self


# --------------------------------------------------------------------------- controller & ECU


class ControllerConfig(Section):
    law: str
    params: dict[str, Any] = {}


class EcuConfig(Section):
    """ECU runtime settings: cycle, input freshness and degraded modes."""

    cycle_s: float = Field(default=0.01, gt=0)
    phase_s: float = Field(default=0.002, ge=0, description="first cycle after each sensor publication")
    stagger_s: float = Field(default=0.0001, ge=0, description="phase step between successive ECUs of a bus")
    neighbour_timeout_s: float = Field(default=0.1, gt=0, description="older neighbour data is dropped")
    reference_timeout_s: float = Field(default=0.5, gt=0, description="older reference -> service brake")
    radio_contact_timeout_s: float = Field(default=2.0, gt=0, description="lost train ahead this long -> emergency brake")


# --------------------------------------------------------------------------- networks


class CanConfig(Section):
    """Per-train CAN bus settings."""

    bitrate: Literal[125_000, 250_000, 500_000, 1_000_000] = 500_000
    sensor_period_s: float = Field(default=0.01, gt=0)
    queue_policy: Literal["priority", "fifo"] = "priority"
    tx_queue_depth: int = Field(default=64, ge=1, description="frames per node TX queue; overflow drops and counts")
    extended_ids: bool = False
    transport: Literal["emulated", "socketcan"] = Field(
        default="emulated", description="real-time runs only: the rig's emulated buses, or the host's SocketCAN (vcan) interfaces")
    socketcan_channels: list[str] = Field(default=[], description="with transport = socketcan: one interface per train, e.g. vcan0")

    @model_validator(mode="after")
    def _check_transport(self) -> "CanConfig":
        if self.transport == "socketcan" and not self.socketcan_channels:
            raise ValueError("transport = 'socketcan' needs socketcan_channels (one interface per train, e.g. ['vcan0'])")
        return self


class LossModel(Section):
    model: Literal["none", "bernoulli", "gilbert_elliott"] = "none"
    p: float = Field(default=0.0, ge=0, le=1, description="bernoulli loss probability")
    p_good_to_bad: float = Field(default=0.0, ge=0, le=1)
    p_bad_to_good: float = Field(default=1.0, ge=0, le=1)
    loss_good: float = Field(default=0.0, ge=0, le=1)
    loss_bad: float = Field(default=1.0, ge=0, le=1)


class Blackout(Section):
    """No radio where either end of the link is inside [start_m, end_m) (tunnel)."""

    start_m: float
    end_m: float


class RadioConfig(Section):
    """Train-to-train link between the tail of train i and the head of train i+1."""

    latency_s: float = Field(default=0.0, ge=0)
    jitter_s: float = Field(default=0.0, ge=0)
    jitter_distribution: Literal["uniform", "normal", "exponential"] = "uniform"
    loss: LossModel = LossModel()
    range_m: float = Field(default=10_000.0, gt=0, description="beta: no frame passes beyond this distance")
    blackouts: list[Blackout] = []
    rate_cap_hz: float | None = Field(default=None, gt=0, description="max frames/s per direction")
    forward_aux: bool = Field(default=True, description="also forward the AgentAux frame (acceleration, command)")


class RecordingConfig(Section):
    period_s: float = Field(default=0.1, gt=0, description="signal sampling period of the recording")
    frames: bool = Field(default=False, description="log every CAN frame as a text row")


# --------------------------------------------------------------------------- scenario


class Scenario(Section):
    name: str
    description: str = ""
    duration_s: float = Field(gt=0)
    seed: int = 0
    trains: TrainsConfig
    plant: PlantConfig = PlantConfig()
    track: TrackConfig = TrackConfig()
    reference: ReferenceConfig
    controller: ControllerConfig
    ecu: EcuConfig = EcuConfig()
    can: CanConfig = CanConfig()
    radio: RadioConfig = RadioConfig()
    recording: RecordingConfig = RecordingConfig()

    @model_validator(mode="after")
    def _periods_fit_the_plant_step(self) -> "Scenario":
        """Periods the plant samples at must be whole multiples of its step."""
        step = round(self.plant.step_s * 1e9)
        for field, value in (("can.sensor_period_s", self.can.sensor_period_s), ("recording.period_s", self.recording.period_s),
                             ("ecu.cycle_s", self.ecu.cycle_s)):
            if round(value * 1e9) % step:
                raise ValueError(f"{field} = {value} must be a whole multiple of plant.step_s = {self.plant.step_s}")
        return self

"""The scenario file's schema: every section of a scenario TOML as a validated pydantic model.

Units are SI in field names' suffixes (``_m``, ``_s``, ``_n``, ``_mps``); speeds may also be
written in km/h where the field name says ``_kmh``. Unknown keys are errors, so a typo in a
scenario file is reported with its dotted path instead of being silently ignored.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationInfo, field_validator, model_validator

from hil.scenario.checks import scenario_inconsistency, wrong_kind
from ecu_sim.track import MAX_SEGMENTS, CurveSegment, GradeSegment, TrackConfig  # noqa: F401 (the [track] schema)

KMH = 1.0 / 3.6


# Bounds a physical train group and its networks justify: beyond them a value is a typo, and it would
# overflow the nanosecond clock or run for ever instead of failing with a message that names it.
MAX_DURATION_S = 1e7  # 116 days of simulated time
MAX_PERIOD_S = 10.0  # ECU phases and staggers
MAX_RADIO_DELAY_S = 60.0  # a train radio that delays a frame longer than a minute is down, not slow
MIN_BITRATE = 125_000  # the slowest CAN bitrate the rig offers
MAX_DATA_BITRATE = 10_000_000  # CAN FD data phase: 8 Mbit/s is common with SIC transceivers, 10 the upper end


class Section(BaseModel):
    """Base of every scenario section: strict about unknown keys, immutable once loaded."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # NaN/inf: "a finite number"

    @field_validator("*", mode="before")
    @classmethod
    def _no_lax_coercion(cls, value: Any, info: ValidationInfo) -> Any:
        """A string, boolean or number of the wrong kind is an error, not coerced (``count = "3"``, ``enabled = "no"``)."""
        why = wrong_kind(cls.model_fields[info.field_name].annotation, value) if info.field_name else None
        if why is not None:
            raise ValueError(why)
        return value


# --------------------------------------------------------------------------- trains


class TrainsConfig(Section):
    """The train group: N trains of n identical units, and their initial state."""

    count: int = Field(ge=1, le=32)
    units: int = Field(ge=1, le=16, description="power units (ECUs) per train")
    unit_mass_kg: float = Field(gt=0)
    unit_length_m: float = Field(gt=0)
    rotating_mass_factor: float = Field(default=0.0, ge=0, le=0.5)
    head_positions_m: list[float] = Field(description="front-end position of each train's head unit")
    unit_positions_m: list[list[float]] | None = Field(
        default=None, description="optional front-end position of every unit, one list per train (head first); "
        "replaces couplers at rest; each list's first value must equal the train's head_positions_m")
    speeds_mps: list[float] | None = None
    speeds_kmh: list[float] | None = None
    spacing_m: float = Field(gt=0, description="l_s: desired gap rear-of-train to front-of-next")
    emergency_gap_m: float = Field(gt=0, description="l_e: emergency-braking trigger gap")
    reference_units: Literal["heads", "all"] = Field(
        default="heads", description="units whose ECU receives the wayside reference: every train's head, or every unit "
        "(seed 004: each car tracks its own x_r - offset)")

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
        if self.unit_positions_m is not None:
            self._check_unit_positions()
        return self

    def _check_unit_positions(self) -> None:
        """Per-unit start positions: one list per train, head first, consistent with head_positions_m, no overlaps."""
        rows = self.unit_positions_m or []
        if len(rows) != self.count:
            raise ValueError(f"unit_positions_m has {len(rows)} lists, expected count = {self.count} (one per train)")
        for i, row in enumerate(rows):
            where = f"unit_positions_m[{i}]"
            if len(row) != self.units:
                raise ValueError(f"{where} has {len(row)} values, expected units = {self.units}")
            if not all(math.isfinite(x) for x in row):
                raise ValueError(f"{where} has a non-finite value: {row}")
            if abs(row[0] - self.head_positions_m[i]) > 1e-9:
                raise ValueError(f"{where}[0] = {row[0]} differs from head_positions_m[{i}] = {self.head_positions_m[i]}")
            for j in range(1, len(row)):
                if row[j] >= row[j - 1]:
                    raise ValueError(f"{where}[{j}] = {row[j]} m is not behind unit {j} at {row[j - 1]} m (positions must decrease)")
            if i > 0 and rows[i][0] >= rows[i - 1][-1] - self.unit_length_m:
                raise ValueError(f"train {i + 1} starts overlapping train {i} (head at {rows[i][0]} m, "
                                 f"rear of train {i} at {rows[i - 1][-1] - self.unit_length_m} m)")

    @property
    def initial_unit_positions(self) -> list[float] | None:
        """Flat per-unit start positions (layout order), or None when couplers start at rest."""
        if self.unit_positions_m is None:
            return None
        return [x for row in self.unit_positions_m for x in row]

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
    """An additive force on some units over a time window, or (``channel = "position"``) an additive
    speed on the position channel, dx/dt = v + d2 (seed 003's mismatched disturbance)."""

    kind: Literal["pulse", "step", "sine", "random"]
    train: int | None = Field(default=None, ge=1, description="1-based; omit for all trains")
    unit: int | None = Field(default=None, ge=1, description="1-based; omit for all units")
    start_s: float = Field(ge=0)
    end_s: float
    amplitude_n: float | None = Field(default=None, description="force channel: the force, N")
    frequency_hz: float = Field(default=0.0, ge=0, description="sine frequency")
    correlation_s: float = Field(default=1.0, gt=0, description="random: correlation time")
    channel: Literal["force", "position"] = Field(
        default="force", description="force: adds amplitude_n to the unit's forces (matched); "
        "position: adds amplitude_mps to dx/dt only (mismatched: v is not changed)")
    amplitude_mps: float | None = Field(default=None, description="position channel: the speed added to dx/dt, m/s")

    @property
    def amplitude(self) -> float:
        """The amplitude in the channel's unit: N (force) or m/s (position)."""
        value = self.amplitude_n if self.channel == "force" else self.amplitude_mps
        return float(value)  # type: ignore[arg-type]

    @model_validator(mode="after")
    def _check(self) -> "Disturbance":
        if self.end_s <= self.start_s:
            raise ValueError(f"end_s ({self.end_s}) must be after start_s ({self.start_s})")
        wanted, other = ("amplitude_n", "amplitude_mps") if self.channel == "force" else ("amplitude_mps", "amplitude_n")
        if getattr(self, wanted) is None:
            raise ValueError(f"a {self.channel}-channel disturbance needs {wanted}")
        if getattr(self, other) is not None:
            raise ValueError(f"{other} does not apply to a {self.channel}-channel disturbance (give {wanted})")
        if self.kind == "sine" and self.frequency_hz <= 0:
            raise ValueError("a sine disturbance needs frequency_hz > 0")
        return self


class SensorConfig(Section):
    """Sensor imperfections on top of the DBC quantisation."""

    position_noise_m: float = Field(default=0.0, ge=0)
    speed_noise_mps: float = Field(default=0.0, ge=0)


class UnitValues(Section):
    """One value per unit: an explicit list, or a uniform draw from a range (seeded by plant.units.seed).

    ``values`` has one entry per unit of a train (repeated for every train) or one per unit of the
    whole group (front to back). ``uniform = [lo, hi]`` draws every unit independently.
    """

    values: list[float] | None = None
    uniform: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _check(self) -> "UnitValues":
        if (self.values is None) == (self.uniform is None):
            raise ValueError("give exactly one of values or uniform")
        if self.values is not None and not self.values:
            raise ValueError("values is empty")
        if self.uniform is not None and not self.uniform[0] <= self.uniform[1]:
            raise ValueError(f"uniform = {list(self.uniform)} must be [lo, hi] with lo <= hi")
        return self

    def bounds(self) -> tuple[float, float]:
        """Smallest and largest value this can give."""
        if self.uniform is not None:
            return self.uniform
        return min(self.values or [0.0]), max(self.values or [0.0])


def _check_range(where: str, uv: UnitValues | None, lo: float, hi: float, lo_open: bool = False) -> None:
    """Every value of ``uv`` lies in [lo, hi] (or (lo, hi] with lo_open); the error names the field."""
    if uv is None:
        return
    a, b = uv.bounds()
    if not ((a > lo if lo_open else a >= lo) and b <= hi):
        side = "(" if lo_open else "["
        raise ValueError(f"{where}: values must lie in {side}{lo}, {hi}], got {a}..{b}")


class UnitResistance(Section):
    """Per-unit Davis resistance, replacing plant.davis_c0/c1/c2 for every unit.

    ``form = "per_kg"``: c0 + c1 v + c2 v^2 in N/kg with v in m/s (the plant's own form).
    ``form = "specific_kmh"``: the Chinese specific resistance w0 [N/kN] = 1e-2 a0 + 1e-4 a1 V + 1e-4 a2 V^2
    with V in km/h, per kN of the unit's weight; converted to per kg with g = 9.81 (hil/plant/units.py).
    """

    form: Literal["per_kg", "specific_kmh"]
    c0: UnitValues | None = None
    c1: UnitValues | None = None
    c2: UnitValues | None = None
    a0: UnitValues | None = None
    a1: UnitValues | None = None
    a2: UnitValues | None = None

    @model_validator(mode="after")
    def _check(self) -> "UnitResistance":
        mine, other = (("c0", "c1", "c2"), ("a0", "a1", "a2")) if self.form == "per_kg" else (("a0", "a1", "a2"), ("c0", "c1", "c2"))
        missing = [k for k in mine if getattr(self, k) is None]
        extra = [k for k in other if getattr(self, k) is not None]
        if missing or extra:
            raise ValueError(f"form = {self.form!r} takes {', '.join(mine)}" + (f"; missing {', '.join(missing)}" if missing else "")
                             + (f"; {', '.join(extra)} belong to the other form" if extra else ""))
        for k in mine:
            _check_range(k, getattr(self, k), 0.0, float("inf"))
        return self


class UnitsConfig(Section):
    """Per-unit masses, rotating-mass factors and resistance (off by default: every unit as in [trains]/[plant]).

    Drawn values use their own seed (not the run's): every law and every run seed meet the same cars.
    The values in effect are logged as a plant event at t = 0.
    """

    seed: int = Field(default=0, ge=0, description="seed of the uniform draws")
    mass_kg: UnitValues | None = Field(default=None, description="physical mass per unit (overrides trains.unit_mass_kg)")
    rotating_mass_factor: UnitValues | None = Field(default=None, description="overrides trains.rotating_mass_factor")
    resistance: UnitResistance | None = None

    @model_validator(mode="after")
    def _check(self) -> "UnitsConfig":
        _check_range("mass_kg", self.mass_kg, 0.0, float("inf"), lo_open=True)
        _check_range("rotating_mass_factor", self.rotating_mass_factor, 0.0, 0.5)
        return self


class ActuatorConfig(Section):
    """The actuator chain of every unit (off by default): applied = lambda (h rho Q(F) + nu), see hil/plant/actuators.py.

    lambda: traction/brake distribution (share of the commanded force F the unit delivers); rho: actuator
    slope; Q: the input nonlinearity (notch quantisation, |rho (Q(F) - F)| <= rho notch_step_n / 2);
    h (health) and nu (fault offset) come from [[plant.actuator_faults]] or the plant's fault API.
    """

    distribution: UnitValues | None = Field(default=None, description="lambda per unit, default 1")
    slope: UnitValues | None = Field(default=None, description="rho per unit, default 1")
    notch_step_n: float = Field(default=0.0, ge=0, description="input nonlinearity: F realised in steps of this (N); 0 = off")

    @model_validator(mode="after")
    def _check(self) -> "ActuatorConfig":
        _check_range("distribution", self.distribution, 0.0, 1.0)
        _check_range("slope", self.slope, 0.0, float("inf"), lo_open=True)
        return self


class ActuatorFault(Section):
    """A partial actuator fault: from start_s the unit's health goes to ``health`` (linearly over ramp_s)
    and a bounded offset ``offset_n`` (nu) is added. The ECU never sees it."""

    train: int = Field(default=1, ge=1, description="1-based")
    unit: int = Field(ge=1, description="1-based")
    start_s: float = Field(ge=0)
    health: float | None = Field(default=None, ge=0, le=1, description="h target (1 = healthy, 0 = no force)")
    offset_n: float | None = Field(default=None, description="nu target, N (before the distribution share)")
    ramp_s: float = Field(default=0.0, ge=0, description="linear change from the value at start_s; 0 = a step")

    @model_validator(mode="after")
    def _check(self) -> "ActuatorFault":
        if self.health is None and self.offset_n is None:
            raise ValueError("give health, offset_n or both")
        return self


PLANT_FMU_QUANTITIES = {  # what [plant.fmu.parameters] can set from the scenario: per unit, or for the group
    "mass_kg": "unit", "effective_mass_kg": "unit", "length_m": "unit", "davis_c0": "unit", "davis_c1": "unit",
    "davis_c2": "unit", "initial_position_m": "unit", "initial_speed_mps": "unit",
    "coupler_stiffness_n_per_m": "group", "coupler_damping_ns_per_m": "group", "step_s": "group",
}
FMU_UNIT_FIELDS = ("{unit}", "{train}", "{car}")  # placeholders of a per-unit variable name (1-based)


class PlantFmuInputs(Section):
    """FMU input variables the plant sets before each step, per unit: names with ``{unit}`` (or ``{train}`` and
    ``{car}``), 1-based, front to back."""

    force: str = Field(description="applied traction (+) or brake (-) force, N, after the actuator chain")
    grade: str | None = Field(default=None, description="grade force per kg (N/kg, + uphill); needed on a track with grades")
    curve: str | None = Field(default=None, description="curve resistance per kg (N/kg); needed on a track with curves")
    disturbance: str | None = Field(default=None, description="force-channel disturbance, N; needed with plant.disturbances")


class PlantFmuOutputs(Section):
    """FMU output variables the plant reads after each step: per unit (``{unit}``), or per coupler (``{coupler}``)."""

    position: str = Field(description="front-end position, m")
    speed: str = Field(description="speed, m/s")
    acceleration: str | None = Field(default=None, description="acceleration, m/s^2 (default: the speed change over the step)")
    coupler: str | None = Field(default=None, description="coupler displacement, m, + stretched, per coupler "
                                "(default: from positions and unit lengths)")


class PlantFmu(Section):
    """A plant from an FMU (FMI 2 or 3 co-simulation): it replaces the built-in dynamics; the actuator chain,
    sensors, faults, CAN and recording stay. Mapping format: docs/fmi.md."""

    path: str = Field(description="the .fmu file (relative to the scenario file), or trainhil:train_plant "
                      "(trainhil:train_plant@3 for FMI 3), the reference FMU built from hil/fmi/c/ for the scenario's trains")
    step_s: float | None = Field(default=None, gt=0, description="communication step: a whole multiple of "
                                 "plant.step_s (default: plant.step_s)")
    inputs: PlantFmuInputs
    outputs: PlantFmuOutputs
    parameters: dict[str, float | str] = Field(default={}, description="FMU variable (a name, or a template with "
                                               "{unit}) -> a number, or a scenario quantity: "
                                               + ", ".join(PLANT_FMU_QUANTITIES))

    @field_validator("parameters")
    @classmethod
    def _check_parameters(cls, value: dict[str, float | str]) -> dict[str, float | str]:
        for name, source in value.items():
            if isinstance(source, str) and source not in PLANT_FMU_QUANTITIES:
                raise ValueError(f"{name} = {source!r}: not a scenario quantity (known: {', '.join(PLANT_FMU_QUANTITIES)})")
            if isinstance(source, str) and PLANT_FMU_QUANTITIES[source] == "unit" and not any(f in name for f in FMU_UNIT_FIELDS):
                raise ValueError(f"{name} = {source!r}: a per-unit quantity needs a variable name with {{unit}}")
        return value


class PlantConfig(Section):
    """Longitudinal dynamics of every unit of every train."""

    step_s: float = Field(default=0.001, ge=1e-5, le=0.1, description="10 us .. 0.1 s: finer steps resolve nothing a "
                          "train does and cost without end")
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
    units: UnitsConfig = UnitsConfig()
    actuator: ActuatorConfig = ActuatorConfig()
    actuator_faults: list[ActuatorFault] = []
    fmu: PlantFmu | None = Field(default=None, description="the dynamics from an FMU instead of the built-in model")

    def check_units(self, count: int, units: int) -> None:
        """Per-unit lists and fault units fit the train group (count trains x units); errors name the field."""
        named = [("units.mass_kg", self.units.mass_kg), ("units.rotating_mass_factor", self.units.rotating_mass_factor),
                 ("actuator.distribution", self.actuator.distribution), ("actuator.slope", self.actuator.slope)]
        res = self.units.resistance
        if res is not None:
            named += [(f"units.resistance.{k}", getattr(res, k)) for k in ("c0", "c1", "c2", "a0", "a1", "a2")]
        for where, uv in named:
            if uv is not None and uv.values is not None and len(uv.values) not in (units, count * units):
                raise ValueError(f"plant.{where}.values has {len(uv.values)} values: give one per unit of a train ({units}) "
                                 f"or one per unit of the group ({count * units})")
        for i, f in enumerate(self.actuator_faults):
            if f.train > count or f.unit > units:
                raise ValueError(f"plant.actuator_faults[{i}]: train {f.train} unit {f.unit} does not exist "
                                 f"({count} train(s) of {units} units)")


# --------------------------------------------------------------------------- track & reference


class SpeedSegment(Section):
    """The reference speed over one stretch (position-based) or one interval (time-based)."""

    start: float = Field(description="m for position profiles, s for time profiles")
    end: float
    speed_mps: float | None = None
    speed_kmh: float | None = None
    to_speed_mps: float | None = Field(default=None, description="time profiles only: v_r ramps linearly from speed to this over [start, end)")
    to_speed_kmh: float | None = None

    @model_validator(mode="after")
    def _check(self) -> "SpeedSegment":
        if (self.speed_mps is None) == (self.speed_kmh is None):
            raise ValueError("give exactly one of speed_mps or speed_kmh")
        if self.to_speed_mps is not None and self.to_speed_kmh is not None:
            raise ValueError("give at most one of to_speed_mps or to_speed_kmh")
        if self.end <= self.start:
            raise ValueError(f"end ({self.end}) must be after start ({self.start})")
        return self

    @property
    def speed(self) -> float:
        return self.speed_mps if self.speed_mps is not None else self.speed_kmh * KMH  # type: ignore[operator]

    @property
    def is_ramp(self) -> bool:
        return self.to_speed_mps is not None or self.to_speed_kmh is not None

    @property
    def to_speed(self) -> float:
        """Speed at the segment's end: the ramp's target, or ``speed`` for a constant segment."""
        if self.to_speed_mps is not None:
            return self.to_speed_mps
        return self.to_speed_kmh * KMH if self.to_speed_kmh is not None else self.speed


class ReferenceConfig(Section):
    """The virtual leader: v_r as a function of x_r (position-based) or of t, x_r = integral of v_r."""

    by: Literal["position", "time"] = "position"
    x0_m: float
    segments: list[SpeedSegment] = Field(min_length=1, max_length=MAX_SEGMENTS)
    period_s: float = Field(default=0.01, gt=0, description="wayside Reference frame period")

    @model_validator(mode="after")
    def _check(self) -> "ReferenceConfig":
        segs = self.segments
        for a, b in zip(segs, segs[1:]):
            if abs(a.end - b.start) > 1e-9:
                raise ValueError(f"segments must be contiguous: one ends at {a.end}, the next starts at {b.start}")
        if self.by == "position" and not (segs[0].start <= self.x0_m < segs[-1].end):
            raise ValueError(f"x0_m = {self.x0_m} lies outside the segments [{segs[0].start}, {segs[-1].end})")
        for i, seg in enumerate(segs):
            if seg.is_ramp and self.by != "time":
                raise ValueError(f"segments[{i}]: a speed ramp (to_speed_*) needs by = \"time\"")
        return self


# --------------------------------------------------------------------------- controller & ECU


class ControllerConfig(Section):
    law: str
    params: dict[str, Any] = {}


class UnitFirmware(Section):
    """One unit's own firmware among standard ones (``[[ecu.units]]``): its program, law and parameters."""

    unit: str = Field(description="'train<t>/unit<k>', 1-based")
    program: str | None = Field(default=None, description="ECU program for this unit (default: ecu.program)")
    law: str | None = Field(default=None, description="control law for this unit (default: controller.law)")
    params: dict[str, Any] | None = Field(default=None, description="the law's parameters (default: controller.params "
                                          "with the scenario's law, the law's defaults with another)")


class EcuConfig(Section):
    """ECU runtime settings: cycle, input freshness and degraded modes; which firmware runs where."""

    program: str = Field(default="standard", description="ECU program of every unit: a registered name, an "
                         "entry point (trainhil.ecu_programs) or 'package.module:QualName' (ecu_sim.programs)")
    units: list[UnitFirmware] = Field(default=[], description="per-unit overrides of program, law and params")
    external: list[str] = Field(default=[], description="units without an emulated ECU: an external device or "
                                "program sends their frames (real time only)")
    join_timeout_s: float = Field(default=30.0, gt=0, description="real time: how long (wall s) the rig waits, "
                                  "from when it is ready, for each external unit's first valid TractionCmd (on the "
                                  "emulated buses simulated t = 0 waits, as long at most, for a client on its bus)")

    cycle_s: float = Field(default=0.01, gt=0)
    phase_s: float = Field(default=0.002, ge=0, le=MAX_PERIOD_S, description="first cycle after each sensor publication")
    stagger_s: float = Field(default=0.0001, ge=0, le=MAX_PERIOD_S, description="phase step between successive ECUs of a bus")
    neighbour_timeout_s: float = Field(default=0.1, gt=0, description="older neighbour data is dropped")
    reference_timeout_s: float = Field(default=0.5, gt=0, description="older reference -> service brake")
    radio_contact_timeout_s: float = Field(default=2.0, gt=0, description="lost train ahead this long -> emergency brake")
    restart_after_s: float | None = Field(default=None, gt=0, description="watchdog: an ECU that stopped (crash, "
                                          "controller error, hang) restarts with a reset controller after this long; "
                                          "omit: it stays down (hil/faults)")


# --------------------------------------------------------------------------- networks


def dbc_file(name: str) -> Path:
    """A DBC named in a scenario: the packaged one of that name (dbc/), else the path as given."""
    from ecu_sim.codec import default_dbc_path

    try:
        return default_dbc_path(name) if "/" not in name else Path(name)
    except FileNotFoundError:
        return Path(name)


class CanConfig(Section):
    """Per-train CAN bus settings."""

    bitrate: Literal[125_000, 250_000, 500_000, 1_000_000] = 500_000
    sensor_period_s: float = Field(default=0.01, gt=0)
    queue_policy: Literal["priority", "fifo"] = "priority"
    tx_queue_depth: int = Field(default=64, ge=1, description="frames per node TX queue; overflow drops and counts")
    extended_ids: bool = False
    fd: bool = Field(default=False, description="CAN FD frames (ISO 11898-1:2015) instead of classical CAN 2.0")
    data_bitrate: int | None = Field(
        default=None, ge=MIN_BITRATE, le=MAX_DATA_BITRATE,
        description="CAN FD data-phase bitrate (bit/s), at least the nominal bitrate; default: the nominal bitrate")
    brs: bool = Field(default=True, description="CAN FD bit-rate switch: the data phase runs at data_bitrate")
    dbc: str = Field(default="train.dbc", description="the train DBC: a packaged one (train.dbc; train_fd.dbc, "
                     "which packs each sender's frames into CAN FD containers) or the path of your own")
    transport: Literal["emulated", "socketcan"] = Field(
        default="emulated", description="real-time runs only: the rig's emulated buses, or the host's SocketCAN (vcan) interfaces")
    socketcan_channels: list[str] = Field(default=[], description="with transport = socketcan: one interface per train, e.g. vcan0")

    @field_validator("dbc")
    @classmethod
    def _check_dbc(cls, value: str) -> str:
        if not dbc_file(value).is_file():
            raise ValueError(f"no DBC {value!r}: name a packaged one (train.dbc, train_fd.dbc) or an existing file")
        return value

    @property
    def dbc_path(self) -> Path:
        """The DBC file: the packaged one of that name, else the path as given."""
        return dbc_file(self.dbc)

    @model_validator(mode="after")
    def _check_transport(self) -> "CanConfig":
        if self.transport == "socketcan" and not self.socketcan_channels:
            raise ValueError("transport = 'socketcan' needs socketcan_channels (one interface per train, e.g. ['vcan0'])")
        return self

    @model_validator(mode="after")
    def _check_fd(self) -> "CanConfig":
        if self.data_bitrate is None:
            return self
        if not self.fd:
            raise ValueError("data_bitrate is a CAN FD setting: set fd = true, or leave data_bitrate out")
        if self.data_bitrate < self.bitrate:
            raise ValueError(f"data_bitrate {self.data_bitrate} is below the nominal bitrate {self.bitrate}: "
                             "the data phase of a CAN FD frame is at least as fast as its arbitration")
        if 1_000_000_000 % self.data_bitrate:
            raise ValueError(f"data_bitrate {self.data_bitrate} has no whole-nanosecond bit time "
                             "(e.g. 1, 2, 4, 5 or 8 Mbit/s)")
        return self

    @property
    def data_rate(self) -> int:
        """The data-phase bitrate: data_bitrate on a CAN FD bus with BRS, else the nominal bitrate."""
        return self.data_bitrate if self.fd and self.brs and self.data_bitrate is not None else self.bitrate


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

    latency_s: float = Field(default=0.0, ge=0, le=MAX_RADIO_DELAY_S)
    jitter_s: float = Field(default=0.0, ge=0, le=MAX_RADIO_DELAY_S)
    jitter_distribution: Literal["uniform", "normal", "exponential"] = "uniform"
    loss: LossModel = LossModel()
    range_m: float = Field(default=10_000.0, gt=0, description="beta: no frame passes beyond this distance")
    blackouts: list[Blackout] = Field(default=[], max_length=MAX_SEGMENTS)
    rate_cap_hz: float | None = Field(default=None, ge=0.01, le=1e6, description="max frames/s per direction")
    forward_aux: bool = Field(default=True, description="also forward the AgentAux frame (acceleration, command)")


class RecordingConfig(Section):
    period_s: float = Field(default=0.1, gt=0, description="signal sampling period of the recording")
    frames: bool = Field(default=False, description="log every CAN frame as a text row")


# --------------------------------------------------------------------------- scenario


class Scenario(Section):
    name: str
    description: str = ""
    duration_s: float = Field(gt=0, le=MAX_DURATION_S)
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
    faults: list[Fault] = Field(default=[], description="fault schedule (hil/faults): [[faults]] tables")

    @model_validator(mode="after")
    def _faults_fit_the_group(self) -> "Scenario":
        """Every fault names a train, unit, radio pair and frame ID that exist (errors name faults.<i>.<field>)."""
        why = fault_target_error(self)
        if why is not None:
            raise ValueError(why)
        return self

    @model_validator(mode="after")
    def _periods_fit_the_plant_step(self) -> "Scenario":
        """Periods the plant samples at must be whole multiples of its step."""
        step = round(self.plant.step_s * 1e9)
        for field, value in (("can.sensor_period_s", self.can.sensor_period_s), ("recording.period_s", self.recording.period_s),
                             ("ecu.cycle_s", self.ecu.cycle_s),
                             ("plant.fmu.step_s", self.plant.fmu.step_s if self.plant.fmu else None)):
            if value is not None and round(value * 1e9) % step:
                raise ValueError(f"{field} = {value} must be a whole multiple of plant.step_s = {self.plant.step_s}")
        return self

    @model_validator(mode="after")
    def _units_fit_the_trains(self) -> "Scenario":
        """Per-unit plant lists and actuator faults name units that exist."""
        self.plant.check_units(self.trains.count, self.trains.units)
        return self

    @model_validator(mode="after")
    def _consistent(self) -> "Scenario":
        """Cross-section rules (``hil.scenario.checks``): each error names its dotted field."""
        why = scenario_inconsistency(self)
        if why is not None:
            raise ValueError(why)
        return self


# --------------------------------------------------------------------------- fault schedule (hil/faults)


class FaultTrigger(Section):
    """When a fault starts and how long it lasts: at a time, or when a train's head reaches a position."""

    at_s: float | None = Field(default=None, ge=0, le=MAX_DURATION_S, description="time trigger (simulated s)")
    at_position_m: float | None = Field(default=None, description="position trigger: the head of trigger_train reaches it")
    trigger_train: int | None = Field(default=None, ge=1, description="1-based; default: the fault's train (else train 1)")
    duration_s: float | None = Field(default=None, gt=0, le=MAX_DURATION_S, description="omit: to the end of the run")

    @model_validator(mode="after")
    def _one_trigger(self) -> "FaultTrigger":
        if (self.at_s is None) == (self.at_position_m is None):
            raise ValueError("give exactly one of at_s or at_position_m")
        if self.trigger_train is not None and self.at_position_m is None:
            raise ValueError("trigger_train only goes with at_position_m")
        return self


class UnitFault(FaultTrigger):
    train: int = Field(ge=1, description="1-based")
    unit: int = Field(ge=1, description="1-based, head = 1")


class EcuCrashFault(UnitFault):
    """The ECU stops dead and leaves the bus (its queued frames are lost). It restarts with a reset controller
    after ``duration_s``; without one, after ``ecu.restart_after_s`` (watchdog) if set, else never."""

    kind: Literal["ecu_crash"]


class EcuHangFault(UnitFault):
    """The ECU stops sending but stays connected (it still receives). It resumes after ``duration_s`` where it
    stopped; ``ecu.restart_after_s`` shorter than the hang restarts it (reset) instead."""

    kind: Literal["ecu_hang"]


class SensorStuckFault(UnitFault):
    """The unit's speed and position sensors freeze at their last value (frames keep coming, counters advance)."""

    kind: Literal["sensor_stuck"]


class SensorNoiseFault(UnitFault):
    """Gaussian noise added to the unit's sensor values (on top of plant.sensor)."""

    kind: Literal["sensor_noise"]
    position_noise_m: float = Field(default=0.0, ge=0)
    speed_noise_mps: float = Field(default=0.0, ge=0)

    @model_validator(mode="after")
    def _some_noise(self) -> "SensorNoiseFault":
        if self.position_noise_m == 0 and self.speed_noise_mps == 0:
            raise ValueError("give position_noise_m or speed_noise_mps > 0")
        return self


class BusFault(FaultTrigger):
    train: int = Field(ge=1, description="1-based: the bus of this train")


class BabblingNodeFault(BusFault):
    """A node floods the bus with one high-priority frame, back to back (a babbling idiot)."""

    kind: Literal["babbling_node"]
    frame_id: int = Field(default=0x000, ge=0, le=0x7FF, description="11-bit ID it babbles (0 = top priority)")
    dlc: int = Field(default=8, ge=0, le=8)


class SelectiveBusFault(BusFault):
    """Which frames of the bus a fault hits: each with ``probability``, only ``frame_ids`` if given, at most ``count``."""

    probability: float = Field(default=1.0, gt=0, le=1)
    frame_ids: list[int] | None = Field(default=None, description="11-bit IDs; omit: every frame")
    count: int | None = Field(default=None, ge=1, description="stop after this many frames hit")


class BusCorruptionFault(SelectiveBusFault):
    """Bits flipped on the wire as the receivers sample them: they reject the frame (stuff, CRC or form error),
    send an error frame, count it (REC), and the sender counts it (TEC) and retransmits (engine/src/errors.rs)."""

    kind: Literal["bus_corruption"]
    bits: int = Field(default=1, ge=1, le=16, description="bits flipped per corrupted frame")


class BusErrorFramesFault(SelectiveBusFault):
    """A faulty transceiver destroys frames with an error flag at a random bit: every node sees the error."""

    kind: Literal["bus_error_frames"]


class FrameDropFault(SelectiveBusFault):
    """Frames vanish from their sender's TX queue before transmission (receivers see a counter gap)."""

    kind: Literal["frame_drop"]


class RadioFault(FaultTrigger):
    pair: int | None = Field(default=None, ge=1, description="the link of trains pair and pair+1 (both ways); omit: all")


class RadioBlackoutFault(RadioFault):
    """Nothing passes the radio (a time-triggered tunnel)."""

    kind: Literal["radio_blackout"]


class RadioBurstLossFault(RadioFault):
    """Each frame offered to the radio is lost with ``probability`` (on top of radio.loss)."""

    kind: Literal["radio_burst_loss"]
    probability: float = Field(default=0.5, gt=0, le=1)


class RadioLatencyFault(RadioFault):
    """Extra latency on every frame (frames are never reordered)."""

    kind: Literal["radio_latency"]
    latency_s: float = Field(gt=0, le=MAX_RADIO_DELAY_S)


class ActuatorDegradationFault(UnitFault):
    """The unit's actuator delivers ``health`` times the force it should (the plant's health factor)."""

    kind: Literal["actuator_degradation"]
    health: float = Field(ge=0, lt=1)


class TractionLossFault(UnitFault):
    """The unit delivers no traction or brake force at all (health 0)."""

    kind: Literal["traction_loss"]


FAULT_MODELS: dict[str, type[FaultTrigger]] = {
    "ecu_crash": EcuCrashFault, "ecu_hang": EcuHangFault, "sensor_stuck": SensorStuckFault,
    "sensor_noise": SensorNoiseFault, "babbling_node": BabblingNodeFault, "bus_corruption": BusCorruptionFault,
    "bus_error_frames": BusErrorFramesFault, "frame_drop": FrameDropFault, "radio_blackout": RadioBlackoutFault,
    "radio_burst_loss": RadioBurstLossFault, "radio_latency": RadioLatencyFault,
    "actuator_degradation": ActuatorDegradationFault, "traction_loss": TractionLossFault,
}
FAULT_KINDS = tuple(FAULT_MODELS)


def _fault_kind(value: Any) -> str | None:
    """The ``kind`` tag of a fault table (None: missing or unknown, which pydantic reports with the known kinds)."""
    kind = value.get("kind") if isinstance(value, dict) else getattr(value, "kind", None)
    return kind if kind in FAULT_MODELS else None


# A callable discriminator: Section's mode="before" validator rules out pydantic's field-based one. The union is
# built at run time from FAULT_MODELS; a type checker sees any of them.
if TYPE_CHECKING:
    Fault = Any
else:
    Fault = Annotated[
        Union[tuple(Annotated[model, Tag(kind)] for kind, model in FAULT_MODELS.items())],
        Discriminator(_fault_kind, custom_error_type="fault_kind",
                      custom_error_message=f"kind must be one of: {', '.join(FAULT_KINDS)}"),
    ]


def fault_target_error(sc: "Scenario") -> str | None:
    """The first fault that names something the scenario does not have (train, unit, radio pair, ID), or None."""
    count, units, ext = sc.trains.count, sc.trains.units, sc.can.extended_ids
    for i, f in enumerate(sc.faults):
        where = f"faults.{i}"
        train = getattr(f, "train", None)
        if train is not None and train > count:
            return f"{where}.train = {train}: there are only {count} trains (trains.count)"
        unit = getattr(f, "unit", None)
        if unit is not None and unit > units:
            return f"{where}.unit = {unit}: a train has only {units} units (trains.units)"
        if f.trigger_train is not None and f.trigger_train > count:
            return f"{where}.trigger_train = {f.trigger_train}: there are only {count} trains (trains.count)"
        pair = getattr(f, "pair", None)
        if pair is not None and pair >= count:
            return f"{where}.pair = {pair}: the radio pairs are 1..{count - 1} (train pair and pair+1)"
        if isinstance(f, RadioFault) and count < 2:
            return f"{where}: a radio fault needs at least 2 trains (trains.count = {count})"
        limit = (1 << 29) if ext else (1 << 11)
        for fid in getattr(f, "frame_ids", None) or []:
            if not 0 <= fid < limit:
                return f"{where}.frame_ids: {fid:#x} is not a {'29' if ext else '11'}-bit CAN ID"
    return None


Scenario.model_rebuild()

"""What a controller sees and what it returns: the local view of one agent and its command.

These are plain data records shared by the ECU runtime (which fills them from decoded CAN
frames) and by the ideal reference loop (which fills them from the true plant state).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Literal

NAN = float("nan")


class BrakeMode(IntEnum):
    """Mode carried in the TractionCmd frame next to the force."""

    NORMAL = 0  # apply the commanded force
    SERVICE = 1  # service brake (degraded mode: stale reference, lost inputs)
    EMERGENCY = 2  # emergency brake (train-wide, through the train line)


@dataclass(frozen=True, slots=True)
class AgentInfo:
    """Static facts an ECU is configured with: who it is and where its slot is.

    ``offset_m`` places the agent's desired position: x*_{i,j} = x_r - offset_m
    (lengths of all units ahead of it plus (i-1) desired gaps l_s).
    """

    train: int  # 0-based train index (0 = first train)
    unit: int  # 0-based unit index inside the train (0 = head)
    n_trains: int
    n_units: int  # units in this train
    mass_kg: float  # effective mass (includes rotating-mass factor)
    length_m: float
    offset_m: float
    has_reference: bool  # a_{i,j}: pinned to the virtual leader (head units)

    @property
    def is_head(self) -> bool:
        """The first unit of its train (for user laws; the packaged ones read the layout themselves)."""
        return self.unit == 0

    @property
    def is_tail(self) -> bool:
        """The last unit of its train."""
        return self.unit == self.n_units - 1


@dataclass(slots=True)
class NeighbourView:
    """Last known state of one neighbour, as received (ages in seconds).

    ``offset_m`` is the neighbour's slot offset, so x~_nbr - x~_self =
    (x_nbr - x_self) + (offset_m - own offset): see :meth:`position_error_from`.
    For the unit ahead in the same train this is the coupler displacement e (> 0 stretched);
    for the train ahead it is the gap error s - l_s.
    """

    link: Literal["intra", "inter"]  # same train (CAN) or adjacent train (radio)
    side: Literal["ahead", "behind"]  # neighbour is in front of us or behind us
    offset_m: float  # the neighbour's slot offset (x*_nbr = x_r - offset_m)
    x: float = NAN
    v: float = NAN
    a: float = NAN  # acceleration, NaN when not carried
    u: float = NAN  # applied command force, NaN when not carried
    age_s: float = float("inf")  # time since the data was measured/sent; inf = never received
    valid: bool = False  # False while never received or dropped by the degraded mode
    weight: float = 1.0  # degraded-mode weight in [0, 1] (1 = fresh)

    def position_error_from(self, x_self: float, offset_self: float) -> float:
        """x~_nbr - x~_self: the neighbour's slot error minus ours (needs no x_r)."""
        return (self.x - x_self) + (self.offset_m - offset_self)


@dataclass(slots=True)
class ReferenceView:
    """Virtual leader x_r(t), v_r(t), a_r(t) as last received from the wayside."""

    x: float = NAN
    v: float = NAN
    a: float = 0.0
    age_s: float = float("inf")
    valid: bool = False


@dataclass(slots=True)
class LocalView:
    """Everything one controller may use in one cycle."""

    t: float  # ECU time of this cycle (s)
    dt: float  # controller period (s)
    x: float  # own measured position (front end), m
    v: float  # own measured speed, m/s
    neighbours: list[NeighbourView] = field(default_factory=list)
    ref: ReferenceView = field(default_factory=ReferenceView)


@dataclass(slots=True)
class Command:
    """Controller output: a force on the unit (N, + = traction) and a brake mode."""

    force_n: float
    mode: BrakeMode = BrakeMode.NORMAL
    accel_mps2: float = NAN  # the acceleration the law demanded (u/m), for the AgentAux frame

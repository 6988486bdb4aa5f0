"""How a run joins Vector SIL Kit (``hil run --silkit``): the registry, the step, wall-clock pacing, who coordinates."""
from __future__ import annotations

from dataclasses import dataclass, field

MIN_STEP_NS = 10_000  # below, a run crawls: every step costs SIL Kit's synchronisation of the participants


@dataclass(frozen=True)
class SilKitOptions:
    """``uri``: the registry ("" for one of the run's own on 127.0.0.1). ``step_s``: the participants' time step.
    ``pace``: None for virtual time as fast as the participants go; else virtual time coupled to the wall clock at
    ``pace`` x real time (SIL Kit's AnimationFactor 1/pace on the rig's participant, which holds every other
    time-synchronised participant to it). ``system_controller``: the rig starts the simulation when the external
    units' participants have joined; False leaves that to another participant (Vector's sil-kit-system-controller,
    CANoe), which must name ``trainhil`` and every external unit. ``config``: a SIL Kit participant configuration
    (YAML or JSON text, as SIL Kit's tools take with ``--configuration``) for the rig's participant. ``networks``:
    the SIL Kit network of a bus where it is not the bus's own name (``{"bus1": "CAN1"}``)."""

    uri: str = ""
    step_s: float = 0.001
    pace: float | None = None
    system_controller: bool = True
    config: str = ""
    networks: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        ns = self.step_s * 1e9
        if not (ns >= MIN_STEP_NS and abs(ns - round(ns)) < 1e-6 and round(ns) % 2 == 0):
            raise ValueError(f"--silkit-step {self.step_s}: expected a time step of a whole, even number of ns, at "
                             f"least {MIN_STEP_NS * 1e-9:g} s (each step costs SIL Kit's synchronisation, ~0.1 ms)")
        if self.pace is not None and not self.pace > 0:
            raise ValueError(f"--pace {self.pace}: expected a positive factor")
        if self.pace is not None and (self.config.lstrip().startswith("{") or "Experimental" in self.config):
            raise ValueError("--realtime --silkit adds an Experimental block (AnimationFactor) to the rig's SIL Kit "
                             "configuration; with --silkit-config, write the configuration in YAML without one, or "
                             "set AnimationFactor yourself and leave out --realtime")

    def check_buses(self, buses: list[str]) -> None:
        """ValueError when ``networks`` names a bus the run does not have."""
        unknown = sorted(set(self.networks) - set(buses))
        if unknown:
            raise ValueError(f"--silkit-network {', '.join(unknown)}: no such bus (the run's buses: {', '.join(buses)})")

    def network_of(self, bus: str) -> str:
        """The SIL Kit network simulating ``bus``."""
        return self.networks.get(bus, bus)

    def participant_config(self) -> str:
        """The rig participant's SIL Kit configuration: the given one, and wall-clock coupling when paced (a JSON
        configuration, or one with an Experimental block, cannot take it: refused when the options are made)."""
        if self.pace is None:
            return self.config
        pacing = f"Experimental:\n  TimeSynchronization:\n    AnimationFactor: {1.0 / self.pace!r}\n"
        return f"{self.config.rstrip()}\n{pacing}" if self.config.strip() else pacing

"""Build a rig for a test: a scenario (packaged name, file or object) with overrides, the user's controller class or
ECU program swapped in, run in virtual time (or real time) for a duration, returning a :class:`HilRun`.

- ``set={"radio.latency_s": 0.2, "controller.params.kx": 0.1}``: dotted keys as in ``hil run --set``.
- ``controller=MyLaw`` (a :class:`~ecu_sim.controllers.base.Controller` subclass), a law's name or a
  ``"module:ClassName"`` reference; ``params={...}`` replaces the law's parameters (default: the law's defaults
  when the law is swapped, the scenario's otherwise).
- ``ecu=MyEcu`` (a subclass of :class:`ecu_sim.runtime.Ecu`, built with the standard wiring), a factory
  ``(setup: EcuSetup) -> Ecu`` (:func:`ecu_sim.programs.standard_program` builds the shipped one, to wrap or
  adjust), or a program's name or reference: the firmware every unit runs instead of the standard one.

There is one seam for user code, the same as ``hil run``'s: the rig writes the class or function into the scenario
as its ``"module:QualName"`` reference (``controller.law``, ``ecu.program``), and every runtime resolves it
(:mod:`hil.runtime.firmware`). Real time runs the scenario on :func:`hil.runtime.realtime.orchestrator.run_realtime`
(separate processes; by default one ECU process per train, ``ecus_per_process`` = units per train, to keep
start-up short), whose node processes import the references themselves; so for real time, user code must be
defined at the top level of an importable module (not inside a test function).
"""
from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


from hil.scenario import Scenario, scenario_from_dict
from hil.testing.results import HilRun, Series

ControllerLike = Any  # type[Controller] | str
EcuLike = Any  # type[Ecu] | Callable[[EcuSetup], Ecu] | str


def law_reference(controller: ControllerLike) -> tuple[str, bool]:
    """(what to put in ``controller.law``, whether other processes can load it). A class defined at the top level
    of a module becomes its ``module:QualName`` reference; any other class is registered under its ``name`` here."""
    from ecu_sim.controllers.base import Controller, get_controller, register
    from ecu_sim.references import reference_of

    if isinstance(controller, str):
        return controller, True
    if not (isinstance(controller, type) and issubclass(controller, Controller)):
        raise TypeError(f"controller={controller!r}: expected a Controller subclass, a registered law's name or a "
                        "'module:ClassName' reference")
    if not hasattr(controller, "Params"):
        raise TypeError(f"controller {controller.__qualname__} has no `Params` (its ControllerParams model)")
    ref = reference_of(controller)
    if ref is not None:
        return ref, True
    name = getattr(controller, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"controller {controller.__qualname__} has no `name` (the law's name in scenario files)")
    try:
        known = get_controller(name)
    except LookupError:
        register(controller)
        return name, False
    if known is not controller:
        raise ValueError(f"controller name {name!r} is already taken by {known.__module__}.{known.__qualname__}; "
                         f"give {controller.__module__}.{controller.__qualname__} another `name`")
    return name, False


def program_reference(ecu: EcuLike) -> tuple[str, bool]:
    """(what to put in ``ecu.program``, whether other processes can load it), as :func:`law_reference`: an Ecu
    subclass or factory at a module's top level by reference, any other registered here under its qualified name."""
    from ecu_sim.programs import as_program, register_program
    from ecu_sim.references import reference_of

    if isinstance(ecu, str):
        return ecu, True
    as_program(ecu, repr(ecu))  # TypeError-like ReferenceLoadError now, not mid-run
    ref = reference_of(ecu)
    if ref is not None:
        return ref, True
    name = f"local:{getattr(ecu, '__module__', '?')}.{getattr(ecu, '__qualname__', type(ecu).__name__)}#{id(ecu):x}"
    register_program(name, ecu)
    return name, False


def build_scenario(scenario: str | Path | Scenario, overrides: dict[str, Any] | None = None,
                   controller: ControllerLike | None = None, params: dict[str, Any] | None = None,
                   ecu: EcuLike | None = None) -> Scenario:
    """Load and validate the scenario with ``overrides`` (dotted keys), the law and the ECU program swapped;
    ScenarioError names the file and the field on bad input, like ``hil run``. As in sweeps, a law different from
    the scenario's gets its own default parameters unless parameters are given (``params`` or
    ``controller.params...`` keys)."""
    from hil.scenario.loader import read_scenario_data, resolve

    sets = dict(overrides or {})
    if controller is not None:
        sets["controller.law"] = law_reference(controller)[0]
    if ecu is not None:
        sets["ecu.program"] = program_reference(ecu)[0]
    if params is not None:
        sets["controller.params"] = dict(params)
    if isinstance(scenario, Scenario):
        data, source = scenario.model_dump(), f"<scenario {scenario.name}>"
    else:
        path = resolve(scenario)
        data, source = read_scenario_data(path), str(path)
    base_law = (data.get("controller") or {}).get("law")
    if "controller.law" in sets and sets["controller.law"] != base_law \
            and not any(k == "controller" or k.startswith("controller.params") for k in sets):
        sets["controller.params"] = {}  # the new law's defaults, not the old law's parameters
    return scenario_from_dict(data, source, sets)


class Rig:
    """A scenario ready to run under test (see the module docstring). ``run()`` can be called several times."""

    def __init__(self, scenario: str | Path | Scenario, *, set: dict[str, Any] | None = None,  # noqa: A002
                 controller: ControllerLike | None = None, params: dict[str, Any] | None = None,
                 ecu: EcuLike | None = None, seed: int | None = None) -> None:
        self.scenario = build_scenario(scenario, set, controller, params, ecu)
        self.controller = controller
        self.ecu = ecu
        # user code registered in this process only (defined inside a function): virtual time only
        self._local = [what for what, obj, ref in (("controller", controller, law_reference),
                                                    ("ECU program", ecu, program_reference))
                       if obj is not None and not ref(obj)[1]]
        self.seed = self.scenario.seed if seed is None else int(seed)
        self.realtime_default: dict[str, Any] | None = None  # set by the pytest plugin from @pytest.mark.hil_realtime
        self.on_run: list[Callable[[HilRun], None]] = []  # the plugin keeps runs for --hil-record
        self.cache: dict | None = None  # the plugin's session cache of virtual runs
        self.work_dir: Callable[[], Path] | None = None  # where real-time runs put their node files

    def __repr__(self) -> str:
        return f"Rig({self.scenario.name!r}, law={self.scenario.controller.law!r}, seed={self.seed})"

    def run(self, duration_s: float | None = None, *, realtime: bool | None = None, pace: float | None = None,
            ecus_per_process: int | None = None) -> HilRun:
        """Run for ``duration_s`` simulated seconds (default: the scenario's). Virtual time unless ``realtime`` (or
        the test is marked ``@pytest.mark.hil_realtime``): then wall-clock time at ``pace``."""
        duration = float(self.scenario.duration_s if duration_s is None else duration_s)
        if not duration > 0:
            raise ValueError(f"duration_s={duration_s!r} must be > 0")
        rt = dict(self.realtime_default or {})
        if realtime is None:
            realtime = bool(self.realtime_default is not None)
        if pace is not None:
            rt["pace"] = pace
        if ecus_per_process is not None:
            rt["ecus_per_process"] = ecus_per_process
        run = self._run_realtime(duration, **rt) if realtime else self._run_virtual(duration)
        for fn in self.on_run:
            fn(run)
        return run

    # ------------------------------------------------------------------ virtual time
    def _key(self, duration: float) -> tuple:
        return (self.scenario.model_dump_json(), self.controller, self.ecu, self.seed, duration)

    def _run_virtual(self, duration: float) -> HilRun:
        key = self._key(duration) if self.cache is not None else None
        if key is not None and key in self.cache:
            return self.cache[key]
        from hil.record.metrics import compute_metrics
        from hil.runtime.virtual import VirtualRig

        rig = VirtualRig(self.scenario, self.seed)
        frames = None
        if self.scenario.recording.frames:
            from hil.record.frames import FrameRecorder

            frames = FrameRecorder(rig.buses, rig.db)
        log = rig.run(duration)
        metrics = compute_metrics(log, self.scenario.plant.coupler_band_m)
        metrics.update(scenario=self.scenario.name, runtime="virtual", interrupted=log.interrupted)
        run = HilRun(self.scenario, log, metrics, "virtual", self.scenario.controller.law, self.seed,
                     frame_recorder=frames)
        if key is not None:
            self.cache[key] = run
        return run

    # ------------------------------------------------------------------ real time
    def _run_realtime(self, duration: float, pace: float = 1.0, ecus_per_process: int | None = None) -> HilRun:
        from hil.runtime.realtime.orchestrator import run_realtime

        if self._local:
            raise ValueError(f"the {' and the '.join(self._local)} of this rig must be defined at the top level of an "
                             "importable module to run in real time (the rig's node processes import it from there)")
        out = self.work_dir() if self.work_dir else Path(tempfile.mkdtemp(prefix="trainhil-rt-"))
        started: list[float] = []
        per_process = ecus_per_process or self.scenario.trains.units
        result = run_realtime(self.scenario, out, pace=pace, duration_s=duration, seed=self.seed,
                              ecus_per_process=per_process, record=False, on_start=started.append)
        if self.scenario.recording.frames:
            from hil.record.runlog import Event

            result.log.events.append(Event(0.0, "INFO", "rig", "recording.frames: per-frame rows are recorded in "
                                                             "virtual time only"))
        wall_clock = (started[0], float(pace)) if started else None
        return HilRun(self.scenario, result.log, result.metrics, "realtime", self.scenario.controller.law, self.seed,
                      extra_series=_timing_series(out / "nodes"), wall_clock=wall_clock)


def _timing_series(nodes_dir: Path) -> dict[str, Series]:
    """The real-time timing series the nodes left (ms), on the entity paths the orchestrator records them under."""
    from hil.runtime.realtime.merge import timing_series as timing_files  # one definition of those paths
    from hil.runtime.realtime.streamed_series import read_series

    out = {}
    for entity, f in timing_files(nodes_dir):
        data = read_series(f)
        if len(data):
            out[entity] = Series(data[:, 0], data[:, 1] * 1e3)
    return out

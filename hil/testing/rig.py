"""Build a rig for a test: a scenario (packaged name, file or object) with overrides, the user's controller class or
ECU program swapped in, run in virtual time (or real time) for a duration, returning a :class:`HilRun`.

- ``set={"radio.latency_s": 0.2, "controller.params.kx": 0.1}``: dotted keys as in ``hil run --set``.
- ``controller=MyLaw`` (a :class:`~ecu_sim.controllers.base.Controller` subclass; registered on first use if it is
  not yet) or a registered law's name; ``params={...}`` replaces the law's parameters (default: the law's
  defaults when the law is swapped, the scenario's otherwise).
- ``ecu=MyEcu`` (a subclass of :class:`ecu_sim.runtime.Ecu`, built with the standard wiring) or a factory
  ``(parts, db, unit) -> Ecu`` (:func:`standard_ecu` builds the shipped one, to wrap or adjust): the firmware
  program every unit runs instead of the standard one.

Real time runs the scenario on :func:`hil.realtime.orchestrator.run_realtime` (separate processes; by default one
ECU process per train, ``ecus_per_process`` = units per train, to keep start-up short). The node
processes import the user's controller and ECU program from their modules (:mod:`hil.testing.nodes`), so these
must be defined at the top level of an importable module (not inside a test function).
"""
from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hil.scenario import Scenario, scenario_from_dict
from hil.testing.results import HilRun, Series

ControllerLike = Any  # type[Controller] | str
EcuLike = Any  # type[Ecu] | Callable[[Assembly, TrainDb, int], Ecu]


def ensure_registered(controller: ControllerLike) -> str:
    """The law name to put in the scenario; a Controller subclass not yet registered is registered under its name."""
    from ecu_sim.controllers.base import Controller, get_controller, register

    if isinstance(controller, str):
        get_controller(controller)  # KeyError listing the known laws
        return controller
    if not (isinstance(controller, type) and issubclass(controller, Controller)):
        raise TypeError(f"controller={controller!r}: expected a Controller subclass or a registered law's name")
    name = getattr(controller, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"controller {controller.__qualname__} has no `name` (the law's name in scenario files)")
    if not hasattr(controller, "Params"):
        raise TypeError(f"controller {controller.__qualname__} has no `Params` (its ControllerParams model)")
    try:
        known = get_controller(name)
    except KeyError:
        register(controller)
        return name
    if known is not controller:
        raise ValueError(f"controller name {name!r} is already taken by {known.__module__}.{known.__qualname__}; "
                         f"give {controller.__module__}.{controller.__qualname__} another `name`")
    return name


def build_scenario(scenario: str | Path | Scenario, overrides: dict[str, Any] | None = None,
                   controller: ControllerLike | None = None, params: dict[str, Any] | None = None) -> Scenario:
    """Load and validate the scenario with ``overrides`` (dotted keys) and the law swapped; ScenarioError names
    the file and the field on bad input, like ``hil run``. As in sweeps, a law different from the scenario's gets
    its own default parameters unless parameters are given (``params`` or ``controller.params...`` keys)."""
    from hil.scenario.loader import ScenarioError, read_toml, resolve

    sets = dict(overrides or {})
    if controller is not None:
        sets["controller.law"] = ensure_registered(controller)
    if params is not None:
        sets["controller.params"] = dict(params)
    if isinstance(scenario, Scenario):
        data, source = scenario.model_dump(), f"<scenario {scenario.name}>"
    else:
        path = resolve(scenario)
        data, source = read_toml(path, ScenarioError), str(path)
    base_law = (data.get("controller") or {}).get("law")
    if "controller.law" in sets and sets["controller.law"] != base_law \
            and not any(k == "controller" or k.startswith("controller.params") for k in sets):
        sets["controller.params"] = {}  # the new law's defaults, not the old law's parameters
    return scenario_from_dict(data, source, sets)


def standard_ecu(parts, db, u: int):
    """The standard firmware of unit u (``hil.runtime.virtual.build_ecu`` as shipped), also while a swap is active:
    a user factory can build it and wrap or adjust it."""
    import hil.runtime.virtual as virtual

    build = virtual.build_ecu
    return getattr(build, "standard", build)(parts, db, u)


def ecu_factory(ecu: EcuLike) -> Callable:
    """``(parts, db, unit) -> Ecu`` for an Ecu subclass or a factory. A subclass is built by the standard
    ``build_ecu`` itself with the class swapped in, so its wiring never drifts from the shipped firmware's."""
    import hil.runtime.virtual as virtual
    from ecu_sim.runtime import Ecu

    standard = getattr(virtual.build_ecu, "standard", virtual.build_ecu)
    if isinstance(ecu, type):
        if not issubclass(ecu, Ecu):
            raise TypeError(f"ecu={ecu.__qualname__}: expected a subclass of ecu_sim.runtime.Ecu or a factory")

        def build(parts, db, u: int, cls=ecu):
            saved = virtual.Ecu
            virtual.Ecu = cls  # build_ecu constructs `Ecu(...)` from its module's namespace
            try:
                return standard(parts, db, u)
            finally:
                virtual.Ecu = saved

    elif callable(ecu):
        def build(parts, db, u: int, factory=ecu):
            return factory(parts, db, u)

    else:
        raise TypeError(f"ecu={ecu!r}: expected a subclass of ecu_sim.runtime.Ecu or a factory (parts, db, unit) -> Ecu")
    build.standard = standard  # type: ignore[attr-defined]
    return build


@contextlib.contextmanager
def ecu_program(ecu: EcuLike | None) -> Iterator[None]:
    """While active, the rig builds every unit's firmware with ``ecu`` (both runtimes build ECUs through
    ``hil.runtime.virtual.build_ecu``; the real-time ECU nodes get the same swap from hil.testing.nodes)."""
    if ecu is None:
        yield
        return
    import hil.runtime.virtual as virtual

    original = virtual.build_ecu
    virtual.build_ecu = ecu_factory(ecu)
    try:
        yield
    finally:
        virtual.build_ecu = original


class Rig:
    """A scenario ready to run under test (see the module docstring). ``run()`` can be called several times."""

    def __init__(self, scenario: str | Path | Scenario, *, set: dict[str, Any] | None = None,  # noqa: A002
                 controller: ControllerLike | None = None, params: dict[str, Any] | None = None,
                 ecu: EcuLike | None = None, seed: int | None = None) -> None:
        self.scenario = build_scenario(scenario, set, controller, params)
        self.controller = controller
        self.ecu = ecu
        if ecu is not None:
            ecu_factory(ecu)  # type errors now, not mid-run
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

        with ecu_program(self.ecu):
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
        from hil.realtime.orchestrator import run_realtime
        from hil.testing.nodes import node_imports

        out = self.work_dir() if self.work_dir else Path(tempfile.mkdtemp(prefix="trainhil-rt-"))
        started: list[float] = []
        per_process = ecus_per_process or self.scenario.trains.units
        with node_imports(self.controller if not isinstance(self.controller, str) else None, self.ecu):
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
    from hil.realtime.orchestrator import _timing_series as timing_files  # one definition of those paths

    out = {}
    for entity, f in timing_files(nodes_dir):
        data = np.load(f)
        if len(data):
            out[entity] = Series(data[:, 0], data[:, 1] * 1e3)
    return out

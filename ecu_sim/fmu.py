"""Running a co-simulation FMU (FMI 2.0 or 3.0) through fmpy: load and check it, set and read its real variables,
step it. The plant (hil/plant/fmu_plant.py) and the FMU law (ecu_sim/controllers/fmu_law.py) are built on this.

Only co-simulation FMUs are taken: a model-exchange-only FMU is refused with an error that says so (its equations
would need a solver picked and tuned here, and a co-simulation export is what Simulink and Modelica tools give for
exchange). Every variable the scenario maps is checked before the run: present, of type Real (FMI 2) or Float64
(FMI 3), of the causality its role needs. Errors are :class:`FmuError`, one line naming the FMU and the variable;
what the FMU logged with an error status is part of the message.

Instances are pooled per process (:meth:`Fmu.acquire`): a sweep worker instantiates an FMU once and resets it
between runs, given back by the plant's and the laws' ``close`` at the end of each run (``fmi2Reset`` / ``fmi3Reset``) rather than loading its library again.
"""
from __future__ import annotations

import atexit
import ctypes
import functools
import itertools
import shutil
import weakref
import zipfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REAL_TYPES = ("Real", "Float64")


class FmuError(ValueError):
    """An FMU that does not load, does not fit its mapping, or failed a call; the message names the FMU."""


@dataclass(frozen=True)
class FmuVariable:
    """One scalar variable of an FMU's model description."""

    name: str
    value_reference: int
    type: str
    causality: str


class Fmu:
    """One FMU file, loaded once per process: its model description, extracted binaries and pooled instances."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.name = path.name
        self.description = _read_description(path)
        md = self.description
        self.fmi_version = int(str(md.fmiVersion).split(".")[0])
        if self.fmi_version not in (2, 3):
            raise FmuError(f"{path}: FMI {md.fmiVersion} is not supported (FMI 2.0 and 3.0 co-simulation are)")
        if md.coSimulation is None:
            kinds = [k for k, v in (("model exchange", md.modelExchange),
                                    ("scheduled execution", getattr(md, "scheduledExecution", None))) if v]
            raise FmuError(f"{path}: not a co-simulation FMU (it offers {' and '.join(kinds) or 'no interface'}); "
                           "trainhil steps FMUs as co-simulation slaves: export it for co-simulation")
        self.variables = {v.name: FmuVariable(v.name, int(v.valueReference), str(v.type), str(v.causality))
                          for v in md.modelVariables}
        self._unzipped: Path | None = None
        self._free: list[FmuInstance] = []
        # its own word that two instances in one process would share its state (static data, as Simulink's often do)
        self.once_per_process = bool(md.coSimulation.canBeInstantiatedOnlyOncePerProcess)
        self._alive: weakref.WeakSet[FmuInstance] = weakref.WeakSet()  # its instances in this process, lent or free


    def variable(self, name: str, causalities: Iterable[str], role: str) -> FmuVariable:
        """The real variable ``name`` of one of ``causalities``, checked; ``role`` says what the mapping uses it for."""
        wanted = tuple(causalities)
        var = self.variables.get(name)
        if var is None:
            close = [n for n in self.variables if n.split("[")[0] == name.split("[")[0]][:3]
            hint = f" (it has {', '.join(close)}, ...)" if close else ""
            raise FmuError(f"{self.path}: no variable {name!r} for {role}{hint}")
        if var.type not in REAL_TYPES:
            raise FmuError(f"{self.path}: variable {name!r} ({role}) is of type {var.type}; a "
                           f"{'Real' if self.fmi_version == 2 else 'Float64'} is needed")
        if var.causality not in wanted:
            raise FmuError(f"{self.path}: variable {name!r} ({role}) has causality {var.causality!r}; "
                           f"expected {' or '.join(repr(c) for c in wanted)}")
        return var

    def acquire(self, owner: object, instance_name: str) -> tuple[FmuInstance, weakref.finalize]:
        """A free instance (reset) or a new one, lent to ``owner``, and the callable that gives it back: the owner
        calls it when its run ends (``close``), or it runs when the owner is collected."""
        if self._free:
            instance = self._free.pop()
            instance.reset()
        else:
            if self.once_per_process and len(self._alive):
                holder = next(iter(self._alive)).name
                raise FmuError(f"{self.path}: it can be instantiated only once per process "
                               "(canBeInstantiatedOnlyOncePerProcess), and this process already has an instance of it "
                               f"({holder}): such an FMU can be the plant or the law of one unit per process (virtual "
                               "time runs every unit in one process; real time with --ecus-per-process 1 one in each); "
                               "export it without that restriction")
            instance = FmuInstance(self, instance_name)
            self._alive.add(instance)
        return instance, weakref.finalize(owner, self._release, instance)

    def _release(self, instance: FmuInstance) -> None:
        """Take an instance back for the next run of this process (not one that failed a call)."""
        if not instance.broken:
            self._free.append(instance)

    def unzipped(self) -> Path:
        """The extracted FMU (once per process, removed at exit)."""
        if self._unzipped is None:
            import fmpy

            try:
                self._unzipped = Path(fmpy.extract(str(self.path)))
            except (OSError, zipfile.BadZipFile) as exc:
                raise FmuError(f"{self.path}: cannot extract: {exc}") from None
            atexit.register(shutil.rmtree, self._unzipped, True)
        return self._unzipped


_LOADED: dict[tuple[str, int, int], Fmu] = {}


def load_fmu(path: str | Path) -> Fmu:
    """The FMU at ``path``, loaded once per process (again when the file changed)."""
    p = Path(path).expanduser().resolve()
    try:
        stat = p.stat()
    except OSError as exc:
        raise FmuError(f"{path}: cannot read the FMU: {exc.strerror}") from None
    if not p.is_file():
        raise FmuError(f"{path}: not a file (an FMU is a .fmu zip archive)")
    key = (str(p), stat.st_mtime_ns, stat.st_size)
    if key not in _LOADED:
        _LOADED[key] = Fmu(p)
    return _LOADED[key]


def _read_description(path: Path) -> Any:
    """fmpy's model description of ``path``; any failure is one FmuError."""
    import fmpy

    try:
        return fmpy.read_model_description(str(path), validate=True)
    except zipfile.BadZipFile:
        raise FmuError(f"{path}: not an FMU (not a zip archive)") from None
    except KeyError:
        raise FmuError(f"{path}: not an FMU (no modelDescription.xml in the archive)") from None
    except Exception as exc:  # fmpy raises plain Exceptions for schema and XML errors
        first = str(exc).strip().splitlines()
        raise FmuError(f"{path}: invalid model description: {' '.join(first[:3])}") from None


class FmuInstance:
    """One instantiated co-simulation slave. Values move through preallocated ctypes arrays: a step of a 12-unit
    plant costs a few tens of microseconds, not fmpy's per-call list conversions."""

    def __init__(self, fmu: Fmu, instance_name: str) -> None:
        self.fmu, self.name = fmu, f"{instance_name}#{next(_NUMBERS)}"  # unique: the FMI 2 logger routes by name
        self.messages: list[str] = []
        self.broken = False
        md, unzipped = fmu.description, fmu.unzipped()
        common = dict(guid=md.guid if fmu.fmi_version == 2 else md.instantiationToken, unzipDirectory=str(unzipped),
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName=self.name)
        try:
            if fmu.fmi_version == 2:
                from fmpy.fmi2 import FMU2Slave

                self._slave: Any = FMU2Slave(**common)
                self._slave.instantiate(callbacks=self._fmi2_callbacks())
            else:
                from fmpy.fmi3 import FMU3Slave

                self._slave = FMU3Slave(**common)
                self._slave.instantiate(logMessage=self._fmi3_log)
        except Exception as exc:
            raise FmuError(f"{fmu.path}: cannot load or instantiate: {_one_line(exc)}{self._logged()}") from None
        self._finalizer = weakref.finalize(self, _free_slave, self._slave)
        self._set = self._slave.fmi2SetReal if fmu.fmi_version == 2 else self._slave.fmi3SetFloat64
        self._get = self._slave.fmi2GetReal if fmu.fmi_version == 2 else self._slave.fmi3GetFloat64
        self.time = 0.0

    # ------------------------------------------------------------------ logging

    def _fmi2_callbacks(self) -> Any:
        """The process's FMI 2 callbacks: fmpy's native logger proxy keeps one Python logger for the whole process,
        so one logger routes every message to its instance by the (unique) instance name."""
        _INSTANCES[self.name] = weakref.ref(self)
        return _fmi2_callbacks()

    def _fmi3_log(self, env: Any, status: int, category: Any, message: Any) -> None:
        self._record(status, message)

    def _record(self, status: int, message: bytes | None) -> None:
        """Keep what the FMU logged with a warning or worse (the last few), for the error message."""
        if status >= 1 and message:
            self.messages = [*self.messages[-4:], message.decode("utf-8", "replace").strip()]

    def _logged(self) -> str:
        return f" (the FMU says: {self.messages[-1]})" if self.messages else ""

    # ------------------------------------------------------------------ lifecycle

    def initialize(self, parameters: Mapping[FmuVariable, float], start_time: float = 0.0) -> None:
        """Set the parameters and start values, then enter and leave initialization at ``start_time``."""
        try:
            if self.fmu.fmi_version == 2:
                self._slave.setupExperiment(startTime=start_time)
                self._write([v.value_reference for v in parameters], list(parameters.values()))
                self._slave.enterInitializationMode()
                self._slave.exitInitializationMode()
            else:
                self._write([v.value_reference for v in parameters], list(parameters.values()))
                self._slave.enterInitializationMode(startTime=start_time)
                self._slave.exitInitializationMode()
        except Exception as exc:
            self.broken = True
            raise FmuError(f"{self.fmu.path}: initialization failed: {_one_line(exc)}{self._logged()}") from None
        self.time = start_time

    def reset(self) -> None:
        """Back to the instantiated state (``fmiNReset``), for the next run."""
        self.messages = []
        self._slave.reset()

    def _write(self, refs: list[int], values: list[float]) -> None:
        if refs:
            vr = (ctypes.c_uint32 * len(refs))(*refs)
            val = (ctypes.c_double * len(values))(*values)
            self._call_set(vr, val)

    def _call_set(self, vr: Any, val: Any) -> None:
        if self.fmu.fmi_version == 2:
            self._set(self._slave.component, vr, len(vr), val)
        else:
            self._set(self._slave.component, vr, len(vr), val, len(val))

    # ------------------------------------------------------------------ stepping

    def port(self, variables: list[FmuVariable]) -> ValuePort:
        """Preallocated access to ``variables`` (set them all or read them all in one FMI call)."""
        return ValuePort(self, variables)

    def do_step(self, t: float, h: float) -> None:
        """One communication step from ``t`` of size ``h``; an error status is an FmuError naming the FMU."""
        try:
            self._slave.doStep(t, h)
        except Exception as exc:
            self.broken = True
            raise FmuError(f"{self.fmu.name}: doStep at t = {t:.6f} s failed: {_one_line(exc)}{self._logged()}") from None
        self.time = t + h


class ValuePort:
    """A fixed set of real variables of one instance with their value buffer (``values``, a ctypes array)."""

    def __init__(self, instance: FmuInstance, variables: list[FmuVariable]) -> None:
        self.instance, self.variables = instance, variables
        self.refs = (ctypes.c_uint32 * len(variables))(*[v.value_reference for v in variables])
        self.values = (ctypes.c_double * len(variables))()
        self.array = np.ctypeslib.as_array(self.values)  # the same memory as a numpy array (no copy)

    def write(self, values: Iterable[float] | np.ndarray) -> None:
        """Set every variable of the port (one fmiNSetReal/SetFloat64 call)."""
        self.array[:] = values
        try:
            self.instance._call_set(self.refs, self.values)
        except Exception as exc:
            raise FmuError(f"{self.instance.fmu.name}: setting {self.variables[0].name} ... failed: "
                           f"{_one_line(exc)}{self.instance._logged()}") from None

    def read(self) -> np.ndarray:
        """Every variable's value (one fmiNGetReal/GetFloat64 call), in :attr:`array`, which is returned: it is
        overwritten by the next read."""
        inst = self.instance
        try:
            if inst.fmu.fmi_version == 2:
                inst._get(inst._slave.component, self.refs, len(self.refs), self.values)
            else:
                inst._get(inst._slave.component, self.refs, len(self.refs), self.values, len(self.values))
        except Exception as exc:
            raise FmuError(f"{inst.fmu.name}: reading {self.variables[0].name} ... failed: "
                           f"{_one_line(exc)}{inst._logged()}") from None
        return self.array

    def first_non_finite(self, values: np.ndarray) -> str | None:
        """``name = value`` of the first variable whose value in ``values`` is not finite, else None."""
        bad = np.flatnonzero(~np.isfinite(values))
        return f"{self.variables[bad[0]].name} = {float(values[bad[0]])!r}" if len(bad) else None


_INSTANCES: dict[str, weakref.ref[FmuInstance]] = {}
_NUMBERS = itertools.count(1)


@functools.cache
def _fmi2_callbacks() -> Any:
    """fmi2CallbackFunctions shared by every FMI 2 instance of the process (kept alive by the cache)."""
    from fmpy.fmi2 import (fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions,
                           fmi2CallbackLoggerTYPE)
    from fmpy.logging import addLoggerProxy

    def log(env: Any, name: bytes | None, status: int, category: Any, message: bytes | None) -> None:
        ref = _INSTANCES.get((name or b"").decode("utf-8", "replace"))
        instance = ref() if ref is not None else None
        if instance is not None:
            instance._record(status, message)

    libc = ctypes.CDLL(None)
    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(log)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(("calloc", libc))
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(("free", libc))
    addLoggerProxy(ctypes.byref(callbacks))  # formats the printf-like message in C before it reaches Python
    return callbacks


def _free_slave(slave: Any) -> None:
    """Terminate and free an instance at garbage collection (errors ignored: the process may be ending)."""
    try:
        slave.terminate()
    except Exception:
        pass
    try:
        slave.freeInstance()
    except Exception:
        pass


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__

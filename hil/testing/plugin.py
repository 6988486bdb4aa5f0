"""The ``trainhil`` pytest plugin (entry point ``pytest11``): the ``hil_rig`` fixture, the ``hil_realtime`` marker
and ``--hil-record DIR``.

Loaded in every pytest session of an environment where trainhil is installed, so it imports nothing heavy until a
test asks for a rig. Identical virtual-time runs within one session are simulated once and shared (a run is
deterministic bit for bit; the cache key is the validated scenario, the law and ECU program objects, the seed and
the duration), so treat a run as read-only. With ``--hil-record DIR`` the rig runs of every failing (or xfailing)
test are written after the test to ``DIR/<test>/<scenario>[-k]/run.rrd`` with their ``metrics.json``; passing
tests cost no recording time.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

RUNS = pytest.StashKey[list]()
CACHE = pytest.StashKey[dict]()
MARKER = "hil_realtime"


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("trainhil", "trainhil rig tests")
    group.addoption("--hil-record", metavar="DIR", default=None,
                    help="keep the rerun recording (.rrd) and metrics.json of every failing test's rig runs in "
                         "DIR/<test>/ (open with: hil view DIR/<test>/<scenario>)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", f"{MARKER}(pace=1.0, ecus_per_process=None): run this test's rigs in real "
                                       "time (separate ECU, plant and radio processes on emulated buses) at this pace")
    config.stash[CACHE] = {}


@pytest.fixture
def hil_rig(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    """Factory: ``hil_rig(scenario, set=..., controller=..., params=..., ecu=..., seed=...)`` -> :class:`Rig`.

    ``scenario``: a packaged name (``hil scenarios``), a .toml path (relative paths are tried next to the test file
    first) or a Scenario. ``rig.run(duration_s)`` runs it in virtual time, or in real time when the test is marked
    ``@pytest.mark.hil_realtime(pace=1.0)``."""
    marker = request.node.get_closest_marker(MARKER)
    return RigFactory(request, tmp_path_factory, None if marker is None else dict(marker.kwargs))


class RigFactory:
    """What ``hil_rig`` is: call it to build a Rig bound to the test (its runs are kept for --hil-record)."""

    def __init__(self, request: pytest.FixtureRequest, tmp: pytest.TempPathFactory, realtime: dict | None) -> None:
        self._request, self._tmp, self.realtime = request, tmp, realtime
        self.runs = request.node.stash.setdefault(RUNS, [])
        self._here = Path(request.node.path).parent

    def __call__(self, scenario: Any, **kwargs: Any):
        from hil.testing.rig import Rig

        rig = Rig(_near_test(scenario, self._here), **kwargs)
        rig.realtime_default = self.realtime
        rig.on_run.append(self.runs.append)
        rig.cache = self._request.config.stash[CACHE]
        rig.work_dir = lambda: self._tmp.mktemp("hil-realtime")
        return rig

    def __repr__(self) -> str:
        mode = "virtual time" if self.realtime is None else f"real time {self.realtime}"
        return f"<hil_rig factory for {self._request.node.name} ({mode})>"


def _near_test(scenario: Any, here: Path) -> Any:
    """A relative .toml path that exists next to the test file is taken from there (tests run from any directory)."""
    if isinstance(scenario, (str, Path)) and str(scenario).endswith(".toml"):
        p = Path(scenario)
        if not p.is_absolute() and not p.exists() and (here / p).exists():
            return here / p
    return scenario


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    outcome = yield
    report = outcome.get_result()
    if report.when != "call":
        return
    runs = item.stash.get(RUNS, None)
    target = item.config.getoption("--hil-record")
    failed = report.failed or (report.skipped and hasattr(report, "wasxfail"))
    if not (runs and target and failed):
        return
    lines = []
    for k, run in enumerate(_unique(runs)):
        name = run.scenario.name if len(runs) == 1 else f"{run.scenario.name}-{k + 1}"
        out = Path(target) / _safe(item.nodeid) / _safe(name)
        try:
            rrd = run.save(out)
            lines.append(f"{rrd}  (open: hil view {out})")
        except Exception as exc:  # keep the test's own report; say why the recording is missing
            lines.append(f"{out}: could not write the recording: {exc!r}")
    report.sections.append(("hil recording", "\n".join(lines)))


def _unique(runs: list) -> list:
    seen, out = set(), []
    for r in runs:
        if id(r) not in seen:
            seen.add(id(r))
            out.append(r)
    return out


def _safe(text: str) -> str:
    """A test id or scenario name as one directory name."""
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", text).strip("_")[:120] or "test"

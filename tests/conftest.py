"""Fixtures shared by the test modules."""
from __future__ import annotations

import shutil
import signal
import tempfile
from pathlib import Path

import pytest

# Started from a shell that ignores SIGINT (a background job, nohup), every child process would inherit the ignored
# SIGINT, and the tests that stop a run or a logger with Ctrl-C would wait in vain. A handled SIGINT here is reset
# to the default in each child at exec, as it is when the suite is started from a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def rt(monkeypatch):
    """A short private runtime root for bus-server sockets (unix socket paths are limited to 107 bytes)."""
    d = tempfile.mkdtemp(prefix="th", dir="/tmp")
    monkeypatch.setenv("XDG_RUNTIME_DIR", d)
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(params=["python", "native"])
def server_cls(request):
    """Each bus-server test runs on the Python server and on the engine's native one: the same behaviour."""
    from tests.oracle.python_server import PythonBusServer as BusServer
    from hil.runtime.realtime.native_server import NativeBusServer

    return BusServer if request.param == "python" else NativeBusServer

"""Fixtures shared by the test modules."""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest


@pytest.fixture
def rt(monkeypatch):
    """A short private runtime root for bus-server sockets (unix socket paths are limited to 107 bytes)."""
    d = tempfile.mkdtemp(prefix="th", dir="/tmp")
    monkeypatch.setenv("XDG_RUNTIME_DIR", d)
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)

"""A SIL Kit registry of the rig's own on loopback: started on a free port, its URI read from the configuration
file it writes, stopped with the run (or the test) that started it."""
from __future__ import annotations

import ctypes
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from hil.silkit.runtime import SilKitRuntime


PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the registry's child process: SIGTERM when the process that started it dies (killed, crashed), so no
    registry outlives its run."""
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class Registry:
    """``sil-kit-registry --listen-uri silkit://HOST:0`` as a child process; :attr:`uri` is where it listens.
    ``launcher``: a command to start it under (``ip netns exec NS`` for a registry on another network host)."""

    def __init__(self, runtime: SilKitRuntime, host: str = "127.0.0.1", timeout_s: float = 10.0,
                 launcher: Sequence[str] = ()) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="trainhil-registry-")
        config = Path(self._dir.name) / "registry.yaml"
        self.process = subprocess.Popen(
            [*launcher, str(runtime.tool("sil-kit-registry")), "--listen-uri", f"silkit://{host}:0",
             "--generate-configuration", str(config), "--log", "warn"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            preexec_fn=_die_with_parent if sys.platform == "linux" else None)
        self.uri = self._wait_for_uri(config, timeout_s)

    def _wait_for_uri(self, config: Path, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                err = self.process.stderr.read().decode(errors="replace") if self.process.stderr else ""
                raise RuntimeError(f"sil-kit-registry exited ({self.process.returncode}): {err.strip()[-300:]}")
            if config.is_file():
                for line in config.read_text().splitlines():
                    if "RegistryUri:" in line:
                        return line.split("RegistryUri:", 1)[1].strip().strip("'\"")
            time.sleep(0.02)
        self.close()
        raise RuntimeError(f"sil-kit-registry did not report its URI within {timeout_s} s")

    def close(self) -> None:
        """Stop the registry (SIGTERM, then SIGKILL after 5 s)."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._dir.cleanup()

    def __enter__(self) -> "Registry":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

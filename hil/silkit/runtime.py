"""Where SIL Kit's library and registry are, and installing them from the silkit-py wheel.

Looked up in this order: ``$TRAINHIL_SILKIT_HOME`` (a folder with ``libSilKit.so`` and ``bin/sil-kit-registry``),
an installed ``SilKit_py`` package (silkit-py under Python 3.12), and the folder ``hil silkit install`` unpacks the
wheel into (``~/.cache/trainhil/silkit/<wheel version>``)."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

HOME_ENV = "TRAINHIL_SILKIT_HOME"
WHEEL = "silkit-py==1.0.5"  # bundles SIL Kit 5.0.3 (libSilKit.so, sil-kit-registry, sil-kit-system-controller)
SILKIT_VERSION = "5.0.3"


class SilKitUnavailable(RuntimeError):
    """SIL Kit's runtime is not installed here; the message says how to install it."""


@dataclass(frozen=True)
class SilKitRuntime:
    """The folder of one SIL Kit runtime: its library and its tools."""

    home: Path

    @property
    def library(self) -> Path:
        return self.home / "libSilKit.so"

    def tool(self, name: str) -> Path:
        """``sil-kit-registry``, ``sil-kit-system-controller`` or ``sil-kit-monitor``."""
        return self.home / "bin" / name


def install_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "trainhil" / "silkit" / WHEEL.split("==")[1]


def _usable(home: Path) -> bool:
    return (home / "libSilKit.so").is_file() and (home / "bin" / "sil-kit-registry").is_file()


def find_runtime() -> SilKitRuntime:
    """The SIL Kit runtime to use, or SilKitUnavailable saying how to install one."""
    given = os.environ.get(HOME_ENV)
    if given:
        if not _usable(Path(given)):
            raise SilKitUnavailable(f"{HOME_ENV}={given}: no libSilKit.so and bin/sil-kit-registry there")
        return SilKitRuntime(Path(given))
    spec = importlib.util.find_spec("SilKit_py")
    if spec is not None and spec.origin is not None and _usable(Path(spec.origin).parent):
        return SilKitRuntime(Path(spec.origin).parent)
    if _usable(install_dir()):
        return SilKitRuntime(install_dir())
    raise SilKitUnavailable("SIL Kit is not installed: run `hil silkit install` (fetches the silkit-py wheel with pip "
                            f"and unpacks SIL Kit {SILKIT_VERSION} into {install_dir()}), or set {HOME_ENV}")


def install(target: Path | None = None) -> SilKitRuntime:
    """Fetch the silkit-py wheel (for CPython 3.12, with this Python's pip: no 3.12 needed) and unpack SIL Kit's
    library, tools and licences into ``target``."""
    target = target or install_dir()
    with tempfile.TemporaryDirectory(prefix="trainhil-silkit-") as tmp:
        command = [sys.executable, "-m", "pip", "download", WHEEL, "--no-deps", "--only-binary=:all:",
                   "--python-version", "3.12", "--platform", "manylinux_2_28_x86_64", "-d", tmp, "-q"]
        done = subprocess.run(command, capture_output=True, text=True)
        wheels = list(Path(tmp).glob("*.whl"))
        if done.returncode != 0 or not wheels:
            raise SilKitUnavailable(f"pip could not fetch {WHEEL}: {done.stderr.strip()[-500:]}")
        with zipfile.ZipFile(wheels[0]) as wheel:
            for item in wheel.namelist():
                if item.endswith("/"):
                    continue
                if item.startswith(("SilKit_py/bin/", "SilKit_py/licenses/")) or item == "SilKit_py/libSilKit.so":
                    relative = Path(item).relative_to("SilKit_py")
                    _replace(target / relative, wheel.read(item), 0o755 if relative.parts[0] == "bin" else 0o644)
    return SilKitRuntime(target)


def _replace(path: Path, data: bytes, mode: int) -> None:
    """Write ``path`` as a new file renamed over the old one: a registry or a participant running from the old
    one keeps it (writing into it would fail, "text file busy", or corrupt a loaded library)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        tmp.chmod(mode)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)

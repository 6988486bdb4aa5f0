"""Where a real-time rig's bus sockets live: private per-run directories and the python-can channel syntax.

Layout: ``<runtime_root>/<run>/<bus>.sock`` with ``runtime_root`` = ``$XDG_RUNTIME_DIR/trainhil``, or
``<tempdir>/trainhil-<uid>`` when XDG_RUNTIME_DIR is unset. The root and every run directory are mode 0o700
and owned by the user; one that is not (a symlink, another owner, group or world access) is refused,
because anyone who can reach a socket can read and inject frames on that bus.

A python-can channel is ``"<run>/<bus>"`` (e.g. ``"seed000/bus1"``) or an absolute path to a ``.sock`` file.
"""
from __future__ import annotations

import os
import re
import socket
import stat
import tempfile
from pathlib import Path

ROOT_NAME = "trainhil"
SOCKET_SUFFIX = ".sock"
MAX_SOCKET_PATH_BYTES = 107  # sizeof(sockaddr_un.sun_path) - 1 on Linux
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
CHANNEL_SYNTAX = '"<run>/<bus>" (e.g. "seed000/bus1") or an absolute path to a .sock file'


class InsecureRunDirError(PermissionError):
    """A runtime or run directory that others could enter (or that is not ours): refused."""


def validate_name(name: object, what: str) -> str:
    """A run or bus name: letters, digits, '_', '.', '-' (no slashes, no '..'), at most 64 characters."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name) or ".." in name:
        raise ValueError(f"{what} name {name!r} is invalid: use 1-64 of A-Z a-z 0-9 _ . - "
                         "(not starting with '.' or '-', no '/' and no '..')")
    return name


def runtime_root() -> Path:
    """$XDG_RUNTIME_DIR/trainhil, or <tempdir>/trainhil-<uid> when XDG_RUNTIME_DIR is unset (not created)."""
    xdg = os.environ.get("XDG_RUNTIME_DIR", "")
    if xdg:
        if not os.path.isabs(xdg):
            raise ValueError(f"XDG_RUNTIME_DIR={xdg!r} must be an absolute path")
        return Path(xdg) / ROOT_NAME
    return Path(tempfile.gettempdir()) / f"{ROOT_NAME}-{os.getuid()}"


def check_private_dir(path: Path) -> None:
    """Raise InsecureRunDirError unless ``path`` is a real directory (no symlink), ours, mode 0o700 or stricter."""
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        raise InsecureRunDirError(f"{path} is not a directory (a symlink or a file): refusing to use it")
    if st.st_uid != os.getuid():
        raise InsecureRunDirError(f"{path} is owned by uid {st.st_uid}, not by you (uid {os.getuid()}): "
                                  "refusing to use it")
    if st.st_mode & 0o077:
        raise InsecureRunDirError(f"{path} has mode {stat.S_IMODE(st.st_mode):#o}: group/others can access it, "
                                  "refusing to use it (chmod 700 it or remove it)")


def _private_dir(path: Path, create: bool) -> Path:
    """``path`` checked by check_private_dir, created with mode 0o700 first if missing and ``create``."""
    if create:
        if not path.parent.is_dir():
            raise FileNotFoundError(f"cannot create {path}: its parent directory {path.parent} does not exist")
        try:
            os.mkdir(path, 0o700)
            os.chmod(path, 0o700)  # the umask may have removed bits we need
        except FileExistsError:
            pass  # checked below, whoever made it
    check_private_dir(path)
    return path


def run_dir(run: str, create: bool = False) -> Path:
    """The private directory of run ``run`` (the root and the run directory created if ``create``)."""
    validate_name(run, "run")
    root = _private_dir(runtime_root(), create)
    return _private_dir(root / run, create)


def _checked_socket_path(path: Path) -> Path:
    if len(os.fsencode(path)) > MAX_SOCKET_PATH_BYTES:
        raise ValueError(f"socket path {path} is {len(os.fsencode(path))} bytes, more than the "
                         f"{MAX_SOCKET_PATH_BYTES} a unix socket allows: set XDG_RUNTIME_DIR to a shorter directory")
    return path


def socket_path(run: str, bus: str, create: bool = False) -> Path:
    """<runtime_root>/<run>/<bus>.sock; the directories are checked (and created if ``create``)."""
    validate_name(bus, "bus")
    return _checked_socket_path(run_dir(run, create) / f"{bus}{SOCKET_SUFFIX}")


def parse_channel(channel: object) -> tuple[str, Path]:
    """A python-can channel -> (channel text, socket path), without touching the file system; ValueError naming
    the channel if it is malformed."""
    text = str(channel)
    if os.path.isabs(text):
        if not text.endswith(SOCKET_SUFFIX):
            raise ValueError(f"channel {text!r}: an absolute channel must be a {SOCKET_SUFFIX} file; "
                             f"use {CHANNEL_SYNTAX}")
        return text, _checked_socket_path(Path(text))
    parts = text.split("/")
    if len(parts) != 2:
        raise ValueError(f"channel {text!r} is malformed: use {CHANNEL_SYNTAX}")
    run, bus = parts
    validate_name(run, f"channel {text!r}: run")
    validate_name(bus, f"channel {text!r}: bus")
    return text, _checked_socket_path(runtime_root() / run / f"{bus}{SOCKET_SUFFIX}")


def bus_sockets() -> list[tuple[str, Path]]:
    """Every (channel "<run>/<bus>", socket path) under the runtime root, live or stale; [] when there is none
    or the root is not private."""
    root = runtime_root()
    try:
        check_private_dir(root)
    except (OSError, ValueError):
        return []
    found = []
    for run in sorted(root.iterdir()):
        if not _NAME_RE.fullmatch(run.name):
            continue
        try:
            check_private_dir(run)
        except OSError:
            continue
        for sock in sorted(run.glob(f"*{SOCKET_SUFFIX}")):
            bus = sock.name[: -len(SOCKET_SUFFIX)]
            if _NAME_RE.fullmatch(bus) and stat.S_ISSOCK(os.lstat(sock).st_mode):
                found.append((f"{run.name}/{bus}", sock))
    return found


def remove_run_dir(run: str) -> bool:
    """Remove run ``run``'s directory if it is empty (True if removed); for the orchestrator at the end of a run."""
    try:
        os.rmdir(run_dir(run))
    except OSError:
        return False
    return True


def socket_is_live(path: Path, timeout: float = 0.5) -> bool:
    """True if something accepts connections on the unix socket ``path`` (a stale socket file refuses them)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        try:
            s.connect(str(path))
        except OSError:
            return False
    return True

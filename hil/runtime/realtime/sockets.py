"""Where a real-time rig's bus sockets live: private per-run directories and the python-can channel syntax.

Layout: ``<runtime_root>/<run>/<bus>.sock`` with ``runtime_root`` = ``$XDG_RUNTIME_DIR/trainhil``, or
``<tempdir>/trainhil-<uid>`` when XDG_RUNTIME_DIR is unset. The root and every run directory are mode 0o700
and owned by the user; one that is not (a symlink, another owner, group or world access) is refused,
because anyone who can reach a socket can read and inject frames on that bus.

A python-can channel is ``"<run>/<bus>"`` (e.g. ``"seed000/bus1"``) or an absolute path to a ``.sock`` file.

Loopback TCP (a bus server started with ``tcp=True``): the server writes ``<run dir>/<bus>.tcp`` (mode 0o600:
host, port and the per-run token), and a client names the bus ``"tcp:<run>/<bus>"``, which finds all three
there, so only the user who owns the run directory can connect; or ``"tcp://127.0.0.1:<port>"`` with the
token given explicitly. Servers bind loopback addresses only (``LOOPBACK_HOSTS``).

The bell: a bus server on the frame engine also makes ``<run dir>/<bus>.bell``, a FIFO (mode 0o600) that its quiet
readers (the rig's own nodes) write a byte to when it must wake for what they sent (``protocol.OPTION_QUIET``).
"""
from __future__ import annotations

import ipaddress
import json
import os
import re
import secrets
import socket
import stat
import tempfile
import time
from pathlib import Path
from typing import Callable

from hil.runtime.realtime.protocol import TOKEN_BYTES

ROOT_NAME = "trainhil"
SOCKET_SUFFIX = ".sock"
MAX_SOCKET_PATH_BYTES = 107  # sizeof(sockaddr_un.sun_path) - 1 on Linux
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
CHANNEL_SYNTAX = '"<run>/<bus>" (e.g. "seed000/bus1") or an absolute path to a .sock file'
TOKEN_SUFFIX = ".tcp"
BELL_SUFFIX = ".bell"
LOOPBACK_HOSTS = ("127.0.0.1", "::1")
TCP_CHANNEL_SYNTAX = '"tcp:<run>/<bus>" (host, port and token read from the run directory) or "tcp://127.0.0.1:<port>"'


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
    try:
        root = _private_dir(runtime_root(), create)
    except InsecureRunDirError as exc:  # e.g. another user made <tempdir>/trainhil-<uid> first
        raise InsecureRunDirError(f"{exc}; or set XDG_RUNTIME_DIR to a private directory of yours, e.g. "
                                  "`mkdir -m 700 ~/.run && export XDG_RUNTIME_DIR=~/.run`") from None
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


STALE_AFTER_S = 60.0  # a run directory younger than this may belong to a rig that is starting its servers


def remove_stale_run_dirs() -> list[str]:
    """Remove our run directories whose every socket is dead (a rig killed with SIGKILL leaves them); the names
    removed. Directories with a live socket, someone else's, or younger than STALE_AFTER_S are left alone."""
    root = runtime_root()
    try:
        check_private_dir(root)
        runs = [d for d in root.iterdir() if d.is_dir() and not d.is_symlink()]
    except (OSError, InsecureRunDirError):
        return []
    removed = []
    for d in runs:
        try:
            check_private_dir(d)
            if time.time() - d.stat().st_mtime < STALE_AFTER_S:
                continue
            files = list(d.iterdir())
            if any(f.suffix == SOCKET_SUFFIX and socket_is_live(f, 0.2) for f in files):
                continue
            for f in files:
                if f.suffix in (SOCKET_SUFFIX, TOKEN_SUFFIX, BELL_SUFFIX):
                    f.unlink()
            d.rmdir()  # fails, and keeps the directory, if anything else is in it
            removed.append(d.name)
        except (OSError, InsecureRunDirError):
            continue
    return removed


def socket_is_live(path: Path, timeout: float = 0.5) -> bool:
    """True if something accepts connections on the unix socket ``path`` (a stale socket file refuses them)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        try:
            s.connect(str(path))
        except OSError:
            return False
    return True


# --------------------------------------------------------------------------- local-only checks and loopback TCP


def check_private_socket(path: Path) -> None:
    """Raise InsecureRunDirError unless ``path`` is a unix socket owned by us that group/others cannot use
    (a socket planted by someone else would let them feed this node frames)."""
    st = os.lstat(path)
    if not stat.S_ISSOCK(st.st_mode):
        raise InsecureRunDirError(f"{path} is not a unix socket: refusing to use it")
    if st.st_uid != os.getuid():
        raise InsecureRunDirError(f"{path} is owned by uid {st.st_uid}, not by you (uid {os.getuid()}): refusing to use it")
    if st.st_mode & 0o077:
        raise InsecureRunDirError(f"{path} has mode {stat.S_IMODE(st.st_mode):#o}: group/others can use it, refusing it")


def check_loopback(host: str) -> str:
    """``host`` if it is a loopback address a bus server may bind (127.0.0.1 or ::1), else ValueError naming it."""
    try:
        ok = ipaddress.ip_address(host).is_loopback
    except ValueError:
        ok = False
    if not ok or host not in LOOPBACK_HOSTS:
        raise ValueError(f"TCP host {host!r} is refused: a bus server listens on loopback only ({', '.join(LOOPBACK_HOSTS)})")
    return host


def token_path(socket_file: Path) -> Path:
    """Where a bus server's TCP endpoint and token are written: beside its socket, ``<bus>.tcp``."""
    return socket_file.with_suffix(TOKEN_SUFFIX)


def check_private_file(path: Path, st: os.stat_result, is_kind: Callable[[int], bool], what: str, kind: str) -> None:
    """Raise InsecureRunDirError unless ``st`` (``path``'s lstat) is of the kind ``is_kind`` tests, ours, and
    owner-only: a file planted or opened up by someone else is refused (a token file, a bus's bell)."""
    if not is_kind(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise InsecureRunDirError(f"{path}: {what} must be {kind} of yours with mode 0o600 "
                                  f"(is mode {stat.S_IMODE(st.st_mode):#o}, uid {st.st_uid}): refusing it")


def bell_path(socket_file: Path) -> Path:
    """Where a bus server's bell is: beside its socket, ``<bus>.bell``."""
    return socket_file.with_suffix(BELL_SUFFIX)


def make_bell(socket_file: Path) -> tuple[int, int]:
    """The server's end of its bell (see the module docstring): the FIFO made anew (mode 0o600) and opened
    read-write, non-blocking (so it never reads as closed): (descriptor, inode). Called once the socket is bound,
    so a bell left by a killed server of this bus is replaced, never a live one's."""
    path = bell_path(socket_file)
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    os.mkfifo(path, 0o600)
    os.chmod(path, 0o600)  # the umask may have taken bits, never added any: exactly owner read-write
    fd = os.open(path, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOFOLLOW)
    return fd, os.fstat(fd).st_ino


def open_bell(socket_file: Path) -> int | None:
    """A quiet reader's end of the bus's bell (write-only, non-blocking), or None if its server has none (the
    node then stays an ordinary lazy reader). A bell that is not a FIFO of ours, owner-only, is refused."""
    path = bell_path(socket_file)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    check_private_file(path, st, stat.S_ISFIFO, "a bell", "a FIFO")
    try:
        return os.open(path, os.O_WRONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOFOLLOW)
    except OSError:  # ENXIO: nobody reads it (its server is gone)
        return None


def write_token_file(path: Path, host: str, port: int, token: bytes) -> None:
    """Write host, port and token to ``path`` with mode 0o600 from the start (never readable by others)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        json.dump({"host": host, "port": port, "token": token.hex()}, fh)
    os.replace(tmp, path)


def read_token_file(path: Path) -> tuple[str, int, bytes]:
    """(host, port, token) from a token file; InsecureRunDirError if it is not ours or others can read it."""
    check_private_file(path, os.lstat(path), stat.S_ISREG, "a token file", "a regular file")
    try:
        data = json.loads(path.read_text())
        return check_loopback(str(data["host"])), int(data["port"]), bytes.fromhex(data["token"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: malformed token file ({exc})") from None


def parse_tcp_channel(channel: object) -> tuple[str, Path | None, str | None, int | None]:
    """``"tcp:<run>/<bus>"`` -> (text, token file, None, None); ``"tcp://host:port"`` -> (text, None, host, port).
    ValueError naming the channel if it is malformed or not loopback."""
    text = str(channel)
    if text.startswith("tcp://"):
        host, sep, port = text[len("tcp://"):].rpartition(":")
        host = host.strip("[]")
        if not sep or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"channel {text!r} is malformed: use {TCP_CHANNEL_SYNTAX}")
        return text, None, check_loopback(host), int(port)
    if not text.startswith("tcp:"):
        raise ValueError(f"channel {text!r} is not a TCP channel: use {TCP_CHANNEL_SYNTAX}")
    _, sock = parse_channel(text[len("tcp:"):])
    if os.path.isabs(text[len("tcp:"):]):
        raise ValueError(f"channel {text!r}: use {TCP_CHANNEL_SYNTAX}")
    return text, token_path(sock), None, None


class BusServerError(RuntimeError):
    """A bus server cannot start (socket taken, not a socket, ...)."""


def bind_unix_socket(path: Path) -> socket.socket:
    """Listen on ``path``: bound under a temporary name, chmod 0o600, then linked into place atomically."""
    if os.path.lexists(path):
        if not stat.S_ISSOCK(os.lstat(path).st_mode):
            raise BusServerError(f"{path} exists and is not a socket: refusing to replace it")
        if socket_is_live(path):
            raise BusServerError(f"a bus server is already running on {path}")
        os.unlink(path)  # stale: its server died
    tmp = path.with_name(f".{secrets.token_hex(4)}.tmp")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(tmp))
        try:
            os.chmod(tmp, 0o600)
            sock.listen(128)
            os.link(tmp, path)
        finally:
            os.unlink(tmp)
    except FileExistsError:
        sock.close()
        raise BusServerError(f"another bus server started on {path} at the same time") from None
    except BaseException:
        sock.close()
        raise
    sock.setblocking(False)
    return sock


def listen_tcp(host: str, port: int, path: Path) -> tuple[socket.socket, bytes, tuple[str, int], Path]:
    """A non-blocking loopback TCP listener for the bus at ``path``, with a fresh token published beside the socket
    (``<bus>.tcp``, mode 0o600): (socket, token, (host, port), token file)."""
    check_loopback(host)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)
        sock.setblocking(False)
        token = secrets.token_bytes(TOKEN_BYTES)
        address = (host, sock.getsockname()[1])
        token_file = token_path(path)
        write_token_file(token_file, host, address[1], token)
    except BaseException:
        sock.close()
        raise
    return sock, token, address, token_file


def check_server_args(run: str, bus: str, tcp: bool, tcp_host: str, spin_us: float, pace: float) -> None:
    """ValueError naming a bad argument of a bus server (either kind), before anything is created."""
    validate_name(run, "run")
    validate_name(bus, "bus")
    if tcp:
        check_loopback(tcp_host)
    if spin_us < 0:
        raise ValueError(f"spin_us={spin_us!r} must be >= 0")
    if not (isinstance(pace, (int, float)) and 0 < pace < float("inf")):
        raise ValueError(f"pace={pace!r} must be a positive number (1.0 = wall clock, 0.5 = half speed)")


def remove_endpoints(path: Path, inode: int, token_file: Path | None, bell_inode: int | None = None) -> None:
    """Remove a closed server's token file, and its socket and bell if they are still the ones it made (same
    inodes)."""
    if bell_inode is not None:
        bell = bell_path(path)
        try:
            if os.lstat(bell).st_ino == bell_inode:
                os.unlink(bell)
        except FileNotFoundError:
            pass
    if token_file is not None:
        try:
            os.unlink(token_file)
        except FileNotFoundError:
            pass
    try:
        if os.lstat(path).st_ino == inode:
            os.unlink(path)
    except FileNotFoundError:
        pass

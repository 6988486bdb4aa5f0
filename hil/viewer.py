"""``hil view DIR``: open a run's recording in the rerun viewer, or say how where no viewer can be started.

DIR is a run directory (``runs/seed000``: its ``run.rrd``), an .rrd file, or a folder of runs (``hil sweep`` output,
``pytest --hil-record`` output): every .rrd below it is opened. The viewer is started only when the ``rerun``
executable exists and there is a display; it is started with its analytics pipeline off (rerun does not send usage
data when ``CI`` is set) and its local server bound to 127.0.0.1, so nothing is sent over the network. Otherwise the
command prints the files and the commands to open them elsewhere, and exits 0.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

from hil.record.rrd_file import check_rrd

ANALYTICS_OFF = {"CI": "1"}  # rerun's analytics pipeline is off when CI is set (and FORCE_RERUN_ANALYTICS is not)
MAX_FILES = 20
VIEWER_SETTLE_S = 2.0  # a viewer still running this long after its start counts as opened


def find_recordings(target: Path) -> list[Path]:
    """The .rrd files DIR stands for (FileNotFoundError naming DIR when there are none)."""
    if target.is_file():
        if target.suffix != ".rrd":
            raise FileNotFoundError(f"{target}: not a rerun recording (.rrd)")
        return [target]
    if not target.exists():
        raise FileNotFoundError(f"{target}: no such run directory or .rrd file")
    if (target / "run.rrd").is_file():
        return [target / "run.rrd"]
    found = sorted(target.rglob("*.rrd"))
    if not found:
        raise FileNotFoundError(f"{target}: no .rrd recording in it (a run directory holds run.rrd; record one with "
                                "`hil run SCENARIO --out DIR`)")
    return found


def rerun_executable() -> str | None:
    """The rerun viewer binary: on PATH, or the one the rerun-sdk wheel ships."""
    found = shutil.which("rerun")
    if found:
        return found
    try:
        import rerun_cli  # type: ignore[import-not-found]
    except ImportError:
        return None
    binary = Path(rerun_cli.__file__).parent / "rerun"
    return str(binary) if binary.is_file() else None


def why_no_viewer(env: dict[str, str], platform: str = sys.platform, executable: str | None = None) -> str | None:
    """Why a viewer cannot be started here (None: it can)."""
    if executable is None:
        return "the rerun viewer is not installed (pip install rerun-sdk)"
    if platform.startswith("linux") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        return "there is no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None


def viewer_command(executable: str, files: list[Path]) -> list[str]:
    """The viewer's command line: local server on loopback only, the recordings as arguments."""
    return [executable, "--bind", "127.0.0.1", *[str(f) for f in files]]


def viewer_env(env: dict[str, str]) -> dict[str, str]:
    out = {k: v for k, v in env.items() if k != "FORCE_RERUN_ANALYTICS"}
    out.update(ANALYTICS_OFF)
    return out


def how_to_open(files: list[Path], reason: str) -> str:
    shown = files[:MAX_FILES]
    lines = [f"hil view: not starting a viewer here: {reason}.", "Recordings:"]
    lines += [f"  {f}" for f in shown]
    if len(files) > MAX_FILES:
        lines.append(f"  ... and {len(files) - MAX_FILES} more")
    args = " ".join(str(f) for f in shown[:3])
    lines += [
        "To look at them, on a machine with a display and rerun-sdk installed (copy the files there if needed):",
        f"  CI=1 rerun --bind 127.0.0.1 {args}",
        "  (CI=1 keeps rerun's usage analytics off; or run `rerun analytics disable` once.)",
        "Or read them in Python without a viewer: hil.record.load_run(RUN_DIR) (signals, events and metrics).",
    ]
    return "\n".join(lines)


def readable_recordings(files: list[Path]) -> list[Path]:
    """The files that are recordings (a cut-short one reads up to its last complete message, and is said so); the
    others are named on stderr; none at all is a FileNotFoundError."""
    good = []
    for f in files:
        check = check_rrd(f)
        if not check.ok:
            print(f"hil view: skipping {f}: {check.why}", file=sys.stderr)
        else:
            if not check.whole:
                print(f"hil view: {f} is cut short: {check.messages} complete messages are readable", file=sys.stderr)
            good.append(f)
    if not good:
        raise FileNotFoundError(f"no readable recording among {len(files)} .rrd file{'s' if len(files) > 1 else ''}")
    return good


def cmd_view(args: argparse.Namespace) -> int:
    files = readable_recordings(find_recordings(Path(args.target)))
    executable = rerun_executable()
    reason = "--print given" if args.print_only else why_no_viewer(dict(os.environ), executable=executable)
    if reason is not None or executable is None:
        print(how_to_open(files, reason or "no viewer"))
        return 0
    cmd = viewer_command(executable, files)
    viewer = subprocess.Popen(cmd, env=viewer_env(dict(os.environ)), stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:  # a viewer that dies at once (no GPU, no display server after all) is not "opened"
        _, err = viewer.communicate(timeout=VIEWER_SETTLE_S)
    except subprocess.TimeoutExpired:
        viewer.stderr.close()  # it runs: let it go on alone
    else:
        tail = (err or b"").decode(errors="replace").strip().splitlines()[-1:]
        print(f"hil view: the rerun viewer exited at once (code {viewer.returncode})"
              + (f": {tail[0]}" if tail else ""), file=sys.stderr)
        return 1
    print(f"hil view: opened {len(files)} recording{'s' if len(files) > 1 else ''} in the rerun viewer: "
          + " ".join(str(f) for f in files[:3]) + (" ..." if len(files) > 3 else ""))
    return 0


def add_view_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``hil view`` on the ``hil`` parser's sub-parsers."""
    p = subparsers.add_parser("view", help="open a run's recording in the rerun viewer (or print how)",
                              description="Open a run's recording (DIR/run.rrd, an .rrd file, or every .rrd under a folder) "
                                          "in the rerun viewer; where none can start, print the files and how to open them.")
    p.add_argument("target", metavar="DIR", help="run directory (holding run.rrd), an .rrd file, or a folder of runs")
    p.add_argument("--print", dest="print_only", action="store_true",
                   help="do not start a viewer: print the recordings and how to open them")
    p.set_defaults(func=cmd_view)
    return p

"""``hil silkit install`` / ``hil silkit info``: SIL Kit's runtime for the co-simulation (hil/silkit).

``install`` fetches the silkit-py wheel (SIL Kit 5.0.3's libSilKit.so, sil-kit-registry,
sil-kit-system-controller) with pip and unpacks it; the wheel is built for CPython 3.12, but what the rig uses
from it is native code, so no Python 3.12 is needed. ``info`` says which runtime would be used.
"""
from __future__ import annotations

import argparse

from hil.scenario import ScenarioError
from hil.silkit.runtime import SILKIT_VERSION, WHEEL, SilKitUnavailable, find_runtime, install


def add_silkit_parser(sub) -> None:
    p = sub.add_parser("silkit", help="install or locate Vector SIL Kit's runtime (library and registry)")
    actions = p.add_subparsers(dest="silkit_command", required=True)
    actions.add_parser("install", help=f"fetch {WHEEL} with pip and unpack SIL Kit {SILKIT_VERSION}").set_defaults(
        func=_cmd_install)
    actions.add_parser("info", help="print where the SIL Kit runtime is").set_defaults(func=_cmd_info)


def _cmd_install(args: argparse.Namespace) -> int:
    try:
        runtime = install()
    except (SilKitUnavailable, OSError) as exc:
        raise ScenarioError(f"hil silkit install: {exc}") from None
    print(f"SIL Kit {SILKIT_VERSION} in {runtime.home}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    try:
        runtime = find_runtime()
    except SilKitUnavailable as exc:
        raise ScenarioError(str(exc)) from None
    print(f"library  {runtime.library}\nregistry {runtime.tool('sil-kit-registry')}")
    return 0

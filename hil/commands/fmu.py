"""``hil fmu build NAME [--fmi 2|3] [--trains N --units U] -o FILE``: compile a reference FMU with gcc.

The reference FMUs are the train plant (the built-in plant's coupled model, RK4) and seed 000's consensus law,
written in C against the FMI headers fmpy ships (hil/fmi/c/). The packaged scenarios name them ``trainhil:NAME``
and build them on first use; this command writes one where you want it, to try in another FMI tool.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from hil.fmi.build import REFERENCE_NAMES, FmuBuildError, build_fmu, spec_for
from hil.scenario import ScenarioError


def add_fmu_parser(sub) -> None:
    p = sub.add_parser("fmu", help="build the reference FMUs (train plant, consensus law) from their C sources")
    actions = p.add_subparsers(dest="fmu_command", required=True)
    build = actions.add_parser("build", help="compile a reference FMU with gcc and write the .fmu")
    build.add_argument("name", choices=REFERENCE_NAMES)
    build.add_argument("--fmi", type=int, choices=(2, 3), default=2, help="FMI version (default 2)")
    build.add_argument("--trains", type=int, default=3, help="train_plant: trains in the group (default 3)")
    build.add_argument("--units", type=int, default=4, help="train_plant: units per train (default 4)")
    build.add_argument("-o", "--out", required=True, help="the .fmu file to write")
    build.set_defaults(func=_cmd_build)


def _cmd_build(args: argparse.Namespace) -> int:
    if not (1 <= args.trains <= 64 and 1 <= args.units <= 64):
        raise ScenarioError(f"--trains {args.trains} --units {args.units}: each must be 1..64")
    try:
        path = build_fmu(spec_for(args.name, args.trains, args.units), args.fmi, Path(args.out))
    except (FmuBuildError, OSError) as exc:
        raise ScenarioError(f"hil fmu build: {exc}") from None
    print(f"wrote {path} ({args.name}, FMI {args.fmi})")
    return 0

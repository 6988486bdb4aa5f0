"""seed000 under Vector SIL Kit in virtual time, beside the same run without it, measured side by side.

Four runs of ``--sim`` simulated seconds, interleaved ``--repeat`` times (the fastest of each kept): the virtual
rig alone; the rig as a SIL Kit participant (its own registry on loopback, no one else); the rig with train1/unit2
as an external SIL Kit participant (the ecu_sim firmware on SIL Kit's CAN API, in this process); and the same unit
as the C reference ECU (examples/silkit_ecu, built here with gcc; skipped without gcc), a process of its own.
Prints x real time and the cost over the plain run.
    python bench/bench_silkit.py [--sim 10] [--repeat 3]
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.scenario import load_scenario  # noqa: E402
from hil.session import run_scenario  # noqa: E402
from hil.silkit.runtime import find_runtime  # noqa: E402
from tests.test_silkit import build_c_ecu, run_with_c_ecu, run_with_external_unit  # noqa: E402


def build_c_ecu_if_gcc(into: Path) -> Path | None:
    """examples/silkit_ecu built as the tests build it; None without gcc."""
    return build_c_ecu(find_runtime(), into) if shutil.which("gcc") else None


def wall(kind: str, sim_s: float, c_ecu: Path | None) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        if kind == "external unit":
            run_with_external_unit(find_runtime(), Path(tmp), sim_s)
        elif kind == "C external unit":
            run_with_c_ecu(find_runtime(), c_ecu, Path(tmp), sim_s)
        else:
            run_scenario(load_scenario("seed000"), Path(tmp), duration_s=sim_s, record=False,
                         silkit="" if kind == "silkit" else None)
        return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as build:
        c_ecu = build_c_ecu_if_gcc(Path(build))
        kinds = ["virtual", "silkit", "external unit"] + (["C external unit"] if c_ecu else [])
        best = {k: float("inf") for k in kinds}
        for _ in range(args.repeat):
            for k in kinds:
                best[k] = min(best[k], wall(k, args.sim, c_ecu))
    if c_ecu is None:
        print("C external unit: skipped (no gcc)")
    for k in kinds:
        print(f"{k:16s} {args.sim / best[k]:6.1f}x real time  ({best[k] / best['virtual']:.1f}x the plain run's wall time)")


if __name__ == "__main__":
    main()

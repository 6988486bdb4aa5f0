"""Run the scenarios of a comparison (virtual time over CAN, or the ideal loop), each judged by a metric family.

One run = one worker call: build the rig, hook the full-rate accumulators of :mod:`hil.compare.report` onto
the plant (every command it receives, every step it takes: the rig and the ideal loop both drive
``parts.plant``), run, let the family compute its metrics, return them with a down-sampled speed-error
trace. Runs are independent, so several go to a local process pool (forkserver, like ``hil sweep``); with
one worker they run in this process.
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from hil.compare.report import CommandStats, CompareRun, Envelope, RunData, families
from hil.runtime.ideal import IdealLoop
from hil.runtime.virtual import VirtualRig
from hil.scenario.model import Scenario


@dataclass(frozen=True)
class CompareItem:
    """One run to do: a label for the table, the (overridden) scenario, the runtime and the family."""

    label: str
    scenario: Scenario
    family: str
    ideal: bool = False
    duration_s: float | None = None


def _hook(plant, reference, commands: CommandStats, envelope: Envelope) -> None:
    """Feed the accumulators from the plant's own entry points (instance attributes shadow the methods)."""
    command, step = plant.command, plant.step

    def hooked_command(u: int, force_n: float, mode: int, t: float) -> None:
        commands.add(u, force_n, t)
        command(u, force_n, mode, t)

    def hooked_step() -> None:
        step()
        envelope.add(plant.t, plant.x, plant.v, reference.state(plant.t)[1])

    plant.command, plant.step = hooked_command, hooked_step


def run_item(item: CompareItem) -> CompareRun:
    """Run one item to the end and judge it (runs in a worker process, or inline)."""
    family = families()[item.family]
    sc = item.scenario
    runner = IdealLoop(sc) if item.ideal else VirtualRig(sc)
    parts = runner.parts
    layout, plant = parts.layout, parts.plant
    split = family.startup_s(sc)
    commands = CommandStats(layout.n_units, split)
    pairs = layout.coupler_pairs()
    envelope = Envelope(layout.n_units, pairs, layout.length_m[pairs[:, 0]] if len(pairs) else np.zeros(0), split)
    envelope.add(0.0, plant.x, plant.v, parts.reference.state(0.0)[1])
    _hook(plant, parts.reference, commands, envelope)
    log = runner.run(item.duration_s)
    commands.finish(plant.t)
    runtime = "ideal" if item.ideal else "virtual"
    metrics = family.compute(RunData(item.label, runtime, sc, log, commands, envelope))
    law = sc.controller.law
    return CompareRun(item.label, law, runtime, metrics, log.t.copy(), log.speed_error.astype(np.float32),
                      family.paper(law))


def run_items(items: list[CompareItem], workers: int = 1, progress=None) -> list[CompareRun]:
    """Run every item (in order of the list in the result); ``progress(label)`` is called as each finishes."""
    if workers <= 1 or len(items) <= 1:
        out = []
        for item in items:
            out.append(run_item(item))
            if progress:
                progress(item.label)
        return out
    ctx = multiprocessing.get_context("forkserver")
    with ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx) as pool:
        futures = [pool.submit(run_item, item) for item in items]
        results = []
        for item, fut in zip(items, futures):
            results.append(fut.result())
            if progress:
                progress(item.label)
        return results

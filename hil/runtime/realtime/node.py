"""What every real-time node process shares: its command line, the scenario it loads, and its python-can buses.

A node is started by the orchestrator as ``python -m hil.runtime.realtime.<kind>_node --run RUN --scenario-json FILE
--seed N --duration S --out DIR [...]``; it prints "ready" once its buses are open, waits for "go <T0>",
runs until the simulated duration or "stop"/SIGTERM, then writes its results into DIR and exits 0.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Iterable

import can
import trainhil_engine as engine

from hil.runtime.realtime.cpu_layout import parse_cores
from hil.scenario.model import CanConfig, Scenario


def node_parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--run", required=True, help="run name: buses are python-can channels <run>/bus<i>")
    p.add_argument("--scenario-json", required=True, help="the validated scenario, as JSON (written by the orchestrator)")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--duration", type=float, required=True, help="simulated seconds to run")
    p.add_argument("--pace", type=float, default=1.0, help="simulated seconds per wall second")
    p.add_argument("--out", required=True, help="directory for this node's results")
    p.add_argument("--fifo", action="store_true",
                   help="run under SCHED_FIFO at the node's priority (hil/runtime/realtime/scheduling.py)")
    p.add_argument("--cpus", type=parse_cores, default=None, metavar="LIST",
                   help="run on these cores, e.g. 1 or 1,2 (hil/runtime/realtime/cpu_layout.py; default: anywhere)")
    p.add_argument("--turns", action="store_true",
                   help="act at each read time as a turn: its frames go on the bus at that instant, the bus waiting "
                        "for them (frame_io.EngineFrames.read_every)")
    return p


def load_scenario_json(path: str) -> Scenario:
    return Scenario.model_validate_json(Path(path).read_text())


def open_bus(run: str, train: int, ids: Iterable[int], can_cfg: CanConfig, name: str,
             receive_own: bool = False, packing: engine.Packing | None = None, lazy: bool = False) -> can.BusABC:
    """A python-can node on train ``train``'s (0-based) bus accepting exactly ``ids`` (none: accepts nothing).

    The bus is the rig's emulated one (``trainhil`` interface, channel ``<run>/bus<i>``) or, with
    ``can.transport = "socketcan"``, the host's SocketCAN interface ``can.socketcan_channels[train]`` (vcan).
    ``receive_own``: the node hears its own frames back (stamped with their end of transmission), which a process
    hosting several ECUs of one bus needs so they hear each other as separate ECUs would. ``packing``: the node
    also accepts the CAN FD containers that carry any of ``ids`` (its frame I/O unpacks them). ``lazy``: on the
    emulated bus, a lazy reader: its frames come at its read times (``frame_io.EngineFrames(lazy=True)``), and a
    quiet one where its server has a bell (its sends wake the server only when needed: its FrameLink rings)."""
    extended = can_cfg.extended_ids
    mask = 0x1FFFFFFF if extended else 0x7FF
    ids = sorted(set(ids))
    if packing is not None:
        ids = sorted(set(ids) | set(packing.containers_of(ids)))
    # an empty set would mean "accept everything" to python-can: match one id that no node sends instead
    filters = [{"can_id": i, "can_mask": mask, "extended": extended} for i in ids] or \
              [{"can_id": mask, "can_mask": mask, "extended": extended}]
    if can_cfg.transport == "socketcan":
        return can.Bus(interface="socketcan", channel=can_cfg.socketcan_channels[train], can_filters=filters,
                       receive_own_messages=receive_own, fd=can_cfg.fd)
    return can.Bus(interface="trainhil", channel=f"{run}/bus{train + 1}", can_filters=filters, node_name=name,
                   receive_own_messages=receive_own, fd=can_cfg.fd, lazy_reader=lazy, quiet=lazy)

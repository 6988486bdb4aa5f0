"""The radio between the real-time rig's train buses, in the engine: the bus servers' threads forward the routed
frames themselves (``trainhil_engine.RadioHub``, engine/src/radio_hub.rs), with no radio process, no socket and no
Python per frame.

The links, routes and random numbers are the virtual rig's (``configure_radio``, the run seed's "radio" stream),
so both runtimes draw the same losses and jitter per offered frame. A serving thread cannot call Python, so the
links' draws are queued ahead in blocks: a small thread here tops them up, every ``TOP_UP_S`` while a link draws
fast and up to ``TOP_UP_MAX_S`` apart while they are quiet (``next_top_up_wait``; a link that ran dry would drop
frames and count them, ``starved``). Radio faults set the links' impairments from the orchestrator
(``impairment_setter``). The counters are saved to ``radio.json`` every ``SAVE_EVERY_S`` as the radio node saves
them, so ``hil recover`` has them if the orchestrator is killed; a full disk only skips a save. On SocketCAN there are no bus servers: the radio is a node process there
(``radio_node``).
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import trainhil_engine as engine

from ecu_sim.codec import TrainDb
from hil.radio.gateway import RadioIds, build_links
from hil.record.integrity import write_json_atomic
from hil.runtime.assembly import random_streams
from hil.runtime.engine_net import configure_radio, engine_impairments
from hil.scenario.layout import TrainLayout
from hil.scenario.model import Scenario

TOP_UP_S = 0.1  # the shortest wait between top-ups of the links' draws (wall seconds)
# the longest, at pace 1 or slower: a link's 8 blocks of 1,024 draws last that long at 16,000 routed frames a second
# (a 1 Mbit/s bus carries at most 9,000 eight-byte frames a second); faster paces shorten it, down to TOP_UP_S
TOP_UP_MAX_S = 0.5
SAVE_EVERY_S = 1.0  # wall seconds between saves of the links' counters


def next_top_up_wait(used: int, waited: float, reserve: int, pace: float) -> float:
    """Wall seconds to the next top-up, given that the busiest link used ``used`` of its ``reserve`` blocks in the
    last ``waited``: at that rate it uses at most half of them before then, and a quiet radio wakes rarely (each
    wake-up of a Python thread costs some 100 µs of CPU here)."""
    longest = max(TOP_UP_S, TOP_UP_MAX_S / max(pace, 1.0))
    if used <= 0:
        return longest
    return min(longest, max(TOP_UP_S, waited * (reserve / 2) / used))


class EngineRadio:
    """The radio of a real-time run: ``port(i)`` goes to bus i's server; ``close()`` stops the top-ups and gives
    the links' counters (``stats()``)."""

    def __init__(self, sc: Scenario, db: TrainDb, seed: int, pace: float, packing: engine.Packing | None,
                 save_to: Path | None = None) -> None:
        """``save_to``: the run's nodes folder (``radio.json`` there, as the radio node writes it)."""
        layout = TrainLayout.from_config(sc.trains)
        self.links = build_links(sc.radio, layout.n_trains, random_streams(seed)["radio"])
        self.hub = engine.RadioHub(pace, packing)
        self._pace = pace
        self._lock = threading.Lock()  # the hub's Python calls (top-ups, fault settings) one at a time
        configure_radio(self.hub, layout.n_trains, self.links, layout.units_per_train, sc.radio.forward_aux,
                        [db.agent_state(k) for k in range(layout.units_per_train)], RadioIds.from_db(db))
        self._save_to = save_to
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._top_up_loop, name="radio draws", daemon=True)
        self._thread.start()

    def port(self, bus: int) -> tuple[engine.RadioHub, int]:
        """What bus ``bus``'s server is given (``NativeBusServer(radio=...)``)."""
        return self.hub, bus

    def impairment_setter(self, rng) -> Callable:
        """``RadioFaults``' setter for these links, the faults' draws from ``rng`` (as in virtual time)."""
        apply = engine_impairments(self.hub, list(self.links), rng)

        def locked(name: str, imp) -> None:
            with self._lock:
                apply(name, imp)

        return locked

    def _top_up_loop(self) -> None:
        next_save = time.monotonic() + SAVE_EVERY_S
        wait = TOP_UP_S
        while not self._stop.wait(wait):
            with self._lock:
                used = self.hub.top_up()
            wait = next_top_up_wait(used, wait, self.hub.RESERVE_BLOCKS, self._pace)
            if self._save_to is not None and time.monotonic() > next_save:
                self.save()
                next_save = time.monotonic() + SAVE_EVERY_S

    def save(self) -> None:
        """The counters so far to ``radio.json`` (skipped on a full or failing disk: the merge gets them anyway)."""
        if self._save_to is None:
            return
        try:
            write_json_atomic(self._save_to / "radio.json", {"links": self.stats(), "starved": self.starved})
        except OSError:
            pass

    def stats(self) -> dict[str, dict[str, int]]:
        """Each link's counters by name (as the radio node's ``radio.json`` has them)."""
        with self._lock:
            return {name: self.hub.link_stats(i) for i, name in enumerate(self.links)}

    @property
    def starved(self) -> int:
        """Frames dropped because a link's draws ran out."""
        with self._lock:
            return self.hub.starved

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

"""A SIL Kit run in one process, for tests and tools: a registry on loopback and participants that run their
lifecycles on threads, the first one (the rig) the system controller that waits for all of them."""
from __future__ import annotations

import threading
from collections.abc import Callable

from hil.silkit.capi import Library
from hil.silkit.participant import Participant
from hil.silkit.registry import Registry
from hil.silkit.runtime import SilKitRuntime, find_runtime

StepHandler = Callable[[int, int], None]


class LocalSimulation:
    """Participants named ``names`` (the first is the system controller) on a registry of our own."""

    def __init__(self, names: list[str], runtime: SilKitRuntime | None = None) -> None:
        self.runtime = runtime or find_runtime()
        self.lib = Library(str(self.runtime.library))
        self.registry = Registry(self.runtime)
        self.participants = {name: Participant(self.lib, name, self.registry.uri) for name in names}
        self.participants[names[0]].require(names)
        self.final_states: dict[str, int] = {}

    def run(self, timeout_s: float = 60.0) -> dict[str, int]:
        """Run every lifecycle to its end (one thread each); the final state of each participant."""
        def run_one(name: str, participant: Participant) -> None:
            self.final_states[name] = participant.run()

        threads = [threading.Thread(target=run_one, args=item, daemon=True) for item in self.participants.items()]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout_s)
        hung = [t.name for t in threads if t.is_alive()]
        if hung:
            raise TimeoutError(f"SIL Kit lifecycles still running after {timeout_s} s")
        return self.final_states

    def close(self) -> None:
        for participant in self.participants.values():
            participant.close()
        self.registry.close()

    def __enter__(self) -> "LocalSimulation":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

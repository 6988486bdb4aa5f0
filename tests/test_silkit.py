"""trainhil as Vector SIL Kit's CAN network simulator (hil/silkit): SIL Kit 5.0.3's own library and registry
(from the silkit-py wheel, `hil silkit install`), participants on a registry of the test's own on loopback, in
virtual time. Skipped where SIL Kit is not installed, except on CI (CI=true), which installs it and must run them."""
from __future__ import annotations

import os

import pytest

from hil.can.frame import frame_bits, frame_duration_ns
from hil.silkit import capi
from hil.silkit.network_simulator import CanNetworkSimulator
from hil.silkit.runtime import SilKitUnavailable, find_runtime

STEP_NS = 1_000_000


@pytest.fixture(scope="module")
def runtime():
    try:
        return find_runtime()
    except SilKitUnavailable as exc:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the SIL Kit tests: {exc}")
        pytest.skip(str(exc))


def simulate(runtime, sends: dict[str, list[tuple[int, int, bytes]]], depth: int = 64, until_ns: int = 5_000_000):
    """Run the rig (network simulator of bus1 at 500 kbit/s) and one participant per key of ``sends``, each sending
    its (step time, id, data) frames; returns (what the rig's controller received, the acknowledgements by sender,
    the simulator, and per participant (its last step before the frame came, frame end, id))."""
    from hil.silkit.session import LocalSimulation

    with LocalSimulation(["rig", *sends], runtime) as sim:
        rig = sim.participants["rig"]
        network = CanNetworkSimulator(sim.lib, rig.handle, "bus1", grid_ns=STEP_NS, tx_queue_depth=depth)
        received: list[tuple[int, int, bytes]] = []
        acks: dict[str, list[tuple[int, int, int]]] = {name: [] for name in sends}
        seen: dict[str, list[tuple[int, int, int]]] = {name: [] for name in sends}
        last_step = {name: -1 for name in sends}
        controllers = {"rig": rig.can_controller("CAN1", "bus1")}
        controllers["rig"].on_frame(lambda t, i, d, f: received.append((t, i, d)))

        def rig_step(now: int, duration: int) -> None:
            network.step(now, duration)
            if now >= until_ns:
                rig.stop("done")

        rig.on_step(rig_step, network.step_ns)
        for name, frames in sends.items():
            controller = controllers[name] = sim.participants[name].can_controller("CAN1", "bus1")
            controller.on_transmit(lambda t, i, s, name=name: acks[name].append((t, i, s)))
            controller.on_frame(lambda t, i, d, f, name=name: seen[name].append((last_step[name], t, i)))

            def step(now: int, duration: int, controller=controller, frames=frames, name=name) -> None:
                last_step[name] = now
                for at, can_id, data in frames:
                    if at == now:
                        controller.send(can_id, data)

            sim.participants[name].on_step(step, STEP_NS)
        for controller in controllers.values():
            controller.set_baud_rate(500_000)
            controller.start()
        network.start()
        states = sim.run()
        assert set(states.values()) == {capi.STATE_SHUTDOWN}, states
    return received, acks, network, seen


def duration_ns(can_id: int, data: bytes) -> int:
    return frame_duration_ns(frame_bits(can_id, data), 500_000)


def test_the_lower_id_wins_and_the_other_ends_one_frame_later(runtime):
    data = bytes(range(8))
    received, acks, _, seen = simulate(runtime, {"ecuA": [(STEP_NS, 0x200, data)], "ecuB": [(STEP_NS, 0x100, data)],
                                                  "ecuC": []})
    first_end = STEP_NS + duration_ns(0x100, data)
    second_end = first_end + duration_ns(0x200, data)  # the engine's frame time includes the intermission
    assert received == [(first_end, 0x100, data), (second_end, 0x200, data)]
    assert acks == {"ecuB": [(first_end, 0x100, capi.TRANSMITTED)], "ecuA": [(second_end, 0x200, capi.TRANSMITTED)],
                    "ecuC": []}
    # both ended within (1 ms, 2 ms): a receiver has them before its step at 2 ms, after its step at 1 ms
    assert seen["ecuC"] == [(STEP_NS, first_end, 0x100), (STEP_NS, second_end, 0x200)]
    assert seen["ecuA"] == [(STEP_NS, first_end, 0x100)] and seen["ecuB"] == [(STEP_NS, second_end, 0x200)]


def test_a_full_tx_queue_reaches_the_sender(runtime):
    frames = [(STEP_NS, 0x300 + k, bytes([k])) for k in range(5)]
    received, acks, network, _ = simulate(runtime, {"ecuA": frames}, depth=2)
    statuses = [s for _, _, s in acks["ecuA"]]
    assert statuses.count(capi.TRANSMIT_QUEUE_FULL) == 3 and statuses.count(capi.TRANSMITTED) == 2
    assert [i for _, i, _ in received] == [0x300, 0x301] and network.queue_full == 3


def test_the_same_participants_give_the_same_run_twice(runtime):
    sends = {f"ecu{k}": [(t * STEP_NS, 0x100 + 16 * k + t, bytes([k, t])) for t in range(1, 4)] for k in range(3)}
    first = simulate(runtime, sends)[0]
    assert first == simulate(runtime, sends)[0]
    ends = [t for t, _, _ in first]
    assert len(first) == 9 and ends == sorted(ends)

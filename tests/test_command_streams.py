"""The plant checks each unit's command stream (hil/plant/command_streams.py): a second sender on a TractionCmd
stream, such as an external device sending another unit's commands with its own alive counters, is refused,
counted and logged, in both runtimes' plant node; the rightful stream goes on."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.plant.command_streams import MAX_DELTA, CommandStreams
from hil.runtime.kernel import to_ns
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario

CRUISE = Path(__file__).resolve().parents[1] / "examples" / "cruise.toml"


def test_a_stream_in_sequence_is_accepted_with_losses_up_to_max_delta():
    s = CommandStreams(1)
    counters = [3, 4, 5, (5 + MAX_DELTA + 1) % 16, (6 + MAX_DELTA + 1) % 16]
    assert [s.accept(0, c) for c in counters] == [None] * 5
    assert s.accept(0, counters[-1]) == "REPEATED"
    assert s.accept(0, (counters[-1] + MAX_DELTA + 2) % 16) == "WRONG_SEQUENCE"


def test_an_interleaved_second_sender_is_refused_and_the_held_stream_goes_on():
    s = CommandStreams(1)
    rng = np.random.default_rng(5)
    own, applied_own, applied_other = 0, 0, 0
    for _ in range(1000):
        own = (own + 1) % 16
        applied_own += s.accept(0, own) is None
        applied_other += s.accept(0, int(rng.integers(16))) is None
    assert applied_own > 900 and applied_other < 100  # one in 16 random counters is the next; the stream goes on
    assert s.rejected["WRONG_SEQUENCE"][0] + s.rejected["REPEATED"][0] >= 1900 - applied_own - applied_other


def test_a_restarted_stream_is_taken_up_after_two_frames_in_sequence():
    s = CommandStreams(1)
    for c in (1, 2, 3, 4):
        assert s.accept(0, c) is None
    assert s.accept(0, 11) == "WRONG_SEQUENCE"  # the ECU restarted: its counter starts elsewhere
    assert s.accept(0, 12) is None and s.accept(0, 13) is None


def test_a_device_sending_another_units_commands_is_refused_by_the_plant():
    """The DUT reproduction in virtual time: a node on train 1's bus sends TractionCmd_U01 (-5 MN) with random alive
    counters beside the rig's own ECU. The plant used to apply it; now it refuses, counts and logs it."""
    sc = load_scenario(str(CRUISE))
    rig = VirtualRig(sc)
    bus = rig.buses[0]
    rogue = bus.attach("Rogue")
    codec, rng = rig.db.traction_cmd(0), np.random.default_rng(1)
    rig.kernel.every(to_ns(0.0053), to_ns(sc.ecu.cycle_s),
                     lambda t_ns: bus.send(rogue, codec.frame_id, codec.encode((0, -5e6), int(rng.integers(16)))))
    log = rig.run(3.0)
    rejects = log.plant_command_rejects["train1/unit1"]
    assert rejects.get("WRONG_SEQUENCE", 0) + rejects.get("REPEATED", 0) > 200
    assert float(np.min(log.signals.array[:, 3 + 4 * rig.layout.n_units])) > -1e6  # unit 1's applied force
    warns = [e for e in log.events if e.source == "bus1/plant" and "or a second sender on this stream?" in e.text]
    assert 1 <= len(warns) <= 4  # the first, then one a second

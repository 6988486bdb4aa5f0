"""Radio bridge process on SocketCAN: the virtual rig's RadioGateway (same links, routes and seeded draws) between
train buses. On the emulated buses the radio is inside the bus servers instead (``engine_radio``).

    python -m hil.runtime.realtime.radio_node --run RUN --scenario-json FILE --seed N --duration S --pace F --out DIR

One process joins every train bus as "RadioGW" (acceptance filters = the gateway's routes from that bus). A
frame heard at simulated time t is offered to the radio links; each delivery is queued by its delivery time
and sent on the destination bus when the clock reaches it (an event of the node's paced kernel, which sleeps
in between and wakes at every frame heard).
At the end it writes ``DIR/radio.json`` (the links' counters). One process for all pairs rather than one per
pair: the gateway is one routing table, as in the virtual rig.
"""
from __future__ import annotations

import sys
from pathlib import Path

from hil.runtime.realtime.frame_io import node_frames
from hil.record.integrity import write_json_atomic
from hil.runtime.realtime.node import load_scenario_json, node_parser, open_bus
from hil.runtime.kernel import to_ns
from hil.runtime.realtime.paced_kernel import PacedKernel
from hil.runtime.realtime.scheduling import enter_role
from hil.runtime.realtime.pacing import SimClock, StopFlag, handshake, linger, set_timer_slack
from hil.runtime.assembly import random_streams
from hil.radio.gateway import build_gateway
from hil.runtime.train_db import bus_packing, load_train_db

IDLE_WAIT_S = 0.05  # simulated seconds between stop checks when nothing is due


def main(argv: list[str] | None = None) -> int:
    p = node_parser("python -m hil.runtime.realtime.radio_node", "Bridge adjacent train buses over the radio model.")
    args = p.parse_args(argv)
    stop = StopFlag()
    set_timer_slack(1)
    scheduling = enter_role("radio", args.fifo, args.cpus)
    sc = load_scenario_json(args.scenario_json)
    db = load_train_db(sc)
    gateway = build_gateway(sc, db, random_streams(args.seed)["radio"])
    faults = None
    if sc.faults:  # radio faults arrive as "fault <k> start|end" lines (hil/runtime/realtime/faults.py)
        from hil.runtime.realtime.faults import RadioNodeFaults

        faults = RadioNodeFaults(sc, gateway, args.seed)
        stop.on_line = faults.on_line
    buses, packing = [], bus_packing(sc, db)
    try:
        for i in range(sc.trains.count):
            buses.append(open_bus(args.run, i, gateway.ids_for_bus(i), sc.can, "RadioGW", packing=packing))
        clock = SimClock(handshake(stop), args.pace)
        bridge = RadioBridge(gateway, faults)
        kernel = bridge.kernel = PacedKernel(clock, node_frames(clock, buses, sc.can, packing), stop, bridge.on_frame,
                                             wake_on_frame=True)
        kernel.every(0, to_ns(IDLE_WAIT_S), bridge.idle)  # the kernel always has an event: it keeps listening
        kernel.at(to_ns(args.duration), bridge.idle)  # ... up to the end of the run
        kernel.run(to_ns(args.duration) + 1)
        linger(clock)
    except (ConnectionError, OSError) as exc:  # the bus server went away (its rig died): write what we have
        print(f"radio node: the bus went away: {exc}", file=sys.stderr)
    finally:
        for b in buses:
            b.shutdown()
    write_json_atomic(Path(args.out) / "radio.json",
               {"links": {name: dict(link.stats) for name, link in gateway.links.items()},
                "undelivered_queued": bridge.in_flight if "bridge" in locals() else 0, "scheduling": scheduling})
    return 0


class RadioBridge:
    """Frames heard on a bus go to the radio links; each delivery is a kernel event at its delivery time."""

    def __init__(self, gateway, faults) -> None:
        self.gateway, self.faults = gateway, faults
        self.kernel: PacedKernel  # set before the run starts
        self.in_flight = 0  # deliveries scheduled, not yet sent

    def on_frame(self, i: int, frame_id: int, data: bytes, t: float) -> None:
        if self.faults is not None:
            self.faults.apply_pending()
        for dst_bus, dst_id, payload, t_deliver in self.gateway.on_frame(i, frame_id, data, round(t * 1e9)):
            self.kernel.at(max(t_deliver, self.kernel.now), self.deliver, (dst_bus, dst_id, payload))
            self.in_flight += 1

    def deliver(self, item: tuple[int, int, bytes]) -> None:
        dst_bus, dst_id, payload = item
        self.in_flight -= 1
        self.kernel.io.send(dst_bus, [(dst_id, payload)])

    def idle(self, t_ns: int) -> None:
        """Every IDLE_WAIT_S: a stop request is noticed and pending fault lines are applied on a quiet radio."""
        if self.faults is not None:
            self.faults.apply_pending()


if __name__ == "__main__":
    sys.exit(main())

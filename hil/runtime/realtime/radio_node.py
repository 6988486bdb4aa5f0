"""Radio bridge process: the virtual rig's RadioGateway (same links, routes and seeded draws) between train buses.

    python -m hil.runtime.realtime.radio_node --run RUN --scenario-json FILE --seed N --duration S --pace F --out DIR

One process joins every train bus as "RadioGW" (acceptance filters = the gateway's routes from that bus). A
frame heard at simulated time t is offered to the radio links; each delivery is queued by its delivery time
and sent on the destination bus when the clock reaches it (a time-ordered heap, sleeping in between).
At the end it writes ``DIR/radio.json`` (the links' counters). One process for all pairs rather than one per
pair: the gateway is one routing table, as in the virtual rig.
"""
from __future__ import annotations

import heapq
import itertools
import sys
from pathlib import Path

from ecu_sim.codec import TrainDb
from hil.runtime.realtime.frame_io import node_frames
from hil.runtime.realtime.node import load_scenario_json, node_parser, open_bus, write_json
from hil.runtime.realtime.pacing import SimClock, StopFlag, handshake, linger, set_timer_slack
from hil.runtime.assembly import random_streams
from hil.runtime.virtual import build_gateway

IDLE_WAIT_S = 0.05  # simulated seconds between stop checks when nothing is due


def main(argv: list[str] | None = None) -> int:
    p = node_parser("python -m hil.runtime.realtime.radio_node", "Bridge adjacent train buses over the radio model.")
    args = p.parse_args(argv)
    stop = StopFlag()
    set_timer_slack(1)
    sc, db = load_scenario_json(args.scenario_json), TrainDb.load()
    gateway = build_gateway(sc, db, random_streams(args.seed)["radio"])
    faults = None
    if sc.faults:  # radio faults arrive as "fault <k> start|end" lines (hil/faults/realtime.py)
        from hil.faults.realtime import RadioNodeFaults

        faults = RadioNodeFaults(sc, gateway, args.seed)
        stop.on_line = faults.on_line
    buses = []
    try:
        for i in range(sc.trains.count):
            buses.append(open_bus(args.run, i, gateway.ids_for_bus(i), sc.can, "RadioGW"))
        clock = SimClock(handshake(stop), args.pace)
        queue: list[tuple[int, int, int, int, bytes]] = []  # (deliver_ns, seq, bus, id, data)
        seq = itertools.count()

        frames = node_frames(clock, buses, sc.can)

        def on_frame(i: int, frame_id: int, data: bytes, t: float) -> None:
            for dst_bus, dst_id, payload, t_deliver in gateway.on_frame(i, frame_id, data, round(t * 1e9)):
                heapq.heappush(queue, (t_deliver, next(seq), dst_bus, dst_id, payload))

        while not stop and clock.now() < args.duration:
            wait = IDLE_WAIT_S / clock.pace
            if queue:
                wait = min(wait, clock.wall_until(queue[0][0] * 1e-9))
            frames.wait_any(wait, on_frame)  # returns as soon as a frame arrives: its delivery may be due first
            if faults is not None:
                faults.apply_pending()
            now_ns = clock.now() * 1e9
            while queue and queue[0][0] <= now_ns:
                _, _, dst_bus, dst_id, payload = heapq.heappop(queue)
                frames.send(dst_bus, [(dst_id, payload)])
        linger(clock)
    except (ConnectionError, OSError) as exc:  # the bus server went away (its rig died): write what we have
        print(f"radio node: the bus went away: {exc}", file=sys.stderr)
    finally:
        for b in buses:
            b.shutdown()
    write_json(Path(args.out) / "radio.json",
               {"links": {name: dict(link.stats) for name, link in gateway.links.items()},
                "undelivered_queued": len(queue) if "queue" in locals() else 0})
    return 0


if __name__ == "__main__":
    sys.exit(main())

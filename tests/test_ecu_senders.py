"""A process hosting several ECUs sends each one as its own sender on its bus (its own TX queue there, as its own
CAN controller would have; issue 25): the senders are the units' ranks per bus, so no two units of one bus share one."""
from __future__ import annotations

from hil.runtime.realtime.ecu_node import senders


def test_each_hosted_unit_is_its_own_sender_on_its_bus():
    bus_of = {0: 0, 1: 0, 2: 0, 4: 1, 5: 1, 9: 2}  # a process hosting units of three trains
    sender = senders(bus_of, bus_of)
    assert sender == {0: 0, 1: 1, 2: 2, 4: 0, 5: 1, 9: 0}
    for bus in set(bus_of.values()):
        mine = [sender[u] for u in bus_of if bus_of[u] == bus]
        assert sorted(mine) == list(range(len(mine)))  # distinct, and 0 (the connection's own node) first


def test_a_process_of_one_unit_sends_as_the_connection_itself():
    assert senders([7], {7: 1}) == {7: 0}

"""Bus load never exceeds 1 (a sweep once showed bus_load_max = 1.0086). The cause was that a frame counted
wholly in the load window its transmission ends in: one that straddles a boundary put more than a window's time
into the later one. Each window now gets its own part of the frame, in both bus models."""
from __future__ import annotations

import numpy as np

from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario
from tests.oracle.python_rig import rig_on


def test_a_saturated_bus_reads_at_most_full_load_in_both_models():
    sc = load_scenario("seed000", {"can.bitrate": 125_000})  # ~680 kbit/s offered: the bus never idles
    loads = {}
    for model in ("engine", "python"):
        log = rig_on(model, sc).run(2.0)
        table = log.buses[0].load.array
        loads[model] = table
        assert table[:, 1].max() <= 1.0 + 1e-12, (model, table[:, 1].max())
        assert table[5:, 1].min() > 0.99, model  # saturated: every window (after the start) is full
    np.testing.assert_allclose(loads["engine"], loads["python"], rtol=0, atol=1e-12)

"""How each node process of a real-time run starts: python-can imported with its MF4 support deferred to its
first use (the rig's nodes write no CAN log; ``hil/deferred_mf4.py``: 0.5-0.9 s less per node where asammdf is
installed), then the node's module run as ``__main__`` with the arguments after its name::

    python -P -m hil.runtime.realtime.node_start hil.runtime.realtime.ecu_node --run RUN ...
"""
from __future__ import annotations

import runpy
import sys

from hil.deferred_mf4 import import_can_deferring_mf4


def main() -> None:
    """Run the module named by the first argument as ``__main__`` (its exit is the process's)."""
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m hil.runtime.realtime.node_start MODULE [ARGUMENT ...]")
    import_can_deferring_mf4()
    module = sys.argv.pop(1)
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()

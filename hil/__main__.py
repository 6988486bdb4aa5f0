"""The ``hil`` command (also ``python -m hil``): the command line of ``hil.cli``, started with python-can's MF4
support deferred to its first use, a run that writes MF4 (``hil/deferred_mf4.py``: 0.5-0.9 s less at every start
where asammdf is installed)."""
from __future__ import annotations

import sys

from hil.deferred_mf4 import import_can_deferring_mf4


def main() -> int:
    """Run ``hil`` with the process's arguments; its exit code."""
    import_can_deferring_mf4()
    from hil.cli import main as cli_main

    return cli_main()


if __name__ == "__main__":
    sys.exit(main())

"""python-can without its MF4 support until a run writes MF4.

python-can 4 imports asammdf as ``can`` is imported, wherever asammdf is installed (the ``mf4`` and ``dev``
extras): 0.5-0.9 s of CPU for pandas (and sympy, where installed) in every process, though only
``--can-log mf4`` uses it. The ``hil`` command and the real-time rig's node processes therefore import python-can
with asammdf held back (:func:`import_can_deferring_mf4`), and the run that writes MF4 loads it then
(:func:`enable_mf4`, called by ``hil.record.canlog.log_format``). Any other process (a user's script, pytest)
imports python-can as usual.
"""
from __future__ import annotations

import importlib
import sys


def import_can_deferring_mf4() -> None:
    """Import python-can with asammdf held back, so that its MF4 writer and reader say asammdf is unavailable
    until :func:`enable_mf4`. ``import asammdf`` works as usual afterwards. Nothing happens where python-can or
    asammdf is imported already."""
    if "can" in sys.modules or "asammdf" in sys.modules:
        return
    sys.modules["asammdf"] = None  # type: ignore[assignment]  # meanwhile, `import asammdf` raises ImportError
    try:
        import can  # noqa: F401
    finally:
        if "asammdf" in sys.modules and sys.modules["asammdf"] is None:
            del sys.modules["asammdf"]


def enable_mf4() -> None:
    """Give python-can its MF4 writer and reader if it was imported without them; ImportError where asammdf is
    not installed."""
    import asammdf  # noqa: F401
    import can.io.mf4

    if getattr(can.io.mf4, "asammdf", None) is None:
        # run the module again, now with asammdf: its classes (bound in `can` too) read these module globals
        importlib.reload(can.io.mf4)

"""python-can with its MF4 support loaded on first use.

python-can 4 imports asammdf as ``can`` is imported, wherever asammdf is installed (the ``mf4`` and ``dev``
extras): 0.5-0.9 s of CPU for pandas (and sympy, where installed) in every process, though only MF4 logs use it.
The ``hil`` command and the real-time rig's node processes therefore import python-can with asammdf held back
(:func:`import_can_deferring_mf4`); the first MF4 writer or reader made afterwards loads it (:func:`enable_mf4`),
whoever makes it: ``--can-log mf4``, or a user's firmware that logs MF4 through python-can inside a node. Any
other process (a user's script, pytest) imports python-can as usual.
"""
from __future__ import annotations

import functools
import importlib
import sys


def import_can_deferring_mf4() -> None:
    """Import python-can with asammdf held back; its MF4 writer and reader load asammdf when the first of them is
    made (``can.MF4Writer``, ``can.Logger("x.mf4")`` ...). ``import asammdf`` works as usual afterwards. Nothing
    happens where python-can or asammdf is imported already."""
    if "can" in sys.modules or "asammdf" in sys.modules:
        return
    sys.modules["asammdf"] = None  # type: ignore[assignment]  # meanwhile, `import asammdf` raises ImportError
    try:
        import can.io.mf4
    finally:
        if "asammdf" in sys.modules and sys.modules["asammdf"] is None:
            del sys.modules["asammdf"]
    for cls in (can.io.mf4.MF4Writer, can.io.mf4.MF4Reader):
        _enable_on_first_use(cls)


def _enable_on_first_use(cls: type) -> None:
    """Have ``cls`` (python-can's MF4 writer or reader, as ``can`` and its log-file tables bind it) load asammdf
    before it starts; where asammdf is not installed it says so itself, as python-can does without the deferral."""
    start = cls.__init__

    @functools.wraps(start)
    def __init__(self, *args, **kwargs) -> None:
        try:
            enable_mf4()
        except ImportError:
            pass
        start(self, *args, **kwargs)

    cls.__init__ = __init__  # type: ignore[misc]


def enable_mf4() -> None:
    """Give python-can its MF4 writer and reader if it was imported without them; ImportError where asammdf is
    not installed."""
    import asammdf  # noqa: F401
    import can.io.mf4

    if getattr(can.io.mf4, "asammdf", None) is None:
        # run the module again, now with asammdf: its classes (bound in `can` too) read these module globals
        importlib.reload(can.io.mf4)

"""trainhil's per-frame engine, compiled from the Rust crate in ``engine/`` (PyO3, built by maturin).

Everything that runs once per CAN frame lives here: exact frame timing, the DBC codec, E2E, the ECU input
mailboxes, the CAN bus model, the radio links and the virtual-time event kernel. The typed surface is
``_native.pyi``; the Rust sources document each piece.
"""
from trainhil_engine._native import *  # noqa: F401,F403
from trainhil_engine._native import __all__  # noqa: F401

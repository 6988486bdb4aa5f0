"""Errors every runtime shares."""
from __future__ import annotations


class RigDidNotStart(RuntimeError):
    """The rig could not start (a node, an external participant, a registry): nothing ran, nothing to recover.
    The message names what failed; metrics.json says ``"status": "failed"`` (hil/record/integrity.mark_failed)."""

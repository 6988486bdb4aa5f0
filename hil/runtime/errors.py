"""Errors every runtime shares."""
from __future__ import annotations


def os_words(exc: BaseException) -> str:
    """Why the OS refused, in its own words (``strerror``), else the exception's text or name."""
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__


class RigDidNotStart(RuntimeError):
    """The rig could not start (a node, an external participant, a registry): nothing ran, nothing to recover.
    The message names what failed; metrics.json says ``"status": "failed"`` (hil/record/integrity.mark_failed)."""

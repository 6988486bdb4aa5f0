"""Polling helper for tests that wait on another thread or process (a bus server, a client)."""
from __future__ import annotations

import time
from typing import Callable


def wait_for(pred: Callable[[], bool], timeout: float = 3.0) -> bool:
    """Poll ``pred`` every 10 ms until it is true or ``timeout`` seconds pass; its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return pred()

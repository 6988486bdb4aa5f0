"""argparse types shared by the ``hil`` commands: numbers that must be positive and finite, named in the error."""
from __future__ import annotations

import argparse
import math


def positive_int(text: str) -> int:
    """An argparse type: an integer > 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{value} must be > 0")
    return value


def _finite_positive(text: str, unit: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text} must be a finite number > 0{unit}")
    return value


def positive_number(text: str) -> float:
    """An argparse type: a finite number > 0 (a factor such as a pace)."""
    return _finite_positive(text, "")


def positive_seconds(text: str) -> float:
    """An argparse type: a positive, finite number of seconds (zero, negative, nan and inf are refused)."""
    return _finite_positive(text, " (seconds)")

"""hil.sample_table: a table interrupted anywhere in an append (a stop signal raises KeyboardInterrupt between two
bytecodes) still agrees with itself, so the metrics of an interrupted run can be computed (CI, 97bfda5 and 2d424eb:
a SIGHUP between the append and the cache reset left a stale array; the bus metrics failed with IndexError)."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from hil.sample_table import SampleTable


def interrupted_at_line(fn, k: int) -> bool:
    """Run ``fn()``, raising KeyboardInterrupt at its k-th line event inside hil/sample_table.py; whether it was."""
    seen = {"n": 0, "hit": False}

    def tracer(frame, event, _arg):
        if frame.f_code.co_filename.endswith("sample_table.py"):
            if event == "line":
                seen["n"] += 1
                if seen["n"] == k:
                    seen["hit"] = True
                    raise KeyboardInterrupt
            return tracer
        return None

    sys.settrace(tracer)
    try:
        fn()
    except KeyboardInterrupt:
        pass
    finally:
        sys.settrace(None)
    return seen["hit"]


@pytest.mark.parametrize("how", ["extend_bytes", "append"])
def test_an_append_interrupted_at_any_line_leaves_the_rows_and_their_array_in_agreement(how):
    k = 1
    while True:
        table = SampleTable(2)
        table.append((0.0, 1.0))
        assert table.array.shape == (1, 2)  # the array is cached now
        row = np.array([2.0, 3.0])
        if how == "extend_bytes":
            hit = interrupted_at_line(lambda: table.extend_bytes(row.tobytes()), k)
        else:
            hit = interrupted_at_line(lambda: table.append(row), k)
        assert len(table.array) == len(table), f"interrupted at line {k} of {how}"
        if not hit:
            break
        k += 1
    assert k > 2 and len(table) == 2  # every line was tried, and the last run appended

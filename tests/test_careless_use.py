"""Careless and hostile use, round three (issue 23): each test is one reproduction and what the user gets instead."""
from __future__ import annotations

import subprocess
import sys

from hil.runtime.realtime.orchestrator import Node


def test_a_node_that_prints_a_lot_is_drained_into_a_bounded_tail(tmp_path):
    """A law that prints on every step: the orchestrator reads the node's stdout as it comes and keeps only the
    last lines, so its memory does not grow with the output (the protocol lines still come through)."""
    code = "import sys\nfor i in range(200000): print('law says', i)\nprint('ready', flush=True)\nsys.stdin.read()"
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            bufsize=1)
    node = Node("chatty", "ecu", proc, tmp_path / "err")
    node.start_reader()
    try:
        assert node.lines.get(timeout=60) == "ready"
        assert node.printed_count == 200000
        assert list(node.printed)[-1] == "law says 199999" and len(node.printed) <= 20
        assert node.lines.empty()
    finally:
        proc.stdin.close()
        proc.wait(10)

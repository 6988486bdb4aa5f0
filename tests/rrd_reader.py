"""Read scalar series back from a .rrd with rerun's own Python API (no CLI, no network)."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader


def read_scalars(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """entity -> (sim_time s, value), concatenated over chunks and sorted by time."""
    parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = defaultdict(list)
    for ch in RrdReader(path).stream():
        rb = ch.to_record_batch()
        if "Scalars:scalars" not in rb.schema.names or "sim_time" not in rb.schema.names:
            continue
        t = rb.column("sim_time").cast("int64").to_numpy() * 1e-9
        v = np.array([row[0] for row in rb.column("Scalars:scalars").to_pylist()])
        parts[ch.entity_path].append((t, v))
    out = {}
    for entity, chunks in parts.items():
        t, v = np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])
        order = np.argsort(t, kind="stable")
        out[entity] = (t[order], v[order])
    return out

"""Read scalar series back from a .rrd with rerun's own Python API (no CLI, no network)."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader

from hil.record.reader import load_run


def read_scalars(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """entity -> (sim_time s, value), concatenated over chunks and sorted by time (the public reader's series)."""
    return dict(load_run(path).series)


def entity_columns(path: Path) -> dict[str, set[str]]:
    """entity -> every column (component and timeline) recorded on it, over all chunks of the recording."""
    out: dict[str, set[str]] = defaultdict(set)
    for ch in RrdReader(path).stream():
        out[ch.entity_path] |= set(ch.to_record_batch().schema.names)
    return dict(out)


def read_component(path: Path, entity: str, column: str, timeline: str = "sim_time") -> tuple[np.ndarray, list]:
    """(times in s, or ns for a timestamp timeline; per-row component values) of one entity's temporal rows."""
    times, values = [], []
    for ch in RrdReader(path).stream():
        if ch.entity_path != entity:
            continue
        rb = ch.to_record_batch()
        if column not in rb.schema.names or timeline not in rb.schema.names:
            continue
        times.append(rb.column(timeline).cast("int64").to_numpy())
        values += rb.column(column).to_pylist()
    t = np.concatenate(times) if times else np.zeros(0, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    scale = 1e-9 if timeline == "sim_time" else 1
    return t[order] * scale, [values[i] for i in order]


def read_text_rows(path: Path, prefix: str) -> dict[str, list[tuple[float, str, str]]]:
    """entity -> [(sim_time s, text, level)] of every TextLog row on entities under ``prefix``."""
    out: dict[str, list[tuple[float, str, str]]] = defaultdict(list)
    for ch in RrdReader(path).stream():
        if not ch.entity_path.startswith(prefix):
            continue
        rb = ch.to_record_batch()
        if "TextLog:text" not in rb.schema.names:
            continue
        t = rb.column("sim_time").cast("int64").to_numpy() * 1e-9
        for ti, text, level in zip(t, rb.column("TextLog:text").to_pylist(), rb.column("TextLog:level").to_pylist()):
            out[ch.entity_path].append((float(ti), text[0], level[0]))
    return dict(out)


def read_blueprint(path: Path) -> dict:
    """The default blueprint stored in the .rrd: its views (class, name, origin), container names, view queries
    and the time panel's timeline, read from the blueprint store with rerun's own reader."""
    reader = RrdReader(path)
    [blue] = reader.blueprints()
    views, containers, queries, timelines = [], set(), set(), set()
    for ch in reader.stream(store=blue):
        rb = ch.to_record_batch()
        names = rb.schema.names
        if "ViewBlueprint:class_identifier" in names:
            for cls, name, origin in zip(*(rb.column(f"ViewBlueprint:{c}").to_pylist()
                                           for c in ("class_identifier", "display_name", "space_origin"))):
                views.append((cls[0], name[0], origin[0]))
        if "ContainerBlueprint:display_name" in names:
            containers |= {n[0] for n in rb.column("ContainerBlueprint:display_name").to_pylist() if n}
        if "ViewContents:query" in names:
            queries |= {q for row in rb.column("ViewContents:query").to_pylist() for q in row}
        if "TimePanelBlueprint:timeline" in names:
            timelines |= {t[0] for t in rb.column("TimePanelBlueprint:timeline").to_pylist() if t}
    return {"application_id": blue.application_id, "views": views, "containers": containers, "queries": queries,
            "timelines": timelines}

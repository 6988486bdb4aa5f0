"""The packages form a layered graph: each imports only packages of lower layers (every import counts, also those
inside functions and under TYPE_CHECKING), so there is no cycle and a newcomer can read them bottom up."""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Lowest first. ecu_sim is firmware: it imports nothing of the rig.
LAYERS: list[list[str]] = [
    ["ecu_sim"],
    ["hil"],  # the package root: its version
    ["hil.fmi"],  # the reference FMUs' sources and their build
    ["hil.scenario"],  # the data model, the loader, the train layout, which firmware each unit runs
    ["hil.sample_table", "hil.reference_profile", "hil.radio", "hil.cli_values", "hil.deferred_mf4"],
    ["hil.can"],
    ["hil.record"],
    ["hil.plant"],
    ["hil.faults"],
    ["hil.silkit"],  # Vector SIL Kit: its runtime, the C API binding, participants, the CAN network simulator
    ["hil.runtime"],  # virtual time, the ideal loop, what both runtimes share, the virtual fault machinery
    ["hil.session", "hil.runtime.realtime"],  # a run to files, in virtual and in real time
    ["hil.compare", "hil.sweep", "hil.testing", "hil.viewer"],
    ["hil.commands"],  # the sub-commands of `hil` (compare, sweep, can-analysis),
    ["hil.cli"],
    ["hil.__main__"],  # the `hil` command: python-can with MF4 deferred, then the CLI
]


def package_of(module: str) -> str | None:
    """The layer unit a module belongs to: a subpackage of hil (hil.runtime.realtime on its own), a top-level hil
    module, ecu_sim; None outside the project."""
    parts = module.split(".")
    if parts[0] == "ecu_sim":
        return "ecu_sim"
    if parts[0] != "hil":
        return None
    if len(parts) == 1:
        return "hil"
    if parts[1] == "runtime" and len(parts) > 2 and parts[2] == "realtime":
        return "hil.runtime.realtime"
    return f"hil.{parts[1]}"


def import_edges() -> dict[tuple[str, str], str]:
    """(from package, to package) -> the first place it happens (file:line)."""
    edges: dict[tuple[str, str], str] = {}
    for path in sorted([*ROOT.glob("hil/**/*.py"), *ROOT.glob("ecu_sim/**/*.py")]):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        src = package_of(module)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets = [node.module]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                continue
            for target in targets:
                dst = package_of(target)
                if dst is not None and dst != src:
                    edges.setdefault((src, dst), f"{path.relative_to(ROOT)}:{node.lineno}")
    return edges


def test_every_package_has_a_layer():
    layer_of = {p: i for i, layer in enumerate(LAYERS) for p in layer}
    packages = {p for edge in import_edges() for p in edge}
    assert packages <= set(layer_of), f"packages without a layer: {sorted(packages - set(layer_of))}"


def test_each_package_imports_only_lower_layers():
    layer_of = {p: i for i, layer in enumerate(LAYERS) for p in layer}
    upward = [f"{src} -> {dst} ({where})" for (src, dst), where in import_edges().items()
              if layer_of[dst] >= layer_of[src]]
    assert not upward, "imports against the layering:\n" + "\n".join(upward)


def test_the_graph_has_no_cycle():
    """Implied by the layering, checked on its own so that a changed layer list cannot hide one."""
    graph: dict[str, set[str]] = defaultdict(set)
    for src, dst in import_edges():
        graph[src].add(dst)
    done: set[str] = set()

    def visit(node: str, path: tuple[str, ...]) -> None:
        assert node not in path, "import cycle: " + " -> ".join((*path, node))
        if node in done:
            return
        for nxt in sorted(graph[node]):
            visit(nxt, (*path, node))
        done.add(node)

    for start in sorted(graph):
        visit(start, ())

"""The engine's typed surface (trainhil_engine/_native.pyi) declares everything the compiled module exports."""
from __future__ import annotations

import ast
from pathlib import Path

import trainhil_engine as engine

STUB = Path(engine.__file__).with_name("_native.pyi")


def test_every_exported_name_and_public_member_is_in_the_stub():
    tree = ast.parse(STUB.read_text())
    top = {n.name: n for n in tree.body if isinstance(n, (ast.ClassDef, ast.FunctionDef))}
    top_vars = {n.target.id for n in tree.body if isinstance(n, ast.AnnAssign)}
    assert set(engine.__all__) <= set(top) | top_vars, set(engine.__all__) - set(top) - top_vars
    for name in engine.__all__:
        cls = getattr(engine, name)
        if not isinstance(cls, type):
            continue
        node = top[name]
        declared = {b.name for b in node.body if isinstance(b, ast.FunctionDef)} | \
                   {b.target.id for b in node.body if isinstance(b, ast.AnnAssign)}
        public = {a for a in dir(cls) if not a.startswith("_")}
        assert public <= declared, f"{name}: {sorted(public - declared)} not in {STUB.name}"


def test_the_stubs_all_is_the_modules():
    """The stub lists the exports literally, so a type checker sees what ``from trainhil_engine import *`` gives."""
    import ast
    from pathlib import Path

    import trainhil_engine as engine

    stub = ast.parse((Path(engine.__file__).parent / "_native.pyi").read_text())
    listed = next(node.value for node in stub.body if isinstance(node, ast.Assign)
                  and any(getattr(t, "id", None) == "__all__" for t in node.targets))
    assert [elt.value for elt in listed.elts] == list(engine.__all__)

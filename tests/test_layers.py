"""Imports run one way: CLI/batch -> fixtures -> reports -> flows -> stages, and no module cycles.

Walks every module's imports (function-level ones too) with ``ast``; a test that fails on
an import from a lower layer to a higher one, or on any import cycle between markcal modules.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"stages": "markcal.stages", "pipeline": "markcal.pipeline", "fixtures": "markcal.fixtures",
            "reports": "markcal.reports"}
#: layer of a module: it may import from its own layer and the ones below
FLOW_LEVEL = ("markcal.pipeline.flows", "markcal.pipeline.config", "markcal.pipeline.tables")
LAYERS = {"stages": 0, "flows": 1, "reports": 2, "fixtures": 3, "commands": 4}


def _modules() -> dict:
    mods = {}
    for folder, pkg in PACKAGES.items():
        for f in sorted((ROOT / folder).rglob("*.py")):
            rel = f.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([pkg, *parts])
            mods[name] = (f, f.name == "__init__.py")
    return mods


def _layer(mod: str) -> str:
    if mod.startswith("markcal.stages"):
        return "stages"
    if mod.startswith(FLOW_LEVEL):
        return "flows"
    if mod.startswith("markcal.reports"):
        return "reports"
    if mod.startswith("markcal.fixtures"):
        return "fixtures"
    return "commands"


def _imports(name: str, path: Path, is_pkg: bool, known: set) -> set:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    base = name if is_pkg else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                pkg = base.rsplit(".", node.level - 1)[0] if node.level > 1 else base
                mod = f"{pkg}.{node.module}" if node.module else pkg
            else:
                mod = node.module or ""
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            if t.startswith("markcal.") and t in known:
                out.add(t)
    return out - {name}


@pytest.fixture(scope="module")
def graph() -> dict:
    mods = _modules()
    return {m: _imports(m, p, pkg, set(mods)) for m, (p, pkg) in mods.items()}


def test_walk_finds_the_code(graph):
    assert "markcal.pipeline.registry" in graph and "markcal.stages.errors" in graph
    assert "markcal.reports.files" in graph["markcal.fixtures.scan_plate"]
    assert "markcal.stages.errors" in graph["markcal.pipeline.batch"]      # the walker sees imports


def test_no_import_from_a_higher_layer(graph):
    bad = [f"{m} ({_layer(m)}) imports {t} ({_layer(t)})" for m, ts in graph.items() for t in sorted(ts)
           if LAYERS[_layer(t)] > LAYERS[_layer(m)]]
    assert not bad, "\n".join(bad)


def test_no_import_cycles(graph):
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                cycles.append(" -> ".join(stack[stack.index(t):] + [t]))
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "\n".join(cycles)


def test_every_flow_registered_once_with_its_writer():
    from markcal.pipeline.registry import all_flows
    flows = all_flows()
    assert list(flows) == ["selfcal", "servo", "grid", "scan", "indents", "path", "pmcal"]
    for name, flow in flows.items():
        d = flow.descriptor
        assert d.name == name and flow.write.__name__.startswith("write_")
        assert set(d.trends) <= set(d.key_names), name
        for tk in d.tolerances:
            assert tk[4:] in d.key_names, (name, tk)

"""The package's layers, checked on its imports: every ``import`` in every module under difftex/
(function-local ones too, read with ast, so nothing is imported to check it) becomes an edge of a
module graph; the graph must have no cycle, and no edge may go from a lower layer to a higher one.

The layers, lowest first (docs/code-map.md describes what each holds):

    core        difftex (the package), errors, config, layout
    scene       difftex.scene        cameras, COLMAP, proxy, files, a scene folder
    geometry    difftex.geometry     frames, pinhole, meshing, ray casting, visibility, density, photo filter
    synth       difftex.synth        synthetic scenes (scene + geometry only)
    sampling    difftex.sampling     photos mapped into texel space, colour transfers
    method      difftex.method       the paper's per-polygon method
    compose     difftex.compose      brightness transfers, composition, the texturing stage, outputs
    export      difftex.export       atlas, OBJ / GLB, overlays
    evaluation  difftex.evaluation   metrics, held-out views, baselines, peers, report
    workflow    difftex.workflow     Snakemake glue, run lock, run log
    cli         difftex.cli          the commands

A module may import from its own layer and the layers below it. Besides, evaluation (baselines,
peers, metrics) imports nothing from the method: it shares photo sampling and composition only.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "difftex"

LAYERS = ["core", "scene", "geometry", "synth", "sampling", "method", "compose", "export", "evaluation",
          "workflow", "cli"]
PACKAGE_LAYER = {f"difftex.{name}": name for name in LAYERS if name != "core"}
CORE = {"difftex", "difftex.errors", "difftex.config", "difftex.layout"}
# (importer's layer, imported layer) pairs that the order would allow but the design does not
FORBIDDEN = {("evaluation", "method")}
MAX_LINES = 550  # about 500: a module much longer than this holds more than one concept; split it


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def layer_of(module: str) -> str:
    if module in CORE:
        return "core"
    if module == "difftex.__main__":
        return "cli"
    for package, layer in PACKAGE_LAYER.items():
        if module == package or module.startswith(package + "."):
            return layer
    raise AssertionError(f"{module}: in no layer; add it to tests/test_layers.py (LAYERS) and docs/code-map.md")


def imports_of(module: str) -> set[str]:
    """The difftex modules that ``module`` imports anywhere in its body."""
    path = MODULES[module]
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # ``from package import module`` imports the module; ``from module import name``, the module
            names = [f"{source}.{a.name}" if f"{source}.{a.name}" in MODULES else source for a in node.names]
        else:
            continue
        for name in names:
            while name and name not in MODULES and "." in name:
                name = name.rsplit(".", 1)[0]
            if name in MODULES and name.startswith("difftex") and name != module:
                out.add(name)
    return out


GRAPH = {m: imports_of(m) for m in MODULES}


def test_every_module_is_in_a_layer():
    for m in MODULES:
        layer_of(m)


def test_no_import_goes_up_a_layer():
    rank = {name: i for i, name in enumerate(LAYERS)}
    bad = []
    for m, deps in GRAPH.items():
        for d in deps:
            a, b = layer_of(m), layer_of(d)
            if rank[b] > rank[a] or (a, b) in FORBIDDEN:
                bad.append(f"{m} ({a}) imports {d} ({b})")
    assert not bad, "imports against the layers:\n" + "\n".join(sorted(bad))


def test_import_graph_has_no_cycle():
    # Tarjan's strongly connected components: any component of more than one module is a cycle
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(GRAPH[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_module_is_short(module):
    n = len(MODULES[module].read_text().splitlines())
    assert n <= MAX_LINES, f"{MODULES[module]}: {n} lines (at most {MAX_LINES}): split it by concept"


def test_the_graph_sees_function_local_imports():
    # difftex.cli imports its commands lazily (torch's import cost); the walk must still see them
    assert "difftex.cli.texture" in GRAPH["difftex.cli"] or any(
        "difftex.compose.texturing" in GRAPH[m] for m in GRAPH if m.startswith("difftex.cli."))

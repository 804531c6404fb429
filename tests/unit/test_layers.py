"""The package's layers: no import circle between modules, and no import that runs back up.

Read statically from the source (every ``import`` and ``from ... import``, at module level or
inside a function), so a lazy import counts as much as a top-level one. Physics and learning
apart is tests/unit/test_separation.py's (what a fresh interpreter brings in); this file is
the order of the folders.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest
from conftest import REPO

PACKAGE = REPO / "src" / "embodied_tactile"

#: bottom up; a module may import modules of its own layer or below. A prefix names a module
#: or a folder; the longest prefix that names a module decides its layer.
LAYERS: tuple[tuple[str, ...], ...] = (
    # facts and typed options, and the run's light helpers (JSON, paths, warnings, threads, pool workers)
    ("constants", "options", "model.options", "jsonio", "paths", "run.quiet", "run.threadenv", "run.workers"),
    # file formats and what the configs register: numpy and h5py, no torch
    ("data.rawformat", "data.modality", "data.statistics", "data.pendulum", "run.config"),
    ("sim",),  # the simulator writes the raw format
    ("data",),  # preprocessing, caches, the preparation stage (simulates missing trials)
    ("model",),  # the Latent Filter: reads modalities, never the data's files
    ("data.datamodule",),  # torch data over the caches
    ("run",),  # run folder, provenance, settings checks, training
    ("eval", "cli"),  # latents, alignment, baselines, tables; the Hydra entry checks
    ("active", "hardware"),  # palpation and acquisition: commands over a trained run / a port
    ("pages",),  # `embodied-tactile report`: every generated page, the active tables included
    ("__main__", ""),  # the one command and the package's face
)


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> int | None:
    """The layer of ``module`` (dotted, relative to the package): its longest matching prefix."""
    best: tuple[int, int] | None = None
    for rank, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if module == p or (p and module.startswith(p + ".")):
                if best is None or len(p) > best[1]:
                    best = (rank, len(p))
    return None if best is None else best[0]


def import_graph() -> dict[str, set[str]]:
    """module -> the package's modules it imports (a name imported from a package that is a
    module of it counts as that module)."""
    files = {module_name(f): f for f in PACKAGE.rglob("*.py")}

    def local(dotted: str) -> str:
        return dotted.removeprefix("embodied_tactile").lstrip(".")

    def resolve(dotted: str) -> str | None:
        while dotted not in files:
            if "." not in dotted:
                return None
            dotted = dotted.rpartition(".")[0]
        return dotted

    graph: dict[str, set[str]] = defaultdict(set)
    for name, path in files.items():
        here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = ".".join([*here[:len(here) - node.level + 1], *([node.module] if node.module else [])])
                    base = "embodied_tactile." + base if base else "embodied_tactile"
                else:
                    base = node.module or ""
                # `from pkg import mod` imports the module mod; `from pkg import name` the package
                targets = [f"{base}.{a.name}" if local(f"{base}.{a.name}") in files else base for a in node.names]
            else:
                continue
            for t in targets:
                if t == "embodied_tactile" or t.startswith("embodied_tactile."):
                    hit = resolve(local(t))
                    if hit is not None and hit != name and not name.startswith(hit + "."):
                        graph[name].add(hit)
        graph.setdefault(name, set())
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.mark.slow
def test_every_module_has_a_layer():
    assert [m for m in sorted(import_graph()) if layer(m) is None] == []


@pytest.mark.slow
def test_no_import_circle_and_none_runs_back_up():
    graph = import_graph()
    assert cycles(graph) == []
    up = [f"{m} (layer {layer(m)}) imports {t} (layer {layer(t)})"
          for m in sorted(graph) for t in sorted(graph[m]) if layer(t) > layer(m)]
    assert up == []


def test_the_checks_see_a_circle_and_an_upward_import():
    graph = {"data.cache": {"model.networks"}, "model.networks": {"data.cache"}, "constants": set()}
    assert cycles(graph) == [["data.cache", "model.networks"]]
    assert layer("data.cache") < layer("model.networks") and layer("data.datamodule") > layer("model.networks")
    assert layer("jsonio") < layer("data.cache") < layer("run.training") and layer("nowhere.module") is None


def test_the_package_top_level_holds_only_its_face_the_commands_and_the_bottom_helpers():
    """The face and the commands above every folder (the one command, its Hydra side, the
    report over eval/ and active/); below every folder the constants and the plain helpers
    that every folder may use (JSON, where the configs are)."""
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert top == ["__init__.py", "__main__.py", "cli.py", "constants.py", "jsonio.py", "pages.py", "paths.py"]
    assert layer("jsonio") == layer("paths") == layer("constants") == 0
    assert layer("pages") > layer("active.evaluation") and layer("pages") > layer("eval.study_report")

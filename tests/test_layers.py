"""The layers of ``pipeline/`` (its docstring) hold: a module imports only from its own
layer and the layers below it, and none imports the stages (``stages/``, above the
library: ``pipeline.workflow.stage_graph.run_stage`` runs one by its declared name).

The layer of a module is the package it sits in under ``pipeline/``; the test walks the
package directories, so a module added anywhere is checked the day it is added, and a
new top-level package or module must be given a layer here first."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

LAYERS = {"common": 0, "formats": 1, "method": 2, "evaluation": 3, "workflow": 4, "views": 5, "commands": 6}
STAGES_LAYER = 7
"""``stages/``: read through the plan (workflow), call the method, publish; above every
layer of ``pipeline/``, commands included, so no library module imports them (the
commands run them through the stage graph's ``run_stage``)."""


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``, relative ones resolved."""
    package = path.relative_to(ROOT).with_suffix("").parts[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(package[: len(package) - node.level + 1]) if node.level else ""
            module = ".".join(p for p in (base, node.module or "") if p)
            out.append((node.lineno, module))
            if node.module is None or module in ("pipeline", *(f"pipeline.{k}" for k in LAYERS)):
                out += [(node.lineno, f"{module}.{a.name}") for a in node.names]
    return out


def _layer_of(module: str) -> float | None:
    """The layer of an imported module name, None when it is not ours or not layered."""
    parts = module.split(".")
    if parts[0] == "stages":
        return STAGES_LAYER
    if parts[0] != "pipeline" or len(parts) < 2:
        return None
    return LAYERS.get(parts[1])


def _modules() -> list[tuple[Path, float]]:
    found = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        rel = path.relative_to(ROOT / "pipeline").parts
        if len(rel) == 1:  # pipeline/__init__.py and __main__.py only
            assert rel[0] in ("__init__.py", "__main__.py"), (
                f"pipeline/{rel[0]} sits outside the layers: put it in one of {sorted(LAYERS)}")
            found.append((path, LAYERS["commands"] if rel[0] == "__main__.py" else -1))
            continue
        assert rel[0] in LAYERS, f"pipeline/{rel[0]}/ is not a layer: add it to LAYERS (and pipeline/__init__.py)"
        found.append((path, LAYERS[rel[0]]))
    found += [(p, STAGES_LAYER) for p in sorted((ROOT / "stages").glob("*.py"))]
    return found


def test_every_module_imports_only_its_own_layer_and_those_below():
    bad = []
    for path, layer in _modules():
        for line, module in _imports(path):
            target = _layer_of(module)
            if target is not None and target > layer:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {module} (layer {target} > {layer})")
    assert bad == []


def test_the_check_sees_an_upward_import():
    # the rule is not vacuous: a method module importing the plan is caught
    assert _layer_of("pipeline.workflow.plan") > LAYERS["method"]
    assert _layer_of("stages.refine") > LAYERS["commands"]
    assert _layer_of("numpy") is None
    src = ROOT / "pipeline" / "method" / "scene_side.py"
    imported = {m for _, m in _imports(src)}
    assert "pipeline.common.config" in imported  # found, and resolved as an absolute name


def test_the_layers_are_the_packages_and_the_docstring_names_them():
    import pipeline

    packages = {p.name for p in (ROOT / "pipeline").iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages == set(LAYERS)
    for name in LAYERS:
        assert f"``pipeline.{name}``" in pipeline.__doc__, name

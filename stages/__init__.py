"""Pipeline stages: one module per stage with one entry point, ``run(plan, item)``.

A stage module reads its upstream artifacts (through ``plan.io(stage, item)``, which
refuses what the stage's declaration does not list), calls one library function that
holds the algorithm, and publishes its own artifact. Its declaration (code version,
items, reads, writes, and where its algorithm lives) is in
:mod:`pipeline.workflow.stage_graph`; bump the code version there whenever a change alters the
stage's output. Modules import their heavy dependencies inside ``run``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from pipeline.workflow.stage_graph import STAGES


def stage_module(stage: str) -> ModuleType:
    if stage not in STAGES:
        raise KeyError(f"unknown stage '{stage}' (known: {', '.join(STAGES)})")
    return importlib.import_module(STAGES[stage].module)


def run_stage(plan, stage: str, item: str, progress: bool = True) -> None:
    """Run ``stage`` for ``item`` of the dataset plan ``plan`` (what ``freeze stage`` and
    every Snakemake job call)."""
    stage_module(stage).run(plan, item, progress=progress)

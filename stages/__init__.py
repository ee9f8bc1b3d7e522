"""Pipeline stages: one module per stage, each with ``CODE_VERSION`` and ``run(plan, item)``.

A stage module reads its upstream artifacts, calls library functions from
``pipeline``, and publishes its own artifact. It holds no algorithm of its own. Modules
import their heavy dependencies inside ``run`` so that the Snakefile can read
``CODE_VERSION`` cheaply at DAG time. Bump ``CODE_VERSION`` whenever a change alters a
stage's output: it is part of the cache key.
"""

from __future__ import annotations

import importlib
from types import ModuleType

STAGE_MODULES = {
    "synth": "stages.synth",
    "render_templates": "stages.render_templates",
    "symmetries": "stages.symmetries",
    "model_features": "stages.model_features",
    "segment_prior": "stages.segment_prior",
    "scene_features": "stages.scene_features",
    "register": "stages.register",
    "refine": "stages.refine",
    "score": "stages.score",
}


def stage_module(stage: str) -> ModuleType:
    if stage not in STAGE_MODULES:
        raise KeyError(f"unknown stage '{stage}' (known: {', '.join(STAGE_MODULES)})")
    return importlib.import_module(STAGE_MODULES[stage])


def code_version(stage: str) -> int:
    return int(stage_module(stage).CODE_VERSION)

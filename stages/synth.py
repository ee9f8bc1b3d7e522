"""Stage synth: generate a synthetic BOP-format dataset (only for synthetic datasets).

Item ``dataset``: the BOP dataset folder ``<item>/<dataset name>/`` with its
localisation prior under ``detections/``.
"""

from __future__ import annotations

from pipeline.plan import DatasetPlan
from pipeline.store import publish

CODE_VERSION = 1


def run(plan: DatasetPlan, item: str = "dataset", progress: bool = True) -> None:
    from pipeline.synth import generate

    sp = plan["synth"]
    if item != "dataset":
        raise ValueError(f"stage synth has a single item 'dataset', not '{item}'")
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        summary = generate(w.dir / plan.name, plan.name, preset=plan.dataset.preset, seed=plan.dataset.seed, progress=progress)
        w.summary.update(summary)

"""Stage synth: generate a synthetic BOP-format dataset (only for synthetic datasets).

Item ``dataset``: the BOP dataset folder ``<item>/<dataset name>/`` with its
localisation prior under ``detections/``. Algorithm: :func:`pipeline.synth.generate`.
"""

from __future__ import annotations

from pipeline.plan import DatasetPlan


def run(plan: DatasetPlan, item: str = "dataset", progress: bool = True) -> None:
    from pipeline.synth import generate

    io = plan.io("synth", item)
    with io.publish() as w:
        w.summary.update(generate(w.dir / plan.name, plan.name, preset=plan.dataset.preset, seed=plan.dataset.seed,
                                  progress=progress))

"""Stage synth: build the dataset of a synthetic, semi-real or real-sample manifest (those only).

Item ``dataset``: the BOP dataset folder ``<item>/<dataset name>/`` with its
localisation prior under ``detections/``. Algorithm: :func:`pipeline.evaluation.synth.build_dataset`
(the generator, :func:`pipeline.evaluation.synth.generate`, or the semi-real builder,
:func:`pipeline.evaluation.synth.build_semireal`, which reads the real sample ``source``, or :func:`pipeline.evaluation.synth.build_real`,
which copies a real sample and writes its two priors).
"""

from __future__ import annotations

from pipeline.workflow.plan import DatasetPlan


def run(plan: DatasetPlan, item: str = "dataset", progress: bool = True) -> None:
    from pipeline.evaluation.synth import build_dataset

    io = plan.io("synth", item)
    source = io.source_dir if plan.dataset.kind in ("semireal", "real") else None
    with io.publish() as w:
        w.summary.update(build_dataset(plan.dataset, w.dir / plan.name, source=source, progress=progress))

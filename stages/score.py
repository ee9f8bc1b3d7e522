"""Stage score: BOP19 evaluation of the results CSV -> ``errors.parquet`` + ``scores.json``.

``errors.parquet`` holds one row per (estimate, ground-truth instance) with MSSD (mm),
MSPD (px) and VSD per tau; ``scores.json`` holds AR, AR_VSD, AR_MSSD, AR_MSPD and the
counts, computed by :func:`pipeline.metrics.score_results_file` (also behind
``freeze score``).
"""

from __future__ import annotations

from pipeline.plan import DatasetPlan
from pipeline.store import publish

CODE_VERSION = 2


def run(plan: DatasetPlan, item: str = "all", progress: bool = True) -> None:
    from pipeline.metrics import score_results_file

    if item != "all":
        raise ValueError(f"score has a single item 'all', not '{item}'")
    sp = plan["score"]
    p = plan.run.stages.score
    csv = plan["refine"].item_dir("all") / plan.results_csv_name
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        scores = score_results_file(csv, plan.root, split=plan.dataset.split,
                                    targets_file=plan.root / plan.dataset.targets_file,
                                    out_dir=w.dir, n_workers=p.n_workers, vsd_delta=plan.dataset.vsd_delta,
                                    progress=progress)
        w.summary.update(scores.summary)

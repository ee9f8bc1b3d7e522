"""Stage score: BOP19 evaluation of the results CSV -> ``errors.parquet`` + ``scores.json``.

``errors.parquet`` holds one row per (estimate, ground-truth instance) with MSSD (mm),
MSPD (px) and VSD per tau; ``scores.json`` holds AR, AR_VSD, AR_MSSD, AR_MSPD and the
counts. Algorithm: :func:`pipeline.evaluation.metrics.score_results_file` (also behind
``freeze score``).

Datasets whose test ground truth is private (ITODD, HB: no ``scene_gt.json`` in the
distributed test split) cannot be scored here: when a target scene has no
``scene_gt.json``, ``scores.json`` says so (:func:`pipeline.evaluation.metrics.evaluate.unscored_summary`),
with AR left empty, and the results CSV is the file to submit to the BOP evaluation server.

A results CSV with an R that is not a rotation (:data:`pipeline.evaluation.metrics.ROTATION_TOLERANCE`)
fails the stage in both cases, with the message of ``freeze score`` (one line naming the
file, the number of bad rows and the first one), and nothing is published: scoring it
would give numbers that mean nothing, submitting it a rejected file.

The images' errors go to the dask cluster the run names (``dask_scheduler``, else
``$DASK_SCHEDULER_ADDRESS``), else to ``score.n_workers`` processes of this job
(:mod:`pipeline.common.parallel`).
"""

from __future__ import annotations

import json

from pipeline.workflow.plan import DatasetPlan, missing_ground_truth
from pipeline.common.store import read_manifest

THREADS_HELP = True
"""The images run on the job's threads (dask's threaded scheduler) when no dask scheduler is
named: faster here (``benchmarks/results/dask.md``). Snakemake's rule gives the job one
thread (``stage_graph``), so there they run one after the other; ``freeze stage``
without ``--threads`` and ``freeze estimate`` use every core."""


def run(plan: DatasetPlan, item: str = "all", progress: bool = True) -> None:
    from pipeline.evaluation.metrics import score_results_file
    from pipeline.evaluation.metrics.evaluate import unscored_summary
    from pipeline.common.parallel import job_mapper

    io = plan.io("score", item)
    csv = io.input_dir("refine") / plan.results_csv_name
    bop = io.bop()
    missing = missing_ground_truth(bop, plan.scene_ids)
    with io.publish() as w:
        if missing:
            why = ("the test ground truth of this dataset is not public" if not plan.dataset.public_gt
                   else f"{len(missing)} target scene(s) have no scene_gt.json (first: {missing[0]})")
            summary = unscored_summary(csv, bop.targets(plan.root / plan.dataset.targets_file), why)
            w.path("scores").write_text(json.dumps({"summary": summary}, indent=1) + "\n")
            w.summary.update(summary)
            return
        with job_mapper(plan.run.dask_scheduler, THREADS_HELP) as mapper:
            scores = score_results_file(csv, plan.root, split=plan.dataset.split, split_type=plan.dataset.split_type,
                                        targets_file=plan.root / plan.dataset.targets_file,
                                        out_dir=w.dir, n_workers=io.params.n_workers,
                                        vsd_delta=plan.dataset.vsd_delta, progress=progress, mapper=mapper)
        w.summary.update(scores.summary)
        # Why there were no estimates (refine's note) belongs next to the AR it explains.
        upstream_notes = read_manifest(io.input_dir("refine")).get("summary", {}).get("notes") or []
        if upstream_notes:
            w.summary["notes"] = list(upstream_notes) + list(w.summary.get("notes") or [])

"""Stage score: BOP19 evaluation of the results CSV -> ``errors.parquet`` + ``scores.json``.

``errors.parquet`` holds one row per (estimate, ground-truth instance) with MSSD (mm),
MSPD (px) and VSD per tau; ``scores.json`` holds AR, AR_VSD, AR_MSSD, AR_MSPD and the
counts, computed by :func:`pipeline.metrics.score_results_file` (also behind
``freeze score``).

Datasets whose test ground truth is private (ITODD, HB: no ``scene_gt.json`` in the
distributed test split) cannot be scored here: when a target scene has no
``scene_gt.json``, ``scores.json`` says so, with AR left empty, and the results CSV is
the file to submit to the BOP evaluation server.
"""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.plan import DatasetPlan, missing_ground_truth
from pipeline.store import publish

CODE_VERSION = 2


def unscored_summary(plan: DatasetPlan, bop, csv: Path, missing: list[Path]) -> dict:
    """What ``scores.json`` says of a dataset without public ground truth: counts, the
    BOP time per image, and where the CSV for the BOP server is."""
    from pipeline.bop import read_results_csv
    from pipeline.metrics.evaluate import mean_time_per_image

    df = read_results_csv(csv)
    targets = bop.targets(plan.root / plan.dataset.targets_file)
    why = ("the test ground truth of this dataset is not public" if not plan.dataset.public_gt
           else f"{len(missing)} target scene(s) have no scene_gt.json (first: {missing[0]})")
    return {
        "status": "no_ground_truth",
        "AR": None, "AR_VSD": None, "AR_MSSD": None, "AR_MSPD": None,
        "n_targets": int(sum(t.inst_count for t in targets)),
        "n_estimates": int(len(df)),
        "mean_time_per_image": mean_time_per_image(df),
        "results_file": str(csv),
        "notes": [f"not scored: {why}; submit {csv} to the BOP evaluation server (bop.felk.cvut.cz)"],
    }


def run(plan: DatasetPlan, item: str = "all", progress: bool = True) -> None:
    from pipeline.metrics import score_results_file

    if item != "all":
        raise ValueError(f"score has a single item 'all', not '{item}'")
    sp = plan["score"]
    p = plan.run.stages.score
    csv = plan["refine"].item_dir("all") / plan.results_csv_name
    bop = plan.bop()
    missing = missing_ground_truth(bop, plan.scene_ids)
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        if missing:
            summary = unscored_summary(plan, bop, csv, missing)
            (w.dir / "scores.json").write_text(json.dumps({"summary": summary}, indent=1) + "\n")
            w.summary.update(summary)
            return
        scores = score_results_file(csv, plan.root, split=plan.dataset.split, split_type=plan.dataset.split_type,
                                    targets_file=plan.root / plan.dataset.targets_file,
                                    out_dir=w.dir, n_workers=p.n_workers, vsd_delta=plan.dataset.vsd_delta,
                                    progress=progress)
        w.summary.update(scores.summary)

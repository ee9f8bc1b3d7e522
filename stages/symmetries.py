"""Stage symmetries: the geometric symmetries of one object -> ``symmetries.json``.

Estimated from the model's shape alone (algorithm: :func:`pipeline.method.model_side.symmetry_record`,
over :func:`pipeline.method.geometry.symmetry.estimate_symmetries`): the symmetry-aware
refinement needs the transforms that leave the *shape* unchanged, including those a
texture breaks (which BOP's ``models_info.json`` does not declare, since it describes
the symmetries that matter for evaluation).

``symmetries.json``: ``estimated`` (BOP models_info form: ``symmetries_discrete`` as 16
row-major floats with mm translations, ``symmetries_continuous`` as axis + offset mm),
``declared`` (the same form, from the dataset's models_info, for comparison),
``n_discrete``, ``n_continuous``, ``threshold_mm`` (acceptance threshold),
``rejected_best_mm`` (score of the best rejected candidate: the margin), ``seconds``.
"""

from __future__ import annotations

import json

from pipeline.workflow.plan import DatasetPlan


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.method.geometry.symmetry import SymmetrySet
    from pipeline.method.model_side import symmetry_record

    io = plan.io("symmetries", item)
    obj_id, p = io.item_id(), io.params
    bop = io.bop()
    info = plan.model_info(bop, obj_id)
    _, doc = symmetry_record(bop.load_model(obj_id), info.diameter, n_points=p.n_points,
                             sample_seed=io.seed(item, p.seed), threshold=p.threshold, seed=p.seed,
                             declared=SymmetrySet.from_model_info(info), obj_id=obj_id)
    with io.publish() as w:
        w.path("symmetries").write_text(json.dumps(doc, indent=1) + "\n")
        w.summary.update({k: doc[k] for k in ("obj_id", "n_discrete", "n_continuous", "threshold_mm", "rejected_best_mm")})

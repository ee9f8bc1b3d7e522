"""Stage symmetries: the geometric symmetries of one object -> ``symmetries.json``.

Estimated from the model's shape alone (:func:`pipeline.geometry.symmetry.estimate_symmetries`):
the symmetry-aware refinement needs the transforms that leave the *shape* unchanged,
including those a texture breaks (which BOP's ``models_info.json`` does not declare,
since it describes the symmetries that matter for evaluation).

``symmetries.json``: ``estimated`` (BOP models_info form: ``symmetries_discrete`` as 16
row-major floats with mm translations, ``symmetries_continuous`` as axis + offset mm),
``declared`` (the same form, from the dataset's models_info, for comparison),
``n_discrete``, ``n_continuous``, ``threshold_mm`` (acceptance threshold),
``rejected_best_mm`` (score of the best rejected candidate: the margin), ``seconds``.
"""

from __future__ import annotations

import json

from pipeline.plan import DatasetPlan, item_id
from pipeline.store import item_seed, publish

CODE_VERSION = 1


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.geometry.symmetry import SymmetrySet
    from pipeline.model_side import symmetry_record

    obj_id = item_id(item, "obj", "symmetries")
    sp = plan["symmetries"]
    p = plan.run.stages.symmetries
    bop = plan.bop()
    info = plan.model_info(bop, obj_id)
    _, doc = symmetry_record(bop.load_model(obj_id), info.diameter, n_points=p.n_points,
                             sample_seed=item_seed(sp.key, item, p.seed), threshold=p.threshold, seed=p.seed,
                             declared=SymmetrySet.from_model_info(info), obj_id=obj_id)
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        (w.dir / "symmetries.json").write_text(json.dumps(doc, indent=1) + "\n")
        w.summary.update({k: doc[k] for k in ("obj_id", "n_discrete", "n_continuous", "threshold_mm", "rejected_best_mm")})


def load_symmetries(plan: DatasetPlan, obj_id: int):
    """The estimated :class:`~pipeline.geometry.symmetry.SymmetrySet` of ``obj_id``."""
    from pipeline.geometry.symmetry import SymmetrySet
    from pipeline.plan import obj_item

    path = plan["symmetries"].item_dir(obj_item(obj_id)) / "symmetries.json"
    return SymmetrySet.from_dict(json.loads(path.read_text())["estimated"])

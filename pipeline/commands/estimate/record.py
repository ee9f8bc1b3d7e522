"""``pose.json`` of ``freeze estimate``: the estimate of the frame's one candidate, read
back from the artifacts the stages published, with the numbers behind it."""

from __future__ import annotations

import json
import math
import re
from typing import Any, Mapping

import numpy as np

from .inputs import EstimateError


def _one(table, what: str) -> Any:
    if len(table) != 1:
        raise EstimateError(f"{what}: expected one row for the frame's candidate, found {len(table)}")
    return table.iloc[0]


def candidate_record(plan, frame) -> dict[str, Any]:
    """The estimate of the wrapped ``frame`` (a :class:`pipeline.commands.estimate.frame.FrameDataset`)
    from the artifacts of ``plan`` (its :class:`pipeline.workflow.plan.DatasetPlan`).

    Keys: R (3, 3) and t (3,) mm model-to-camera, evidence (RANSAC inlier ratio x ICP
    fitness), n_inliers, inlier_ratio, ransac_fitness, n_correspondences, fitness (ICP),
    inlier_rmse_mm, sar_variant / sar_reason / sar_n_variants / sar_scores, n_valid_points,
    n_points, the chosen hypothesis (its source, index and parent, verification terms,
    whether the fine ICP kept its pose, the fusion weights) and every hypothesis' score,
    coarse and icp poses, and the symmetry counts. For a turn (source ``turn``, see
    :mod:`pipeline.method.refinement.turns`) the RANSAC numbers and the coarse pose are those
    of the hypothesis it turned (its parent). Raises EstimateError, with
    the stage's reason, when the candidate was skipped or got no pose.
    """

    scene, obj = frame.scene_item(), frame.obj_item()
    sf = _one(plan["scene_features"].table(scene, "candidate_status"), "scene_features")
    if sf.status != "ok":
        raise EstimateError(f"the candidate was skipped: {sf.reason} (scene_features.min_points); check the mask or "
                            "box, the depth image and --depth-scale")
    refined = _one(plan["refine"].table(scene, "candidate_choices"), "refine")
    hyps = plan["register"].table(scene, "coarse_hypotheses")
    # A turn (refine's source "turn") has no row in register's table: its parent has.
    registered_hyp = int(refined.parent) if int(refined.parent) >= 0 else int(refined.hyp)
    reg = _one(hyps[hyps.hyp == registered_hyp], "register (the chosen hypothesis)")
    verified = plan["refine"].table(scene, "hypotheses")
    poses = plan["refine"].table(scene, "poses")
    if len(poses) == 0:
        raise EstimateError(f"refine kept no estimate: {refined.note or 'see ' + str(plan['refine'].item_dir(scene))}")
    pose = _one(poses, "refine poses")
    sar = plan["refine"].table(scene, "sar")
    sym = json.loads(plan["symmetries"].path(obj, "symmetries").read_text())
    return {
        "R": np.asarray(pose.R, float).reshape(3, 3), "t": np.asarray(pose.t, float),
        "evidence": float(refined.evidence),
        "n_inliers": int(reg.n_inliers), "inlier_ratio": float(reg.inlier_ratio),
        "ransac_fitness": float(reg.ransac_fitness), "n_correspondences": int(reg.n_correspondences),
        "fitness": float(refined.fitness), "inlier_rmse_mm": float(refined.inlier_rmse),
        "sar_variant": int(pose.sar_variant), "sar_reason": str(pose.sar_reason),
        "sar_n_variants": int(len(sar)), "sar_scores": [float(s) for s in sar.similarity],
        "n_valid_points": int(sf.n_valid_points), "n_points": int(sf.n_points),
        "hypothesis": {"source": str(refined.source), "index": int(refined.hyp), "parent": int(refined.parent),
                       "verification": {k: float(refined[k]) for k in
                                        ("silhouette", "depth_fit", "coverage", "free_space", "verification")},
                       "fine_icp": bool(refined.fine_icp),
                       "fusion_weights": {"geometric": float(reg.w_geometric), "visual": float(reg.w_visual)}},
        "hypotheses": [{"source": str(h.source), "verification": float(h.verification), "evidence": float(h.evidence),
                        "chosen": bool(h.chosen)} for h in verified.itertuples()],
        "coarse": {"R": np.asarray(reg.R, float).reshape(3, 3).tolist(), "t": np.asarray(reg.t, float).tolist()},
        "icp": {"R": np.asarray(refined.R, float).reshape(3, 3).tolist(), "t": np.asarray(refined.t, float).tolist()},
        "n_discrete_symmetries": int(sym["n_discrete"]), "n_continuous_symmetries": int(sym["n_continuous"]),
    }


def jsonable(obj: Any) -> Any:
    """Plain JSON values (numpy scalars and arrays converted; NaN and infinities -> None)."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [jsonable(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(record: Mapping[str, Any]) -> str:
    """Indented JSON with each innermost list of numbers on one line (matrix rows stay readable)."""
    text = json.dumps(jsonable(record), indent=1, allow_nan=False)
    return re.sub(r"\[\s+([-+0-9.eE,\s]+?)\s+\]", lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]",
                  text) + "\n"

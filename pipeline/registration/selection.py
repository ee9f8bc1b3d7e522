"""Choosing among registered candidates, and the score of an estimate."""

from __future__ import annotations

from typing import Sequence

import pandas as pd


def select_per_target(candidates: pd.DataFrame, targets: Sequence) -> pd.DataFrame:
    """Per target (scene, image, object) keep the ``inst_count`` candidates with the most
    RANSAC inliers (the paper keeps the single best; BOP asks for ``inst_count``
    estimates). Ties go to the higher prior score. Adds a ``rank`` column (0 = best)."""
    want = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in targets}
    if candidates.empty:
        return candidates.assign(rank=pd.Series(dtype="int64"))
    ordered = candidates.sort_values(["scene_id", "im_id", "obj_id", "n_inliers", "prior_score", "cand_id"],
                                     ascending=[True, True, True, False, False, True])
    ordered = ordered.assign(rank=ordered.groupby(["scene_id", "im_id", "obj_id"]).cumcount())
    limit = ordered.apply(lambda r: want.get((r.scene_id, r.im_id, r.obj_id), 0), axis=1)
    return ordered[ordered["rank"] < limit].reset_index(drop=True)


def estimate_score(inlier_ratio: float, fitness: float) -> float:
    """Confidence of a refined estimate in [0, 1]: the RANSAC inlier ratio of its
    candidate times the ICP fitness (fraction of scene points with a model point
    within the final correspondence distance). BOP's matching keeps the top-scored
    estimates per (image, object), so both kinds of evidence should raise it."""
    return float(max(0.0, min(1.0, inlier_ratio)) * max(0.0, min(1.0, fitness)))

"""Choosing among refined candidates, and the evidence of an estimate."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd


def registration_evidence(inlier_ratio: float, fitness: float) -> float:
    """Evidence for a refined estimate, in [0, 1]: the RANSAC inlier ratio of its
    candidate times the ICP fitness (fraction of scene points with a model point
    within the final correspondence distance). BOP's matching keeps the top-scored
    estimates per (image, object), so both kinds of evidence should raise it."""
    return float(max(0.0, min(1.0, inlier_ratio)) * max(0.0, min(1.0, fitness)))


SELECT_BY_COLUMN = {"verification": "verification", "evidence": "evidence", "inliers": "n_inliers",
                "prior": "prior_score", "fitness": "fitness"}
"""The column each ranking rule of :func:`select_estimates` sorts by."""


def select_estimates(
    candidates: pd.DataFrame,
    targets: Sequence,
    diameters: dict[int, float],
    *,
    by: str = "evidence",
    duplicate_frac: float = 0.25,
) -> pd.DataFrame:
    """Choose up to ``inst_count`` distinct estimates per target among refined candidates.

    candidates: one row per registered candidate with scene_id, im_id, obj_id, cand_id,
    t (3 floats, mm), evidence (:func:`registration_evidence`), n_inliers and prior_score.
    Candidates of a target are taken in order of ``by`` (``"verification"``: the
    verification score, :mod:`pipeline.method.refinement.verification`; ``"evidence"``: the evidence;
    ``"inliers"``: RANSAC inliers, the paper's rule; ``"prior"``: the localisation
    prior's confidence; ``"fitness"``: the ICP fitness alone), ties broken by the
    evidence, inliers and prior score and then cand_id; a candidate
    whose translation lies within ``duplicate_frac * diameter`` of one already kept for
    the target is a duplicate hypothesis of the same instance and is skipped.

    Returns ``candidates`` with ``selected`` (bool), ``target_rank`` (0 = best kept, -1 when
    not kept) and ``note`` (why a candidate was not kept: ``duplicate of N``,
    ``beyond inst_count``, ``not a target``).
    """
    if by not in SELECT_BY_COLUMN:
        raise ValueError(f"select_estimates: 'by' must be one of {sorted(SELECT_BY_COLUMN)}, got {by!r}")
    want = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in targets}
    out = candidates.copy()
    out["selected"] = False
    out["target_rank"] = -1
    out["note"] = ""
    if out.empty:
        return out
    keys = [SELECT_BY_COLUMN[by]] + [c for c in ("evidence", "n_inliers", "prior_score") if c != SELECT_BY_COLUMN[by]]
    ordered = out.sort_values(["scene_id", "im_id", "obj_id", *keys, "cand_id"],
                              ascending=[True, True, True] + [False] * len(keys) + [True])
    for (scene_id, im_id, obj_id), group in ordered.groupby(["scene_id", "im_id", "obj_id"], sort=False):
        limit = want.get((int(scene_id), int(im_id), int(obj_id)), 0)
        radius = duplicate_frac * diameters[int(obj_id)]
        kept: list[tuple[int, np.ndarray]] = []
        for idx, row in group.iterrows():
            t = np.asarray(row["t"], dtype=np.float64)
            if limit == 0:
                out.at[idx, "note"] = "not a target"
                continue
            dup = next((c for c, tk in kept if np.linalg.norm(t - tk) < radius), None)
            if dup is not None:
                out.at[idx, "note"] = f"duplicate of {dup}"
            elif len(kept) >= limit:
                out.at[idx, "note"] = "beyond inst_count"
            else:
                out.at[idx, "selected"] = True
                out.at[idx, "target_rank"] = len(kept)
                kept.append((int(row["cand_id"]), t))
    return out

"""Which GT instances count as targets, and greedy matching of estimates to them.

Both follow the BOP toolkit's 6D localisation evaluation (``eval_calc_scores.py``):
estimates are taken in order of decreasing score, and each takes the not-yet-matched
valid GT instance of its object with the lowest error strictly below the threshold.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np


def valid_gt_mask(
    gt_obj_ids: Sequence[int],
    visib_fracts: Sequence[float],
    inst_counts: Mapping[int, int],
    visib_gt_min: float = -1.0,
) -> np.ndarray:
    """Which GT instances of one image are targets; (G,) bool.

    gt_obj_ids / visib_fracts: per GT instance (scene_gt order).
    inst_counts: obj_id -> inst_count of this image's targets (objects absent here
    are not targets).
    visib_gt_min < 0 (the toolkit's BOP19 default): the ``inst_count`` most visible
    instances of each target object are valid (ties: lower gt_id first). With the
    official BOP19 targets, whose ``inst_count`` counts the instances at least 10%
    visible, this keeps exactly those.
    visib_gt_min >= 0: every instance of a target object with at least this visible
    fraction is valid.
    """
    n = len(gt_obj_ids)
    valid = np.zeros(n, dtype=bool)
    if visib_gt_min >= 0:
        for g in range(n):
            valid[g] = gt_obj_ids[g] in inst_counts and visib_fracts[g] >= visib_gt_min
        return valid
    to_add = {int(k): int(v) for k, v in inst_counts.items()}
    order = sorted(range(n), key=lambda g: visib_fracts[g], reverse=True)
    for g in order:
        obj = int(gt_obj_ids[g])
        if to_add.get(obj, 0) > 0:
            valid[g] = True
            to_add[obj] -= 1
    return valid


def greedy_match(errors: np.ndarray, valid: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Greedy matching for K independent settings at once.

    errors: (E, G, K) float, error of estimate e w.r.t. GT g under setting k, with the
    estimates already in matching order (decreasing score, stable); NaN/inf never match.
    valid: (G,) bool, GT instances that may be matched.
    thresholds: (K,) correctness thresholds (error must be strictly below).
    Returns (K, E) int64: matched GT index per estimate, -1 if none.
    """
    errors = np.asarray(errors, dtype=np.float64)
    E, G, K = errors.shape
    thresholds = np.asarray(thresholds, dtype=np.float64).reshape(K)
    matched = np.full((K, E), -1, dtype=np.int64)
    taken = np.zeros((K, G), dtype=bool)
    ks = np.arange(K)
    for e in range(E):
        err = errors[e].T  # (K, G)
        ok = (err < thresholds[:, None]) & valid[None, :] & ~taken
        # argmin returns the first minimum: ties go to the lower gt index, as in the
        # toolkit's strict "<" scan.
        best = np.where(ok, err, np.inf).argmin(1)
        hit = ok[ks, best]
        matched[hit, e] = best[hit]
        taken[ks[hit], best[hit]] = True
    return matched

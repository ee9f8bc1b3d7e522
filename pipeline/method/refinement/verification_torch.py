"""The verification terms of several poses at once, in torch on the run's device (issue
31's GPU scene side).

:func:`compare_depth_batch` computes what
:func:`pipeline.method.refinement.verification.compare_depth` computes, for B rendered
windows of one candidate (they share its window, so they stack into one (B, h, w)
tensor) against the one observed window and mask: the same masks, the same integer
counts, and the same float64 ratios, so the terms are equal to the bit
(``tests/test_verification_torch.py``). The renders themselves come from OpenGL (EGL,
the GPU of an NVIDIA machine) and are read back by pyrender; this moves the comparison
of a candidate's hypotheses into one set of tensor operations beside the torch ICP,
instead of B numpy passes.

On a CPU the numpy comparison stays the path the pipeline takes: one window is a few
hundred microseconds there, and torch's per-call overhead over a dozen small windows
buys nothing (``benchmarks/scene_paths.py`` times both).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.method.refinement.verification import Verification, verification_score


def compare_depth_batch(rendered: np.ndarray | Sequence[np.ndarray], observed: np.ndarray, mask: np.ndarray,
                        tol: float, evidence: Sequence[float], device: str = "cuda") -> list[Verification]:
    """The terms of B poses from aligned windows, computed on ``device``: rendered
    (B, h, w) float32 mm (0 off the model), observed (h, w) float32 mm (0 where the
    sensor has no depth), mask (h, w) bool (the candidate's), tol mm, evidence (B,)
    (each pose's feature evidence). One :class:`Verification` per pose, in order."""
    import torch

    rendered = np.asarray(rendered, dtype=np.float32)
    B = len(rendered)
    if rendered.ndim != 3 or rendered.shape[1:] != np.shape(observed) or np.shape(mask) != np.shape(observed):
        raise ValueError(f"compare_depth_batch: windows differ: rendered {rendered.shape}, observed "
                         f"{np.shape(observed)}, mask {np.shape(mask)}")
    evidence = [float(e) for e in evidence]
    if len(evidence) != B:
        raise ValueError(f"compare_depth_batch: {len(evidence)} evidence values for {B} renders")
    if B == 0:
        return []
    # The tolerance as float32, as numpy compares a float32 array with a Python float.
    tol32 = float(np.float32(tol))
    r = torch.as_tensor(rendered, device=device)
    o = torch.as_tensor(np.asarray(observed, dtype=np.float32), device=device)[None]
    m = torch.as_tensor(np.asarray(mask, dtype=bool), device=device)[None]
    on, seen = r > 0, o > 0
    both = on & seen
    diff = o - r
    agree = both & (diff.abs() <= tol32)
    behind = both & (diff > tol32)
    visible = on & ~(both & (diff < -tol32))
    mask_seen = m & seen

    def count(a):
        return a.flatten(1).sum(dim=1)

    counts = torch.stack([count(agree | behind), count(visible | m), count(visible & m), count(agree),
                          count(agree & mask_seen), count(behind)]).cpu().numpy()
    n_mask_seen = int(mask_seen.sum())
    out = []
    for (n_both, union, inter, n_agree, n_cover, n_behind), e in zip(counts.T.tolist(), evidence):
        # Python ints divided as numpy divides its counts: float64, the same bits.
        silhouette = inter / union if union else 0.0
        depth_fit = n_agree / n_both if n_both else 0.0
        coverage = n_cover / n_mask_seen if n_mask_seen else 0.0
        free_space = n_behind / n_both if n_both else 0.0
        out.append(Verification(silhouette, depth_fit, coverage, free_space, e,
                                verification_score(silhouette, depth_fit, coverage, free_space, e)))
    return out

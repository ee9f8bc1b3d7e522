"""RANSAC's sampling loop and the feature matching in torch, on the run's device (issue
31's GPU scene side).

:func:`ransac_pool_torch` computes what :func:`pipeline.method.registration.ransac._ransac_numpy`
computes, the pool of the hypotheses with the most feature inliers, with the same
samples (drawn by the same numpy Generator, batch by batch), the same edge-length and
distance checks, the same closed-form triangle fits and the same residual expansion
(the helpers of :mod:`~pipeline.method.registration.ransac` run on tensors unchanged).
What differs is how the batches are evaluated: several at once, as one set of tensor
operations, so that a GPU gets enough work per launch. The stopping rule is then
replayed batch by batch on the per-batch best counts, and the hypotheses of the batches
the numpy loop would not have drawn are dropped, so that the pool and the winner are the
numpy loop's, only with sums taken in another order (``tests/test_ransac_torch.py``: the
same pool, counts and order, poses to 1e-9 mm and 1e-9 rad, on the CPU).

:func:`feature_neighbours_torch` is :func:`~pipeline.method.registration.ransac.feature_neighbours`
(top-k nearest rows, float32, brute force in blocks) on the device.

On a CPU the numpy path stays the one the pipeline runs (see
``benchmarks/scene_paths.py``): the numpy loop evaluates one batch at a time, its
einsum kernels have less overhead per call than torch's, and it does no speculative work.
"""

from __future__ import annotations

import math
import numpy as np

from pipeline.method.registration.ransac import (
    RansacParams,
    _needed_iterations,
    checked_features,
    edge_lengths,
    fit_triangles,
    pool_poses,
    score_terms,
    squared_residuals,
)

CHUNK_ELEMENTS = 1 << 24
"""Largest number of (hypothesis, correspondence) residuals evaluated at once (128 MiB in
float64): the batches evaluated together are as many as fit, at least one."""

NN_ELEMENTS = 1 << 24
"""Largest number of (query, reference) feature distances held at once (64 MiB in float32)."""


def _torch():
    import torch

    return torch


def feature_neighbours_torch(query: np.ndarray, reference: np.ndarray, k: int = 1,
                             device: str = "cuda") -> np.ndarray:
    """Indices (Q, k) int64 of the k nearest rows of ``reference`` (R, D) for each row of
    ``query`` (Q, D), Euclidean distance in float32, nearest first, computed on
    ``device``; as :func:`~pipeline.method.registration.ransac.feature_neighbours`
    (the same expansion |r|^2 - 2 q.r; only the order of the sums differs, so only
    near-exact ties can resolve otherwise)."""
    torch = _torch()
    q, r = checked_features(query, reference)
    k = min(k, len(r))
    # TF32 would round the products to 10 bits of mantissa; torch leaves it off for
    # matrix products unless a process turns it on (and the project never does): then
    # the products are taken in float64 instead, without touching the global setting,
    # which other threads' matching reads too.
    tf32 = torch.backends.cuda.matmul.allow_tf32 or torch.get_float32_matmul_precision() != "highest"
    dtype = torch.float64 if tf32 and str(device).startswith("cuda") else torch.float32
    rt = torch.as_tensor(r, device=device).to(dtype)
    r_sq = (rt * rt).sum(dim=1)
    qt = torch.as_tensor(q, device=device).to(dtype)
    block = max(64, NN_ELEMENTS // max(len(r), 1))
    out = []
    for s in range(0, len(q), block):
        d = torch.addmm(r_sq[None], qt[s:s + block], rt.T, alpha=-2.0)
        if k == 1:
            out.append(torch.argmin(d, dim=1, keepdim=True))
        else:
            out.append(torch.topk(d, k, dim=1, largest=False, sorted=True).indices)
    return torch.cat(out).cpu().numpy().astype(np.int64) if out else np.empty((0, k), np.int64)


def ransac_pool_torch(src: np.ndarray, dst: np.ndarray, thr: float, params: RansacParams,
                      rng: np.random.Generator, pool: int = 1, device: str = "cuda",
                      ) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The ``pool`` hypotheses (count, R (3, 3), t (3,) mm) with the most feature inliers,
    dst ~ R src + t over the correspondences src, dst (C, 3) mm, most inliers first
    (ties: the earlier sample), computed on ``device``: the result of
    ``_ransac_numpy(src, dst, thr, params, rng, pool)`` (see the module docstring).

    The batches of ``params.batch_size`` samples are drawn from ``rng`` exactly as the
    numpy loop draws them; a chunk of them (1, 2, 4, ... batches, up to
    :data:`CHUNK_ELEMENTS` residuals) is evaluated at once, and the stopping rule
    replayed after each of its batches on the best count so far. The chunk's batches
    after the stop are drawn but dropped, so ``rng`` ends further on than the numpy
    loop leaves it: :func:`~pipeline.method.registration.ransac.ransac_hypotheses`, which
    makes it, draws nothing from it afterwards.
    """
    torch = _torch()
    C = len(src)
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    kw = {"dtype": torch.float64, "device": device}
    S = torch.as_tensor(src - ms, **kw)
    D = torch.as_tensor(dst - md, **kw)
    terms = score_terms(S, D)
    S_t, D_t = S.T.contiguous(), D.T.contiguous()
    # The pool, as in the numpy loop: the best so far, in the order of their samples
    # among equal counts (so no sample index is kept, as the numpy loop's lexsort needs);
    # the placeholder (count -1, identity) stands until something is fitted.
    p_count = torch.full((1,), -1, dtype=torch.int64, device=device)
    p_R, p_t = torch.eye(3, **kw)[None], torch.zeros((1, 3), **kw)
    done, needed, best = 0, math.inf, -1
    ratio, thr2 = params.edge_length_ratio, thr * thr
    max_batches = max(1, CHUNK_ELEMENTS // max(params.batch_size * C, 1))
    n_batches = 1
    while done < min(params.max_iterations, needed):
        sizes, drawn = [], []
        while len(sizes) < n_batches and done + sum(sizes) < params.max_iterations:
            B = min(params.batch_size, params.max_iterations - done - sum(sizes))
            drawn.append(rng.integers(0, C, size=(B, 3)))
            sizes.append(B)
        n_batches = min(2 * n_batches, max_batches)
        idx = torch.as_tensor(np.concatenate(drawn), device=device)
        idx_t = idx.T.contiguous()
        ls, ld = edge_lengths(S_t, idx_t), edge_lengths(D_t, idx_t)
        ok = torch.all((ls >= ratio * ld) & (ld >= ratio * ls) & (ls > 0), dim=0)
        sample = torch.nonzero(ok).flatten()
        triples = idx[sample]
        R, t, res, fit_ok = fit_triangles(S[triples], D[triples])
        ok = fit_ok & (res < thr)
        R, t, sample = R[ok], t[ok], sample[ok]
        counts = torch.count_nonzero(squared_residuals(R, t, terms) < thr2, dim=1)
        # Each sample's batch, and every batch's best count (-1: nothing fitted there).
        starts = torch.as_tensor(np.cumsum([0] + sizes[:-1]), device=device)
        batch = torch.bucketize(sample, starts, right=True) - 1
        batch_best = torch.full((len(sizes),), -1, dtype=torch.int64, device=device)
        batch_best = batch_best.scatter_reduce(0, batch, counts, reduce="amax").cpu().numpy()
        used = len(sizes)
        for j, B in enumerate(sizes):  # the numpy loop's stopping rule, batch by batch
            done += B
            best = max(best, int(batch_best[j]))
            needed = _needed_iterations(max(best, 0) / C, params.confidence)
            if not done < min(params.max_iterations, needed):
                used = j + 1
                break
        keep = batch < used
        # The pool and the new hypotheses, whose samples all come later: a stable sort
        # by count keeps the numpy loop's tie-break (the earlier sample first).
        p_count = torch.cat([p_count, counts[keep]])
        p_R, p_t = torch.cat([p_R, R[keep]]), torch.cat([p_t, t[keep]])
        top = torch.sort(-p_count, stable=True).indices[:pool]
        p_count, p_R, p_t = p_count[top], p_R[top], p_t[top]
    return pool_poses(p_count.cpu().numpy(), p_R.cpu().numpy(), p_t.cpu().numpy(), ms, md)

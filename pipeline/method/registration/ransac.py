"""Coarse pose by RANSAC over 3D-3D feature correspondences, as in FreeZe.

Correspondences pair each scene point with its nearest model point(s) in feature space
(optionally only mutual nearest neighbours). RANSAC draws 3 correspondences, rejects
samples whose pairwise edge lengths disagree between model and scene (or that are
collinear), fits a rigid transform (closed form for 3 points, :func:`fit_triangles`),
rejects fits that leave one of their own 3 points farther than the threshold
``inlier_frac * diameter``, and counts each survivor's feature inliers (correspondences
within the threshold after the transform). The stopping rule follows the most feature
inliers. With ``rank_by="fitness"`` (default) the ``rescore_pool`` hypotheses with the
most feature inliers are then ranked by geometric fitness (the share of scene points with
a model point within the threshold, on ``fitness_points`` of them) plus inlier ratio
(feature inliers / correspondences); the best distinct ones are refitted on their
inliers and ranked again by fitness (on every scene point) plus inlier ratio. With
``rank_by="inliers"`` (before issue 15) the most feature inliers win.

Why: on the registration benchmark's views (benchmarks/coarse_vs_open3d.py), the pose
with the most feature inliers was often wrong where the true pose had fewer feature
inliers but explained every scene point (FPFH alone: 21/30 and 15/30 coarse poses within
0.1 d ADD, normal and hard views; with fitness: 24/30 and 18/30; Open3D's
feature-matching RANSAC, which ranks by fitness alone, 24/30 and 16/30). Fitness alone
is blind on a blob-like shape, where many wrong poses fit about as well: there the
feature inliers decide (tests/test_hypotheses.py, coherent but wrong matches).

Two backends: ``"numpy"`` (default), batches of ``batch_size`` samples with no Python
loop over samples (inliers of all a batch's hypotheses as one matrix product,
:func:`squared_residuals`), reproducible for a seed by construction (one numpy
Generator); and ``"open3d"`` (``registration_ransac_based_on_correspondence`` with
edge-length and distance checkers, seeded through ``o3d.utility.random.seed``; repeated
runs agreed in our tests, but it is multi-threaded and does not document determinism;
it gives the winner only). Speed against Open3D: benchmarks/results/coarse_registration.md.
The numpy backend's loop and the feature matching also run in torch on a run's CUDA
device (``device=``; :mod:`pipeline.method.registration.ransac_torch`): the same samples
from the same Generator, the helpers below applied to tensors, the same pool.

Scores are comparable between candidates (e.g. several masks) of one object with the
same number of scene points: ``n_inliers`` always counts, among the M top-1 scene ->
model feature matches, those within the threshold under the returned pose, whatever
the filtering (mutual, k nearest) used to build RANSAC's correspondence set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import open3d as o3d
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree


class RansacParams(BaseModel):
    """RANSAC settings (plain values: they go into cache keys).

    inlier_frac: inlier threshold as a fraction of the object diameter.
    knn: model candidates per scene point (top-k in feature space).
    mutual: keep only mutual nearest neighbours (falls back to all correspondences
        when fewer than ``min_mutual`` survive).
    edge_length_ratio: minimal ratio of corresponding edge lengths in a sample.
    max_iterations / confidence: stop after ``max_iterations`` hypotheses or once the
        best inlier ratio ``w`` makes ``log(1-confidence)/log(1-w^3)`` hypotheses enough.
    refine_iterations: Kabsch refits of the winner on its inliers.
    batch_size: hypotheses evaluated together (numpy backend).
    rank_by: how the numpy backend ranks its hypotheses. ``"fitness"``: the
        ``rescore_pool`` hypotheses with the most feature inliers are ranked by geometric
        fitness (the share of ``fitness_points`` scene points with a model point within
        the threshold, as Open3D's RANSAC scores) plus inlier ratio; ``"inliers"``: by
        feature inliers alone (before issue 15).
    rescore_pool / fitness_points: see ``rank_by``.
    final_candidates: with ``rank_by="fitness"``, the best distinct hypotheses (at least
        k) refitted on their inliers and ranked again by fitness (every scene point) plus
        inlier ratio.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    inlier_frac: float = Field(0.05, gt=0)
    knn: int = Field(1, ge=1)
    mutual: bool = False
    min_mutual: int = Field(30, ge=3)
    edge_length_ratio: float = Field(0.9, gt=0, le=1)
    max_iterations: int = Field(50000, ge=1)
    confidence: float = Field(0.999, gt=0, lt=1)
    refine_iterations: int = Field(3, ge=0)
    batch_size: int = Field(1000, ge=1)
    rank_by: Literal["fitness", "inliers"] = "fitness"
    rescore_pool: int = Field(32, ge=1)
    fitness_points: int = Field(128, ge=1)
    final_candidates: int = Field(4, ge=1)
    backend: Literal["numpy", "open3d"] = "numpy"


@dataclass(frozen=True)
class Registration:
    """Coarse model-to-camera pose and its support.

    R (3, 3) float64, t (3,) float64 mm.
    n_inliers: top-1 feature matches within the threshold under (R, t).
    inlier_ratio: n_inliers / number of scene points.
    fitness: fraction of scene points with a model point within the threshold.
    n_correspondences: size of the correspondence set RANSAC sampled from.
    """

    R: np.ndarray
    t: np.ndarray
    n_inliers: int
    inlier_ratio: float
    fitness: float
    n_correspondences: int


def checked_features(query: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """query (Q, D) and reference (R, D) as float32 arrays, checked for matching feature
    dimensions (both paths of :func:`feature_neighbours`)."""
    q = np.asarray(query, dtype=np.float32)
    r = np.asarray(reference, dtype=np.float32)
    if q.ndim != 2 or r.ndim != 2 or q.shape[1] != r.shape[1]:
        raise ValueError(f"feature_neighbours: feature dims differ: {q.shape} vs {r.shape}")
    return q, r


def feature_neighbours(query: np.ndarray, reference: np.ndarray, k: int = 1, device: str | None = None) -> np.ndarray:
    """Indices (Q, k) int64 of the k nearest rows of ``reference`` (R, D) for each row of
    ``query`` (Q, D), Euclidean distance, nearest first. Exact (brute force in blocks).
    ``device``: None for numpy, else a torch device (:func:`~pipeline.method.registration.ransac_torch.feature_neighbours_torch`)."""
    if device is not None:
        from pipeline.method.registration.ransac_torch import feature_neighbours_torch

        return feature_neighbours_torch(query, reference, k, device)
    q, r = checked_features(query, reference)
    k = min(k, len(r))
    r_sq = np.sum(r * r, axis=1)
    rt = np.ascontiguousarray(r.T)
    out = np.empty((len(q), k), dtype=np.int64)
    # Few, large matrix products (up to 8M distances, 32 MB, per block), updated in place
    # rather than through temporaries: with 2 OpenBLAS threads on cores busy with other
    # work, blocks of 256 queries took 68 ms for 1000 x 5000 x 96 and blocks of 1024,
    # 33-36 ms (one thread: 23-26 ms either way).
    block = max(64, min(2048, 8_000_000 // max(len(r), 1)))
    for s in range(0, len(q), block):
        # |q - r|^2 up to the per-query constant |q|^2, which does not change the order.
        d = q[s : s + block] @ rt
        d *= -2.0
        d += r_sq
        if k == 1:
            # argmin is a single pass; argpartition was 30x slower for the same answer.
            out[s : s + block, 0] = np.argmin(d, axis=1)
            continue
        part = np.argpartition(d, k - 1, axis=1)[:, :k] if k < len(r) else np.tile(np.arange(len(r)), (len(d), 1))
        order = np.take_along_axis(d, part, axis=1).argsort(axis=1, kind="stable")
        out[s : s + block] = np.take_along_axis(part, order, axis=1)
    return out


def build_correspondences(
    model_feats: np.ndarray, scene_feats: np.ndarray, params: RansacParams, device: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC correspondence set ``(C, 2)`` int64 rows ``(model_idx, scene_idx)`` and the
    top-1 matches ``(M,)`` model index per scene point (matched on ``device``, None: numpy)."""
    nn = feature_neighbours(scene_feats, model_feats, k=params.knn, device=device)
    top1 = nn[:, 0]
    scene_idx = np.repeat(np.arange(len(scene_feats)), nn.shape[1])
    corr = np.stack([nn.reshape(-1), scene_idx], axis=1)
    if params.mutual:
        back = feature_neighbours(model_feats, scene_feats, k=1, device=device)[:, 0]
        mutual = back[top1] == np.arange(len(scene_feats))
        if mutual.sum() >= params.min_mutual:
            corr = np.stack([top1[mutual], np.flatnonzero(mutual)], axis=1)
    return corr.astype(np.int64), top1


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform with ``dst ~ R @ src + t`` for (n, 3) or batched
    (B, n, 3) arrays; returns R (..., 3, 3), t (..., 3) float64."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    cs = src.mean(axis=-2, keepdims=True)
    cd = dst.mean(axis=-2, keepdims=True)
    H = np.swapaxes(src - cs, -1, -2) @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    # Flip the last axis where needed so that R is a rotation, not a reflection.
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(V.shape[:-2] + (3,))
    D[..., 2] = d
    R = (V * D[..., None, :]) @ Ut
    t = cd[..., 0, :] - np.einsum("...ij,...j->...i", R, cs[..., 0, :])
    return R, t


def _needed_iterations(inlier_ratio: float, confidence: float, n: int = 3) -> float:
    p = inlier_ratio**n
    if p <= 0:
        return math.inf
    if p >= 1:
        return 1.0
    return math.log(1.0 - confidence) / math.log(1.0 - p)


def array_module(a: Any) -> Any:
    """numpy for a numpy array, torch for a tensor: the helpers below (the triangle fits,
    the residual expansion) run unchanged on either, so that the torch RANSAC
    (:mod:`pipeline.method.registration.ransac_torch`) computes what this one computes."""
    if isinstance(a, np.ndarray):
        return np
    import torch

    return torch


def _triangle_frames(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal frames of B triangles p (B, 3, 3): e1 along the edge p0 -> p1, n the
    normal (p1 - p0) x (p2 - p0), e2 = n x e1, each (B, 3); and a mask (B,) of the
    triangles that have a normal (not degenerate). numpy arrays or torch tensors."""
    xp = array_module(p)
    u, w = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    n = _cross(u, w)
    nu, nn = _lengths(u), _lengths(n)
    # |u x w| = |u| |w| sin(angle): below 1e-9 the three points are collinear to rounding.
    ok = nn > 1e-9 * nu * _lengths(w)
    e1 = u / xp.where(ok, nu, 1.0)[:, None]
    n = n / xp.where(ok, nn, 1.0)[:, None]
    return e1, _cross(n, e1), n, ok


# np.cross and np.linalg.norm spend most of their time on argument handling for arrays
# this small (a RANSAC batch's few hundred triangles): these are 1.6-1.8x faster per call.
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (B, 3) arrays (or tensors)."""
    out = array_module(a).empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _lengths(a: np.ndarray) -> np.ndarray:
    """Euclidean length along the last axis (arrays or tensors)."""
    xp = array_module(a)
    return xp.sqrt(xp.einsum("...i,...i->...", a, a))


def fit_triangles(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid transforms ``dst ~ R @ src + t`` of B point triples.

    src, dst (B, 3, 3) float64 (triple, point, xyz), mm. Returns R (B, 3, 3), t (B, 3),
    the largest residual of the three points (B,) mm, and a mask (B,) of the triples
    that are not degenerate (collinear; their R is meaningless). Same optimum as
    :func:`kabsch` but in closed form, without a batched SVD: centred, three points lie
    in a plane, so the best rotation takes the source plane onto the target plane (its
    normal onto the normal, or onto the opposite normal, whichever fits better) and then
    turns it in the plane by the 2D Procrustes angle. numpy arrays, or torch tensors
    (the same operations, on their device).
    """
    xp = array_module(src)
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    a, b = src - cs[:, None], dst - cd[:, None]
    e1s, e2s, ns, oks = _triangle_frames(src)
    e1d, e2d, nd, okd = _triangle_frames(dst)
    # In-plane coordinates (B, 3) of the centred points in their own triangle's frame.
    x, y = xp.einsum("bki,bi->bk", a, e1s), xp.einsum("bki,bi->bk", a, e2s)
    u, v = xp.einsum("bki,bi->bk", b, e1d), xp.einsum("bki,bi->bk", b, e2d)
    # sum_k b_k . R a_k = c * C + s * S for a turn by (c, s) = (cos, sin): maximal at
    # (C, S) / hypot(C, S). The mirrored target frame (v -> -v, n -> -n) is also a
    # proper rotation of the source frame onto the target plane.
    C1, S1 = xp.sum(u * x + v * y, axis=1), xp.sum(v * x - u * y, axis=1)
    C2, S2 = xp.sum(u * x - v * y, axis=1), xp.sum(-v * x - u * y, axis=1)
    h1, h2 = xp.hypot(C1, S1), xp.hypot(C2, S2)
    mirror = h2 > h1
    sign = xp.where(mirror, -1.0, 1.0)
    C, S, h = xp.where(mirror, C2, C1), xp.where(mirror, S2, S1), xp.maximum(h1, h2)
    c = xp.where(h > 0, C / xp.where(h > 0, h, 1.0), 1.0)
    s = xp.where(h > 0, S / xp.where(h > 0, h, 1.0), 0.0)
    e2d, nd = e2d * sign[:, None], nd * sign[:, None]
    # R = Fd Rz(angle) Fs^T with F = [e1 e2 n] as columns, written out.
    outer = lambda p, q: p[:, :, None] * q[:, None, :]  # noqa: E731
    R = (c[:, None, None] * (outer(e1d, e1s) + outer(e2d, e2s))
         + s[:, None, None] * (outer(e2d, e1s) - outer(e1d, e2s)) + outer(nd, ns))
    t = cd - xp.einsum("bij,bj->bi", R, cs)
    # Residuals in the plane: (u, +-v) against the turned (x, y); both triangles are flat.
    vs = v * sign[:, None]
    res2 = (u - (c[:, None] * x - s[:, None] * y)) ** 2 + (vs - (s[:, None] * x + c[:, None] * y)) ** 2
    return R, t, xp.sqrt(xp.amax(res2, axis=1)), oks & okd


def score_terms(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(17, C) per-correspondence terms of |R s + t - d|^2 for :func:`squared_residuals`,
    of src, dst (C, 3) float64 arrays or tensors."""
    xp = array_module(src)
    sd = (dst[:, :, None] * src[:, None, :]).reshape(-1, 9)  # d_i s_j, row-major (i, j)
    sq = xp.sum(src * src, axis=1) + xp.sum(dst * dst, axis=1)
    one = np.ones(len(src)) if xp is np else src.new_ones(len(src))
    terms = xp.concatenate([sd, src, dst, one[:, None], sq[:, None]], axis=1).T
    return np.ascontiguousarray(terms) if xp is np else terms.contiguous()


def squared_residuals(R: np.ndarray, t: np.ndarray, terms: np.ndarray) -> np.ndarray:
    """|R_b s_c + t_b - d_c|^2 (B, C) of B transforms R (B, 3, 3), t (B, 3) over the
    correspondences of ``terms`` (:func:`score_terms`), as one matrix product (arrays or
    tensors):
    |s|^2 + |d|^2 + |t|^2 + 2 (R^T t).s - 2 t.d - 2 sum_ij R_ij d_i s_j.
    The coordinates should be centred (small magnitudes) for the expansion to stay
    accurate; in float64 at object scale its error is far below a threshold squared."""
    xp = array_module(R)
    B = len(R)
    coef = np.empty((B, 17)) if xp is np else R.new_empty((B, 17))
    coef[:, :9] = -2.0 * R.reshape(B, 9)
    coef[:, 9:12] = 2.0 * xp.einsum("bji,bj->bi", R, t)
    coef[:, 12:15] = -2.0 * t
    coef[:, 15] = xp.sum(t * t, axis=1)
    coef[:, 16] = 1.0
    # einsum, not BLAS: a product this small ran 100x slower with 2 OpenBLAS threads on
    # busy cores (22 ms vs 0.2 ms) and gains nothing from threads on idle ones.
    return xp.einsum("bk,kc->bc", coef, terms)


def edge_lengths(points_t: np.ndarray, idx_t: np.ndarray) -> np.ndarray:
    """Lengths (3, B) mm of the edges p0-p1, p1-p2, p2-p0 of B triangles whose vertices
    are the points ``points_t`` (3, C) (coordinate-major) at ``idx_t`` (3, B). One
    gather and a few operations on whole (3, 3, B) arrays: for a RANSAC batch of 1000
    samples 3x faster than gathering (B, 3, 3) triangles and measuring their edges,
    where numpy's per-call overhead dominated (the same lengths to the bit)."""
    xp = array_module(points_t)
    # (coordinate, vertex, triangle); take is numpy's faster gather, indexing torch's
    p = points_t.take(idx_t, axis=1) if xp is np else points_t[:, idx_t]
    d = p - p[:, (1, 2, 0)]
    d *= d
    return xp.sqrt(d[0] + d[1] + d[2])


def _ransac_numpy(
    src: np.ndarray, dst: np.ndarray, thr: float, params: RansacParams, rng: np.random.Generator, pool: int = 1
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The ``pool`` hypotheses (count, R, t) with the most inliers, dst ~ R src + t over
    correspondences src, dst (C, 3) mm, most inliers first (ties: the earlier sample);
    the first is RANSAC's winner. The sampling and the stopping rule depend on the winner
    only, so the winner is the same whatever ``pool``.

    Per batch of ``batch_size`` samples, without a Python loop over samples: draw the
    triples, reject those whose edge lengths disagree (``edge_length_ratio``) or that
    are collinear, fit the survivors in closed form (:func:`fit_triangles`), reject
    those that do not bring their own three points within ``thr`` (Open3D's distance
    checker: such a pose cannot be the one that explains the sample), and count the
    inliers of the rest over all C correspondences with one matrix product
    (:func:`squared_residuals`).
    """
    C = len(src)
    # Centre both sides: the residual expansion then works on small numbers; poses are
    # mapped back at the end (t = t_c + md - R ms).
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    src, dst = src - ms, dst - md
    terms = score_terms(src, dst)
    # The pool: the best hypotheses so far, with the index of their sample (tie-break).
    p_count = np.full(1, -1, dtype=np.int64)
    p_order = np.zeros(1, dtype=np.int64)
    p_R, p_t = np.eye(3)[None], np.zeros((1, 3))
    done, needed = 0, math.inf
    ratio = params.edge_length_ratio
    thr2 = thr * thr
    src_t, dst_t = np.ascontiguousarray(src.T), np.ascontiguousarray(dst.T)
    while done < min(params.max_iterations, needed):
        B = min(params.batch_size, params.max_iterations - done)
        first = done
        done += B
        idx = rng.integers(0, C, size=(B, 3))
        idx_t = np.ascontiguousarray(idx.T)
        ls, ld = edge_lengths(src_t, idx_t), edge_lengths(dst_t, idx_t)  # (3, B) each
        ok = np.all((ls >= ratio * ld) & (ld >= ratio * ls) & (ls > 0), axis=0)
        if not ok.any():
            continue
        sample = np.flatnonzero(ok)
        triples = idx[sample]
        R, t, res, fit_ok = fit_triangles(src[triples], dst[triples])
        ok = fit_ok & (res < thr)
        if not ok.any():
            continue
        R, t, sample = R[ok], t[ok], sample[ok]
        counts = np.count_nonzero(squared_residuals(R, t, terms) < thr2, axis=1)
        p_count = np.concatenate([p_count, counts])
        p_order = np.concatenate([p_order, first + sample])
        p_R, p_t = np.concatenate([p_R, R]), np.concatenate([p_t, t])
        keep = np.lexsort((p_order, -p_count))[:pool]
        p_count, p_order, p_R, p_t = p_count[keep], p_order[keep], p_R[keep], p_t[keep]
        needed = _needed_iterations(max(int(p_count[0]), 0) / C, params.confidence)
    return pool_poses(p_count, p_R, p_t, ms, md)


def pool_poses(p_count: np.ndarray, p_R: np.ndarray, p_t: np.ndarray, ms: np.ndarray,
               md: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """A RANSAC loop's pool as (count, R (3, 3), t (3,) mm), the poses mapped back from
    the centred frames (source centroid ``ms``, target ``md``): t = md - R ms + t_c. The
    placeholder (count -1: identity, centroids aligned) only when nothing was fitted."""
    real = p_count >= 0
    sel = real if real.any() else np.arange(len(p_count)) == 0
    return [(int(c), R, md - R @ ms + t) for c, R, t in zip(p_count[sel], p_R[sel], p_t[sel])]


def _rank_by_fitness(found: list[tuple[int, np.ndarray, np.ndarray]], n_corr: int, tree: cKDTree,
                     scene: np.ndarray, thr: float, n_points: int) -> list[int]:
    """Order of hypotheses ``found`` (count, R, t) by fitness plus inlier ratio, best
    first: the share of ``n_points`` scene points (M, 3) mm, evenly spread over their
    order, with a model point (``tree``) within ``thr`` mm under the pose, plus count /
    ``n_corr``; ties as given. One k-d tree query for all hypotheses (scene points taken
    to the model frame)."""
    sub = scene[np.linspace(0, len(scene) - 1, min(n_points, len(scene))).astype(np.int64)]
    R = np.stack([h[1] for h in found])
    t = np.stack([h[2] for h in found])
    q = np.einsum("hsj,hji->hsi", sub[None] - t[:, None], R)  # (H, S, 3): R^T (p - t)
    dist, _ = tree.query(q.reshape(-1, 3), k=1, distance_upper_bound=thr)
    fit = np.count_nonzero(np.isfinite(dist).reshape(len(found), -1), axis=1) / len(sub)
    score = fit + np.array([h[0] for h in found]) / n_corr
    return list(np.lexsort((np.arange(len(found)), -score)))


def _ransac_open3d(
    src: np.ndarray, dst: np.ndarray, thr: float, params: RansacParams, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst))
    corr = np.stack([np.arange(len(src)), np.arange(len(src))], axis=1).astype(np.int32)
    result = reg.registration_ransac_based_on_correspondence(
        source,
        target,
        o3d.utility.Vector2iVector(corr),
        thr,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(params.edge_length_ratio),
         reg.CorrespondenceCheckerBasedOnDistance(thr)],
        reg.RANSACConvergenceCriteria(params.max_iterations, params.confidence),
    )
    T = np.asarray(result.transformation)
    return T[:3, :3].copy(), T[:3, 3].copy()


def _count_within(src: np.ndarray, dst: np.ndarray, R: np.ndarray, t: np.ndarray, thr: float) -> np.ndarray:
    res = src @ R.T + t - dst
    return np.sum(res * res, axis=1) < thr * thr


def distinct_poses(poses: list[tuple[np.ndarray, np.ndarray]], k: int, min_angle_deg: float,
                   min_trans: float) -> list[int]:
    """Non-maximum suppression in pose space: indices of up to ``k`` of ``poses`` (R (3, 3),
    t (3,) mm; best first), each kept one differing from every earlier kept one by more
    than ``min_angle_deg`` in rotation or ``min_trans`` mm in translation."""
    from pipeline.method.geometry.transforms import rotation_angle_deg

    kept: list[int] = []
    for i, (R, t) in enumerate(poses):
        if len(kept) >= k:
            break
        if all(rotation_angle_deg(poses[j][0], R) > min_angle_deg or np.linalg.norm(poses[j][1] - t) > min_trans
               for j in kept):
            kept.append(i)
    return kept


def ransac_align(
    model_points: np.ndarray,
    model_feats: np.ndarray,
    scene_points: np.ndarray,
    scene_feats: np.ndarray,
    diameter: float,
    *,
    params: RansacParams | None = None,
    seed: int = 0,
    device: str | None = None,
) -> Registration:
    """Coarse model-to-camera pose from feature matches: the best of :func:`ransac_hypotheses`."""
    return ransac_hypotheses(model_points, model_feats, scene_points, scene_feats, diameter, params=params,
                             seed=seed, k=1, device=device)[0]


def ransac_hypotheses(
    model_points: np.ndarray,
    model_feats: np.ndarray,
    scene_points: np.ndarray,
    scene_feats: np.ndarray,
    diameter: float,
    *,
    params: RansacParams | None = None,
    seed: int = 0,
    k: int = 1,
    nms_deg: float = 30.0,
    nms_frac: float = 0.2,
    device: str | None = None,
) -> list[Registration]:
    """Up to ``k`` distinct coarse model-to-camera poses from feature matches, best first.

    model_points (N, 3) mm with model_feats (N, D); scene_points (M, 3) mm camera frame
    with scene_feats (M, D) (same feature space, e.g. :func:`fusion.fuse` outputs);
    diameter: object diameter in mm. The first pose is RANSAC's best (see the module
    docstring for ``params.rank_by``); the others are runners-up that survive non-maximum
    suppression in pose space (:func:`distinct_poses`: ``nms_deg`` degrees, ``nms_frac``
    diameters), each refitted on its inliers. With ``rank_by="fitness"``, the
    ``max(k, final_candidates)`` best distinct poses are refitted and the k with the
    highest fitness + inlier ratio returned, best first, so the first is the same for
    every k up to ``final_candidates`` (:func:`ransac_align` is k = 1). Deterministic for
    a given seed (numpy backend); the open3d backend gives the winner only.

    ``device``: None, the numpy backend's sampling loop and feature matching on the CPU;
    or a torch device (``cuda``) for both
    (:mod:`~pipeline.method.registration.ransac_torch`: the same samples, checks and
    pool, the batches evaluated several at once). The ranking and refits after the loop
    (a few dozen poses, one k-d tree) stay in numpy either way.
    """
    params = params or RansacParams()
    mp = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    sp = np.asarray(scene_points, dtype=np.float64).reshape(-1, 3)
    if len(mp) != len(model_feats) or len(sp) != len(scene_feats):
        raise ValueError(
            f"ransac_align: {len(mp)} model points vs {len(model_feats)} features, "
            f"{len(sp)} scene points vs {len(scene_feats)} features"
        )
    if len(sp) < 3 or len(mp) < 3:
        raise ValueError("ransac_align: need at least 3 model and 3 scene points")
    thr = params.inlier_frac * float(diameter)
    if device is not None and params.backend != "numpy":
        raise ValueError(f"ransac_hypotheses: device={device!r} needs the numpy backend's loop, not {params.backend!r}")
    corr, top1 = build_correspondences(model_feats, scene_feats, params, device)
    src, dst = mp[corr[:, 0]], sp[corr[:, 1]]
    tree = cKDTree(mp)
    if params.backend == "numpy":
        rng = np.random.default_rng(seed)
        if device is None:
            loop = _ransac_numpy
        else:
            from functools import partial

            from pipeline.method.registration.ransac_torch import ransac_pool_torch

            loop = partial(ransac_pool_torch, device=device)
        if params.rank_by == "fitness":
            found = loop(src, dst, thr, params, rng, pool=max(params.rescore_pool, k))
            found = [found[i] for i in _rank_by_fitness(found, len(corr), tree, sp, thr, params.fitness_points)]
        else:
            found = loop(src, dst, thr, params, rng, pool=64 * k if k > 1 else 1)
        n = max(k, params.final_candidates) if params.rank_by == "fitness" else k
        found = [found[i] for i in distinct_poses([(R, t) for _, R, t in found], n, nms_deg, nms_frac * diameter)]
    else:
        found = [(0, *_ransac_open3d(src, dst, thr, params, seed))]
    out = []
    for _, R, t in found:
        for _ in range(params.refine_iterations):
            inl = _count_within(src, dst, R, t, thr)
            if inl.sum() < 3:
                break
            R, t = kabsch(src[inl], dst[inl])
        top1_in = _count_within(mp[top1], sp, R, t, thr)
        # Geometric fitness: scene points explained by the posed model surface samples
        # (the scene taken to the model frame: one tree for every pose).
        dist, _ = tree.query((sp - t) @ R, k=1, distance_upper_bound=thr)  # inf beyond thr
        n_inliers = int(top1_in.sum())
        out.append(Registration(
            R=np.asarray(R, dtype=np.float64),
            t=np.asarray(t, dtype=np.float64),
            n_inliers=n_inliers,
            inlier_ratio=n_inliers / len(sp),
            fitness=float(np.mean(dist < thr)),
            n_correspondences=int(len(corr)),
        ))
    if params.backend == "numpy" and params.rank_by == "fitness":
        # The refit can lift a right pose's fitness well above a wrong one's that scored
        # the same on the subset: compare the refitted poses on every scene point.
        order = sorted(range(len(out)), key=lambda i: (-(out[i].fitness + out[i].inlier_ratio), i))
        out = [out[i] for i in order[:k]]
    return out

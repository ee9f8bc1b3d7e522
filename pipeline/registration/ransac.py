"""Coarse pose by RANSAC over 3D-3D feature correspondences, as in FreeZe.

Correspondences pair each scene point with its nearest model point(s) in feature space
(optionally only mutual nearest neighbours). RANSAC draws 3 correspondences, rejects
samples whose pairwise edge lengths disagree between model and scene, fits a rigid
transform (Kabsch), and keeps the hypothesis with the most correspondences closer than
``inlier_frac * diameter`` after the transform; the winner is refitted on its inliers.

Two backends: ``"numpy"`` (default), a vectorised implementation that evaluates
hypotheses in batches of ``batch_size`` and is reproducible for a seed by construction
(one numpy Generator); and ``"open3d"`` (``registration_ransac_based_on_correspondence``
with edge-length and distance checkers, seeded through ``o3d.utility.random.seed``;
repeated runs agreed in our tests, but it is multi-threaded and does not document
determinism). On the synthetic benchmark (benchmarks/registration.py, FPFH only,
3 objects x 3 radius sets x 10 views) numpy recovered 57/90 poses vs 54/90 for open3d,
at similar speed (~50-150 ms for 1000 scene vs 5000 model points).

Scores are comparable between candidates (e.g. several masks) of one object with the
same number of scene points: ``n_inliers`` always counts, among the M top-1 scene ->
model feature matches, those within the threshold under the returned pose, whatever
the filtering (mutual, k nearest) used to build RANSAC's correspondence set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

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


def feature_neighbours(query: np.ndarray, reference: np.ndarray, k: int = 1) -> np.ndarray:
    """Indices (Q, k) int64 of the k nearest rows of ``reference`` (R, D) for each row of
    ``query`` (Q, D), Euclidean distance, nearest first. Exact (brute force in blocks)."""
    q = np.asarray(query, dtype=np.float32)
    r = np.asarray(reference, dtype=np.float32)
    if q.ndim != 2 or r.ndim != 2 or q.shape[1] != r.shape[1]:
        raise ValueError(f"feature_neighbours: feature dims differ: {q.shape} vs {r.shape}")
    k = min(k, len(r))
    r_sq = np.sum(r * r, axis=1)
    out = np.empty((len(q), k), dtype=np.int64)
    block = 2048
    for s in range(0, len(q), block):
        # |q - r|^2 up to the per-query constant |q|^2, which does not change the order.
        d = r_sq[None, :] - 2.0 * (q[s : s + block] @ r.T)
        part = np.argpartition(d, k - 1, axis=1)[:, :k] if k < len(r) else np.tile(np.arange(len(r)), (len(d), 1))
        order = np.take_along_axis(d, part, axis=1).argsort(axis=1, kind="stable")
        out[s : s + block] = np.take_along_axis(part, order, axis=1)
    return out


def build_correspondences(
    model_feats: np.ndarray, scene_feats: np.ndarray, params: RansacParams
) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC correspondence set ``(C, 2)`` int64 rows ``(model_idx, scene_idx)`` and the
    top-1 matches ``(M,)`` model index per scene point."""
    nn = feature_neighbours(scene_feats, model_feats, k=params.knn)
    top1 = nn[:, 0]
    scene_idx = np.repeat(np.arange(len(scene_feats)), nn.shape[1])
    corr = np.stack([nn.reshape(-1), scene_idx], axis=1)
    if params.mutual:
        back = feature_neighbours(model_feats, scene_feats, k=1)[:, 0]
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


def _ransac_numpy(
    src: np.ndarray, dst: np.ndarray, thr: float, params: RansacParams, rng: np.random.Generator, pool: int = 1
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The best hypotheses (count, R, t) with dst ~ R src + t over correspondences src,
    dst (C, 3), most inliers first: the winner, then up to ``pool - 1`` runners-up (the
    best of each batch). The sampling and the stopping rule depend on the winner only,
    so the winner is the same whatever ``pool``."""
    C = len(src)
    best_count, best = -1, (np.eye(3), np.zeros(3))
    kept: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # (count, order, R, t)
    done, needed = 0, math.inf
    ratio = params.edge_length_ratio
    pairs = np.array([[0, 1], [1, 2], [2, 0]])
    thr2 = thr * thr
    while done < min(params.max_iterations, needed):
        B = min(params.batch_size, params.max_iterations - done)
        done += B
        idx = rng.integers(0, C, size=(B, 3))
        s, d = src[idx], dst[idx]  # (B, 3, 3)
        ls = np.linalg.norm(s[:, pairs[:, 0]] - s[:, pairs[:, 1]], axis=-1)
        ld = np.linalg.norm(d[:, pairs[:, 0]] - d[:, pairs[:, 1]], axis=-1)
        ok = np.all((ls >= ratio * ld) & (ld >= ratio * ls) & (ls > 0), axis=1)
        if not ok.any():
            continue
        R, t = kabsch(s[ok], d[ok])
        res = np.einsum("bij,cj->bci", R, src) + t[:, None, :] - dst[None]
        counts = np.sum(np.sum(res * res, axis=-1) < thr2, axis=1)
        if pool > 1:
            for j in np.argsort(-counts, kind="stable")[: 4 * pool]:
                kept.append((int(counts[j]), len(kept), R[j], t[j]))
            kept = sorted(kept, key=lambda h: (-h[0], h[1]))[: 64 * pool]
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best_count, best = int(counts[i]), (R[i], t[i])
            needed = _needed_iterations(best_count / C, params.confidence)
    out = [(best_count, best[0], best[1])]
    out += [(c, R, t) for c, _, R, t in kept if not (R is best[0] or np.array_equal(R, best[0]))]
    return out


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
    from pipeline.geometry.transforms import rotation_angle_deg

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
) -> Registration:
    """Coarse model-to-camera pose from feature matches: the best of :func:`ransac_hypotheses`."""
    return ransac_hypotheses(model_points, model_feats, scene_points, scene_feats, diameter, params=params,
                             seed=seed, k=1)[0]


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
) -> list[Registration]:
    """Up to ``k`` distinct coarse model-to-camera poses from feature matches, best first.

    model_points (N, 3) mm with model_feats (N, D); scene_points (M, 3) mm camera frame
    with scene_feats (M, D) (same feature space, e.g. :func:`fusion.fuse` outputs);
    diameter: object diameter in mm. The first pose is RANSAC's winner; the others are
    the runners-up that survive non-maximum suppression in pose space
    (:func:`distinct_poses`: ``nms_deg`` degrees, ``nms_frac`` diameters), each refitted
    on its inliers. Deterministic for a given seed (numpy backend); the open3d backend
    gives the winner only.
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
    corr, top1 = build_correspondences(model_feats, scene_feats, params)
    src, dst = mp[corr[:, 0]], sp[corr[:, 1]]
    if params.backend == "numpy":
        found = _ransac_numpy(src, dst, thr, params, np.random.default_rng(seed), pool=k)
        found = [found[i] for i in distinct_poses([(R, t) for _, R, t in found], k, nms_deg, nms_frac * diameter)]
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
        # Geometric fitness: scene points explained by the posed model surface samples.
        dist, _ = cKDTree(mp @ R.T + t).query(sp, k=1)
        n_inliers = int(top1_in.sum())
        out.append(Registration(
            R=np.asarray(R, dtype=np.float64),
            t=np.asarray(t, dtype=np.float64),
            n_inliers=n_inliers,
            inlier_ratio=n_inliers / len(sp),
            fitness=float(np.mean(dist < thr)),
            n_correspondences=int(len(corr)),
        ))
    return out

"""PCA fusion, Kabsch and RANSAC on synthetic correspondences with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.method.geometry.transforms import rotation_angle_deg
from pose_helpers import random_rotation
from pipeline.method.registration.fusion import apply_pca, fit_pca, fuse
from pipeline.method.registration.ransac import (
    RansacParams,
    build_correspondences,
    feature_neighbours,
    kabsch,
    ransac_align,
    ransac_hypotheses,
)

# --- fusion -----------------------------------------------------------------------


def test_fit_pca_recovers_known_subspace():
    rng = np.random.default_rng(0)
    basis_true = np.linalg.qr(rng.normal(size=(10, 3)))[0].T  # (3, 10) orthonormal rows
    scales = np.array([10.0, 5.0, 2.0])
    X = (rng.normal(size=(4000, 3)) * scales) @ basis_true + 7.0
    pca = fit_pca(X, n_components=64)
    assert pca.components.shape == (10, 10)  # V = min(64, C=10, N)
    np.testing.assert_allclose(pca.mean, 7.0, atol=0.6)
    # Leading components span the true subspace, in order of variance.
    for i in range(3):
        assert abs(pca.components[i] @ basis_true[i]) == pytest.approx(1.0, abs=1e-2)
    np.testing.assert_allclose(pca.explained_variance[:3], scales**2, rtol=0.1)
    assert pca.explained_variance[3] < 1e-6
    # Orthonormal rows, so projecting and back-projecting keeps the centred data.
    Y = apply_pca(pca, X)
    np.testing.assert_allclose(Y @ pca.components + pca.mean, X, atol=1e-3)
    assert fit_pca(X[:5], 64).components.shape == (5, 10)  # V limited by N
    # Deterministic signs.
    np.testing.assert_array_equal(fit_pca(X, 4).components, fit_pca(X.copy(), 4).components)


def test_fuse_normalises_each_part():
    rng = np.random.default_rng(1)
    g, v = rng.normal(size=(50, 66)) * 30, rng.normal(size=(50, 64)) * 0.01
    f = fuse(g, v)
    assert f.shape == (50, 130) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f[:, :66], axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(f[:, 66:], axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(fuse(g, None), f[:, :66])
    # vision-only: an empty geometric part leaves the normalised visual part alone
    np.testing.assert_allclose(fuse(np.zeros((50, 0)), v), f[:, 66:])
    with pytest.raises(ValueError, match="rows"):
        fuse(g, v[:10])


# --- correspondences and Kabsch ---------------------------------------------------


def test_feature_neighbours_matches_brute_force():
    rng = np.random.default_rng(2)
    q, r = rng.normal(size=(300, 16)), rng.normal(size=(700, 16))
    nn = feature_neighbours(q, r, k=4)
    d = np.linalg.norm(q[:, None] - r[None], axis=2)
    np.testing.assert_array_equal(nn, np.argsort(d, axis=1)[:, :4])


def test_mutual_filter_and_fallback():
    rng = np.random.default_rng(3)
    model = rng.normal(size=(200, 8)).astype(np.float32)
    scene = model[:100] + 0.01 * rng.normal(size=(100, 8)).astype(np.float32)
    corr, top1 = build_correspondences(model, scene, RansacParams(mutual=True, min_mutual=30))
    np.testing.assert_array_equal(top1, np.arange(100))
    np.testing.assert_array_equal(corr, np.stack([np.arange(100)] * 2, axis=1))
    # Few mutual matches: fall back to all scene -> model matches.
    corr, _ = build_correspondences(model, scene[:20], RansacParams(mutual=True, min_mutual=30))
    assert len(corr) == 20
    corr, _ = build_correspondences(model, scene, RansacParams(knn=3))
    assert corr.shape == (300, 2)


def test_kabsch_exact_and_batched():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(30, 3)) * 50
    R, t = random_rotation(5), np.array([1.0, 2.0, 300.0])
    Re, te = kabsch(src, src @ R.T + t)
    np.testing.assert_allclose(Re, R, atol=1e-10)
    np.testing.assert_allclose(te, t, atol=1e-8)
    Rs = np.stack([random_rotation(i) for i in range(4)])
    dst = np.einsum("bij,nj->bni", Rs, src)
    Rb, tb = kabsch(np.broadcast_to(src, dst.shape), dst)
    np.testing.assert_allclose(Rb, Rs, atol=1e-10)
    np.testing.assert_allclose(tb, 0, atol=1e-8)
    # A mirrored target still yields a proper rotation.
    Rm, _ = kabsch(src, src * [1, 1, -1])
    assert np.linalg.det(Rm) == pytest.approx(1.0)


# --- RANSAC -----------------------------------------------------------------------


def _synthetic_problem(seed: int, inlier_share: float):
    """A 2000-point model, a 600-point noisy partial scene under a known pose, and
    features that match correctly for ``inlier_share`` of the scene points."""
    rng = np.random.default_rng(seed)
    model = rng.normal(size=(2000, 3)) * [60, 40, 25]
    R, t = random_rotation(rng), np.array([20.0, -10.0, 650.0])
    idx = rng.choice(2000, 600, replace=False)
    scene = model[idx] @ R.T + t + rng.normal(scale=0.5, size=(600, 3))
    model_feats = rng.normal(size=(2000, 32)).astype(np.float32)
    scene_feats = model_feats[idx] + 0.05 * rng.normal(size=(600, 32)).astype(np.float32)
    wrong = rng.random(600) > inlier_share
    scene_feats[wrong] = rng.normal(size=(wrong.sum(), 32))
    return model, model_feats, scene, scene_feats, R, t, int((~wrong).sum())


@pytest.mark.parametrize("backend", ["numpy", "open3d"])
def test_register_recovers_known_pose_with_outliers(backend):
    model, mf, scene, sf, R, t, n_good = _synthetic_problem(0, inlier_share=0.15)
    diameter = 250.0
    reg = ransac_align(model, mf, scene, sf, diameter, params=RansacParams(backend=backend, inlier_frac=0.02), seed=1)
    assert rotation_angle_deg(reg.R, R) < 0.5
    assert np.linalg.norm(reg.t - t) < 1.0
    # Inliers: the correct matches (plus rare lucky wrong ones).
    assert n_good <= reg.n_inliers <= n_good + 10
    assert reg.inlier_ratio == pytest.approx(reg.n_inliers / 600)
    assert reg.fitness > 0.99  # every scene point lies on the posed model
    assert reg.n_correspondences == 600


def test_register_numpy_backend_is_reproducible():
    model, mf, scene, sf, *_ = _synthetic_problem(1, inlier_share=0.1)
    params = RansacParams(inlier_frac=0.02, refine_iterations=0)
    a = ransac_align(model, mf, scene, sf, 250.0, params=params, seed=7)
    b = ransac_align(model, mf, scene, sf, 250.0, params=params, seed=7)
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.t, b.t)
    assert a.n_inliers == b.n_inliers


def test_inlier_counts_rank_candidates():
    """The candidate whose features match more often gets more inliers."""
    model, mf, scene, sf_good, R, t, _ = _synthetic_problem(2, inlier_share=0.3)
    _, _, _, sf_bad, _, _, _ = _synthetic_problem(2, inlier_share=0.08)
    params = RansacParams(inlier_frac=0.02)
    good = ransac_align(model, mf, scene, sf_good, 250.0, params=params, seed=0)
    bad = ransac_align(model, mf, scene, sf_bad, 250.0, params=params, seed=0)
    assert good.n_inliers > 2 * bad.n_inliers


def test_register_rejects_mismatched_inputs():
    with pytest.raises(ValueError, match="features"):
        ransac_align(np.zeros((10, 3)), np.zeros((9, 4)), np.zeros((5, 3)), np.zeros((5, 4)), 1.0)
    with pytest.raises(ValueError, match="extra|Extra"):
        RansacParams(threshold=3)


def test_apply_pca_zeroes_components_without_signal():
    # A textureless object: visual features constant up to 1e-4 noise; the scene adds an
    # offset. Every component is below the noise floor, so the visual part vanishes and
    # the fused features equal the normalised geometric part on both sides.
    rng = np.random.default_rng(3)
    model_vis = 0.01 + 1e-4 * rng.normal(size=(500, 30))
    basis = fit_pca(model_vis, 64)
    assert not basis.informative
    scene_vis = 0.05 + 1e-3 * rng.normal(size=(40, 30))
    np.testing.assert_array_equal(apply_pca(basis, scene_vis), 0.0)
    g = rng.normal(size=(40, 66))
    f = fuse(g, apply_pca(basis, scene_vis))
    np.testing.assert_allclose(f[:, :66], g / np.linalg.norm(g, axis=1, keepdims=True), rtol=1e-5)
    np.testing.assert_array_equal(f[:, 66:], 0.0)
    # Known answer: total variance 1e-4 + 1e-6 is above a 1e-5 floor, so every component
    # is kept, even the weak third one; with the floor at 1e-3 the basis is not informative.
    X = rng.normal(size=(20000, 3)) * np.array([1e-2, 1e-3, 1e-3])
    b = fit_pca(X, 3, min_variance=1e-5)
    assert b.informative
    np.testing.assert_allclose(apply_pca(b, X) @ b.components, X - b.mean, atol=1e-6)
    assert not fit_pca(X, 3, min_variance=1e-3).informative
    np.testing.assert_array_equal(apply_pca(fit_pca(X, 3, min_variance=1e-3), X), 0.0)
    # min_variance=0 keeps everything (the paper's plain PCA), even constant features.
    assert fit_pca(np.ones((10, 4)), 4, min_variance=0.0).informative


# --- choosing estimates per target ---------------------------------------------------


def _cands(rows):
    import pandas as pd

    cols = ["cand_id", "scene_id", "im_id", "obj_id", "t", "evidence", "n_inliers", "prior_score"]
    return pd.DataFrame([dict(zip(cols, r)) for r in rows], columns=cols)


def test_select_estimates_keeps_distinct_instances_in_rank_order():
    from types import SimpleNamespace as T

    from pipeline.method.refinement.selection import select_estimates

    # target (1, 0, 7) has two instances, 100 mm apart; candidates 0 and 1 are the same
    # instance (5 mm apart, diameter 80 mm); candidate 3 is weak; object 9 is one instance
    cands = _cands([
        (0, 1, 0, 7, [0, 0, 500], 0.60, 90, 0.5),
        (1, 1, 0, 7, [5, 0, 500], 0.70, 80, 0.9),
        (2, 1, 0, 7, [100, 0, 500], 0.40, 70, 0.8),
        (3, 1, 0, 7, [-100, 0, 500], 0.10, 10, 0.95),
        (4, 1, 0, 9, [0, 50, 400], 0.30, 50, 0.6),
        (5, 1, 0, 9, [0, 90, 400], 0.50, 40, 0.7),
        (6, 1, 1, 9, [0, 0, 400], 0.50, 40, 0.7),  # image 1 has no target
    ])
    targets = [T(scene_id=1, im_id=0, obj_id=7, inst_count=2), T(scene_id=1, im_id=0, obj_id=9, inst_count=1)]
    diam = {7: 80.0, 9: 80.0}
    out = select_estimates(cands, targets, diam, by="evidence").set_index("cand_id")
    assert sorted(out.index[out.selected]) == [1, 2, 5]
    assert out.loc[1, "target_rank"] == 0 and out.loc[2, "target_rank"] == 1
    assert out.loc[0, "note"] == "duplicate of 1" and out.loc[3, "note"] == "beyond inst_count"
    assert out.loc[6, "note"] == "not a target" and out.loc[4, "note"] == "beyond inst_count"
    # the paper's rule (most inliers) and the prior's ranking choose differently
    by_inliers = select_estimates(cands, targets, diam, by="inliers").set_index("cand_id")
    assert sorted(by_inliers.index[by_inliers.selected]) == [0, 2, 4]
    by_prior = select_estimates(cands, targets, diam, by="prior").set_index("cand_id")
    assert sorted(by_prior.index[by_prior.selected]) == [1, 3, 5]
    # a smaller duplicate radius keeps both hypotheses of the first instance
    tight = select_estimates(cands, targets, diam, by="evidence", duplicate_frac=0.05).set_index("cand_id")
    assert sorted(tight.index[tight.selected]) == [0, 1, 5]
    # ICP fitness alone: candidate 3 fits best for object 7, candidate 4 for object 9
    by_fitness = select_estimates(cands.assign(fitness=[0.5, 0.6, 0.7, 0.9, 0.8, 0.2, 0.1]), targets, diam,
                                  by="fitness").set_index("cand_id")
    assert sorted(by_fitness.index[by_fitness.selected]) == [2, 3, 4]
    with pytest.raises(ValueError, match="'by'"):
        select_estimates(cands, targets, diam, by="luck")


# --- the batched RANSAC's parts (issue 15) ------------------------------------------


def test_fit_triangles_matches_kabsch_on_noisy_and_mirrored_triples():
    from pipeline.method.registration.ransac import fit_triangles

    rng = np.random.default_rng(5)
    B = 500
    src = rng.normal(size=(B, 3, 3)) * 50
    rots = np.stack([random_rotation(rng) for _ in range(B)])
    # exact, slightly noisy and badly inconsistent triples; the last ones mirrored
    noise = rng.choice([0.0, 1.0, 30.0], size=(B, 1, 1))
    dst = np.einsum("bij,bkj->bki", rots, src) + rng.normal(size=(B, 1, 3)) * 100 + rng.normal(size=(B, 3, 3)) * noise
    dst[-50:, :, 2] *= -1
    R, t, res, ok = fit_triangles(src, dst)
    assert ok.all()
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    Rk, tk = kabsch(src, dst)

    def sse(R, t):
        return np.sum((np.einsum("bij,bkj->bki", R, src) + t[:, None] - dst) ** 2, axis=(1, 2))

    # the same least-squares optimum (the rotation itself is not unique for flat triples
    # only in degenerate cases), and the residual it reports is the largest of the three
    np.testing.assert_allclose(sse(R, t), sse(Rk, tk), rtol=1e-9, atol=1e-8)
    worst = np.sqrt(np.max(np.sum((np.einsum("bij,bkj->bki", R, src) + t[:, None] - dst) ** 2, axis=2), axis=1))
    np.testing.assert_allclose(res, worst, atol=1e-8)
    exact = noise[:-50, 0, 0] == 0
    np.testing.assert_allclose(R[:-50][exact], rots[:-50][exact], atol=1e-9)
    # collinear triples are flagged, not fitted
    line = np.array([[[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]])
    assert not fit_triangles(line, line)[3][0]


def test_edge_lengths_of_sampled_triangles_are_exact():
    import math

    from pipeline.method.registration.ransac import edge_lengths

    # Integer coordinates: every squared length is an exact integer, so the batched
    # lengths must equal the correctly rounded ones to the bit, edge by edge.
    rng = np.random.default_rng(8)
    pts = rng.integers(-300, 300, size=(40, 3)).astype(np.float64)
    idx = rng.integers(0, 40, size=(500, 3))
    lengths = edge_lengths(np.ascontiguousarray(pts.T), np.ascontiguousarray(idx.T))
    expected = np.array([[math.dist(pts[i], pts[j]) for i, j in ((a, b), (b, c), (c, a))] for a, b, c in idx]).T
    assert lengths.shape == (3, 500)
    np.testing.assert_array_equal(lengths, expected)


def test_squared_residuals_expansion_matches_direct():
    from pipeline.method.registration.ransac import score_terms, squared_residuals

    rng = np.random.default_rng(6)
    src, dst = rng.normal(size=(400, 3)) * 40, rng.normal(size=(400, 3)) * 40
    R = np.stack([random_rotation(i) for i in range(7)])
    t = rng.normal(size=(7, 3)) * 30
    direct = np.sum((np.einsum("bij,cj->bci", R, src) + t[:, None] - dst[None]) ** 2, axis=2)
    np.testing.assert_allclose(squared_residuals(R, t, score_terms(src, dst)), direct, rtol=1e-9, atol=1e-8)


def test_feature_neighbours_top1_matches_brute_force():
    rng = np.random.default_rng(7)
    q, r = rng.normal(size=(600, 24)), rng.normal(size=(900, 24))
    d = np.linalg.norm(q[:, None] - r[None], axis=2)
    np.testing.assert_array_equal(feature_neighbours(q, r, k=1)[:, 0], np.argmin(d, axis=1))


def test_batched_ransac_recovers_a_known_transform_from_correspondences_with_outliers():
    """Correspondences given directly: 12 % consistent with a known pose (0.3 mm noise),
    the rest random pairs. The winner is the pose; its count is the consistent pairs
    (plus rare lucky outliers); the winner does not depend on the pool size and a seed
    gives the same answer twice."""
    from pipeline.method.registration.ransac import _ransac_numpy

    rng = np.random.default_rng(8)
    C, n_good = 1500, 180
    src = rng.normal(size=(C, 3)) * [60, 40, 25]
    R, t = random_rotation(rng), np.array([-30.0, 15.0, 700.0])
    dst = rng.normal(size=(C, 3)) * [60, 40, 25] + t  # outliers: unrelated points in the same volume
    dst[:n_good] = src[:n_good] @ R.T + t + rng.normal(scale=0.3, size=(n_good, 3))
    perm = rng.permutation(C)
    src, dst = src[perm], dst[perm]
    params = RansacParams(max_iterations=20000)
    found = _ransac_numpy(src, dst, 3.0, params, np.random.default_rng(0), pool=8)
    count, Re, te = found[0]
    assert rotation_angle_deg(Re, R) < 1.0 and np.linalg.norm(te - t) < 2.0
    assert n_good - 5 <= count <= n_good + 10
    assert [c for c, _, _ in found] == sorted((c for c, _, _ in found), reverse=True)
    alone = _ransac_numpy(src, dst, 3.0, params, np.random.default_rng(0), pool=1)
    np.testing.assert_array_equal(alone[0][1], Re)
    again = _ransac_numpy(src, dst, 3.0, params, np.random.default_rng(0), pool=8)
    for (c1, R1, t1), (c2, R2, t2) in zip(found, again):
        assert c1 == c2
        np.testing.assert_array_equal(R1, R2)
        np.testing.assert_array_equal(t1, t2)


@pytest.mark.parametrize("score", ["fitness", "inliers"])
def test_ransac_hypotheses_scores_recover_the_pose(score):
    model, mf, scene, sf, R, t, n_good = _synthetic_problem(4, inlier_share=0.12)
    params = RansacParams(inlier_frac=0.02, rank_by=score)
    hyps = ransac_hypotheses(model, mf, scene, sf, 250.0, params=params, seed=3, k=3)
    assert rotation_angle_deg(hyps[0].R, R) < 0.5 and np.linalg.norm(hyps[0].t - t) < 1.0
    assert hyps[0].fitness > 0.99 and n_good <= hyps[0].n_inliers <= n_good + 10
    assert len(hyps) >= 2  # runners-up, distinct from the winner
    assert all(rotation_angle_deg(h.R, hyps[0].R) > 30 or np.linalg.norm(h.t - hyps[0].t) > 50 for h in hyps[1:])
    first = ransac_align(model, mf, scene, sf, 250.0, params=params, seed=3)
    np.testing.assert_array_equal(first.R, hyps[0].R)

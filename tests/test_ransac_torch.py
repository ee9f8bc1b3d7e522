"""The torch RANSAC (issue 31's GPU path) against the numpy one, on the CPU: the same
samples and checks give the same pool (counts, order, poses to rounding), the same
registrations and the same feature matches."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.method.registration import ransac_torch
from pipeline.method.registration.ransac import (
    RansacParams,
    _ransac_numpy,
    build_correspondences,
    feature_neighbours,
    ransac_hypotheses,
)
from pipeline.method.registration.ransac_torch import feature_neighbours_torch, ransac_pool_torch


def _problem(seed: int, noise: float, n_model: int = 800, n_scene: int = 300) -> tuple:
    """A model (N, 3) mm with features (N, 16), and a posed, noisy partial scene with
    features whose noise ``noise`` sets the share of right matches."""
    rng = np.random.default_rng(seed)
    mp = rng.normal(size=(n_model, 3)) * 40
    mf = rng.normal(size=(n_model, 16)).astype(np.float32)
    R, t = Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 100
    idx = rng.choice(n_model, n_scene, replace=False)
    sp = mp[idx] @ R.T + t + rng.normal(size=(n_scene, 3))
    sf = mf[idx] + rng.normal(size=(n_scene, 16)).astype(np.float32) * noise
    return mp, mf, sp, sf


def _batches_drawn(seed: int, C: int, params: RansacParams, after: np.random.Generator) -> int:
    """How many batches a RANSAC loop drew from ``default_rng(seed)`` to leave it in
    ``after``'s state."""
    rng, done, n = np.random.default_rng(seed), 0, 0
    while rng.bit_generator.state != after.bit_generator.state:
        B = min(params.batch_size, params.max_iterations - done)
        rng.integers(0, C, size=(B, 3))
        done, n = done + B, n + 1
        assert done <= params.max_iterations
    return n


@pytest.mark.parametrize("pool", [1, 32])
def test_the_torch_loop_gives_the_numpy_loops_pool(pool):
    """From a clear winner (one batch) to matches near chance (every batch): the same
    counts in the same order, the same poses to rounding. Small batches make the loop
    stop inside a chunk of the torch path (chunks of 1, 2, 4, ... batches) and run to
    max_iterations with a short last batch."""
    params = RansacParams(batch_size=40, max_iterations=1010)
    stops = set()
    for seed, noise in enumerate([0.3, 0.9, 1.1, 1.3, 1.6, 2.5]):
        mp, mf, sp, sf = _problem(seed, noise)
        corr, _ = build_correspondences(mf, sf, params)
        src, dst = mp[corr[:, 0]], sp[corr[:, 1]]
        rng = np.random.default_rng(seed)
        a = _ransac_numpy(src, dst, 8.0, params, rng, pool=pool)
        stops.add(_batches_drawn(seed, len(src), params, rng))
        b = ransac_pool_torch(src, dst, 8.0, params, np.random.default_rng(seed), pool=pool, device="cpu")
        assert [h[0] for h in b] == [h[0] for h in a], (seed, noise)
        for (_, Ra, ta), (_, Rb, tb) in zip(a, b):
            np.testing.assert_allclose(Rb, Ra, atol=1e-9)
            np.testing.assert_allclose(tb, ta, atol=1e-9)
    # one batch, a stop inside the torch path's third chunk (batches 4-7), and all 26
    assert 1 in stops and any(4 < n < 7 for n in stops) and 26 in stops, stops


def test_the_torch_loop_keeps_the_placeholder_when_nothing_fits():
    """Every sample degenerate (all scene points at one place): no fit, the identity
    placeholder with count -1, as the numpy loop returns."""
    params = RansacParams(batch_size=50, max_iterations=200)
    src = np.random.default_rng(0).normal(size=(30, 3))
    dst = np.zeros((30, 3))
    a = _ransac_numpy(src, dst, 1.0, params, np.random.default_rng(1), pool=4)
    b = ransac_pool_torch(src, dst, 1.0, params, np.random.default_rng(1), pool=4, device="cpu")
    assert [h[0] for h in a] == [h[0] for h in b] == [-1]
    np.testing.assert_allclose(b[0][1], np.eye(3))
    np.testing.assert_allclose(b[0][2], a[0][2], atol=1e-12)


def test_a_chunk_holds_at_most_the_residuals_it_may(monkeypatch):
    """With a residual budget of two batches, the loop evaluates at most two batches at
    once, and still gives the numpy loop's pool."""
    params = RansacParams(batch_size=40, max_iterations=600)
    mp, mf, sp, sf = _problem(5, 2.5)
    corr, _ = build_correspondences(mf, sf, params)
    src, dst = mp[corr[:, 0]], sp[corr[:, 1]]
    monkeypatch.setattr(ransac_torch, "CHUNK_ELEMENTS", 2 * 40 * len(src))
    seen = []
    real_edge_lengths = ransac_torch.edge_lengths

    def spy(points_t, idx_t):
        seen.append(idx_t.shape[1])
        return real_edge_lengths(points_t, idx_t)

    monkeypatch.setattr(ransac_torch, "edge_lengths", spy)
    a = _ransac_numpy(src, dst, 8.0, params, np.random.default_rng(0), pool=8)
    b = ransac_pool_torch(src, dst, 8.0, params, np.random.default_rng(0), pool=8, device="cpu")
    assert [h[0] for h in a] == [h[0] for h in b]
    assert max(seen) == 80 and seen[:2] == [40, 40]  # chunks 1, 2, 2, ... batches (two calls each)


@pytest.mark.parametrize("k", [1, 3])
def test_feature_neighbours_on_torch_are_numpys(k):
    rng = np.random.default_rng(k)
    q, r = rng.normal(size=(700, 24)), rng.normal(size=(1500, 24))
    got = feature_neighbours_torch(q, r, k, device="cpu")
    assert got.dtype == np.int64 and got.shape == (700, k)
    np.testing.assert_array_equal(got, feature_neighbours(q, r, k))
    np.testing.assert_array_equal(feature_neighbours(q, r, k, device="cpu"), got)


def test_feature_neighbours_on_torch_refuse_mismatched_dims():
    with pytest.raises(ValueError, match="feature dims differ"):
        feature_neighbours_torch(np.zeros((3, 4)), np.zeros((5, 6)), device="cpu")


@pytest.mark.parametrize("rank_by,mutual", [("fitness", False), ("inliers", False), ("fitness", True)])
def test_ransac_hypotheses_on_torch_are_numpys(rank_by, mutual):
    """The whole registration (matching, loop, ranking, refits): the same hypotheses,
    inlier counts and fitness, poses to rounding, and the right pose first."""
    params = RansacParams(rank_by=rank_by, mutual=mutual, min_mutual=10)
    for seed, noise in enumerate([0.5, 1.0, 1.4]):
        mp, mf, sp, sf = _problem(10 + seed, noise)
        a = ransac_hypotheses(mp, mf, sp, sf, 160.0, params=params, seed=seed, k=3)
        b = ransac_hypotheses(mp, mf, sp, sf, 160.0, params=params, seed=seed, k=3, device="cpu")
        assert [(h.n_inliers, h.fitness, h.n_correspondences) for h in b] == \
            [(h.n_inliers, h.fitness, h.n_correspondences) for h in a], (seed, noise)
        for ha, hb in zip(a, b):
            np.testing.assert_allclose(hb.R, ha.R, atol=1e-9)
            np.testing.assert_allclose(hb.t, ha.t, atol=1e-9)


def test_the_open3d_backend_has_no_torch_path():
    mp, mf, sp, sf = _problem(0, 0.5)
    with pytest.raises(ValueError, match="numpy backend"):
        ransac_hypotheses(mp, mf, sp, sf, 160.0, params=RansacParams(backend="open3d"), device="cpu")

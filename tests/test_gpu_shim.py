"""The GPU check's open3d stand-in (scripts/gpu_shim/open3d) against open3d itself, on
the same clouds: the check substitutes it on a machine that cannot receive open3d, so
what it computes there must be what open3d computes here."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def shim():
    spec = importlib.util.spec_from_file_location("open3d_shim", ROOT / "scripts" / "gpu_shim" / "open3d" / "__init__.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _cloud(seed: int, n: int = 1500) -> np.ndarray:
    """A bumpy sheet with a detached blob, a few far outliers and some exact duplicates (mm)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-40, 40, (n, 2))
    sheet = np.column_stack([uv, 4 * np.sin(uv[:, 0] / 9) + rng.normal(0, 0.3, n)])
    blob = rng.normal([120, 0, 0], 3, (60, 3))
    far = rng.uniform(-300, 300, (8, 3))
    pts = np.vstack([sheet, blob, far, sheet[:5], sheet[:5]])
    return pts


@pytest.mark.parametrize("seed", [0, 1])
def test_normals_equal_open3d_up_to_sign(shim, seed):
    pts = _cloud(seed)
    for radius, max_nn in ((6.0, 30), (2.0, 30), (15.0, 10)):
        ref = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        ref.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
        ours = shim.geometry.PointCloud(shim.utility.Vector3dVector(pts))
        ours.estimate_normals(shim.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
        a, b = np.asarray(ref.normals), np.asarray(ours.normals)
        cos = np.abs((a * b).sum(1))
        # equal up to sign except where the neighbourhood's two smallest eigenvalues tie
        # (the far, isolated points); ties at the k-th neighbour are measure zero here
        assert np.quantile(cos, 0.99) > 1 - 1e-9 and np.mean(cos > 1 - 1e-6) > 0.99, (radius, max_nn)


@pytest.mark.parametrize("seed", [0, 1])
def test_statistical_outliers_equal_open3d(shim, seed):
    pts = _cloud(seed)
    for nb, ratio in ((20, 3.0), (10, 1.0)):
        _, ref = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).remove_statistical_outlier(nb, ratio)
        _, ours = shim.geometry.PointCloud(pts).remove_statistical_outlier(nb, ratio)
        assert sorted(ref) == sorted(ours) and len(ours) < len(pts)


@pytest.mark.parametrize("seed", [0, 1])
def test_dbscan_gives_open3d_s_partition(shim, seed):
    pts = _cloud(seed)
    ref = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).cluster_dbscan(eps=8.0, min_points=5))
    ours = shim.geometry.PointCloud(pts).cluster_dbscan(eps=8.0, min_points=5)
    assert np.array_equal(ref < 0, ours < 0)
    # the same clusters, whatever their numbers
    pairs = {(int(a), int(b)) for a, b in zip(ref[ref >= 0], ours[ours >= 0])}
    assert len(pairs) == len(set(ref[ref >= 0])) == len(set(ours[ours >= 0])) >= 2


def test_anything_else_fails_loudly(shim):
    with pytest.raises(NotImplementedError, match="open3d.pipelines.registration.registration_ransac"):
        shim.pipelines.registration.registration_ransac_based_on_correspondence
    with pytest.raises(NotImplementedError, match="open3d.t.geometry"):
        shim.t.geometry


@pytest.mark.parametrize("seed", [0, 1])
def test_fpfh_equals_open3d(shim, seed):
    """FPFH as the default geometric encoder computes it (radius search, and hybrid with
    max_nn), on a bumpy sheet with a detached blob and isolated far points (no
    neighbour: all zero), with the sheet's normals estimated by open3d."""
    pts = _cloud(seed)[:-10]  # without the duplicates: which of two coincident points is "itself" is open3d's choice
    ref = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    ref.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=6.0, max_nn=30))
    normals = np.asarray(ref.normals)
    ours = shim.geometry.PointCloud(shim.utility.Vector3dVector(pts))
    ours.normals = shim.utility.Vector3dVector(normals)
    for radius, max_nn in ((8.0, None), (15.0, None), (15.0, 40), (1.0, 10)):
        if max_nn is None:
            a_search, b_search = o3d.geometry.KDTreeSearchParamRadius(radius), \
                shim.geometry.KDTreeSearchParamRadius(radius)
        else:
            a_search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn)
            b_search = shim.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn)
        a = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(ref, a_search).data)
        b = shim.pipelines.registration.compute_fpfh_feature(ours, b_search).data
        assert b.shape == a.shape == (33, len(pts))
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9, err_msg=f"radius {radius}, max_nn {max_nn}")
        assert (a[:, -8:] == 0).all()  # the far points have no neighbour
        assert radius < 8 or (a[:, :100] != 0).any(axis=0).all()  # the sheet's do

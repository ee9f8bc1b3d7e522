"""A stand-in for the few open3d calls of the pipeline's paper configuration, for the GPU
check only (``scripts/gpu_check.sh`` puts this folder on ``PYTHONPATH`` when the machine
cannot import open3d; nothing else does).

Why: the GPU machine has no network, and what reaches it is limited to 64 MiB, while
open3d-cpu's wheel is 100 MB (61 MB even as tar.xz). With GeDi + DINOv2 the pipeline
calls open3d only for point-cloud housekeeping on the CPU: normal estimation, DBSCAN
and statistical outlier removal of lifted depth points, and the optional open3d RANSAC
backend and FPFH encoder (not used by that configuration). This module computes the
first three with scipy, as open3d defines them:

- ``PointCloud.estimate_normals(KDTreeSearchParamHybrid(radius, max_nn))``: the
  eigenvector of the smallest eigenvalue of the covariance of the (at most ``max_nn``)
  nearest points within ``radius``, the point itself included; fewer than 3
  neighbours give (0, 0, 1), as open3d does. The sign is arbitrary (the pipeline
  orients normals itself).
- ``PointCloud.cluster_dbscan(eps, min_points)``: DBSCAN, the point itself counted among
  its neighbours within ``eps`` (as open3d counts it): core points joined when within
  ``eps``, a border point to a cluster of a core point within ``eps``, noise -1. Cluster
  numbers may differ from open3d's; the partition is the same up to border points that
  two clusters reach.
- ``PointCloud.remove_statistical_outlier(nb_neighbors, std_ratio)``: a point's mean
  distance to its ``nb_neighbors`` nearest points (itself included, as open3d's KNN
  search returns it), kept when positive and below mean + std_ratio x std (Bessel's
  sample std) of the positive means.

``tests/test_gpu_shim.py`` compares each with open3d on the same clouds. Any other
open3d name raises ``NotImplementedError`` naming it, so the check cannot silently use
something this stand-in does not do.
"""

from __future__ import annotations

import numpy as np

__version__ = "0.0-gpu-check-shim"


class _Missing:
    """A namespace whose unknown attributes fail loudly."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str):
        raise NotImplementedError(f"open3d stand-in (scripts/gpu_shim): open3d.{self._name}.{attr} is not provided")


class _Utility(_Missing):
    def __init__(self) -> None:
        super().__init__("utility")
        self.random = _Random()

    @staticmethod
    def Vector3dVector(a) -> np.ndarray:  # noqa: N802  (open3d's name)
        return np.array(a, dtype=np.float64).reshape(-1, 3)

    @staticmethod
    def Vector2iVector(a) -> np.ndarray:  # noqa: N802
        return np.array(a, dtype=np.int32).reshape(-1, 2)


class _Random(_Missing):
    def __init__(self) -> None:
        super().__init__("utility.random")

    @staticmethod
    def seed(_seed: int) -> None:  # the stand-in draws nothing at random
        return None


class KDTreeSearchParamHybrid:
    def __init__(self, radius: float, max_nn: int) -> None:
        self.radius, self.max_nn = float(radius), int(max_nn)


class KDTreeSearchParamRadius:
    def __init__(self, radius: float) -> None:
        self.radius, self.max_nn = float(radius), None


class PointCloud:
    """``points`` and ``normals`` as (N, 3) float64 arrays."""

    def __init__(self, points=None) -> None:
        self.points = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.normals = np.zeros((0, 3))

    def estimate_normals(self, search_param: KDTreeSearchParamHybrid) -> None:
        from scipy.spatial import cKDTree

        pts = self.points
        k = min(int(search_param.max_nn or len(pts)), len(pts))
        normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
        if k == 0:
            self.normals = normals
            return
        dist, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=search_param.radius)
        dist, idx = dist.reshape(len(pts), k), idx.reshape(len(pts), k)
        valid = np.isfinite(dist)
        count = valid.sum(1)
        safe = np.where(valid, idx, 0)
        nb = pts[safe] * valid[..., None]
        mean = nb.sum(1) / np.maximum(count, 1)[:, None]
        centred = (pts[safe] - mean[:, None]) * valid[..., None]
        cov = np.einsum("nki,nkj->nij", centred, centred) / np.maximum(count, 1)[:, None, None]
        _, vecs = np.linalg.eigh(cov)
        ok = count >= 3
        normals[ok] = vecs[ok, :, 0]
        self.normals = normals

    def cluster_dbscan(self, eps: float, min_points: int, print_progress: bool = False) -> np.ndarray:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        n = len(self.points)
        if n == 0:
            return np.zeros(0, dtype=np.int32)
        pairs = cKDTree(self.points).query_pairs(float(eps), output_type="ndarray")  # i < j within eps
        degree = np.bincount(pairs.ravel(), minlength=n) + 1  # the point itself counts
        core = degree >= int(min_points)
        both = pairs[core[pairs[:, 0]] & core[pairs[:, 1]]]
        graph = coo_matrix((np.ones(len(both)), (both[:, 0], both[:, 1])), shape=(n, n))
        _, comp = connected_components(graph, directed=False)
        labels = np.full(n, -1, dtype=np.int64)
        core_ids = np.flatnonzero(core)
        _, labels[core_ids] = np.unique(comp[core_ids], return_inverse=True)
        # a border point joins the cluster of a core point within eps (the lowest-numbered)
        for a, b in ((0, 1), (1, 0)):
            reach = pairs[core[pairs[:, a]] & ~core[pairs[:, b]]]
            for border in np.unique(reach[:, b]):
                cands = labels[reach[reach[:, b] == border, a]]
                labels[border] = cands.min() if labels[border] < 0 else min(labels[border], cands.min())
        return labels.astype(np.int32)

    def remove_statistical_outlier(self, nb_neighbors: int, std_ratio: float):
        from scipy.spatial import cKDTree

        pts = self.points
        k = min(int(nb_neighbors), len(pts))
        if k < 1 or len(pts) == 0:
            return self, np.arange(0)
        dist, _ = cKDTree(pts).query(pts, k=k)
        avg = np.asarray(dist, dtype=np.float64).reshape(len(pts), k).mean(1)
        # a point whose neighbours all coincide with it (mean 0) counts nowhere and is dropped
        valid = avg > 0
        n = int(valid.sum())
        if n == 0:
            return PointCloud(), []
        mean = avg[valid].mean()
        std = np.sqrt(((avg[valid] - mean) ** 2).sum() / (n - 1)) if n > 1 else 0.0
        keep = np.flatnonzero(valid & (avg < mean + std_ratio * std))
        return PointCloud(pts[keep]), keep.tolist()


class _Geometry(_Missing):
    PointCloud = PointCloud
    KDTreeSearchParamHybrid = KDTreeSearchParamHybrid
    KDTreeSearchParamRadius = KDTreeSearchParamRadius

    def __init__(self) -> None:
        super().__init__("geometry")


utility = _Utility()
geometry = _Geometry()
pipelines = _Missing("pipelines")
core = _Missing("core")
t = _Missing("t")

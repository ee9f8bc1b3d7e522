"""A stand-in for the few open3d calls of the pipeline's paper configuration, for the GPU
check only (``scripts/gpu_check.sh`` puts this folder on ``PYTHONPATH`` when the machine
cannot import open3d; nothing else does).

Why: the GPU machine has no network, and what reaches it is limited to 64 MiB, while
open3d-cpu's wheel is 100 MB (61 MB even as tar.xz). With GeDi + DINOv2 the pipeline
calls open3d only for point-cloud housekeeping on the CPU: normal estimation, DBSCAN
and statistical outlier removal of lifted depth points, and the optional open3d RANSAC
backend (not used there). The check also runs the default encoders' stand-ins, whose
geometric encoder is open3d's FPFH. This module computes those four with numpy and
scipy, as open3d defines them:

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
- ``pipelines.registration.compute_fpfh_feature(pcd, search)`` (radius or hybrid search):
  Rusu's FPFH as open3d computes it. A point's neighbours are those of the search
  without itself; each (point, neighbour) pair gives the three angles of
  the Darboux frame, taken from the end whose normal is more nearly perpendicular to the
  line between them (the pair features are zero when the points coincide or the line is
  parallel to that normal), binned in 11 bins each, with 100 / (neighbours) a pair: the
  SPFH (33 values). The FPFH is the SPFH plus the neighbours' SPFH weighted by 1 /
  squared distance, each third scaled to sum to 100. The sums run in another order than
  open3d's, so values agree to rounding.

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


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (P, 3) arrays, summed left to right as open3d's Eigen
    does: in another order, pairs whose line runs along both normals (|cos| near 1 at
    both ends) can take the other end's frame, and their third feature lands at the
    other end of the histogram (seen on a noisy sheet, tests/test_gpu_shim.py)."""
    return (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (P, 3) arrays, as Eigen writes them out (np.cross's
    argument handling costs more than the products at a few million rows)."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def _pair_bins(p: np.ndarray, n: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The histogram bins (P, 3) int64 (0-10, 11-21, 22-32) of the pair features of the
    pairs (i, j) of points p (N, 3) with normals n (N, 3), and the pairs' squared
    distances (P,)."""
    d = p[j] - p[i]
    d2 = _dot(d, d)
    length = np.sqrt(d2)
    safe = np.where(length > 0, length, 1.0)
    ni, nj = n[i], n[j]
    a1 = _dot(ni, d) / safe
    a2 = _dot(nj, d) / safe
    # open3d compares acos(|a1|) > acos(|a2|): the same as |a1| < |a2|, acos falling
    # (where two cosines a last bit apart meet one acos value, open3d's build turned out
    # to swap, as this does, where the C library's acos would not)
    swap = np.abs(a1) < np.abs(a2)
    n1 = np.where(swap[:, None], nj, ni)
    n2 = np.where(swap[:, None], ni, nj)
    d[swap] *= -1.0
    f2 = np.where(swap, -a2, a1)
    v = _cross(d, n1)
    v_norm = np.sqrt(_dot(v, v))
    v /= np.where(v_norm > 0, v_norm, 1.0)[:, None]
    w = _cross(n1, v)
    f1 = _dot(v, n2)
    f0 = np.arctan2(_dot(w, n2), _dot(n1, n2))
    zero = (length == 0) | (v_norm == 0)
    bins = np.empty((len(d), 3), np.int64)
    for col, (f, lo, width) in enumerate(((f0, -np.pi, 2 * np.pi), (f1, -1.0, 2.0), (f2, -1.0, 2.0))):
        f = np.where(zero, 0.0, f)
        # open3d's own expressions, so that a feature on a bin's edge falls as there
        b = np.floor(11 * (f + np.pi) / (2.0 * np.pi)) if col == 0 else np.floor(11 * (f + 1.0) * 0.5)
        bins[:, col] = np.clip(b, 0, 10).astype(np.int64) + 11 * col
    return bins, d2


PAIR_CHUNK = 1 << 18
"""Pairs evaluated per task of :func:`compute_fpfh_feature`'s thread pool (numpy releases
the GIL over arrays this long, so the chunks run on every core, as open3d's OpenMP loop
does)."""


def _neighbour_pairs(p: np.ndarray, search) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's neighbours by ``search`` without itself: pairs i, j (P,), and each
    point's count with itself (N,)."""
    from scipy.spatial import cKDTree

    tree, N = cKDTree(p), len(p)
    if search.max_nn is None:  # every point within the radius, both ways
        pairs = tree.query_pairs(search.radius, output_type="ndarray")
        i = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
        j = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
        return i, j, np.bincount(i, minlength=N) + 1
    k = min(int(search.max_nn), N)  # the max_nn nearest within the radius, the first itself
    dist, idx = tree.query(p, k=k, distance_upper_bound=search.radius)
    dist, idx = np.reshape(dist, (N, k)), np.reshape(idx, (N, k))
    valid = np.isfinite(dist)
    count = valid.sum(1)
    valid[:, 0] = False
    i = np.repeat(np.arange(N), k).reshape(N, k)[valid]
    return i, idx[valid].astype(np.int64), count


class _Feature:
    """``compute_fpfh_feature``'s result: ``data`` (33, N) float64."""

    def __init__(self, data: np.ndarray) -> None:
        self.data = data

    def dimension(self) -> int:
        return int(self.data.shape[0])

    def num(self) -> int:
        return int(self.data.shape[1])


def compute_fpfh_feature(pcd: PointCloud, search) -> _Feature:
    """open3d.pipelines.registration.compute_fpfh_feature (see the module docstring)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    from scipy.sparse import csr_matrix

    p, n = pcd.points, pcd.normals
    if len(n) != len(p):
        raise ValueError("open3d stand-in: compute_fpfh_feature needs normals")
    N = len(p)
    i, j, count = _neighbour_pairs(p, search)
    chunks = [slice(s, s + PAIR_CHUNK) for s in range(0, len(i), PAIR_CHUNK)]
    with ThreadPoolExecutor(max_workers=min(len(chunks), os.cpu_count() or 1) or 1) as pool:
        done = list(pool.map(lambda c: _pair_bins(p, n, i[c], j[c]), chunks))
    bins = np.concatenate([b for b, _ in done]) if done else np.zeros((0, 3), np.int64)
    d2 = np.concatenate([x for _, x in done]) if done else np.zeros(0)
    incr = (100.0 / np.maximum(count - 1, 1))[i]
    spfh = sum(np.bincount(i * 33 + bins[:, col], weights=incr, minlength=N * 33) for col in range(3))
    spfh = np.reshape(spfh, (N, 33)) if N else np.zeros((0, 33))
    near = d2 > 0
    acc = csr_matrix((1.0 / d2[near], (i[near], j[near])), shape=(N, N)) @ spfh
    sums = acc.reshape(N, 3, 11).sum(axis=2)
    scale = np.where(sums != 0, 100.0 / np.where(sums != 0, sums, 1.0), 0.0)
    fpfh = (acc.reshape(N, 3, 11) * scale[:, :, None]).reshape(N, 33) + spfh
    fpfh[count <= 1] = 0.0
    return _Feature(np.ascontiguousarray(fpfh.T))


class _Registration(_Missing):
    def __init__(self) -> None:
        super().__init__("pipelines.registration")

    compute_fpfh_feature = staticmethod(compute_fpfh_feature)


class _Pipelines(_Missing):
    def __init__(self) -> None:
        super().__init__("pipelines")
        self.registration = _Registration()


class _Geometry(_Missing):
    PointCloud = PointCloud
    KDTreeSearchParamHybrid = KDTreeSearchParamHybrid
    KDTreeSearchParamRadius = KDTreeSearchParamRadius

    def __init__(self) -> None:
        super().__init__("geometry")


utility = _Utility()
geometry = _Geometry()
pipelines = _Pipelines()
core = _Missing("core")
t = _Missing("t")

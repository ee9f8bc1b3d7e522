"""Seeded point sampling on meshes and point clouds.

All functions are deterministic for a given seed. Points are (N, 3) float32 in mm.
"""

from __future__ import annotations

import numpy as np
import trimesh


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``n`` points uniformly over the surface area of ``mesh``.

    Returns ``(points (n, 3) float32 mm, normals (n, 3) float32 unit)``; each normal is
    the normal of the face the point lies on (outward for a consistently wound mesh).
    """
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("sample_surface needs a trimesh.Trimesh with at least one face")
    if n <= 0:
        raise ValueError(f"sample_surface: n must be positive, got {n}")
    points, face_index = trimesh.sample.sample_surface(mesh, int(n), seed=int(seed))
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[face_index]
    return np.asarray(points, dtype=np.float32), normals.astype(np.float32)


def farthest_point_subsample(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Indices (min(n, P),) int64 of a farthest-point subsample of ``points`` (P, 3).

    The first point is drawn with ``seed``; each next one is the point farthest from
    those already chosen, which spreads samples evenly over the cloud regardless of its
    density (useful for scene clouds whose density falls with depth).
    """
    pts = np.asarray(points, dtype=np.float64)
    P = len(pts)
    n = min(int(n), P)
    if n <= 0:
        return np.zeros(0, dtype=np.int64)
    rng = np.random.default_rng(seed)
    chosen = np.empty(n, dtype=np.int64)
    chosen[0] = rng.integers(P)
    dist = np.sum((pts - pts[chosen[0]]) ** 2, axis=1)
    for i in range(1, n):
        chosen[i] = int(np.argmax(dist))
        np.minimum(dist, np.sum((pts - pts[chosen[i]]) ** 2, axis=1), out=dist)
    return chosen


def voxel_subsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Indices (K,) int64, sorted, of one point per occupied voxel of side ``voxel_size`` mm:
    the point closest to the mean of its voxel. Deterministic."""
    if voxel_size <= 0:
        raise ValueError(f"voxel_subsample: voxel_size must be positive, got {voxel_size}")
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(pts / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    K = len(counts)
    means = np.zeros((K, 3))
    np.add.at(means, inverse, pts)
    means /= counts[:, None]
    d = np.sum((pts - means[inverse]) ** 2, axis=1)
    # Sort by (voxel, distance) and keep the first point of each voxel.
    order = np.lexsort((d, inverse))
    first = np.ones(len(order), dtype=bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    return np.sort(order[first])


def sample_points(
    points: np.ndarray, m: int, seed: int, *, method: str = "random", pad: bool = True
) -> np.ndarray:
    """Indices of ``m`` points of ``points`` (P, 3).

    method: ``"random"`` (uniform without replacement) or ``"fps"`` (farthest point).
    If P < m and ``pad`` is true, all P points are returned followed by random repeats so
    that the result always has length ``m`` (fixed-size arrays downstream); with
    ``pad=False`` only the P indices are returned. Returns (m,) int64 (or (P,) if short
    and not padded).
    """
    P = len(points)
    if m <= 0:
        raise ValueError(f"sample_points: m must be positive, got {m}")
    if P == 0:
        raise ValueError("sample_points: the point cloud is empty")
    rng = np.random.default_rng(seed)
    if P <= m:
        idx = np.arange(P, dtype=np.int64)
        if pad and P < m:
            idx = np.concatenate([idx, rng.integers(0, P, size=m - P)])
        return idx
    if method == "random":
        return np.sort(rng.choice(P, size=m, replace=False)).astype(np.int64)
    if method == "fps":
        return farthest_point_subsample(points, m, seed=int(rng.integers(2**31)))
    raise ValueError(f"sample_points: unknown method {method!r} (known: 'random', 'fps')")

"""Normal estimation for point clouds (open3d), oriented like outward model normals."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def estimate_normals(
    points: np.ndarray,
    radius: float,
    *,
    max_nn: int = 30,
    viewpoint: np.ndarray | None = None,
) -> np.ndarray:
    """Unit normals (N, 3) float32 of ``points`` (N, 3) mm from local PCA.

    radius: neighbourhood radius in mm (at most ``max_nn`` neighbours are used).
    viewpoint: (3,) mm, the camera centre in the points' frame (the origin for
    camera-frame scene points). Normals are flipped to face it, which for a visible
    surface is the outward direction, so they match outward mesh normals. Without a
    viewpoint the normals are oriented away from the centroid, which is outward for
    roughly convex closed objects.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros((0, 3), dtype=np.float32)
    if radius <= 0:
        raise ValueError(f"estimate_normals: radius must be positive, got {radius}")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius), max_nn=int(max_nn)))
    normals = np.asarray(pcd.normals, dtype=np.float64)
    if viewpoint is not None:
        towards = np.asarray(viewpoint, dtype=np.float64).reshape(1, 3) - pts
    else:
        towards = pts - pts.mean(axis=0, keepdims=True)
    flip = np.sum(normals * towards, axis=1) < 0
    normals[flip] *= -1.0
    return normals.astype(np.float32)

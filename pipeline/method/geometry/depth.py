"""Depth images <-> camera-frame point clouds (OpenCV pinhole, mm).

Pixel ``(u, v)`` is column ``u``, row ``v``; its centre is at integer coordinates, so
``lift_depth`` followed by ``project`` returns the same pixels exactly (up to float
round-off). Depth is the z coordinate in mm, 0 where invalid.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"camera matrix K must be (3, 3), got shape {K.shape}")
    return K


def lift_depth(
    depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project valid depth pixels to the camera frame.

    depth: (H, W) float mm (0 or non-finite = invalid); K: (3, 3); mask: (H, W) bool or
    None (all pixels). Returns ``(points (P, 3) float32 mm camera frame, pixels (P, 2)
    int64 (u, v))`` in row-major pixel order.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    K = _check_K(K)
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != depth.shape:
            raise ValueError(f"mask shape {mask.shape} differs from depth shape {depth.shape}")
        valid &= mask
    v, u = np.nonzero(valid)
    z = depth[v, u].astype(np.float64)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    if K[0, 1] != 0:  # skewed cameras: the skew term shifts x with y
        x -= K[0, 1] * y / K[0, 0]
    points = np.stack([x, y, z], axis=1).astype(np.float32)
    pixels = np.stack([u, v], axis=1).astype(np.int64)
    return points, pixels


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Project camera-frame points (P, 3) mm to pixel coordinates (P, 2) float64 (u, v).

    Points must have z > 0.
    """
    K = _check_K(K)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    uvw = pts @ K.T
    return uvw[:, :2] / uvw[:, 2:3]


def remove_outliers(
    points: np.ndarray,
    diameter: float,
    *,
    max_center_dist_frac: float = 1.0,
    nb_neighbors: int = 20,
    std_ratio: float = 3.0,
    cluster_eps_frac: float | None = 0.1,
    cluster_min_points: int = 5,
) -> np.ndarray:
    """Keep mask (P,) bool for an object's lifted depth points (P, 3) mm.

    Segmentation masks bleed onto the background or occluders, which puts a few points
    far behind or in front of the object. Three filters, all scaled by the object
    ``diameter`` (mm), are applied in turn:

    1. drop points farther than ``max_center_dist_frac * diameter`` from the per-axis
       median (no object point can be farther than one diameter from it);
    2. if ``cluster_eps_frac`` is set, keep the largest DBSCAN cluster (neighbourhood
       radius ``cluster_eps_frac * diameter``), which removes separate background blobs;
    3. statistical outlier removal (``nb_neighbors``, ``std_ratio``; open3d).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = len(pts)
    keep = np.ones(P, dtype=bool)
    if P == 0:
        return keep
    if diameter <= 0:
        raise ValueError(f"remove_outliers: diameter must be positive, got {diameter}")
    center = np.median(pts, axis=0)
    keep &= np.linalg.norm(pts - center, axis=1) <= max_center_dist_frac * diameter

    if cluster_eps_frac is not None and keep.sum() > cluster_min_points:
        idx = np.flatnonzero(keep)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx]))
        labels = np.asarray(
            pcd.cluster_dbscan(eps=cluster_eps_frac * diameter, min_points=cluster_min_points)
        )
        if (labels >= 0).any():
            largest = np.bincount(labels[labels >= 0]).argmax()
            keep[idx[labels != largest]] = False

    if nb_neighbors > 0 and keep.sum() > nb_neighbors:
        idx = np.flatnonzero(keep)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx]))
        _, inliers = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
        inlier_mask = np.zeros(len(idx), dtype=bool)
        inlier_mask[np.asarray(inliers, dtype=np.int64)] = True
        keep[idx[~inlier_mask]] = False
    return keep

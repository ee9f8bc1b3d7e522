"""The object's depth points inside a bounding box, without a mask (``freeze estimate --bbox``).

:func:`box_candidate_points` states the rule; its kept points become the candidate's
mask, and from there the scene side treats the box like any mask prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np


@dataclass
class BoxSelection:
    """What :func:`box_candidate_points` kept: points (P, 3) float32 mm (camera frame),
    their pixels (P, 2) int64 (u, v), and the numbers of each step (for pose.json)."""

    points: np.ndarray
    pixels: np.ndarray
    details: dict[str, Any]


def box_candidate_points(
    depth: np.ndarray,
    K: np.ndarray,
    bbox: Sequence[float],
    diameter: float,
    *,
    centre_frac: float = 0.5,
    radius_frac: float = 1.0,
    plane_frac: float = 0.02,
    plane_min_share: float = 0.15,
    plane_ring_share: float = 0.3,
    ring_frac: float = 0.25,
    cluster_eps_frac: float = 0.05,
    seed: int = 0,
) -> BoxSelection:
    """The object's depth points inside a bounding box, without a mask.

    depth (H, W) float mm; K (3, 3); bbox (x, y, w, h) px; diameter mm. The rule:

    1. *Centre.* Lift the valid depth inside the box; the reference point is the
       per-axis median of the points in the box's central window (``centre_frac`` of
       its width and height): a box prior is centred on its object, so the centre sees
       the object. Keep the points within ``radius_frac`` diameters of it (no point of
       the object is farther from a point of the object).
    2. *Support plane* (:func:`_drop_support_plane`). Fit the dominant plane (distance
       ``plane_frac`` x diameter, at least 3 mm); it is the table or a wall, removed
       with every point behind it, when it holds at least ``plane_min_share`` of the
       points *and* at least ``plane_ring_share`` of the valid pixels of a ring around
       the box (``ring_frac`` of its longer side wide).
    3. *Cluster* (:func:`_keep_largest_cluster`). DBSCAN (``cluster_eps_frac`` x
       diameter, at least 3 mm) and keep the largest cluster (ties: the one with most
       points in the central window): it drops parts of neighbouring objects that the
       box overlaps.

    The scene-side outlier filter of the stages (:func:`pipeline.method.geometry.depth.remove_outliers`)
    runs afterwards, as for masks.
    """
    from pipeline.method.geometry.depth import lift_depth

    H, W = depth.shape
    x, y, w, h = (float(v) for v in bbox)
    x0, y0 = max(0, int(math.floor(x))), max(0, int(math.floor(y)))
    x1, y1 = min(W, int(math.ceil(x + w))), min(H, int(math.ceil(y + h)))
    box = np.zeros((H, W), bool)
    box[y0:y1, x0:x1] = True
    pts, pix = lift_depth(depth, K, box)
    details: dict[str, Any] = {"box_points": int(len(pts))}
    if len(pts) < 10:
        return BoxSelection(pts, pix, details)
    # 1. centre
    cx, cy = x + w / 2, y + h / 2
    central = (np.abs(pix[:, 0] - cx) <= centre_frac * w / 2) & (np.abs(pix[:, 1] - cy) <= centre_frac * h / 2)
    ref = np.median(pts[central] if central.sum() >= 10 else pts, axis=0)
    keep = np.linalg.norm(pts - ref, axis=1) <= radius_frac * diameter
    details.update({"centre_mm": [round(float(v), 1) for v in ref], "within_radius": int(keep.sum())})
    # 2. dominant plane; 3. the largest cluster
    ring_width = max(1, int(round(ring_frac * max(w, h))))
    _drop_support_plane(pts, keep, lambda: _ring_points(depth, K, box, (x0, y0, x1, y1), ring_width),
                        max(3.0, plane_frac * diameter), plane_min_share, plane_ring_share, seed, details)
    _keep_largest_cluster(pts, keep, central, max(3.0, cluster_eps_frac * diameter), details)
    details["kept"] = int(keep.sum())
    return BoxSelection(pts[keep], pix[keep], details)


def _ring_points(depth: np.ndarray, K: np.ndarray, box: np.ndarray, corners: tuple[int, int, int, int],
                 width: int) -> np.ndarray:
    """(R, 3) mm: the valid depth of the ring ``width`` px wide around the box (``box``
    (H, W) bool, pixel ``corners`` (x0, y0, x1, y1), x1 and y1 exclusive), clipped to
    the image."""
    from pipeline.method.geometry.depth import lift_depth

    H, W = depth.shape
    x0, y0, x1, y1 = corners
    ring = np.zeros((H, W), bool)
    ring[max(0, y0 - width):min(H, y1 + width), max(0, x0 - width):min(W, x1 + width)] = True
    ring &= ~box
    return lift_depth(depth, K, ring)[0]


def _drop_support_plane(pts: np.ndarray, keep: np.ndarray, ring_points: Callable[[], np.ndarray], thr: float,
                        min_share: float, ring_share_min: float, seed: int, details: dict[str, Any]) -> None:
    """Step 2 of :func:`box_candidate_points`, in place: fit the dominant plane of the
    kept points (``pts`` (P, 3) mm, ``keep`` (P,) bool; open3d RANSAC, distance ``thr``
    mm, seeded) and, when it holds at least ``min_share`` of them and at least
    ``ring_share_min`` of the ring's points (``ring_points()``: (R, 3) mm, the depth
    around the box) lie on it, unmark the points on or behind it (seen from the camera).
    Nothing is fitted with fewer than 50 kept points. Records the plane, its shares and
    whether it was removed in ``details``.

    The plane must continue outside the box: an object's own flat face (a box seen
    face-on) fills its box too, but ends at the box's edge, so it is not removed.
    """
    import open3d as o3d

    details["plane_removed"] = False
    idx = np.flatnonzero(keep)
    if len(idx) >= 50:
        o3d.utility.random.seed(seed)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx].astype(np.float64)))
        plane, inl = pcd.segment_plane(distance_threshold=thr, ransac_n=3, num_iterations=1000)
        a = np.asarray(plane, float)
        a = a / np.linalg.norm(a[:3])
        if a[3] < 0:  # orient the normal towards the camera (origin on the positive side)
            a = -a
        share = len(inl) / len(idx)
        ring_pts = ring_points()
        ring_share = float(np.mean(np.abs(ring_pts @ a[:3] + a[3]) <= thr)) if len(ring_pts) else 0.0
        details.update({"plane": [round(float(v), 4) for v in a], "plane_share": round(share, 3), "ring_on_plane": round(ring_share, 3)})
        if share >= min_share and ring_share >= ring_share_min:
            keep &= (pts @ a[:3] + a[3]) > thr
            details["plane_removed"] = True
    details["after_plane"] = int(keep.sum())


def _keep_largest_cluster(pts: np.ndarray, keep: np.ndarray, central: np.ndarray, eps: float,
                          details: dict[str, Any]) -> None:
    """Step 3 of :func:`box_candidate_points`, in place: DBSCAN the kept points (``pts``
    (P, 3) mm, ``keep`` (P,) bool; ``eps`` mm, 10 points) and unmark all but the largest
    cluster (ties: the one with most points in the box's central window, ``central``
    (P,) bool). Nothing changes with fewer than 10 kept points or no cluster. Records
    the number of clusters and the kept cluster's size in ``details``.

    A box prior is fitted to its object, which fills most of it. (The cluster with most
    points in the central window, the former rule, fails on open objects: the centre of
    the box of the TYO-L basket sees its inside, and that rule kept the inside and the
    handle, 6 % of the kept points within 5 mm of the model at the ground-truth pose;
    the largest cluster is its front wall and rim, 71 %.)
    """
    import open3d as o3d

    idx = np.flatnonzero(keep)
    if len(idx) >= 10:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx].astype(np.float64)))
        labels = np.asarray(pcd.cluster_dbscan(eps=eps, min_points=10))
        if (labels >= 0).any():
            n_lab = labels.max() + 1
            in_centre = np.bincount(labels[(labels >= 0) & central[idx]], minlength=n_lab)
            sizes = np.bincount(labels[labels >= 0], minlength=n_lab)
            best = int(np.lexsort((in_centre, sizes))[-1])
            keep[idx[labels != best]] = False
            details.update({"clusters": int(n_lab), "cluster_points": int(sizes[best])})

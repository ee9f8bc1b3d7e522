"""Visible Surface Discrepancy (VSD) with the BOP 2019 visibility rule.

Inputs are depth images (H, W) in mm along the optical axis, 0 = no measurement /
background; they are converted to distances from the camera centre before comparing,
as the BOP toolkit does. Missing test depth counts as visible (``bop19`` mode), so
VSD also works on shiny objects that the sensor does not see.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Misalignment tolerances of BOP19, as fractions of the object diameter. Built with
#: ``np.arange`` like the toolkit so that thresholds compare bit-identically.
VSD_TAUS: np.ndarray = np.arange(0.05, 0.51, 0.05)


def ray_lengths(K: np.ndarray, width: int, height: int, x0: int = 0, y0: int = 0) -> np.ndarray:
    """(height, width) float64: distance from the camera centre per mm of depth, for the
    pixels of the image region starting at ``(x0, y0)`` (pixel centres at integer
    coordinates, OpenCV). A crop of the full image's array equals the array of the crop,
    bit for bit (each element is computed from its own coordinates)."""
    K = np.asarray(K, dtype=np.float64)
    xs = (np.arange(x0, x0 + width) - K[0, 2]) / K[0, 0]
    ys = (np.arange(y0, y0 + height) - K[1, 2]) / K[1, 1]
    return np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)


def depth_to_distance(depth: np.ndarray, K: np.ndarray, x0: int = 0, y0: int = 0) -> np.ndarray:
    """Distance image (h, w) float64 mm from a depth image (h, w) mm.

    ``(x0, y0)`` is the image position of the top-left pixel when ``depth`` is a crop;
    pixel centres are at integer coordinates (OpenCV).
    """
    h, w = depth.shape
    return depth.astype(np.float64) * ray_lengths(K, w, h, x0, y0)


def _visible(d_test: np.ndarray, d_model: np.ndarray, delta: float) -> np.ndarray:
    # The toolkit takes the difference in float32; keep that for identical ties.
    diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    return ((diff <= delta) | (d_test == 0)) & (d_model > 0)


def visibility_gt(dist_test: np.ndarray, dist_gt: np.ndarray, delta: float) -> np.ndarray:
    """Visible mask (h, w) bool of the model in the GT pose."""
    return _visible(dist_test, dist_gt, delta)


def visibility_est(dist_test: np.ndarray, dist_est: np.ndarray, visib_gt: np.ndarray, delta: float) -> np.ndarray:
    """Visible mask (h, w) bool of the model in the estimated pose.

    Pixels visible in the GT pose where the estimate has a surface count as visible
    too: an occluder explained by the GT must not hide the estimate's errors there.
    """
    return _visible(dist_test, dist_est, delta) | (visib_gt & (dist_est > 0))


def vsd_from_distances(
    dist_test: np.ndarray,
    dist_est: np.ndarray,
    dist_gt: np.ndarray,
    delta: float,
    taus: np.ndarray,
    diameter: float,
) -> np.ndarray:
    """VSD errors (T,) float64 in [0, 1] for each tau (fraction of ``diameter``).

    dist_*: aligned distance images (h, w) in mm; delta in mm; ``step`` pixel cost.
    The error is 1 for every tau when neither pose has a visible pixel.
    """
    visib_gt = visibility_gt(dist_test, dist_gt, delta)
    visib_est = visibility_est(dist_test, dist_est, visib_gt, delta)
    inter = visib_gt & visib_est
    union_count = int((visib_gt | visib_est).sum())
    taus = np.asarray(taus, dtype=np.float64)
    if union_count == 0:
        return np.ones(len(taus))
    comp_count = union_count - int(inter.sum())
    dists = np.abs(dist_gt[inter] - dist_est[inter]) / diameter
    bad = (dists[None, :] >= taus[:, None]).sum(1)
    return (bad + comp_count) / float(union_count)


def vsd(
    depth_test: np.ndarray,
    depth_est: np.ndarray,
    depth_gt: np.ndarray,
    K: np.ndarray,
    delta: float,
    diameter: float,
    taus: np.ndarray = VSD_TAUS,
    x0: int = 0,
    y0: int = 0,
) -> np.ndarray:
    """VSD errors (T,) from aligned depth images (h, w) in mm.

    depth_est / depth_gt are renders of the model alone (0 off the object). Only the
    bounding box of the two renders matters (visibility needs a rendered surface), so
    the distances are computed on that crop. ``(x0, y0)``: image position of the
    images' top-left pixel when they are crops of the image (0, 0 for full images).
    """
    rendered = (depth_est > 0) | (depth_gt > 0)
    rows = np.flatnonzero(rendered.any(1))
    if len(rows) == 0:
        return np.ones(len(taus))
    cols = np.flatnonzero(rendered.any(0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    crop = (slice(r0, r1), slice(c0, c1))
    return vsd_from_distances(
        depth_to_distance(depth_test[crop], K, x0 + c0, y0 + r0),
        depth_to_distance(depth_est[crop], K, x0 + c0, y0 + r0),
        depth_to_distance(depth_gt[crop], K, x0 + c0, y0 + r0),
        delta,
        taus,
        diameter,
    )


class Crop(NamedTuple):
    """A depth render (h, w) float32 mm covering image pixels [y0, y0+h) x [x0, x0+w)."""

    depth: np.ndarray
    x0: int
    y0: int


def vsd_crops(
    depth_test: np.ndarray,
    est: Crop | None,
    gt: Crop | None,
    K: np.ndarray,
    delta: float,
    diameter: float,
    taus: np.ndarray = VSD_TAUS,
) -> np.ndarray:
    """VSD errors (T,) from the full test depth (H, W) and the two renders as crops.

    Same value as :func:`vsd` on the full-size renders: only pixels with a rendered
    surface can be visible, so both crops are pasted into their union box (clipped to
    the image) and compared there. ``None`` is a render with no pixel in the image.
    """
    H, W = depth_test.shape
    crops = [c for c in (est, gt) if c is not None and c.depth.size]
    if not crops:
        return np.ones(len(taus))
    x0 = max(0, min(c.x0 for c in crops))
    y0 = max(0, min(c.y0 for c in crops))
    x1 = min(W, max(c.x0 + c.depth.shape[1] for c in crops))
    y1 = min(H, max(c.y0 + c.depth.shape[0] for c in crops))
    if x1 <= x0 or y1 <= y0:
        return np.ones(len(taus))

    def paste(c: Crop | None) -> np.ndarray:
        out = np.zeros((y1 - y0, x1 - x0), dtype=np.float32)
        if c is None or not c.depth.size:
            return out
        cx0, cy0 = max(c.x0, x0), max(c.y0, y0)
        cx1, cy1 = min(c.x0 + c.depth.shape[1], x1), min(c.y0 + c.depth.shape[0], y1)
        if cx1 > cx0 and cy1 > cy0:
            out[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0] = c.depth[cy0 - c.y0 : cy1 - c.y0, cx0 - c.x0 : cx1 - c.x0]
        return out

    return vsd(depth_test[y0:y1, x0:x1], paste(est), paste(gt), K, delta, diameter, taus, x0=x0, y0=y0)


def sphere_projections_overlap(radius: float, t1: np.ndarray, t2: np.ndarray) -> bool:
    """Whether the image projections of two spheres (centres t1, t2 in mm) may overlap.

    The toolkit's conservative shortcut: VSD is 1 without rendering when this is False.
    """
    t1 = np.asarray(t1, dtype=np.float64).reshape(3)
    t2 = np.asarray(t2, dtype=np.float64).reshape(3)
    if t1[2] == 0 or t2[2] == 0:
        return False
    dist = np.linalg.norm(t1[:2] / t1[2] - t2[:2] / t2[2])
    return bool(dist < radius * (1.0 / t1[2] + 1.0 / t2[2]))


class DistanceCrop(NamedTuple):
    """A model's distance image (h, w) float64 mm from the camera centre (0: no surface),
    covering image pixels [y0, y0+h) x [x0, x0+w) (inside the image)."""

    dist: np.ndarray
    x0: int
    y0: int


def distance_crop(crop: Crop, rays: np.ndarray) -> DistanceCrop:
    """The :class:`DistanceCrop` of a depth :class:`Crop`, clipped to the image.

    rays: :func:`ray_lengths` of the whole image (H, W). The distances equal
    :func:`depth_to_distance` of the crop, bit for bit.
    """
    H, W = rays.shape
    x0, y0 = max(crop.x0, 0), max(crop.y0, 0)
    h, w = crop.depth.shape
    x1, y1 = min(crop.x0 + w, W), min(crop.y0 + h, H)
    if x1 <= x0 or y1 <= y0:
        return DistanceCrop(np.zeros((0, 0)), x0, y0)
    depth = crop.depth[y0 - crop.y0 : y1 - crop.y0, x0 - crop.x0 : x1 - crop.x0]
    return DistanceCrop(depth.astype(np.float64) * rays[y0:y1, x0:x1], x0, y0)


def vsd_distance_crops(
    dist_test: np.ndarray,
    est: DistanceCrop | None,
    gt: DistanceCrop | None,
    delta: float,
    diameter: float,
    taus: np.ndarray = VSD_TAUS,
) -> np.ndarray:
    """VSD errors (T,), as :func:`vsd_crops`, from distance images: the test image's
    (H, W) float64 mm and the two renders' :class:`DistanceCrop` (None: no pixel in the
    image). Computing the distances once per image and once per render, instead of per
    (estimate, GT) pair, gives the same values."""
    crops = [c for c in (est, gt) if c is not None and c.dist.size]
    if not crops:
        return np.ones(len(taus))
    x0 = min(c.x0 for c in crops)
    y0 = min(c.y0 for c in crops)
    x1 = max(c.x0 + c.dist.shape[1] for c in crops)
    y1 = max(c.y0 + c.dist.shape[0] for c in crops)

    def paste(c: DistanceCrop | None) -> np.ndarray:
        if c is not None and c.dist.shape == (y1 - y0, x1 - x0):
            return c.dist  # the union box is this crop's own box
        out = np.zeros((y1 - y0, x1 - x0))
        if c is not None and c.dist.size:
            h, w = c.dist.shape
            out[c.y0 - y0 : c.y0 - y0 + h, c.x0 - x0 : c.x0 - x0 + w] = c.dist
        return out

    return vsd_from_distances(dist_test[y0:y1, x0:x1], paste(est), paste(gt), delta, taus, diameter)

"""Lifting dense 2D feature maps to 3D points, as in FreeZe.

Crop geometry: :mod:`pipeline.method.geometry.crops` (re-exported here). A crop box
``(x0, y0, side)`` is the square of image pixels ``[x0, x0+side)^2`` resized to
``size x size``; image pixel ``u`` maps to crop coordinate
``c = (u - x0 + 0.5) * size/side - 0.5`` (the convention of ``cv2.resize``).

Feature maps. A visual encoder returns ``(D, h, w)`` per crop; cell ``j`` covers crop
pixels ``[j*size/w, (j+1)*size/w)``. Upsampling to the crop's pixel grid is bilinear
with ``align_corners=False`` (cell centres at ``(j+0.5)*size/w - 0.5``, edges clamped),
i.e. ``torch.nn.functional.interpolate(..., mode="bilinear", align_corners=False)``.
A point takes the upsampled feature of its nearest crop pixel.
:func:`sample_features_at_pixels` evaluates exactly that interpolation at the needed
pixels only (``grid_sample`` with the same convention) instead of materialising the
``(D, size, size)`` map.
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from pipeline.method.encoders.registry import VisualEncoder
from pipeline.method.geometry.crops import (  # re-exported: the crop geometry of lifting
    CropBox,
    crop_and_resize,
    image_to_crop_coords,
    mask_to_bbox,
    square_crop_box,
)
from pipeline.method.geometry.depth import lift_depth
from pipeline.formats.bop.extent import point_cloud_diameter  # re-exported

View = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]

__all__ = [
    "CropBox", "View", "crop_and_resize", "image_to_crop_coords", "lift_model_visual_features",
    "lift_scene_visual_features", "mask_to_bbox", "point_cloud_diameter", "sample_features_at_pixels",
    "square_crop_box", "upsample_to_crop",
]


def upsample_to_crop(features: np.ndarray, size: int) -> np.ndarray:
    """Bilinear upsampling (``align_corners=False``) of a map (D, h, w) to (D, size, size)
    float32: the crop's pixel grid. Materialises the map; prefer
    :func:`sample_features_at_pixels` for lifting."""
    t = torch.as_tensor(np.asarray(features, dtype=np.float32))[None]
    return F.interpolate(t, size=(size, size), mode="bilinear", align_corners=False)[0].numpy()


def sample_features_at_pixels(
    features: np.ndarray, box: CropBox, size: int, pixels: np.ndarray
) -> np.ndarray:
    """Features (P, D) float32 of image pixels (P, 2) (u, v) from the map (D, h, w) of
    the crop ``box`` resized to ``size``: the value of :func:`upsample_to_crop` at each
    pixel's nearest crop pixel (clamped to the crop)."""
    feats = torch.as_tensor(np.asarray(features, dtype=np.float32))
    if feats.ndim != 3:
        raise ValueError(f"sample_features_at_pixels: features must be (D, h, w), got {tuple(feats.shape)}")
    if feats.shape[0] == 0:  # the empty encoder of geometry-only runs
        return np.zeros((len(np.asarray(pixels).reshape(-1, 2)), 0), np.float32)
    c = np.clip(np.rint(image_to_crop_coords(pixels, box, size)), 0, size - 1)
    # With align_corners=False, normalised coordinate -1..1 spans the outer edges of the
    # map, so crop pixel c (whose centre is at (c + 0.5) / size of the crop) maps to
    # 2 (c + 0.5) / size - 1 whatever the map resolution; border padding reproduces the
    # edge clamping of F.interpolate.
    grid = torch.as_tensor(2.0 * (c + 0.5) / size - 1.0, dtype=torch.float32)
    out = F.grid_sample(feats[None], grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0, :].T.contiguous().numpy()


def lift_model_visual_features(
    points: np.ndarray,
    views: Sequence[View],
    encoder: VisualEncoder,
    *,
    batch_size: int = 16,
    diameter: float | None = None,
    tol_frac: float = 0.02,
    erode_px: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Visual features of model points from rendered template views.

    points: (N, 3) mm, model frame. views: ``(rgb (S, S, 3) uint8, depth (S, S) float32
    mm, K (3, 3), R_m2c (3, 3), t_m2c (3,) mm)`` per template; each render is already an
    object-centred square crop (any S: it is resized to ``encoder.input_size``).

    Each view is encoded; its foreground pixels (depth > 0) are back-projected through
    the rendered depth into the model frame; each model point takes the feature of its
    nearest back-projected pixel if that lies within ``tol_frac * diameter`` (diameter
    of ``points`` if not given), and features are averaged over the views that see
    the point. Points seen by no view take the feature of the nearest seen point.
    Foreground pixels within ``erode_px`` pixels (of the encoder input) of the
    silhouette are not used: their
    colour is blended with the background by multisampling, and at the silhouette
    the surface is seen at a grazing angle (0 keeps them).

    An encoder with ``dim == 0`` (geometry-only runs) is not called; the view counts
    are still computed.

    Returns ``(features (N, D) float32, view_count (N,) int32)``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(views) == 0:
        raise ValueError("lift_model_visual_features: no views given")
    if diameter is None:
        diameter = point_cloud_diameter(pts)
    tol = tol_frac * diameter
    S_in = encoder.input_size
    acc = np.zeros((len(pts), encoder.dim), dtype=np.float64)
    count = np.zeros(len(pts), dtype=np.int32)
    for start in range(0, len(views), batch_size):
        chunk = views[start : start + batch_size]
        crops = []
        for i, (rgb, depth, *_rest) in enumerate(chunk):
            rgb = np.asarray(rgb)
            if rgb.ndim != 3 or rgb.shape[0] != rgb.shape[1] or rgb.shape[:2] != np.shape(depth):
                raise ValueError(
                    f"view {start + i}: rgb {rgb.shape} and depth {np.shape(depth)} must be the same square size"
                )
            crops.append(crop_and_resize(rgb, (0, 0, rgb.shape[0]), S_in))
        if encoder.dim:
            fmaps = encoder.encode(np.stack(crops))
        else:
            fmaps = np.zeros((len(crops), 0, 1, 1), np.float32)
        for fmap, (rgb, depth, K, R, t) in zip(fmaps, chunk):
            mask = np.asarray(depth) > 0
            if erode_px > 0:
                # erode_px counts encoder-input pixels; one of them spans several render
                # pixels when the render is larger than the encoder input.
                r = erode_px * int(math.ceil(rgb.shape[0] / S_in))
                kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
                mask = cv2.erode(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
            cam_pts, pixels = lift_depth(depth, K, mask)
            if len(cam_pts) == 0:
                continue
            R = np.asarray(R, dtype=np.float64).reshape(3, 3)
            t = np.asarray(t, dtype=np.float64).reshape(1, 3)
            model_pts = (cam_pts.astype(np.float64) - t) @ R  # R^T (x - t), row-wise
            pix_feats = sample_features_at_pixels(fmap, (0, 0, rgb.shape[0]), S_in, pixels)
            dist, idx = cKDTree(model_pts).query(pts, k=1, distance_upper_bound=tol)
            seen = np.isfinite(dist)
            acc[seen] += pix_feats[idx[seen]]
            count[seen] += 1
    seen = count > 0
    if not seen.any():
        raise ValueError(
            f"lift_model_visual_features: no model point lies within {tol:.2f} mm of any "
            "back-projected template pixel; check the views' poses, intrinsics and units"
        )
    feats = np.zeros_like(acc)
    feats[seen] = acc[seen] / count[seen, None]
    if not seen.all():
        _, nearest = cKDTree(pts[seen]).query(pts[~seen], k=1)
        feats[~seen] = feats[seen][nearest]
    return feats.astype(np.float32), count


def lift_scene_visual_features(
    rgb: np.ndarray,
    bbox_xywh: Sequence[float],
    pixels: np.ndarray,
    encoder: VisualEncoder,
    *,
    margin: float = 0.1,
) -> np.ndarray:
    """Visual features (P, D) float32 of scene pixels (P, 2) (u, v) of one detection.

    The square crop around ``bbox_xywh`` (see :func:`square_crop_box`) of ``rgb``
    (H, W, 3) uint8 is resized to ``encoder.input_size``, encoded, and sampled at the
    pixels (usually the foreground pixels whose depth was lifted).
    """
    rgb = np.asarray(rgb)
    box = square_crop_box(bbox_xywh, rgb.shape[:2], margin)
    crop = crop_and_resize(rgb, box, encoder.input_size)
    fmap = encoder.encode(crop[None])[0]
    return sample_features_at_pixels(fmap, box, encoder.input_size, pixels)

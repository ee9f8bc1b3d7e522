"""Square crops of images (no torch: the report and the figures use them too).

A crop box ``(x0, y0, side)`` (ints, image pixels) is the square of image pixels
``[x0, x0+side) x [y0, y0+side)``; it is resized to ``size x size``. With pixel centres
at integer coordinates, image pixel ``u`` maps to crop coordinate
``c = (u - x0 + 0.5) * size/side - 0.5`` (the convention of ``cv2.resize``).
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

CropBox = tuple[int, int, int]


def mask_to_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """BOP bbox ``(x, y, w, h)`` (ints, pixels) of the True pixels of ``mask`` (H, W)."""
    v, u = np.nonzero(np.asarray(mask, dtype=bool))
    if len(u) == 0:
        raise ValueError("mask_to_bbox: the mask is empty")
    return int(u.min()), int(v.min()), int(u.max() - u.min() + 1), int(v.max() - v.min() + 1)


def square_crop_box(
    bbox_xywh: Sequence[float], image_hw: tuple[int, int], margin: float = 0.1
) -> CropBox:
    """Square box ``(x0, y0, side)`` centred on ``bbox_xywh`` (BOP ``x, y, w, h`` pixels).

    side = ceil(max(w, h) * (1 + 2 * margin)): ``margin`` is added on each side as a
    fraction of the longer bbox side. The box may extend beyond the image (``image_hw``
    = (H, W) is only used to check that the bbox lies on the image); cropping pads with
    zeros.
    """
    x, y, w, h = (float(v) for v in bbox_xywh)
    H, W = image_hw
    if w <= 0 or h <= 0:
        raise ValueError(f"square_crop_box: bbox width and height must be positive, got {bbox_xywh}")
    if x >= W or y >= H or x + w <= 0 or y + h <= 0:
        raise ValueError(f"square_crop_box: bbox {bbox_xywh} lies outside the {W}x{H} image")
    side = max(1, int(math.ceil(max(w, h) * (1.0 + 2.0 * margin))))
    x0 = int(round(x + 0.5 * w - 0.5 * side))
    y0 = int(round(y + 0.5 * h - 0.5 * side))
    return x0, y0, side


def crop_and_resize(image: np.ndarray, box: CropBox, size: int, fill: float = 0) -> np.ndarray:
    """Crop ``box`` from ``image`` (H, W, C) or (H, W) and resize to ``size x size``.

    Pixels outside the image are ``fill`` (0, as the encoders see them). Area
    interpolation when shrinking, bilinear when enlarging. Keeps the dtype.
    """
    x0, y0, side = (int(v) for v in box)
    img = np.asarray(image)
    H, W = img.shape[:2]
    out_shape = (side, side) + img.shape[2:]
    crop = np.full(out_shape, fill, dtype=img.dtype)
    sx0, sy0 = max(x0, 0), max(y0, 0)
    sx1, sy1 = min(x0 + side, W), min(y0 + side, H)
    if sx1 > sx0 and sy1 > sy0:
        crop[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = img[sy0:sy1, sx0:sx1]
    if side == size:
        return crop
    interp = cv2.INTER_AREA if side > size else cv2.INTER_LINEAR
    return cv2.resize(crop, (size, size), interpolation=interp)


def image_to_crop_coords(pixels: np.ndarray, box: CropBox, size: int) -> np.ndarray:
    """Image pixel coordinates (P, 2) (u, v) -> crop coordinates (P, 2) float64."""
    x0, y0, side = box
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    scale = size / side
    return (px - np.array([x0, y0], dtype=np.float64) + 0.5) * scale - 0.5

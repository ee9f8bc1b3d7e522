"""A Primesense-like RGB-D sensor model applied to clean renders.

Depth: structured-light shadows (the projector sits ``baseline_mm`` to the right of
the depth camera, so surfaces it cannot see get no depth), missing values along depth
discontinuities and at grazing angles, random dropout blobs, axial noise with
sigma = ``noise_k`` * z^2 (1.5 mm at 1 m by default), an optional quantisation of
disparity, and a working range. Colour: exposure gain, slight blur, vignetting and
pixel noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DepthSensor:
    """Parameters of the depth model (lengths in mm)."""

    baseline_mm: float = 75.0
    noise_k: float = 1.5e-6
    disparity_step_px: float | None = None
    min_range_mm: float = 400.0
    max_range_mm: float = 3500.0
    edge_jump_mm: float = 12.0
    edge_drop_prob: float = 0.6
    grazing_cos: float = 0.12
    dropout_fraction: float = 0.004

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Axial noise standard deviation (mm) at depth z (mm)."""
        return self.noise_k * np.square(z)


def _projector_shadow(depth: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """(H, W) bool: pixels whose surface point the projector cannot see.

    A point at column u and depth z appears in the projector image at
    u - fx * baseline / z; in each row, the nearest point wins each projector column.
    """
    h, w = depth.shape
    valid = depth > 0
    z = np.where(valid, depth, np.inf)
    u = np.arange(w, dtype=np.float64)[None, :]
    up = np.round(u - fx * baseline / np.where(valid, depth, 1.0)).astype(np.int64)
    offset = int(np.ceil(fx * baseline / max(depth[valid].min(initial=1e9), 1.0))) + 2
    col = np.clip(up + offset, 0, w + offset + 1)
    rows = np.repeat(np.arange(h)[:, None], w, axis=1)
    zbuf = np.full((h, w + offset + 2), np.inf)
    np.minimum.at(zbuf, (rows[valid], col[valid]), z[valid])
    seen = zbuf[rows, col]
    return valid & (z > seen + np.maximum(2.0, 0.01 * seen))


def _edges(depth: np.ndarray, jump_mm: float) -> np.ndarray:
    """(H, W) bool: pixels next to a depth jump larger than ``jump_mm`` (or 2 % of z)."""
    big = np.where(depth > 0, depth, 1e6).astype(np.float32)
    small = np.where(depth > 0, depth, 0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    dmax = cv2.dilate(small, kernel)
    dmin = cv2.erode(big, kernel)
    return (depth > 0) & ((dmax - dmin) > np.maximum(jump_mm, 0.02 * depth))


def _grazing(depth: np.ndarray, K: np.ndarray, min_cos: float) -> np.ndarray:
    """(H, W) bool: surfaces seen at a grazing angle (|cos| between normal and ray < min_cos)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    P = np.stack([x, y, depth], axis=-1)
    du = np.gradient(P, axis=1)
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    ray = P / np.maximum(np.linalg.norm(P, axis=-1, keepdims=True), 1e-9)
    cos = np.abs(np.sum(n * ray, axis=-1)) / np.maximum(np.linalg.norm(n, axis=-1), 1e-12)
    return (depth > 0) & (cos < min_cos)


def simulate_depth(depth: np.ndarray, K: np.ndarray, rng: np.random.Generator, sensor: DepthSensor = DepthSensor()) -> np.ndarray:
    """Measured depth (H, W) float32 mm from a clean render (H, W) float32 mm; 0 = no value."""
    depth = np.asarray(depth, np.float32)
    h, w = depth.shape
    valid = (depth >= sensor.min_range_mm) & (depth <= sensor.max_range_mm)
    clean = np.where(valid, depth, 0.0).astype(np.float32)
    drop = _projector_shadow(clean, float(K[0, 0]), sensor.baseline_mm)
    drop |= _edges(clean, sensor.edge_jump_mm) & (rng.random((h, w)) < sensor.edge_drop_prob)
    drop |= _grazing(clean, K, sensor.grazing_cos) & (rng.random((h, w)) < 0.8)
    seeds = (rng.random((h, w)) < sensor.dropout_fraction / 25.0).astype(np.uint8)
    blobs = cv2.dilate(seeds, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))).astype(bool)
    drop |= blobs | (rng.random((h, w)) < sensor.dropout_fraction / 4.0)
    z = clean.astype(np.float64) + rng.standard_normal((h, w)) * sensor.sigma(clean.astype(np.float64))
    if sensor.disparity_step_px:
        fb = float(K[0, 0]) * sensor.baseline_mm
        disp = np.round(fb / np.maximum(z, 1.0) / sensor.disparity_step_px) * sensor.disparity_step_px
        z = fb / np.maximum(disp, 1e-6)
    out = np.where(valid & ~drop, z, 0.0)
    return out.astype(np.float32)


def simulate_rgb(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Camera-like (H, W, 3) uint8 image from a clean render: gain, blur, vignetting, noise."""
    img = rgb.astype(np.float32)
    img *= rng.uniform(0.85, 1.15) * rng.uniform(0.95, 1.05, size=3)[None, None, :]
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.4, 0.8))
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    img *= (1.0 - rng.uniform(0.1, 0.3) * r2)[..., None]
    img += rng.standard_normal(img.shape).astype(np.float32) * rng.uniform(1.0, 3.0)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)

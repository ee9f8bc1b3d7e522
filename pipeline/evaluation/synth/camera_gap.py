"""How a camera image departs from a render of the same scene (the ``hard`` preset).

The templates and the default synthetic scenes come out of one renderer with one
texture per object, so a colour descriptor matches them far better than it matches a
camera image. :class:`CameraGap` describes the departures a real RGB-D camera adds,
and the functions here apply them to a clean render:

- the object's own colours drift between the model (what the templates see) and the
  scene (:func:`drift_colours`: a per-object 3x3 colour matrix near the identity plus an
  offset), as a print fades or a scan's texture is baked under other light;
- specular highlights (:func:`camera_rgb`: a Blinn-Phong lobe from normals estimated on
  the clean depth and a random light direction, on the objects only);
- white balance and exposure (per-channel and global gains), a gamma shift, blur,
  vignetting, and noise with a chromatic part;
- Kinect-like depth: the sensor model's axial noise growing with z², edges and
  quantised disparity (:class:`pipeline.evaluation.synth.sensor.DepthSensor`), plus holes on
  dark and on specular surfaces (:func:`surface_holes`).

Lengths in mm, colours in [0, 255].
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh


@dataclass(frozen=True)
class CameraGap:
    """Ranges of the departures (each drawn per image, or per object for the drift)."""

    colour_drift: float = 0.12
    colour_offset: float = 12.0
    white_balance: tuple[float, float] = (0.8, 1.2)
    exposure: tuple[float, float] = (0.6, 1.4)
    gamma: tuple[float, float] = (0.75, 1.35)
    blur_sigma: tuple[float, float] = (0.5, 1.5)
    vignetting: tuple[float, float] = (0.2, 0.5)
    noise_sigma: tuple[float, float] = (3.0, 8.0)
    chroma_noise: float = 0.5
    specular: tuple[float, float] = (60.0, 160.0)
    shininess: tuple[float, float] = (20.0, 80.0)
    dark_luma: float = 35.0
    dark_hole_prob: float = 0.7
    specular_hole_level: float = 60.0


def drift_colours(mesh: trimesh.Trimesh, rng: np.random.Generator, gap: CameraGap) -> trimesh.Trimesh:
    """A copy of a vertex-coloured mesh whose colours went through a random colour
    matrix ``I + N(0, colour_drift)`` and offset ``N(0, colour_offset)``."""
    out = mesh.copy()
    rgba = np.asarray(mesh.visual.vertex_colors, np.float64)
    M = np.eye(3) + rng.normal(0.0, gap.colour_drift, (3, 3))
    rgb = rgba[:, :3] @ M.T + rng.normal(0.0, gap.colour_offset, 3)
    rgba[:, :3] = np.clip(np.rint(rgb), 0, 255)
    out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=rgba.astype(np.uint8))
    return out


def depth_normals(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals (camera frame, facing the camera) of a depth map (mm); zero where no depth."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    P = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], axis=-1)
    n = np.cross(np.gradient(P, axis=1), np.gradient(P, axis=0))
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n = np.where((np.sum(n * P, axis=-1) > 0)[..., None], -n, n)  # towards the camera
    return np.where((depth > 0)[..., None], n, 0.0)


def camera_rgb(rgb: np.ndarray, depth: np.ndarray, objects: np.ndarray, K: np.ndarray, rng: np.random.Generator,
               gap: CameraGap) -> tuple[np.ndarray, np.ndarray]:
    """(camera-like (H, W, 3) uint8 image, specular highlight (H, W) float in [0, 255])
    from a clean render ``rgb`` with its depth (mm) and the mask of the objects."""
    img = rgb.astype(np.float32)
    n = depth_normals(depth.astype(np.float64), K)
    light = rng.normal(size=3)
    light[2] = -abs(light[2]) - 0.5  # from the camera's side
    light /= np.linalg.norm(light)
    half = light + np.array([0.0, 0.0, -1.0])
    half /= np.linalg.norm(half)
    lobe = np.clip(n @ half, 0.0, 1.0) ** rng.uniform(*gap.shininess)
    highlight = (rng.uniform(*gap.specular) * lobe * objects).astype(np.float32)
    img += highlight[..., None]
    img *= rng.uniform(*gap.exposure) * rng.uniform(*gap.white_balance, size=3)[None, None, :]
    img = 255.0 * (np.clip(img, 0, 255) / 255.0) ** rng.uniform(*gap.gamma)
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(*gap.blur_sigma))
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    img *= (1.0 - rng.uniform(*gap.vignetting) * r2)[..., None]
    sigma = rng.uniform(*gap.noise_sigma)
    grey = rng.standard_normal((h, w, 1)).astype(np.float32)
    chroma = rng.standard_normal((h, w, 3)).astype(np.float32)
    img += sigma * ((1.0 - gap.chroma_noise) * grey + gap.chroma_noise * chroma)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), highlight


def surface_holes(rgb_clean: np.ndarray, highlight: np.ndarray, objects: np.ndarray, rng: np.random.Generator,
                  gap: CameraGap) -> np.ndarray:
    """(H, W) bool: object pixels where an active depth sensor returns nothing: dark
    surfaces (luma of the clean render below ``dark_luma``, with ``dark_hole_prob``)
    and specular spots (highlight above ``specular_hole_level``)."""
    luma = rgb_clean.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    dark = (luma < gap.dark_luma) & (rng.random(luma.shape) < gap.dark_hole_prob)
    return objects & (dark | (highlight > gap.specular_hole_level))

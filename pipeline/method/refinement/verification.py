"""Verification of a pose hypothesis against the observed depth and the candidate mask.

No learned features: the model is rendered at the pose (depth only) in a window around
the candidate, and compared with what the camera saw there. Every term is a fraction in
[0, 1]:

- ``silhouette``: intersection over union of the rendered silhouette's visible part
  (without the pixels where the sensor sees something in front of the model: occluders)
  and the candidate mask;
- ``depth_fit``: of the rendered pixels where the sensor has depth, those where the
  rendered and observed depths agree within ``tol`` mm;
- ``coverage``: of the mask's pixels with depth, those the render explains (depths
  agree within ``tol``): a pose that fits a part of the object well but leaves the rest
  unexplained scores low here;
- ``free_space``: of the rendered pixels where the sensor has depth, those where the
  camera sees *behind* the model by more than ``tol``: the model would stand in empty
  space in front of an observed surface. Pixels where the observed surface is in front
  of the model are occlusions, not evidence against the pose, and count in neither
  ``depth_fit`` nor ``free_space``; sensor holes count nowhere.

Clutter is tolerated: occluders only remove pixels from the comparison, and the mask
terms concern the candidate's own pixels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Hashable, Sequence

import numpy as np

TERMS = ("silhouette", "depth_fit", "coverage", "free_space", "evidence")
"""The terms of :class:`Verification`, in the order of refine's ``hypotheses.parquet``."""


@dataclass(frozen=True)
class Verification:
    """The terms of one pose's verification (see the module docstring) and its score (``value``)."""

    silhouette: float
    depth_fit: float
    coverage: float
    free_space: float
    evidence: float
    value: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def verification_score(silhouette: float, depth_fit: float, coverage: float, free_space: float,
                       evidence: float) -> float:
    """One number from the terms, in [-1, 1]: the mean of the three agreement terms
    (silhouette, depth fit, coverage) minus the free-space violation, plus the feature
    evidence (inlier ratio x ICP fitness, typically 0.01-0.3), which mostly breaks ties
    between poses the depth cannot tell apart (a symmetric shape seen from its axis)."""
    return float((silhouette + depth_fit + coverage) / 3.0 - free_space + evidence)


def verification_window(bbox: Sequence[float], shape: tuple[int, int],
                        margin: float = 0.25) -> tuple[int, int, int, int]:
    """The image window ``(x0, y0, w, h)`` px compared: the candidate's box ``(x, y, w, h)``
    grown by ``margin`` of its size on every side, clipped to the image ``(H, W)``."""
    x, y, w, h = (float(v) for v in bbox)
    H, W = shape
    x0, y0 = max(0, int(math.floor(x - margin * w))), max(0, int(math.floor(y - margin * h)))
    x1, y1 = min(W, int(math.ceil(x + w + margin * w))), min(H, int(math.ceil(y + h + margin * h)))
    return x0, y0, max(0, x1 - x0), max(0, y1 - y0)


def compare_depth(rendered: np.ndarray, observed: np.ndarray, mask: np.ndarray, tol: float,
                  evidence: float = 0.0) -> Verification:
    """The terms from aligned windows: rendered (h, w) float mm (0 off the model),
    observed (h, w) float mm (0 where the sensor has no depth), mask (h, w) bool (the
    candidate's), tol mm."""
    on = rendered > 0
    seen = observed > 0
    both = on & seen
    diff = observed - rendered
    agree = both & (np.abs(diff) <= tol)
    behind = both & (diff > tol)
    visible = on & ~(both & (diff < -tol))
    n_both = int((agree | behind).sum())  # occluded pixels judge nothing
    mask_seen = mask & seen
    union = int((visible | mask).sum())
    silhouette = float((visible & mask).sum() / union) if union else 0.0
    depth_fit = float(agree.sum() / n_both) if n_both else 0.0
    coverage = float((agree & mask_seen).sum() / mask_seen.sum()) if mask_seen.any() else 0.0
    free_space = float(behind.sum() / n_both) if n_both else 0.0
    return Verification(silhouette, depth_fit, coverage, free_space, float(evidence),
                        verification_score(silhouette, depth_fit, coverage, free_space, float(evidence)))


def verify_pose(renderer, key: Hashable, R: np.ndarray, t: np.ndarray, K: np.ndarray, depth: np.ndarray,
                mask: np.ndarray, window: tuple[int, int, int, int], tol: float, evidence: float = 0.0) -> Verification:
    """Verify the model-to-camera pose (R (3, 3), t (3,) mm) of the mesh ``key`` of
    ``renderer`` (a :class:`pipeline.method.render.Renderer` of the image's size) in ``window``
    (:func:`verification_window`) of the observed depth (H, W) mm and the candidate's
    mask (H, W) bool; tol mm."""
    (v,) = verify_poses(renderer, key, [(R, t)], K, depth, mask, window, tol, [evidence])
    return v


def verify_poses(renderer, key: Hashable, poses: Sequence[tuple[np.ndarray, np.ndarray]], K: np.ndarray,
                 depth: np.ndarray, mask: np.ndarray, window: tuple[int, int, int, int], tol: float,
                 evidence: Sequence[float], device: str | None = None) -> list[Verification]:
    """:func:`verify_pose` of several poses (R (3, 3), t (3,) mm) of one mesh in one
    window, with their evidence: each rendered, then compared one at a time in numpy
    (``device`` None) or all together in torch on ``device``
    (:func:`pipeline.method.refinement.verification_torch.compare_depth_batch`, the same
    terms to the bit)."""
    x0, y0, w, h = window
    observed, window_mask = depth[y0:y0 + h, x0:x0 + w], mask[y0:y0 + h, x0:x0 + w]
    rendered = [renderer.render_depth_crop(key, R, t, K, window) for R, t in poses]
    if device is None:
        return [compare_depth(r, observed, window_mask, tol, e) for r, e in zip(rendered, evidence)]
    from pipeline.method.refinement.verification_torch import compare_depth_batch

    return compare_depth_batch(np.stack(rendered) if rendered else np.zeros((0, h, w), np.float32), observed,
                               window_mask, tol, evidence, device)

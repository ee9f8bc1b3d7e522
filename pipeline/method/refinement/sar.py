"""Symmetry-aware refinement (SAR) of FreeZe (Caraffa et al., ECCV 2024).

Geometric registration (RANSAC on fused features, then ICP) cannot tell apart the poses
of a geometrically symmetric object that differ by one of its symmetries: ``T_m2c`` and
``T_m2c @ S`` put the same surface at the same place. When the texture breaks the
symmetry (a can's label, a box's print) only appearance decides. SAR renders the object
under every symmetric variant of the refined pose, directly into the square crop of the
candidate (the crop the scene features come from), encodes the renders and the scene
crop with the visual encoder, and keeps the variant whose feature map agrees best with
the scene's: the mean cell-wise cosine similarity over the feature-map cells the
rendered object covers.

Conventions. Poses are BOP model-to-camera ``R_m2c`` (3, 3), ``t_m2c`` (3,) mm;
intrinsics are the OpenCV ``K`` (3, 3) (pixel centres at integer coordinates).
Symmetries are model-frame (4, 4) transforms ``S`` (translation in mm) with
``model == S(model)``, so ``T_m2c`` and ``T_m2c @ S`` render the same shape. A crop box
``(x0, y0, side)`` is the square of image pixels ``[x0, x0+side)^2`` resized to
``size x size`` (see :mod:`pipeline.method.encoders.lifting`); a visual encoder's map cell
``j`` covers crop pixels ``[j*S/w, (j+1)*S/w)``.

Cost. Each variant is rendered at the encoder's input size only (not the whole image,
then cropped): the crop's own intrinsics (:func:`crop_intrinsics`) make the renderer
draw exactly the crop. With a ``Renderer(S, S)`` nothing else is drawn or read back;
a larger renderer also works (the crop is its top-left ``S x S`` corner).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Hashable, Sequence

import cv2
import numpy as np

from pipeline.method.geometry.crops import CropBox, crop_and_resize, square_crop_box
from pipeline.method.encoders.registry import VisualEncoder
from pipeline.method.render.renderer import Lighting, Renderer
from pipeline.method.render.templates import TEMPLATE_LIGHTING, match_image_mode

__all__ = [
    "SarResult",
    "cell_cover",
    "crop_intrinsics",
    "render_in_crop",
    "sar_similarity",
    "symmetry_aware_refinement",
    "unique_symmetries",
    "variant_angles",
    "variant_poses",
    "coarse_variants",
    "fine_variants",
]


def crop_intrinsics(K: np.ndarray, box: CropBox, size: int) -> np.ndarray:
    """Intrinsics (3, 3) float64 of the crop ``box = (x0, y0, side)`` of an image with
    intrinsics ``K`` (3, 3), resized to ``size x size``.

    Image pixel ``u`` maps to crop coordinate ``(u - x0 + 0.5) * s - 0.5`` with
    ``s = size / side`` (the ``cv2.resize`` convention of
    :func:`pipeline.method.encoders.lifting.crop_and_resize`); substituting the projection
    ``u = fx X/Z + skew Y/Z + cx`` gives focal lengths and skew scaled by ``s`` and
    ``c' = s (c - x0 + 0.5) - 0.5``.

    The renderer's own sample-position correction of the principal point
    (:meth:`Renderer._camera`) is applied by the renderer to whatever ``K`` it is
    given, so it must not be added here.
    """
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    x0, y0, side = (int(v) for v in box)
    if side <= 0 or size <= 0:
        raise ValueError(f"crop_intrinsics: side {side} and size {size} must be positive")
    s = size / side
    Kc = K.copy()
    Kc[0, :2] *= s
    Kc[1, 1] *= s
    Kc[0, 2] = s * (K[0, 2] - x0 + 0.5) - 0.5
    Kc[1, 2] = s * (K[1, 2] - y0 + 0.5) - 0.5
    return Kc


def render_in_crop(
    renderer: Renderer,
    key: Hashable,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    box: CropBox,
    size: int,
    lighting: Lighting | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render mesh ``key`` at pose ``R`` (3, 3), ``t`` (3,) mm as it appears in the crop
    ``box`` of the image with intrinsics ``K``, resized to ``size``.

    Equals ``crop_and_resize`` of a full-image render up to resampling (tested), but
    draws only the crop. ``renderer`` must be at least ``size x size`` (a
    ``Renderer(size, size)`` is fastest); the crop is its top-left corner. ``lighting``
    defaults to the templates' (:data:`TEMPLATE_LIGHTING`), so that renders look like
    the views the model's features were lifted from. Unlike ``crop_and_resize``, the
    render is not clipped at the image border.

    Returns ``(rgb (size, size, 3) uint8, mask (size, size) bool)``; the mask comes
    from depth (exact at pixel centres), the background is black.
    """
    if renderer.width < size or renderer.height < size:
        raise ValueError(
            f"render_in_crop: the renderer ({renderer.width}x{renderer.height}) is smaller than the crop size {size}"
        )
    Kc = crop_intrinsics(K, box, size)
    color, depth = renderer.render([(key, R, t)], Kc, rgb=True, lighting=lighting or TEMPLATE_LIGHTING)
    assert color is not None
    return np.ascontiguousarray(color[:size, :size]), depth[:size, :size] > 0


def unique_symmetries(
    symmetries: np.ndarray | Sequence[np.ndarray] | None,
    rot_tol_deg: float = 1.0,
    trans_tol_mm: float = 1.0,
) -> np.ndarray:
    """Symmetry transforms (V, 4, 4) float64 with the identity first and duplicates removed.

    symmetries: (K, 4, 4) model-frame transforms (translation in mm), with or without
    the identity; None or empty means none. Two transforms are duplicates when their
    relative rotation is below ``rot_tol_deg`` and their translations differ by less
    than ``trans_tol_mm``; the first one given is kept. Raises ValueError when a
    rotation part is not a proper rotation (det +1, orthonormal to 1e-3).
    """
    S = np.asarray(symmetries if symmetries is not None else np.zeros((0, 4, 4)), dtype=np.float64)
    if S.size == 0:
        S = np.zeros((0, 4, 4))
    if S.ndim == 2:
        S = S[None]
    if S.ndim != 3 or S.shape[1:] != (4, 4):
        raise ValueError(f"unique_symmetries: expected (K, 4, 4) transforms, got shape {S.shape}")
    if len(S):
        Rs = S[:, :3, :3]
        err = np.abs(Rs @ Rs.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
        bad = np.nonzero((err > 1e-3) | (np.linalg.det(Rs) < 0))[0]
        if len(bad):
            raise ValueError(f"unique_symmetries: transform {int(bad[0])} is not a rotation plus translation")
    # cos of the tolerance angle, compared with (trace(Ra^T Rb) - 1) / 2.
    cos_tol = np.cos(np.radians(rot_tol_deg))
    kept = [np.eye(4)]
    for T in S:
        dup = False
        for U in kept:
            cos = 0.5 * (np.trace(U[:3, :3].T @ T[:3, :3]) - 1.0)
            if cos >= cos_tol and np.linalg.norm(U[:3, 3] - T[:3, 3]) < trans_tol_mm:
                dup = True
                break
        if not dup:
            kept.append(T.copy())
    out = np.stack(kept)
    out[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return out


def variant_poses(
    R: np.ndarray,
    t: np.ndarray,
    symmetries: np.ndarray | Sequence[np.ndarray] | None,
    rot_tol_deg: float = 1.0,
    trans_tol_mm: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric variants ``T_m2c @ S`` of the pose ``R`` (3, 3), ``t`` (3,) mm.

    ``symmetries`` go through :func:`unique_symmetries` (identity first, duplicates
    removed), so variant 0 is the pose itself. Returns ``(Rs (V, 3, 3), ts (V, 3))``
    float64, mm.
    """
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    S = unique_symmetries(symmetries, rot_tol_deg, trans_tol_mm)
    # x_c = R (S_R x + S_t) + t
    return R @ S[:, :3, :3], S[:, :3, 3] @ R.T + t


COARSE_LEADS = 2
"""The fine pass of SAR's coarse-to-fine search looks around this many of the best coarse
variants. Replayed on the exhaustive similarities of 50 estimates with 4-24 variants
(colortex; synthhard, synthmini, synthtiny and the BOP-layout sets), one lead chose
another variant than the exhaustive search 6 times (often a second mode 150-180 degrees
away), two leads never, with 32 % fewer renders (``benchmarks/results/sar_search.md``)."""


def variant_angles(symmetries: np.ndarray) -> np.ndarray:
    """Rotation angle (V, V) float64, degrees, between every two model-frame transforms
    ``symmetries`` (V, 4, 4): the angle of ``S_a^T S_b``'s rotation."""
    Rs = np.asarray(symmetries, dtype=np.float64)[:, :3, :3]
    cos = (np.einsum("aji,bji->ab", Rs, Rs) - 1.0) / 2.0  # (trace(R_a^T R_b) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def coarse_variants(angles: np.ndarray, coarse_deg: float) -> list[int]:
    """The first pass of SAR's coarse-to-fine search: variant 0 (the ICP pose), then, in
    order, every variant at least ``coarse_deg`` (minus 1e-6) from all those already
    taken. ``angles``: :func:`variant_angles`. For a continuous symmetry sampled every 30
    degrees with a half-turn flip (24 variants) and 60 degrees, 12 are taken, and the
    second pass adds those 30 degrees either side of the two best (at most 4)."""
    taken = [0]
    for v in range(1, len(angles)):
        if angles[v, taken].min() >= coarse_deg - 1e-6:
            taken.append(v)
    return taken


def fine_variants(angles: np.ndarray, first: Sequence[int], similarities: np.ndarray, coarse_deg: float,
                  leads: int = COARSE_LEADS) -> list[int]:
    """The second pass of SAR's coarse-to-fine search: the variants not in ``first`` (the
    coarse pass, :func:`coarse_variants`) nearer than ``coarse_deg`` to one of the
    ``leads`` best of ``first`` by ``similarities`` (V,) (ties: the earlier first)."""
    first = list(first)
    top = [first[i] for i in np.argsort(-np.asarray(similarities)[first], kind="stable")[:leads]]
    taken = set(first)
    return [v for v in range(len(angles)) if v not in taken and angles[top, v].min() < coarse_deg]


def cell_cover(masks: np.ndarray, grid_hw: tuple[int, int]) -> np.ndarray:
    """Fraction (B, h, w) float32 of each feature-map cell covered by ``masks``
    (B, S, S) bool: the area average over the cell's pixels (cells may span fractional
    pixels; ``cv2.INTER_AREA`` weighs the split pixels by area)."""
    masks = np.asarray(masks, dtype=np.float32)
    h, w = grid_hw
    if masks.shape[1:] == (h, w):
        return masks.copy()
    if len(masks) == 0:
        return np.zeros((0, h, w), np.float32)
    return np.stack([cv2.resize(m, (w, h), interpolation=cv2.INTER_AREA) for m in masks]).reshape(-1, h, w)


def _unit(features: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Features (B, D, h, w) scaled to unit length along D (zero vectors stay zero)."""
    norm = np.linalg.norm(features, axis=1, keepdims=True)
    return features / np.maximum(norm, eps)


def sar_similarity(
    encoder: VisualEncoder,
    scene_crop: np.ndarray,
    renders: np.ndarray,
    masks: np.ndarray,
    min_cover: float = 0.5,
    centre: bool = True,
    batch_size: int = 16,
    scene_map: np.ndarray | None = None,
) -> np.ndarray:
    """Appearance agreement (V,) float64 of each render with the scene crop.

    scene_crop: (S, S, 3) uint8, S = ``encoder.input_size``; renders: (V, S, S, 3)
    uint8 in the same crop; masks: (V, S, S) bool, the pixels where each render shows
    the object. Each image is encoded to a (D, h, w) map (renders in batches of
    ``batch_size``, the scene once); a render's score is the cosine similarity of its
    cell features with the scene's, averaged over the cells whose area is at least
    ``min_cover`` covered by its mask, in [-1, 1]. A render covering no such cell
    scores ``-inf`` (never preferred; argmax stays well defined). A cell whose feature
    vector is zero has similarity 0.

    centre: subtract from the render's and the scene's cell features their own mean
    over the render's covered cells before taking cosines, so that the score compares
    the *pattern* on the object, not what all its cells share. FreeZe compares raw
    features (``centre=False``). Centring cancels offsets common to the whole object,
    such as a colour cast of the scene light in colour features, which otherwise pulls
    the choice towards the variant showing most of the colour the cast mimics. On
    rendered soup-can scenes (20 viewpoints at 550 and at 900 mm, textured wall,
    camera noise, 12 variants every 30 degrees, colortex) the ground-truth variant won
    18/20 and 18/20 views raw under white light, 18/20 and 17/20 under warm light, and
    20/20 in all four settings centred, mostly with larger margins (the cereal box's 4
    variants: 20/20 either way).

    scene_map: the scene crop's map (1, D, h, w) when already encoded (then
    ``scene_crop`` is only checked), so that several calls on one crop encode it once.
    """
    S = encoder.input_size
    scene_crop = np.asarray(scene_crop)
    renders = np.asarray(renders)
    masks = np.asarray(masks, dtype=bool)
    if scene_crop.shape != (S, S, 3):
        raise ValueError(f"sar_similarity: scene_crop must be ({S}, {S}, 3), got {scene_crop.shape}")
    if renders.ndim != 4 or renders.shape[1:] != (S, S, 3) or masks.shape != renders.shape[:3]:
        raise ValueError(f"sar_similarity: renders {renders.shape} and masks {masks.shape} must be (V, {S}, {S}[, 3])")
    V = len(renders)
    if V == 0:
        return np.zeros(0)
    scene = (encoder.encode(scene_crop[None]) if scene_map is None else scene_map).astype(np.float32)  # (1, D, h, w)
    scene_unit = _unit(scene)
    similarities = np.empty(V)
    for start in range(0, V, batch_size):
        stop = min(start + batch_size, V)
        feats = encoder.encode(renders[start:stop]).astype(np.float32)  # (b, D, h, w)
        if feats.shape[1:] != scene.shape[1:]:
            raise ValueError(f"sar_similarity: render maps {feats.shape[1:]} differ from the scene map {scene.shape[1:]}")
        covered = cell_cover(masks[start:stop], scene.shape[2:]) >= min_cover  # (b, h, w)
        n = covered.sum(axis=(1, 2))
        if centre:
            w = covered[:, None].astype(np.float32) / np.maximum(n, 1)[:, None, None, None]
            mean_r = (feats * w).sum(axis=(2, 3), keepdims=True)  # (b, D, 1, 1)
            mean_s = (scene * w).sum(axis=(2, 3), keepdims=True)
            cos = np.einsum("bdhw,bdhw->bhw", _unit(feats - mean_r), _unit(scene - mean_s))
        else:
            cos = np.einsum("bdhw,dhw->bhw", _unit(feats), scene_unit[0])
        total = np.where(covered, cos, 0.0).sum(axis=(1, 2), dtype=np.float64)
        similarities[start:stop] = np.where(n > 0, total / np.maximum(n, 1), -np.inf)
    return similarities


@dataclass
class SarResult:
    """Outcome of :func:`symmetry_aware_refinement` for one estimate.

    index: the chosen variant (0 = the input pose kept).
    R (3, 3), t (3,) mm: the chosen pose, ``Rs[index]``, ``ts[index]``.
    Rs (V, 3, 3), ts (V, 3) mm: every variant, the input pose first.
    symmetries (V, 4, 4): the model-frame transform of each variant (identity first),
    ``T_variant = T_input @ symmetries[v]``.
    similarities (V,): each variant's mean cell-wise cosine similarity with the scene
    (``-inf``: covered no cell; NaN: not rendered, by the coarse-to-fine search or,
    all of them, when there was a single variant).
    """

    index: int
    R: np.ndarray
    t: np.ndarray
    Rs: np.ndarray
    ts: np.ndarray
    symmetries: np.ndarray
    similarities: np.ndarray

    @property
    def changed(self) -> bool:
        """Whether SAR replaced the input pose by another variant."""
        return self.index != 0

    @property
    def gain(self) -> float:
        """Score of the chosen variant minus that of the input pose (0 when kept)."""
        return 0.0 if self.index == 0 else float(self.similarities[self.index] - self.similarities[0])


def symmetry_aware_refinement(
    renderer: Renderer,
    key: Hashable,
    encoder: VisualEncoder,
    rgb_image: np.ndarray,
    K: np.ndarray,
    bbox_xywh: Sequence[float],
    R: np.ndarray,
    t: np.ndarray,
    symmetries: np.ndarray | Sequence[np.ndarray] | None,
    margin: float = 0.1,
    min_cover: float = 0.5,
    min_gain: float = 0.0,
    centre: bool = True,
    lighting: Lighting | None = None,
    batch_size: int = 16,
    scene_mask: np.ndarray | None = None,
    image_mode: str = "rgb",
    coarse_deg: float = 0.0,
) -> SarResult:
    """Choose among the symmetric variants of a refined pose the one that looks most
    like the scene.

    renderer: holds the model under ``key`` (added by the caller; at least S x S,
    S = ``encoder.input_size``, a ``Renderer(S, S)`` being fastest). rgb_image:
    (H, W, 3) uint8 scene image with intrinsics ``K`` (3, 3). bbox_xywh: the
    candidate's BOP box (pixels); the crop is ``square_crop_box(bbox_xywh, (H, W),
    margin)``, the crop the scene features come from. R (3, 3), t (3,) mm: the pose
    after ICP. symmetries: (K, 4, 4) model-frame symmetries, identity included or
    not (see :func:`unique_symmetries`).

    Every variant is rendered into the crop (``lighting``: see :func:`render_in_crop`)
    and scored by :func:`sar_similarity` (``min_cover``, ``centre``, ``batch_size``);
    render pixels outside the image are dropped from its mask, since the scene crop is
    zero-padded there. The best-scoring variant replaces the input pose only if it
    beats the input's score by more than ``min_gain`` (0: any strict improvement), so
    that, with ``min_gain > 0``, an object whose variants look alike keeps the ICP pose
    rather than following rendering noise. With a single variant (no non-trivial
    symmetry) nothing is rendered.

    scene_mask: (H, W) bool, the candidate's mask (the visible part of the object).
    When given, only render pixels inside it count, so that an occluder in front of the
    object, which the render cannot know about, does not enter the comparison.

    image_mode: "gray" for grey datasets (ITODD): the renders are turned grey like the
    scene image (:func:`pipeline.method.render.templates.match_image_mode`).

    coarse_deg: > 0 searches coarse to fine (:func:`coarse_variants`): first the variants
    at least this far apart, then those closer than it to the :data:`COARSE_LEADS` best
    of them; the others are not rendered and keep a NaN similarity. 0 scores every
    variant.
    """
    rgb_image = np.asarray(rgb_image)
    if rgb_image.ndim != 3 or rgb_image.shape[2] != 3 or rgb_image.dtype != np.uint8:
        raise ValueError(f"symmetry_aware_refinement: rgb_image must be (H, W, 3) uint8, got {rgb_image.shape} {rgb_image.dtype}")
    Ss = unique_symmetries(symmetries)
    Rs, ts = variant_poses(R, t, Ss)
    V = len(Rs)
    if V == 1:
        return SarResult(0, Rs[0].copy(), ts[0].copy(), Rs, ts, Ss, np.full(1, np.nan))
    size = encoder.input_size
    box = square_crop_box(bbox_xywh, rgb_image.shape[:2], margin)
    scene_crop = crop_and_resize(rgb_image, box, size)
    inside = crop_and_resize(np.ones(rgb_image.shape[:2], np.uint8), box, size) > 0
    if scene_mask is not None:
        scene_mask = np.asarray(scene_mask, dtype=bool)
        if scene_mask.shape != rgb_image.shape[:2]:
            raise ValueError(f"symmetry_aware_refinement: scene_mask {scene_mask.shape} differs from the image "
                             f"{rgb_image.shape[:2]}")
        inside &= crop_and_resize(scene_mask.astype(np.uint8) * 255, box, size) >= 128
    scene_map = encoder.encode(scene_crop[None])
    similarities = np.full(V, np.nan)

    def score(which: Sequence[int]) -> None:
        renders = np.empty((len(which), size, size, 3), np.uint8)
        masks = np.empty((len(which), size, size), bool)
        for i, v in enumerate(which):
            renders[i], m = render_in_crop(renderer, key, Rs[v], ts[v], K, box, size, lighting)
            masks[i] = m & inside
        renders = match_image_mode(renders, image_mode)
        similarities[list(which)] = sar_similarity(encoder, scene_crop, renders, masks, min_cover, centre,
                                                   batch_size, scene_map=scene_map)

    if coarse_deg > 0:
        angles = variant_angles(Ss)
        first = coarse_variants(angles, coarse_deg)
        score(first)
        score(fine_variants(angles, first, similarities, coarse_deg))
    else:
        score(range(V))
    best = int(np.argmax(np.where(np.isnan(similarities), -np.inf, similarities)))
    index = best if similarities[best] > similarities[0] + min_gain else 0
    return SarResult(index, Rs[index].copy(), ts[index].copy(), Rs, ts, Ss, similarities)

"""A CNOS-like localisation prior with realistic faults, derived from the visible masks.

Per image: most visible instances get a mask (eroded, dilated and with a wobbly
boundary) with a high score; a few percent are missed; some get an extra fragment or a
looser duplicate with a lower score; and a few false positives appear: a segment of
another object labelled with a wrong category, or a blob of the table. All detections
of one image share a run time near a constant, as a detector reports it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.formats.bop import Detection, detection_from_mask


@dataclass(frozen=True)
class PriorFaults:
    """Rates and ranges of the simulated detector's faults."""

    miss_prob: float = 0.04
    low_visib_miss_prob: float = 0.6
    min_pixels: int = 60
    fragment_prob: float = 0.08
    duplicate_prob: float = 0.05
    false_positives_per_image: float = 0.8
    max_morph_px: int = 3
    time_s: float = 0.26
    time_jitter_s: float = 0.02


@dataclass
class VisibleInstance:
    """What the prior generator needs of one annotated instance."""

    obj_id: int
    mask_visib: np.ndarray
    visib_fract: float


def _smooth_field(shape: tuple[int, int], rng: np.random.Generator, cell: int = 12) -> np.ndarray:
    h, w = shape
    small = rng.standard_normal((h // cell + 2, w // cell + 2)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def morph_mask(mask: np.ndarray, radius: int, dilate: bool) -> np.ndarray:
    """A (H, W) mask eroded (or dilated) by a disc of ``radius`` px, as bool."""
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    m = np.asarray(mask).astype(np.uint8)
    return (cv2.dilate(m, k) if dilate else cv2.erode(m, k)).astype(bool)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks (0 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


def perturb_mask(mask: np.ndarray, rng: np.random.Generator, max_px: int = 3) -> np.ndarray:
    """A segmenter-like version of a (H, W) bool mask: eroded or dilated, boundary jittered."""
    m = mask.astype(np.uint8)
    r = int(rng.integers(0, max_px + 1))
    op = rng.choice(3, p=[0.35, 0.35, 0.3])
    if r > 0 and op < 2:
        m = morph_mask(m, r, dilate=op == 1)
    soft = cv2.GaussianBlur(m.astype(np.float32), (0, 0), 1.5)
    # The jitter only moves the boundary: far from it the blurred mask is 0 or 1.
    near = soft > 0.02
    out = near & (soft + 0.15 * _smooth_field(mask.shape, rng) > 0.5)
    return out if out.sum() >= max(10, 0.3 * mask.sum()) else mask.copy()


def fragment(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Part of a mask cut off by a random line near its centroid (30-70 % of it)."""
    ys, xs = np.nonzero(mask)
    ang = rng.uniform(0, np.pi)
    d = (xs - xs.mean()) * np.cos(ang) + (ys - ys.mean()) * np.sin(ang)
    cut = np.quantile(d, rng.uniform(0.3, 0.7))
    keep = d > cut if rng.random() < 0.5 else d < cut
    out = np.zeros_like(mask, dtype=bool)
    out[ys[keep], xs[keep]] = True
    return out


def _true_score(visib: float, rng: np.random.Generator) -> float:
    s = 0.45 + 0.5 * rng.beta(5.0, 1.5) * (0.65 + 0.35 * visib)
    return float(np.clip(s + rng.normal(0, 0.02), 0.05, 0.99))


def image_detections(
    scene_id: int,
    im_id: int,
    instances: list[VisibleInstance],
    table_mask: np.ndarray,
    all_obj_ids: list[int],
    rng: np.random.Generator,
    faults: PriorFaults = PriorFaults(),
    clutter: list[np.ndarray] | None = None,
) -> list[Detection]:
    """Detections of one image, best score first.

    table_mask: (H, W) bool pixels of the support plane not covered by any object,
    where table false positives may appear. all_obj_ids: the dataset's categories.
    clutter: visible masks (H, W) bool of objects outside the dataset, which a
    detector may take for one of its categories.
    """
    t_img = float(max(0.05, rng.normal(faults.time_s, faults.time_jitter_s)))
    dets: list[tuple[int, float, np.ndarray]] = []
    for inst in instances:
        if inst.mask_visib.sum() < faults.min_pixels:
            continue
        miss = faults.low_visib_miss_prob if inst.visib_fract < 0.1 else faults.miss_prob
        if rng.random() < miss:
            continue
        score = _true_score(inst.visib_fract, rng)
        dets.append((inst.obj_id, score, perturb_mask(inst.mask_visib, rng, faults.max_morph_px)))
        if rng.random() < faults.fragment_prob:
            dets.append((inst.obj_id, score * rng.uniform(0.5, 0.85), fragment(inst.mask_visib, rng)))
        if rng.random() < faults.duplicate_prob:
            loose = perturb_mask(inst.mask_visib, rng, faults.max_morph_px + 3)
            dets.append((inst.obj_id, score * rng.uniform(0.6, 0.9), loose))
    for _ in range(int(rng.poisson(faults.false_positives_per_image))):
        fp = _false_positive(instances, table_mask, clutter or [], all_obj_ids, rng, faults)
        if fp is not None:
            dets.append(fp)
    dets.sort(key=lambda d: -d[1])
    return [detection_from_mask(scene_id, im_id, o, round(s, 4), m, round(t_img, 4)) for o, s, m in dets if m.any()]


def _false_positive(
    instances: list[VisibleInstance],
    table_mask: np.ndarray,
    clutter: list[np.ndarray],
    all_obj_ids: list[int],
    rng: np.random.Generator,
    faults: PriorFaults,
) -> tuple[int, float, np.ndarray] | None:
    """One wrong detection: another object's segment with a wrong label, clutter, or table."""
    visible = [i for i in instances if i.mask_visib.sum() >= faults.min_pixels]
    junk = [m for m in clutter if m.sum() >= faults.min_pixels]
    sources = [s for s, ok in (("object", visible), ("clutter", junk), ("table", table_mask.any())) if ok]
    if not sources:
        return None
    source = sources[int(rng.integers(len(sources)))]
    if source == "object":
        inst = visible[rng.integers(len(visible))]
        wrong = [o for o in all_obj_ids if o != inst.obj_id]
        if not wrong:
            return None
        mask = inst.mask_visib if rng.random() < 0.5 else fragment(inst.mask_visib, rng)
        return int(rng.choice(wrong)), float(rng.uniform(0.15, 0.55)), perturb_mask(mask, rng, faults.max_morph_px)
    if source == "clutter":
        mask = junk[rng.integers(len(junk))]
        return int(rng.choice(all_obj_ids)), float(rng.uniform(0.15, 0.6)), perturb_mask(mask, rng, faults.max_morph_px)
    ys, xs = np.nonzero(table_mask)
    k = rng.integers(len(xs))
    blob = np.zeros(table_mask.shape, np.uint8)
    axes = (int(rng.uniform(12, 50)), int(rng.uniform(10, 40)))
    cv2.ellipse(blob, (int(xs[k]), int(ys[k])), axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    blob = blob.astype(bool) & table_mask
    if blob.sum() < faults.min_pixels:
        return None
    return int(rng.choice(all_obj_ids)), float(rng.uniform(0.1, 0.45)), perturb_mask(blob, rng, 1)

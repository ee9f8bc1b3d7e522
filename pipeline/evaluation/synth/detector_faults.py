"""A faulty localisation prior derived from an exact one, with stated rates.

Real detectors (CNOS, SAM-6D's ISM) err in a few typical ways. Given exact detections
(one per visible instance: a ground-truth mask, score 1), :func:`derive_faulty_prior`
makes a prior with those errors, each at the rate of :class:`DetectorFaults`:

- an instance is **missed** (its detection dropped);
- a kept mask is **eroded** or **dilated** by 1 to ``max_morph_px`` pixels;
- a kept mask is **cut as by an occluder**: the part beyond a straight edge through it
  is removed (``cut_fraction`` of its pixels);
- an instance is **labelled as another object present** in the same image;
- **stray detections** of objects absent from the image appear (Poisson per image):
  a piece of a present instance's mask, or a blob elsewhere in the image, labelled
  with an object of the dataset that the image does not show;
- **scores do not follow quality**: a score mixes the detection's quality (IoU with the
  instance's true mask; 0 for a wrong label or a stray) and uniform noise, with weight
  ``score_quality_weight`` on the quality, so a stray may outrank a good detection.

Every draw comes from one generator seeded by the caller, in a fixed order, so the
prior is reproducible from its seed. :class:`FaultLog` counts what was done, so a
dataset's summary states the rates it really has.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from pipeline.formats.bop import Detection, detection_from_mask

from .priors import mask_iou, morph_mask


@dataclass(frozen=True)
class DetectorFaults:
    """Rates of :func:`derive_faulty_prior`'s faults (probabilities per instance unless
    said; ``stray_per_image`` is a Poisson mean)."""

    miss: float = 0.08
    erode: float = 0.25
    dilate: float = 0.25
    max_morph_px: int = 4
    occlusion_cut: float = 0.10
    cut_fraction: tuple[float, float] = (0.2, 0.5)
    wrong_label: float = 0.06
    stray_per_image: float = 0.5
    score_quality_weight: float = 0.3
    min_pixels: int = 60

    def __post_init__(self) -> None:
        for name in ("miss", "erode", "dilate", "occlusion_cut", "wrong_label", "score_quality_weight"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"detector fault '{name}' is {v}: a probability in [0, 1]")
        if self.erode + self.dilate > 1.0:
            raise ValueError(f"detector faults 'erode' + 'dilate' is {self.erode + self.dilate}: at most 1")
        lo, hi = self.cut_fraction
        if not 0.0 < lo <= hi < 1.0:
            raise ValueError(f"detector fault 'cut_fraction' is {self.cut_fraction}: 0 < low <= high < 1")
        if self.stray_per_image < 0 or self.max_morph_px < 1 or self.min_pixels < 1:
            raise ValueError("detector faults: 'stray_per_image' >= 0, 'max_morph_px' >= 1, 'min_pixels' >= 1")


@dataclass
class FaultLog:
    """What :func:`derive_faulty_prior` did: instance counts per fault."""

    instances: int = 0
    missed: int = 0
    eroded: int = 0
    dilated: int = 0
    cut: int = 0
    wrong_label: int = 0
    stray: int = 0
    images: int = 0
    kept_small: int = 0
    detections: int = 0
    stray_sources: dict[str, int] = field(default_factory=lambda: {"piece": 0, "blob": 0})

    def rates(self) -> dict[str, float]:
        """Measured rates: per instance (missed, eroded, dilated, cut, wrong_label; the
        last three over the instances kept) and strays per image."""
        kept = max(1, self.instances - self.missed - self.kept_small)
        return {"miss": self.missed / max(1, self.instances), "erode": self.eroded / kept,
                "dilate": self.dilated / kept, "occlusion_cut": self.cut / kept,
                "wrong_label": self.wrong_label / kept, "stray_per_image": self.stray / max(1, self.images)}

    def to_json(self) -> dict:
        out = asdict(self)
        out["rates"] = {k: round(v, 4) for k, v in self.rates().items()}
        return out


def _cut(mask: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """``mask`` with the ``fraction`` of its pixels beyond a straight edge of random
    direction removed, as an occluder's edge would."""
    ys, xs = np.nonzero(mask)
    ang = rng.uniform(0.0, 2.0 * np.pi)
    d = xs * np.cos(ang) + ys * np.sin(ang)
    edge = np.quantile(d, 1.0 - fraction)
    out = mask.copy()
    out[ys[d > edge], xs[d > edge]] = False
    return out


def _score(quality: float, rng: np.random.Generator, faults: DetectorFaults) -> float:
    w = faults.score_quality_weight
    return round(float(np.clip(0.5 + 0.49 * (w * quality + (1.0 - w) * rng.random()), 0.05, 0.99)), 4)


def _stray(masks: list[np.ndarray], shape: tuple[int, int], rng: np.random.Generator) -> tuple[np.ndarray, str]:
    """A stray detection's mask and its kind: a piece of one of ``masks`` or an elliptic blob."""
    if masks and rng.random() < 0.5:
        m = masks[int(rng.integers(len(masks)))]
        return _cut(m, float(rng.uniform(0.4, 0.7)), rng), "piece"
    h, w = shape
    blob = np.zeros(shape, np.uint8)
    axes = (int(rng.uniform(12, 50)), int(rng.uniform(10, 40)))
    centre = (int(rng.integers(w)), int(rng.integers(h)))
    cv2.ellipse(blob, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return blob.astype(bool), "blob"


def derive_faulty_prior(exact: list[Detection], obj_ids: list[int], rng: np.random.Generator,
                        faults: DetectorFaults = DetectorFaults()) -> tuple[list[Detection], FaultLog]:
    """A faulty prior from the exact detections ``exact`` (one per visible instance; its
    mask the instance's), with the faults of ``faults`` (module docstring).

    obj_ids: the dataset's objects (the labels of stray detections are drawn from those
    absent from an image). Returns the detections, per image best score first, each
    keeping its exact detection's ``time``, and the log of the faults made."""
    log = FaultLog()
    by_image: dict[tuple[int, int], list[Detection]] = defaultdict(list)
    for d in exact:
        by_image[(d.scene_id, d.image_id)].append(d)
    out: list[Detection] = []
    for (scene_id, im_id), dets in sorted(by_image.items()):
        log.images += 1
        masks = [d.mask() for d in dets]
        present = sorted({d.category_id for d in dets})
        t = dets[0].time
        made: list[tuple[int, float, np.ndarray]] = []
        for det, true in zip(dets, masks):
            log.instances += 1
            if rng.random() < faults.miss:
                log.missed += 1
                continue
            mask = true
            if true.sum() < faults.min_pixels:  # too small to erode or cut meaningfully
                log.kept_small += 1
                made.append((det.category_id, _score(1.0, rng, faults), mask))
                continue
            u = rng.random()
            if u < faults.erode + faults.dilate:
                dilate = u >= faults.erode
                eroded = morph_mask(mask, int(rng.integers(1, faults.max_morph_px + 1)), dilate)
                if eroded.sum() >= faults.min_pixels:
                    mask = eroded
                    log.dilated += dilate
                    log.eroded += not dilate
            if rng.random() < faults.occlusion_cut:
                mask = _cut(mask, float(rng.uniform(*faults.cut_fraction)), rng)
                log.cut += 1
            label = det.category_id
            others = [o for o in present if o != det.category_id]
            if rng.random() < faults.wrong_label and others:
                label = others[int(rng.integers(len(others)))]
                log.wrong_label += 1
            quality = mask_iou(mask, true) if label == det.category_id else 0.0
            made.append((label, _score(quality, rng, faults), mask))
        absent = [o for o in obj_ids if o not in present]
        for _ in range(int(rng.poisson(faults.stray_per_image))):
            mask, kind = _stray(masks, masks[0].shape, rng)
            if absent and mask.sum() >= faults.min_pixels:
                made.append((absent[int(rng.integers(len(absent)))], _score(0.0, rng, faults), mask))
                log.stray += 1
                log.stray_sources[kind] += 1
        made.sort(key=lambda m: -m[1])
        out += [detection_from_mask(scene_id, im_id, o, s, m, t) for o, s, m in made if m.any()]
    log.detections = len(out)
    return out, log

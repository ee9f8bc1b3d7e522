"""Localisation priors in the BOP/CNOS detection format, and COCO run-length masks.

A detection file is a JSON list of ``{"scene_id", "image_id", "category_id" (= obj_id),
"score", "bbox" [x, y, w, h] px, "segmentation" {"counts", "size" [H, W]}, "time" s}``,
as written by CNOS and SAM-6D and distributed as the BOP default detections.

Masks use COCO run-length encoding: the mask is read in column-major (Fortran) order,
and ``counts`` alternate background/foreground run lengths starting with background
(so the first count is 0 when pixel (0, 0) is foreground). The *uncompressed* form
stores counts as a list of ints; the *compressed* form (pycocotools) packs them into
a string (see ``rle_counts_from_string``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .errors import BopFormatError
from .jsonio import load_json, save_bop_json

# ---------------------------------------------------------------------------- RLE


def rle_encode(mask: np.ndarray) -> dict:
    """Uncompressed COCO RLE of a (H, W) bool mask: ``{"counts": list[int], "size": [H, W]}``."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"rle_encode: mask must be 2-D (H, W), got shape {mask.shape}")
    h, w = mask.shape
    flat = mask.astype(bool).ravel(order="F")
    if flat.size == 0:
        return {"counts": [], "size": [int(h), int(w)]}
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.concatenate(([0], change, [flat.size])))
    counts = runs.tolist()
    if flat[0]:
        counts = [0] + counts
    return {"counts": counts, "size": [int(h), int(w)]}


def rle_counts_from_string(s: str) -> list[int]:
    """Decode pycocotools' compressed counts string into run lengths.

    Each count is written in chunks of 5 bits, least significant first, one character
    per chunk as ``chr(48 + chunk)``; bit 0x20 of a chunk says another chunk follows,
    and bit 0x10 of the last chunk is the sign. From the fourth count on, the value
    stored is the difference to the count two places earlier.
    """
    counts: list[int] = []
    p = 0
    n = len(s)
    while p < n:
        x = 0
        k = 0
        more = True
        while more:
            if p >= n:
                raise ValueError("compressed RLE string ends inside a count")
            c = ord(s[p]) - 48
            if c < 0 or c > 63:
                raise ValueError(f"compressed RLE string has an invalid character {s[p]!r} at {p}")
            x |= (c & 0x1F) << (5 * k)
            more = bool(c & 0x20)
            p += 1
            k += 1
            if not more and (c & 0x10):
                x |= -1 << (5 * k)
        if len(counts) > 2:
            x += counts[-2]
        counts.append(x)
    return counts


def rle_counts_to_string(counts: Iterable[int]) -> str:
    """Inverse of ``rle_counts_from_string`` (pycocotools' compressed counts string)."""
    counts = [int(c) for c in counts]
    out = []
    for i, value in enumerate(counts):
        x = value - counts[i - 2] if i > 2 else value
        more = True
        while more:
            c = x & 0x1F
            x >>= 5  # arithmetic shift, so negative deltas terminate at -1
            more = (x != -1) if (c & 0x10) else (x != 0)
            if more:
                c |= 0x20
            out.append(chr(c + 48))
    return "".join(out)


def _rle_counts(rle: dict) -> tuple[list[int], int, int]:
    """Validated (counts, H, W) of an RLE dict; raises ValueError describing the problem."""
    if not isinstance(rle, dict):
        raise ValueError(f"RLE must be a dict with 'counts' and 'size', got {type(rle).__name__}")
    if "size" not in rle or "counts" not in rle:
        raise ValueError(f"RLE lacks {'size' if 'size' not in rle else 'counts'}")
    size = rle["size"]
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(_is_int(v) and v >= 0 for v in size)):
        raise ValueError(f"RLE size must be [H, W] non-negative ints, got {size!r}")
    h, w = int(size[0]), int(size[1])
    raw = rle["counts"]
    if isinstance(raw, bytes):
        raw = raw.decode("ascii")
    if isinstance(raw, str):
        counts = rle_counts_from_string(raw)
    elif isinstance(raw, (list, tuple)):
        if not all(_is_int(c) for c in raw):
            raise ValueError("RLE counts must be integers")
        counts = [int(c) for c in raw]
    else:
        raise ValueError(f"RLE counts must be a list of ints or a string, got {type(raw).__name__}")
    if any(c < 0 for c in counts):
        raise ValueError("RLE counts must be non-negative")
    if sum(counts) != h * w:
        raise ValueError(f"RLE counts sum to {sum(counts)} but size {h}x{w} has {h * w} pixels")
    return counts, h, w


def rle_uncompressed(rle: dict) -> dict:
    """The same RLE, validated, with list counts (COCO compressed strings expanded)."""
    counts, h, w = _rle_counts(rle)
    return {"counts": counts, "size": [h, w]}


def rle_decode(rle: dict) -> np.ndarray:
    """(H, W) bool mask of an uncompressed (list counts) or compressed (string) COCO RLE."""
    counts, h, w = _rle_counts(rle)
    values = np.arange(len(counts)) % 2 == 1
    flat = np.repeat(values, counts)
    return flat.reshape((h, w), order="F")


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)


# ---------------------------------------------------------------------------- detections


@dataclass
class Detection:
    """One localisation prior.

    bbox: (x, y, w, h) float px, top-left corner. segmentation: COCO RLE dict (list or
    string counts). time: detector run time for the image, s (-1 if unknown).
    """

    scene_id: int
    image_id: int
    category_id: int
    score: float
    bbox: tuple[float, float, float, float]
    segmentation: dict = field(repr=False)
    time: float = -1.0

    @property
    def obj_id(self) -> int:
        return self.category_id

    def mask(self) -> np.ndarray:
        """(H, W) bool mask decoded from ``segmentation``."""
        return rle_decode(self.segmentation)

    def to_json(self) -> dict:
        return {
            "scene_id": int(self.scene_id),
            "image_id": int(self.image_id),
            "category_id": int(self.category_id),
            "score": float(self.score),
            "bbox": [float(v) for v in self.bbox],
            "segmentation": self.segmentation,
            "time": float(self.time),
        }


def detection_from_mask(
    scene_id: int, image_id: int, obj_id: int, score: float, mask: np.ndarray, time: float = -1.0
) -> Detection:
    """A ``Detection`` whose bbox and RLE come from a (H, W) bool mask.

    The bbox follows the BOP toolkit and CNOS: (x_min, y_min, x_max - x_min,
    y_max - y_min) over the foreground pixel indices, so a single pixel has w = h = 0.
    """
    mask = np.asarray(mask, bool)
    ys, xs = np.nonzero(mask)
    if len(xs):
        bbox = (float(xs.min()), float(ys.min()), float(xs.max() - xs.min()), float(ys.max() - ys.min()))
    else:
        bbox = (0.0, 0.0, 0.0, 0.0)
    return Detection(int(scene_id), int(image_id), int(obj_id), float(score), bbox, rle_encode(mask), float(time))


def _parse_detection(path: Path, index: int, entry: Any) -> Detection:
    def err(field_name: str | None, msg: str) -> BopFormatError:
        where = f"entry {index}" + (f", field '{field_name}'" if field_name else "")
        return BopFormatError(f"{path}: {where}: {msg}")

    if not isinstance(entry, dict):
        raise err(None, f"expected an object, got {type(entry).__name__}")
    for key in ("scene_id", "image_id", "category_id"):
        if key not in entry:
            raise err(key, "missing")
        if not (_is_int(entry[key]) or (isinstance(entry[key], float) and entry[key].is_integer())):
            raise err(key, f"expected an integer, got {entry[key]!r}")
    if "score" not in entry:
        raise err("score", "missing")
    if not _is_number(entry["score"]):
        raise err("score", f"expected a finite number, got {entry['score']!r}")
    if "bbox" not in entry:
        raise err("bbox", "missing")
    bbox = entry["bbox"]
    if not (isinstance(bbox, (list, tuple)) and len(bbox) == 4 and all(_is_number(v) for v in bbox)):
        raise err("bbox", f"expected [x, y, w, h] numbers, got {bbox!r}")
    if "segmentation" not in entry:
        raise err("segmentation", "missing")
    try:
        _rle_counts(entry["segmentation"])
    except ValueError as e:
        raise err("segmentation", str(e)) from None
    t = entry.get("time", -1.0)
    if t is None:
        t = -1.0
    if not _is_number(t):
        raise err("time", f"expected a number, got {t!r}")
    return Detection(
        scene_id=int(entry["scene_id"]),
        image_id=int(entry["image_id"]),
        category_id=int(entry["category_id"]),
        score=float(entry["score"]),
        bbox=tuple(float(v) for v in bbox),
        segmentation=entry["segmentation"],
        time=float(t),
    )


def load_detections(path: Path | str) -> list[Detection]:
    """Read and validate a BOP/CNOS detection file.

    Every entry is checked; the first bad one raises ``BopFormatError`` naming the
    file, the entry index and the field. ``time`` may be absent (-1).
    """
    path = Path(path)
    content = load_json(path)
    if not isinstance(content, list):
        raise BopFormatError(f"{path}: expected a JSON list of detections, got {type(content).__name__}")
    return [_parse_detection(path, i, e) for i, e in enumerate(content)]


def save_detections(path: Path | str, detections: Iterable[Detection]) -> None:
    """Write detections as a JSON list, one detection per line (BOP layout), atomically."""
    save_bop_json(path, [d.to_json() for d in detections])

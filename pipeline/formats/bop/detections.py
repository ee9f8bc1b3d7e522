"""Localisation priors in the BOP/CNOS detection format, and COCO run-length masks.

A detection file is a JSON list of ``{"scene_id", "image_id", "category_id" (= obj_id),
"score", "bbox" [x, y, w, h] px, "segmentation" {"counts", "size" [H, W]}, "time" s}``,
as written by CNOS and SAM-6D and distributed as the BOP default detections
(``load_detections`` lists the variants it also accepts). ``map_category_ids`` turns
index-style category ids into obj_ids; ``merge_detections`` pools several prior files.

Masks use COCO run-length encoding: the mask is read in column-major (Fortran) order,
and ``counts`` alternate background/foreground run lengths starting with background
(so the first count is 0 when pixel (0, 0) is foreground). The *uncompressed* form
stores counts as a list of ints; the *compressed* form (pycocotools) packs them into
a string (see ``rle_counts_from_string``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from .errors import BopFormatError
from .jsonio import brief, load_json, save_bop_json

# ---------------------------------------------------------------------------- RLE

#: Largest mask side (px) an RLE may declare. No camera image comes near it; a larger
#: size is a corrupt file, and decoding it would allocate H * W bytes.
MAX_MASK_SIDE = 65535


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
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(_is_integral(v) and v >= 0 for v in size)):
        raise ValueError(f"RLE size must be [H, W] non-negative ints, got {brief(size)}")
    h, w = int(size[0]), int(size[1])
    if max(h, w) > MAX_MASK_SIDE:
        raise ValueError(f"RLE size {h}x{w} exceeds {MAX_MASK_SIDE} px a side (a corrupt size?)")
    raw = rle["counts"]
    if isinstance(raw, bytes):  # pycocotools returns bytes; JSON never does
        try:
            raw = raw.decode("ascii")
        except UnicodeDecodeError:
            raise ValueError("RLE counts string is not ASCII") from None
    if isinstance(raw, str):
        counts = rle_counts_from_string(raw)
    elif isinstance(raw, (list, tuple)):
        if not all(_is_integral(c) for c in raw):
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


def prior_row_mask(row: Any) -> np.ndarray:
    """(H, W) bool mask of one row of segment_prior's table (its ``rle_counts``, ``height``
    and ``width``): the one place a stored prior is decoded."""
    return rle_decode({"counts": list(row.rle_counts), "size": [int(row.height), int(row.width)]})


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_integral(v: Any) -> bool:
    """An int, or a float holding an integral value (JSON writers that emit ``3.0``)."""
    return _is_int(v) or (isinstance(v, (float, np.floating)) and math.isfinite(v) and float(v).is_integer())


def _is_number(v: Any) -> bool:
    """A finite int or float (not a bool); an int beyond the float range is not."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # JSON ints have any number of digits
        return False


# ---------------------------------------------------------------------------- detections

#: How the ``category_id`` of a detection file names the object (see ``map_category_ids``).
CATEGORY_ID_MODES = ("obj_id", "index0", "index1")

#: Alternative spellings accepted when reading a detection file: canonical -> alias.
FIELD_ALIASES = {"image_id": "im_id", "category_id": "obj_id"}


@dataclass
class Detection:
    """One localisation prior.

    bbox: (x, y, w, h) float px, top-left corner. segmentation: COCO RLE dict (list or
    string counts). time: detector run time for the image, s (-1 if unknown). source:
    which prior file/detector the detection came from ("" if not recorded); it is not
    part of the BOP format and ``to_json`` never writes it.
    """

    scene_id: int
    image_id: int
    category_id: int
    score: float
    bbox: tuple[float, float, float, float]
    segmentation: dict = field(repr=False)
    time: float = -1.0
    source: str = ""

    @property
    def obj_id(self) -> int:
        return self.category_id

    def mask(self) -> np.ndarray:
        """(H, W) bool mask decoded from ``segmentation``."""
        return rle_decode(self.segmentation)

    def to_json(self) -> dict:
        """The BOP/CNOS JSON entry (``source`` is not part of the format and is left out)."""
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
    scene_id: int, image_id: int, obj_id: int, score: float, mask: np.ndarray, time: float = -1.0,
    source: str = "",
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
    return Detection(int(scene_id), int(image_id), int(obj_id), float(score), bbox, rle_encode(mask), float(time),
                     str(source))


_ErrorMaker = Callable[[str | None, str], BopFormatError]


def _id_field(entry: dict, name: str, err: _ErrorMaker) -> int:
    """Integer id ``name`` of an entry, read under its canonical name or its alias.

    Integral floats (``3.0``) are accepted. Both spellings present with different values
    is an error.
    """
    alias = FIELD_ALIASES.get(name)
    present = [k for k in (name, alias) if k is not None and k in entry]
    if not present:
        raise err(name, "missing" + (f" (the alias '{alias}' is accepted too)" if alias else ""))
    values = []
    for key in present:
        if not _is_integral(entry[key]):
            raise err(key, f"expected an integer, got {brief(entry[key])}")
        value = int(entry[key])
        if not -(2 ** 63) <= value < 2 ** 63:  # ids end up in int64 columns
            raise err(key, f"{value} does not fit in int64")
        values.append(value)
    if len(values) == 2 and values[0] != values[1]:
        raise err(name, f"{values[0]} disagrees with '{alias}' = {values[1]} (both spellings given, with different values)")
    return values[0]


def _segmentation_field(entry: dict, err: _ErrorMaker) -> dict:
    """The validated RLE of an entry, list counts as ints, string counts kept as a str."""
    seg = entry.get("segmentation")
    if seg is None:
        raise err("segmentation", "missing: the pipeline needs an instance mask (COCO RLE) per detection; "
                                  "a detection file with 2D boxes only cannot be used as a localisation prior")
    if isinstance(seg, list):
        raise err("segmentation", "COCO polygons are not supported; expected an RLE {\"counts\", \"size\"}")
    try:
        counts, h, w = _rle_counts(seg)
    except ValueError as e:
        raise err("segmentation", str(e)) from None
    raw = seg["counts"]
    if isinstance(raw, (str, bytes)):
        return {"counts": raw.decode("ascii") if isinstance(raw, bytes) else raw, "size": [h, w]}
    return {"counts": counts, "size": [h, w]}


def _parse_detection(path: Path, index: int, entry: Any, source: str = "") -> Detection:
    def err(field_name: str | None, msg: str) -> BopFormatError:
        where = f"entry {index}" + (f", field '{field_name}'" if field_name else "")
        return BopFormatError(f"{path}: {where}: {msg}")

    if not isinstance(entry, dict):
        raise err(None, f"expected an object, got {type(entry).__name__}")
    ids = {name: _id_field(entry, name, err) for name in ("scene_id", "image_id", "category_id")}
    if "score" not in entry:
        raise err("score", "missing")
    if not _is_number(entry["score"]):
        raise err("score", f"expected a finite number, got {brief(entry['score'])}")
    if "bbox" not in entry:
        raise err("bbox", "missing")
    bbox = entry["bbox"]
    if not (isinstance(bbox, (list, tuple)) and len(bbox) == 4 and all(_is_number(v) for v in bbox)):
        raise err("bbox", f"expected [x, y, w, h] numbers, got {brief(bbox)}")
    segmentation = _segmentation_field(entry, err)
    t = entry.get("time", -1.0)
    if t is None:
        t = -1.0
    if not _is_number(t):
        raise err("time", f"expected a number, got {brief(t)}")
    return Detection(
        scene_id=ids["scene_id"],
        image_id=ids["image_id"],
        category_id=ids["category_id"],
        score=float(entry["score"]),
        bbox=tuple(float(v) for v in bbox),
        segmentation=segmentation,
        time=float(t),
        source=source,
    )


def load_detections(path: Path | str, source: str = "") -> list[Detection]:
    """Read and validate a BOP/CNOS detection file (a JSON list of entries).

    Accepted variants: ``im_id`` for ``image_id`` and ``obj_id`` for ``category_id``
    (both spellings in one entry must agree); ``time`` absent or null (-1); integral
    floats for ids and RLE counts/size; RLE counts as a list or a compressed string.
    Every entry needs a ``segmentation`` (instance mask). The first bad entry raises
    ``BopFormatError`` naming the file, the entry index and the field. ``source`` is
    stored in every detection (not part of the file format).
    """
    path = Path(path)
    content = load_json(path)
    if isinstance(content, dict):
        keys = ", ".join(brief(k, 30) for k in list(content)[:5]) + (", ..." if len(content) > 5 else "")
        raise BopFormatError(
            f"{path}: expected a JSON list of detections at the top level, got an object (keys {keys}); "
            "a file mapping a key to the list is not accepted: save the list itself")
    if not isinstance(content, list):
        raise BopFormatError(f"{path}: expected a JSON list of detections, got {type(content).__name__}")
    return [_parse_detection(path, i, e, source) for i, e in enumerate(content)]


def save_detections(path: Path | str, detections: Iterable[Detection]) -> None:
    """Write detections as a JSON list, one detection per line (BOP layout), atomically."""
    save_bop_json(path, [d.to_json() for d in detections])


# ---------------------------------------------------------------------------- category ids


def map_category_ids(
    detections: Sequence[Detection], obj_ids: Iterable[int], mode: str = "obj_id",
    path: Path | str = "<detections>",
) -> list[Detection]:
    """New detections whose ``category_id`` is the dataset's obj_id.

    mode "obj_id": category_id already is the obj_id (the BOP convention; identity).
    "index0" / "index1": category_id is the 0-based / 1-based position in the sorted
    list of the dataset's obj_ids. Under the index modes an id outside the list raises
    ``BopFormatError`` naming ``path`` and the entry (its position in ``detections``).
    """
    if mode not in CATEGORY_ID_MODES:
        raise ValueError(f"category id mode must be one of {', '.join(CATEGORY_ID_MODES)}, got {mode!r}")
    if mode == "obj_id":
        return [replace(d) for d in detections]
    ordered = sorted({int(o) for o in obj_ids})
    offset = 0 if mode == "index0" else 1
    out = []
    for i, d in enumerate(detections):
        pos = int(d.category_id) - offset
        if not 0 <= pos < len(ordered):
            raise BopFormatError(
                f"{path}: entry {i}, field 'category_id': {d.category_id} is not a valid {mode} position "
                f"({offset}..{len(ordered) - 1 + offset}) in the dataset's sorted obj_ids {ordered}")
        out.append(replace(d, category_id=ordered[pos]))
    return out


def _id_list(ids: Sequence[int], limit: int = 12) -> str:
    shown = ", ".join(str(i) for i in ids[:limit])
    return f"[{shown}{', ...' if len(ids) > limit else ''}]"


def category_id_problem(detections: Sequence[Detection], obj_ids: Iterable[int]) -> str | None:
    """A message if some category_ids are not obj_ids of the dataset (mode "obj_id"), else None.

    When every category_id of the file fits the 0-based (``index0``) or 1-based
    (``index1``) position interpretation of the sorted obj_ids, the message suggests it
    (both when both fit). The message does not name the file; callers prefix it.
    """
    valid = sorted({int(o) for o in obj_ids})
    valid_set = set(valid)
    ids = sorted({int(d.category_id) for d in detections})
    unknown = [c for c in ids if c not in valid_set]
    if not unknown:
        return None
    n_bad = sum(1 for d in detections if int(d.category_id) not in valid_set)
    msg = (f"{n_bad} of {len(detections)} detections have a category_id that is not an obj_id of the dataset: "
           f"{_id_list(unknown)} (dataset obj_ids {_id_list(valid)}; in BOP detections category_id is the obj_id).")
    fits = [m for m, off in (("index0", 0), ("index1", 1)) if all(off <= c < len(valid) + off for c in ids)]
    if len(fits) == 1:
        base = "0-based" if fits[0] == "index0" else "1-based"
        msg += (f" Every category_id is a {base} position in the sorted obj_ids: the file probably uses "
                f"category id mode '{fits[0]}'.")
    elif len(fits) == 2:
        msg += (" Every category_id fits both a 0-based ('index0') and a 1-based ('index1') position in the sorted "
                "obj_ids; check the detector's export to choose the mode.")
    return msg


# ---------------------------------------------------------------------------- merging priors


class _MaskGeom:
    """Geometry of one RLE mask for IoU tests, without decoding the whole image.

    area: foreground pixels. box: (x0, y0, x1, y1) inclusive px of the foreground, None
    when empty. ``crop()`` decodes only the box, (y1 - y0 + 1, x1 - x0 + 1) bool, once.
    """

    def __init__(self, rle: dict) -> None:
        counts, self.h, self.w = _rle_counts(rle)
        self._counts = np.asarray(counts, dtype=np.int64)
        self._ends = np.cumsum(self._counts)
        self._starts = self._ends - self._counts
        self.area = int(self._counts[1::2].sum())
        self.box = self._fg_box()
        self._crop: np.ndarray | None = None

    def _fg_box(self) -> tuple[int, int, int, int] | None:
        s, e = self._starts[1::2], self._ends[1::2]
        nonempty = e > s
        if not nonempty.any():
            return None
        first, last = s[nonempty], e[nonempty] - 1  # flat column-major indices
        c_first, c_last = first // self.h, last // self.h
        same = c_first == c_last  # a run crossing a column boundary covers rows H-1 and 0
        y0 = 0 if not same.all() else int((first % self.h).min())
        y1 = self.h - 1 if not same.all() else int((last % self.h).max())
        return int(c_first.min()), y0, int(c_last.max()), y1

    def crop(self) -> np.ndarray:
        if self._crop is None:
            x0, y0, x1, y1 = self.box
            lo, hi = x0 * self.h, (x1 + 1) * self.h
            runs = np.clip(self._ends, lo, hi) - np.clip(self._starts, lo, hi)
            flat = np.repeat(np.arange(len(runs)) % 2 == 1, runs)
            self._crop = np.ascontiguousarray(flat.reshape((x1 - x0 + 1, self.h)).T[y0:y1 + 1])
        return self._crop


def _box_overlap(a: _MaskGeom, b: _MaskGeom) -> tuple[int, int, int, int] | None:
    """Intersection (x0, y0, x1, y1) inclusive of two foreground boxes, None if disjoint."""
    if a.box is None or b.box is None:
        return None
    x0, y0 = max(a.box[0], b.box[0]), max(a.box[1], b.box[1])
    x1, y1 = min(a.box[2], b.box[2]), min(a.box[3], b.box[3])
    return (x0, y0, x1, y1) if x0 <= x1 and y0 <= y1 else None


def _mask_iou(a: _MaskGeom, b: _MaskGeom, at_least: float = 0.0) -> float:
    """Mask IoU in [0, 1]; 0.0 is returned without decoding when it is provably < at_least.

    The bound: the intersection is at most min(area a, area b, box-overlap area).
    """
    ov = _box_overlap(a, b)
    if ov is None:
        return 0.0
    x0, y0, x1, y1 = ov
    bound = min(a.area, b.area, (x1 - x0 + 1) * (y1 - y0 + 1))
    if bound / (a.area + b.area - bound) < at_least:
        return 0.0
    sa = a.crop()[y0 - a.box[1]:y1 - a.box[1] + 1, x0 - a.box[0]:x1 - a.box[0] + 1]
    sb = b.crop()[y0 - b.box[1]:y1 - b.box[1] + 1, x0 - b.box[0]:x1 - b.box[0] + 1]
    inter = int(np.count_nonzero(sa & sb))
    return inter / (a.area + b.area - inter)


_Pooled = tuple[int, int, Detection]  # (source index, index in its file, detection)


def _group_duplicates(members: list[_Pooled], names: Sequence[str], iou_threshold: float) -> dict[int, int]:
    """Dropped members of one (scene, image, category) group: {position in members: source index of the keeper}."""
    order = sorted(range(len(members)), key=lambda p: (-members[p][2].score, members[p][0], members[p][1]))
    geoms: dict[int, _MaskGeom] = {}
    kept: list[int] = []
    dropped: dict[int, int] = {}
    first_src, first_idx, _ = members[order[0]]
    for p in order:
        src, idx, det = members[p]
        g = geoms[p] = _MaskGeom(det.segmentation)
        ref = geoms[order[0]]
        if (g.h, g.w) != (ref.h, ref.w):
            raise BopFormatError(
                f"{names[src]}: entry {idx}, field 'segmentation': mask size {g.h}x{g.w} differs from "
                f"{ref.h}x{ref.w} of '{names[first_src]}' entry {first_idx} for the same image "
                f"(scene {det.scene_id}, image {det.image_id})")
        keeper = next((q for q in kept if members[q][0] != src
                       and _mask_iou(g, geoms[q], iou_threshold) >= iou_threshold), None)
        if keeper is None:
            kept.append(p)
        else:
            dropped[p] = members[keeper][0]
    return dropped


def merge_detections(
    sources: Sequence[tuple[str, Sequence[Detection]]], iou_threshold: float = 0.5,
) -> tuple[list[Detection], dict]:
    """Merge the detections of several prior files (an ensemble of detectors) into one list.

    Rule: the detections of all files are pooled; within each (scene_id, image_id,
    category_id) group they are visited by decreasing score (ties: source order, then
    file order); a detection is dropped when its mask IoU with an already kept
    detection from a different source is >= ``iou_threshold`` (two detectors found the
    same instance; the more confident mask is kept); detections of the same source are
    never suppressed against each other (a detector's own multiple instances stay).
    A kept detection keeps its own score, bbox, mask and time; its ``source`` is set to
    the name of its source. The result lists the kept detections in source order, then
    file order; a single source comes back unchanged and in the same order (only
    ``source`` set).

    sources: (name, detections) pairs, names unique (file paths or detector names);
    category ids must already be obj_ids (see ``map_category_ids``). iou_threshold in
    (0, 1]. Masks of one image must have the same size in every source.
    Returns (detections, report) with report = {"iou_threshold", "n_read", "n_kept",
    "n_dropped_duplicates", "sources": {name: {"n_read", "n_kept", "n_dropped_duplicates",
    "duplicate_of": {other source name: count}}}}.
    """
    if not 0.0 < iou_threshold <= 1.0:
        raise ValueError(f"iou_threshold must be in (0, 1], got {iou_threshold}")
    names = [str(name) for name, _ in sources]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"merge_detections: source names must be unique, repeated: {repeated}")
    pooled: list[_Pooled] = [(s, i, d) for s, (_, dets) in enumerate(sources) for i, d in enumerate(dets)]
    groups: dict[tuple[int, int, int], list[int]] = {}
    for pos, (_, _, d) in enumerate(pooled):
        groups.setdefault((int(d.scene_id), int(d.image_id), int(d.category_id)), []).append(pos)
    dropped_by: dict[int, int] = {}  # pooled position -> source index of the kept duplicate
    for positions in groups.values():
        if len({pooled[p][0] for p in positions}) < 2:
            continue  # a single source in the group: nothing to suppress
        members = [pooled[p] for p in positions]
        for local, keeper_src in _group_duplicates(members, names, iou_threshold).items():
            dropped_by[positions[local]] = keeper_src
    merged = [replace(d, source=names[s]) for pos, (s, _, d) in enumerate(pooled) if pos not in dropped_by]
    return merged, _merge_report(names, sources, pooled, dropped_by, iou_threshold)


def _merge_report(names: Sequence[str], sources: Sequence[tuple[str, Sequence[Detection]]],
                  pooled: Sequence[_Pooled], dropped_by: dict[int, int], iou_threshold: float) -> dict:
    per_source = {n: {"n_read": len(dets), "n_kept": len(dets), "n_dropped_duplicates": 0, "duplicate_of": {}}
                  for n, (_, dets) in zip(names, sources)}
    for pos, keeper_src in dropped_by.items():
        entry = per_source[names[pooled[pos][0]]]
        entry["n_kept"] -= 1
        entry["n_dropped_duplicates"] += 1
        entry["duplicate_of"][names[keeper_src]] = entry["duplicate_of"].get(names[keeper_src], 0) + 1
    n_read = len(pooled)
    return {"iou_threshold": float(iou_threshold), "n_read": n_read, "n_kept": n_read - len(dropped_by),
            "n_dropped_duplicates": len(dropped_by), "sources": per_source}


def detector_name(prior_file: Path | str) -> str:
    """The detector of a prior file: the part of its name before the first '_' (BOP's
    ``<method>_<dataset>-<split>...json``)."""
    return Path(prior_file).stem.split("_")[0]

"""Localisation priors: select candidate masks for the targets of a dataset."""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from pipeline.formats.bop.detections import rle_uncompressed


def rle_area(counts: Sequence[int]) -> int:
    """Foreground pixels of an uncompressed RLE (odd runs are foreground)."""
    return int(np.asarray(counts[1::2], dtype=np.int64).sum())


def select_candidates(
    detections: Sequence[Any],
    targets: Sequence[Any],
    *,
    top_k: int,
    min_score: float = 0.0,
    min_area: int = 1,
    source: str = "detections",
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Keep the ``top_k * inst_count`` most confident detections of each target (image,
    object): ``top_k`` candidates per instance to find.

    detections: :class:`pipeline.formats.bop.detections.Detection` items; targets: items with
    scene_id, im_id, obj_id and inst_count (1 if absent). Returns the candidate table (see stage segment_prior;
    the last column, ``prior_source``, is the detection's ``source``: the prior file/detector
    it came from, "" when not recorded) and a report of what was dropped and why, plus the
    targets left without any candidate.
    """
    target_keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
    inst_count = {(t.scene_id, t.im_id, t.obj_id): max(1, int(getattr(t, "inst_count", 1))) for t in targets}
    dropped: Counter[str] = Counter()
    per_target: dict[tuple[int, int, int], list[tuple[float, int, Any]]] = defaultdict(list)
    image_time: dict[tuple[int, int], float] = {}
    for idx, det in enumerate(detections):
        key = (int(det.scene_id), int(det.image_id), int(det.category_id))
        if det.time is not None and det.time >= 0:
            image_time.setdefault(key[:2], float(det.time))
        if key not in target_keys:
            dropped["not_a_target"] += 1
            continue
        if det.score < min_score:
            dropped["low_score"] += 1
            continue
        per_target[key].append((float(det.score), idx, det))
    rows = []
    for key in sorted(per_target):
        ranked = sorted(per_target[key], key=lambda x: (-x[0], x[1]))
        kept = 0
        for score, idx, det in ranked:
            if kept >= top_k * inst_count[key]:
                dropped["beyond_top_k"] += 1
                continue
            rle = rle_uncompressed(det.segmentation)
            area = rle_area(rle["counts"])
            if area < min_area:
                dropped["small_mask"] += 1
                continue
            h, w = (int(v) for v in rle["size"])
            x, y, bw, bh = (float(v) for v in det.bbox)
            rows.append({
                "scene_id": key[0], "im_id": key[1], "obj_id": key[2], "prior_score": score,
                "bbox_x": x, "bbox_y": y, "bbox_w": bw, "bbox_h": bh,
                "area": area, "height": h, "width": w,
                "rle_counts": [int(c) for c in rle["counts"]],
                "det_index": idx, "prior_time": image_time.get(key[:2], -1.0),
                "prior_source": str(getattr(det, "source", "") or ""),
            })
            kept += 1
    table = pd.DataFrame(rows, columns=[
        "scene_id", "im_id", "obj_id", "prior_score", "bbox_x", "bbox_y", "bbox_w", "bbox_h",
        "area", "height", "width", "rle_counts", "det_index", "prior_time", "prior_source"])
    table.insert(0, "cand_id", np.arange(len(table), dtype=np.int64))
    covered = {tuple(k) for k in table[["scene_id", "im_id", "obj_id"]].itertuples(index=False)}
    missing = sorted(target_keys - covered)
    report = {
        "source": source,
        "n_detections": len(detections),
        "n_candidates": int(len(table)),
        "n_targets": len(target_keys),
        "dropped": dict(dropped),
        "targets_without_candidate": [list(k) for k in missing],
    }
    return table, report


def candidates_from_priors(paths: Sequence[Path], targets: Sequence[Any], obj_ids: Sequence[int], params) -> tuple[
        pd.DataFrame, dict[str, Any]]:
    """The candidate table of a dataset from its prior file(s) (stage segment_prior).

    paths: BOP/CNOS detection files; targets: the dataset's targets; obj_ids: the
    object ids on disk (for index-style category ids); params: the run's
    :class:`pipeline.common.config.SegmentPriorParams`. Each file's category ids are mapped to
    obj_ids (``params.category_ids``; a file whose ids are not obj_ids fails, naming
    it), several files are merged (:func:`pipeline.formats.bop.detections.merge_detections`,
    ``params.merge_iou``), and the ``top_k * inst_count`` most confident candidates of
    each target are kept (:func:`select_candidates`). Returns the table and the report
    (with ``prior_files`` and, for several files, ``merge``).
    """
    from pipeline.formats.bop.detections import (category_id_problem, detector_name, load_detections, map_category_ids,
                                         merge_detections)
    from pipeline.formats.bop.errors import BopFormatError

    sources = []
    for path in paths:
        name = detector_name(path)
        if any(name == n for n, _ in sources):
            name = str(path)  # two files of one detector: their paths tell them apart
        dets = map_category_ids(load_detections(path, source=name), obj_ids, params.category_ids, path=path)
        if params.category_ids == "obj_id":
            problem = category_id_problem(dets, obj_ids)
            if problem:
                raise BopFormatError(f"{path}: {problem}")
        sources.append((name, dets))
    if len(sources) == 1:
        detections, merge_report = sources[0][1], None
    else:
        detections, merge_report = merge_detections(sources, iou_threshold=params.merge_iou)
    table, report = select_candidates(detections, targets, top_k=params.top_k, min_score=params.min_score,
                                      min_area=params.min_area, source=", ".join(str(p) for p in paths))
    report["prior_files"] = [str(p) for p in paths]
    if merge_report is not None:
        report["merge"] = merge_report
    return table, report

"""Stage segment_prior: ingest BOP/CNOS detections JSON files -> ``candidates.parquet``.

One row per kept candidate mask: cand_id, scene_id, im_id, obj_id, score, bbox
(x, y, w, h px), area (mask pixels), height, width, rle_counts (uncompressed COCO RLE,
column-major, starting with background), det_index (position in the prior file, or
in the merged list when several files are merged), prior_time (s, the detector's time
for that image) and prior_source (the detector name of the file it came from). Only detections of (image, object) pairs
that are targets are kept, the ``top_k * inst_count`` most confident per pair (top_k
per instance to find).

Several prior files (``--config prior=a,b``) are merged first by
:func:`pipeline.bop.detections.merge_detections`: detections of one (image, object)
from different files whose masks overlap by ``merge_iou`` or more are one instance,
and the more confident one is kept.
"""

from __future__ import annotations

from pipeline.plan import DatasetPlan, detector_name
from pipeline.store import publish, write_table

CODE_VERSION = 3


def run(plan: DatasetPlan, item: str = "all", progress: bool = True) -> None:
    from pipeline.bop.detections import category_id_problem, load_detections, map_category_ids, merge_detections
    from pipeline.bop.errors import BopFormatError
    from pipeline.segmentation import select_candidates

    if item != "all":
        raise ValueError(f"segment_prior has a single item 'all', not '{item}'")
    sp = plan["segment_prior"]
    p = plan.run.stages.segment_prior
    bop = plan.bop()
    targets = bop.targets(plan.root / plan.dataset.targets_file)
    obj_ids = bop.obj_ids()  # what is on disk (models_info), for index-style category ids
    paths = plan.prior_paths
    sources = []
    for path in paths:
        name = detector_name(path)
        if any(name == n for n, _ in sources):
            name = str(path)  # two files of one detector: their paths tell them apart
        dets = map_category_ids(load_detections(path, source=name), obj_ids, p.category_ids, path=path)
        if p.category_ids == "obj_id":
            problem = category_id_problem(dets, obj_ids)
            if problem:
                raise BopFormatError(f"{path}: {problem}")
        sources.append((name, dets))
    if len(sources) == 1:
        detections, merge_report = sources[0][1], None
    else:
        detections, merge_report = merge_detections(sources, iou_threshold=p.merge_iou)
    source = ", ".join(str(path) for path in paths)
    table, report = select_candidates(detections, targets, top_k=p.top_k, min_score=p.min_score,
                                      min_area=p.min_area, source=source)
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        write_table(table, w.dir / "candidates.parquet", metadata={"key": sp.key, "stage": "segment_prior"})
        w.summary.update(report)
        w.summary["prior_files"] = [str(path) for path in paths]
        if merge_report is not None:
            w.summary["merge"] = merge_report

"""Stage segment_prior: ingest a BOP/CNOS detections JSON -> ``candidates.parquet``.

One row per kept candidate mask: cand_id, scene_id, im_id, obj_id, score, bbox
(x, y, w, h px), area (mask pixels), height, width, rle_counts (uncompressed COCO RLE,
column-major, starting with background), det_index (position in the source file) and
prior_time (s, the detector's time for that image). Only detections of (image,
object) pairs that are targets are kept, the ``top_k * inst_count`` most confident per
pair (top_k per instance to find).
"""

from __future__ import annotations

from pipeline.plan import DatasetPlan
from pipeline.store import publish, write_table

CODE_VERSION = 2


def run(plan: DatasetPlan, item: str = "all", progress: bool = True) -> None:
    from pipeline.bop.detections import load_detections
    from pipeline.segmentation import select_candidates

    if item != "all":
        raise ValueError(f"segment_prior has a single item 'all', not '{item}'")
    sp = plan["segment_prior"]
    p = plan.run.stages.segment_prior
    bop = plan.bop()
    targets = bop.targets(plan.root / plan.dataset.targets_file)
    detections = load_detections(plan.prior_path)
    table, report = select_candidates(detections, targets, top_k=p.top_k, min_score=p.min_score,
                                      min_area=p.min_area, source=str(plan.prior_path))
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        write_table(table, w.dir / "candidates.parquet", metadata={"key": sp.key, "stage": "segment_prior"})
        w.summary.update(report)
        w.summary["prior_file"] = str(plan.prior_path)

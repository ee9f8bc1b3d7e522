"""Stage segment_prior: ingest BOP/CNOS detections JSON files -> ``prior_candidates.parquet``.

One row per kept candidate mask: cand_id, scene_id, im_id, obj_id, prior_score, bbox
(x, y, w, h px), area (mask pixels), height, width, rle_counts (uncompressed COCO RLE,
column-major, starting with background), det_index (position in the prior file, or
in the merged list when several files are merged), prior_time (s, the detector's time
for that image) and prior_source (the detector name of the file it came from). Only
detections of (image, object) pairs that are targets are kept, the ``top_k *
inst_count`` most confident per pair (top_k per instance to find).

Several prior files (``--config prior=a,b``) are merged first: detections of one
(image, object) from different files whose masks overlap by ``merge_iou`` or more are
one instance, and the more confident one is kept. Algorithm:
:func:`pipeline.method.segmentation.candidates_from_priors`.

Before that, where the dataset's ground truth is public, the stage refuses ground truth
the score stage could not read (:meth:`pipeline.formats.bop.BopDataset.ground_truth_problems`),
in one line naming the file, the entry and the field: it is the first scene-side job,
so a bad ``scene_gt.json`` stops the run at its start.
"""

from __future__ import annotations

from pipeline.formats.bop.errors import BopFormatError
from pipeline.workflow.plan import DatasetPlan


def run(plan: DatasetPlan, item: str = "all", progress: bool = True) -> None:
    from pipeline.method.segmentation import candidates_from_priors

    io = plan.io("segment_prior", item)
    bop = io.bop()
    targets = bop.targets(plan.root / plan.dataset.targets_file)
    if plan.dataset.public_gt:
        # No stage before score reads the ground truth: a NaN pose or a missing
        # scene_gt_info.json would otherwise fail the run at its end, after every
        # estimate was made. This is the first scene-side job; refusing here costs a
        # parse of the target scenes' ground truth, once per dataset key.
        problems = bop.ground_truth_problems(targets)
        if problems:
            more = f" (and {len(problems) - 1} more problems: freeze datasets check lists them)" if len(problems) > 1 else ""
            raise BopFormatError(f"{problems[0]}{more}; the score stage would fail on it (to make estimates without "
                                 "scoring them, set 'public_gt: false' in the dataset's manifest)")
    table, report = candidates_from_priors(io.prior_paths, targets, bop.obj_ids(), io.params)
    with io.publish() as w:
        w.write("prior_candidates", table, metadata={"stage": "segment_prior"})
        w.summary.update(report)

"""Stage scene_features: per candidate of one scene (or of a chunk of its images, see
``images_per_job``), lifted points and their features.

``features.zarr`` (C = candidates of the scene, M = ``scene_features.n_points``):
points (C, M, 3) float32 mm camera frame, pixels (C, M, 2) int32 (u, v), geometric
(C, M, G) and visual (C, M, V) float32 (NaN beyond n_points), n_points (C,) int32,
cand_id (C,) int64. ``candidate_status.parquet``: every candidate of the scene with status
``ok`` or ``skipped`` and the reason. ``image_times.parquet``: processing time per image (s).
(Every column and array: ``docs/artifacts.md``.)
Algorithm: :meth:`pipeline.method.estimator.Estimator.scene_features`
(:func:`pipeline.method.scene_side.scene_features`).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from pipeline.workflow.plan import DatasetPlan, build_encoders, encoder_runtime, warm_imports


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.common.progress import progress_bar
    from pipeline.formats.bop.detections import prior_row_mask
    from pipeline.method.estimator import Estimator, Observation
    from pipeline.method.scene_side import CandidateMask, pack_candidates
    from pipeline.workflow.prepared import prepared_objects

    io = plan.io("scene_features", item)
    scene_id, p = io.item_id(), io.params
    bop = io.bop()
    cams = bop.scene_camera(scene_id)
    cands = io.table("segment_prior", "prior_candidates")
    cands = cands[(cands.scene_id == scene_id) & cands.im_id.isin(io.images())].sort_values("cand_id")
    estimator = Estimator(prepared_objects(io, bop), plan.run.stages, build_encoders(plan.run))
    warm_imports("pipeline.method.encoders.lifting", "pipeline.method.geometry.depth")
    geo_enc, vis_enc = estimator.encoders
    found = {}
    image_rows = []
    with progress_bar(f"scene_features {item}", total=len(cands), enabled=progress) as bar:
        for im_id, rows in cands.groupby("im_id", sort=True):
            t0 = time.perf_counter()
            depth = bop.load_depth(scene_id, int(im_id))
            masks = []
            for r in rows.itertuples(index=False):
                mask = prior_row_mask(r)
                if mask.shape != depth.shape:
                    src = getattr(r, "prior_source", "") or ", ".join(str(x) for x in plan.prior_paths)
                    raise ValueError(f"{src}: detection {r.det_index} (scene {scene_id}, image {im_id}): "
                                     f"mask size {mask.shape} differs from the depth image {depth.shape}")
                masks.append(CandidateMask(int(r.cand_id), int(r.obj_id), mask, (r.bbox_x, r.bbox_y, r.bbox_w, r.bbox_h),
                                           estimator.objects[int(r.obj_id)].diameter,
                                           io.candidate_seed(int(r.cand_id), p.seed)))
            obs = Observation(bop.load_rgb(scene_id, int(im_id)), depth, cams[int(im_id)].K)
            for f in estimator.scene_features(obs, masks, progress=bar.advance):
                found[f.cand_id] = f
            image_rows.append({"scene_id": scene_id, "im_id": int(im_id), "n_candidates": len(rows),
                               "time_s": time.perf_counter() - t0})
    ordered = [found[int(c)] for c in cands.cand_id]
    n = len(ordered)
    table = cands.drop(columns=["rle_counts"]).copy()
    table["status"] = ["ok" if f.ok else "skipped" for f in ordered]
    table["reason"] = [f.reason for f in ordered]
    table["n_valid_points"] = np.asarray([f.n_valid for f in ordered], np.int64)
    table["n_points"] = np.asarray([len(f.points) for f in ordered], np.int32)
    with io.publish() as w:
        # where the encoders ran and in what precision: recorded, not keyed
        w.manifest["runtime"] = {"geometric": encoder_runtime(geo_enc), "visual": encoder_runtime(vis_enc)}
        w.write("features", pack_candidates(ordered, p.n_points, geo_enc.dim, vis_enc.dim),
                chunks={"n_points": (max(1, n),), "cand_id": (max(1, n),)},
                attrs={"scene_id": scene_id, "geometric_encoder": geo_enc.signature(),
                       "visual_encoder": vis_enc.signature()})
        w.write("candidate_status", table)
        w.write("image_times", pd.DataFrame(image_rows, columns=["scene_id", "im_id", "n_candidates", "time_s"]))
        w.summary.update({"scene_id": scene_id, "n_candidates": n, "n_ok": sum(f.ok for f in ordered),
                          "skipped": {str(f.cand_id): f.reason for f in ordered if not f.ok}})

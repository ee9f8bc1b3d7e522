"""Stage scene_features: per candidate mask of one scene -> ``features.zarr`` + tables.

Zarr arrays, chunked one candidate per chunk (C candidates, M sampled points, padded
with NaN past ``n_points``): points (C, M, 3) float32 mm camera frame, pixels (C, M, 2)
int32 (u, v), geometric (C, M, G) float32, visual (C, M, D) float32, n_points (C,)
int32, cand_id (C,) int64.
``candidates.parquet``: every candidate of the scene with status ``ok`` or
``skipped`` and the reason. ``images.parquet``: processing time per image (s).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from pipeline.plan import DatasetPlan, item_id
from pipeline.store import item_seed, publish, read_table, save_arrays, write_table

CODE_VERSION = 1


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.bop.detections import rle_decode
    from pipeline.encoders.lifting import crop_and_resize, sample_features_at_pixels, square_crop_box
    from pipeline.geometry.depth import lift_depth, remove_outliers
    from pipeline.plan import build_encoders
    from pipeline.progress import progress_bar

    scene_id = item_id(item, "scene", "scene_features")
    sp = plan["scene_features"]
    p = plan.run.stages.scene_features
    bop = plan.bop()
    infos = bop.models_info()
    cams = bop.scene_camera(scene_id)
    cands = read_table(plan["segment_prior"].item_dir("all") / "candidates.parquet")
    cands = cands[cands.scene_id == scene_id].sort_values("cand_id")
    geo_enc, vis_enc = build_encoders(plan.run)
    M = p.n_points
    n = len(cands)
    points = np.full((n, M, 3), np.nan, np.float32)
    pixels = np.full((n, M, 2), -1, np.int32)
    geometric = np.full((n, M, geo_enc.dim), np.nan, np.float32)
    visual = np.full((n, M, vis_enc.dim), np.nan, np.float32)
    n_points = np.zeros(n, np.int32)
    status = ["ok"] * n
    reasons = [""] * n
    n_valid = np.zeros(n, np.int64)
    image_rows = []

    rows = list(cands.itertuples(index=False))
    row_pos = {r.cand_id: i for i, r in enumerate(rows)}
    by_image: dict[int, list] = {}
    for r in rows:
        by_image.setdefault(int(r.im_id), []).append(r)
    with progress_bar(f"scene_features {item}", total=n, enabled=progress) as bar:
        for im_id, im_rows in sorted(by_image.items()):
            t0 = time.perf_counter()
            cam = cams[im_id]
            depth = bop.load_depth(scene_id, im_id)
            rgb = bop.load_rgb(scene_id, im_id)
            crops, crop_boxes, crop_idx = [], [], []
            for r in im_rows:
                i = row_pos[r.cand_id]
                mask = rle_decode({"counts": list(r.rle_counts), "size": [int(r.height), int(r.width)]})
                if mask.shape != depth.shape:
                    src = getattr(r, "prior_source", "") or ", ".join(str(x) for x in plan.prior_paths)
                    raise ValueError(f"{src}: detection {r.det_index} (scene {scene_id}, image {im_id}): "
                                     f"mask size {mask.shape} differs from the depth image {depth.shape}")
                diameter = infos[int(r.obj_id)].diameter
                pts, pix = lift_depth(depth, cam.K, mask)
                if len(pts):
                    keep = remove_outliers(pts, diameter)
                    pts, pix = pts[keep], pix[keep]
                n_valid[i] = len(pts)
                if len(pts) < p.min_points:
                    status[i], reasons[i] = "skipped", f"{len(pts)} valid depth points < min_points {p.min_points}"
                    bar.advance()
                    continue
                rng = np.random.default_rng(item_seed(sp.key, f"{item}/{r.cand_id}", p.seed))
                sel = rng.choice(len(pts), size=min(M, len(pts)), replace=False)
                sel.sort()
                k = len(sel)
                points[i, :k], pixels[i, :k], n_points[i] = pts[sel], pix[sel], k
                geometric[i, :k] = geo_enc.encode(pts[sel], None, diameter, viewpoint=np.zeros(3))
                box = square_crop_box((r.bbox_x, r.bbox_y, r.bbox_w, r.bbox_h), depth.shape, margin=p.crop_margin)
                crops.append(crop_and_resize(rgb, box, vis_enc.input_size))
                crop_boxes.append(box)
                crop_idx.append(i)
                bar.advance()
            if crops and vis_enc.dim:
                feats = vis_enc.encode(np.stack(crops))
                for j, i in enumerate(crop_idx):
                    k = n_points[i]
                    visual[i, :k] = sample_features_at_pixels(feats[j], crop_boxes[j], vis_enc.input_size, pixels[i, :k].astype(np.float32))
            image_rows.append({"scene_id": scene_id, "im_id": im_id, "n_candidates": len(im_rows),
                               "time_s": time.perf_counter() - t0})

    table = cands.drop(columns=["rle_counts"]).copy()
    table["status"] = status
    table["reason"] = reasons
    table["n_valid_points"] = n_valid
    table["n_points"] = n_points
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        save_arrays(
            w.dir / "features.zarr",
            {"points": points, "pixels": pixels, "geometric": geometric, "visual": visual,
             "n_points": n_points, "cand_id": cands.cand_id.to_numpy(np.int64)},
            chunks={"n_points": (max(1, n),), "cand_id": (max(1, n),)},
            attrs={"key": sp.key, "scene_id": scene_id,
                   "geometric_encoder": geo_enc.signature(), "visual_encoder": vis_enc.signature()},
        )
        write_table(table, w.dir / "candidates.parquet", metadata={"key": sp.key})
        write_table(pd.DataFrame(image_rows, columns=["scene_id", "im_id", "n_candidates", "time_s"]),
                    w.dir / "images.parquet", metadata={"key": sp.key})
        w.summary.update({"scene_id": scene_id, "n_candidates": n, "n_ok": status.count("ok"),
                          "skipped": {str(r.cand_id): reasons[row_pos[r.cand_id]] for r in rows if status[row_pos[r.cand_id]] != "ok"}})

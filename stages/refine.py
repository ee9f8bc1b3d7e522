"""Stage refine: ICP from the coarse pose -> ``poses.parquet`` per scene, and (item
``all``) the BOP results CSV ``<method>_<dataset>-<split>.csv`` of the whole dataset.

Per-scene ``poses.parquet``: scene_id, im_id, obj_id, cand_id, R (9 floats, row-major),
t (mm), score, fitness, inlier_rmse (mm), coarse n_inliers, time_s.
The CSV's ``time`` is, per image, the prior's time plus this pipeline's scene-side
time (scene_features + register + refine) for that image, in seconds (BOP: the time to
produce all estimates of the image, excluding model onboarding).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from pipeline.plan import DatasetPlan, obj_item, item_id, scene_item
from pipeline.store import load_arrays, publish, read_table, write_table

CODE_VERSION = 1


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    if item == "all":
        return _collect(plan)
    from pipeline.geometry.icp import refine_icp
    from pipeline.progress import progress_bar
    from pipeline.registration.selection import estimate_score

    scene_id = item_id(item, "scene", "refine")
    sp = plan["refine"]
    p = plan.run.stages.refine
    infos = plan.bop().models_info()
    coarse = read_table(plan["register"].item_dir(item) / "poses.parquet")
    scene = load_arrays(plan["scene_features"].item_dir(item) / "features.zarr")
    pos = {int(c): i for i, c in enumerate(scene["cand_id"])}
    models: dict[int, dict] = {}
    rows = []
    with progress_bar(f"refine {item}", total=len(coarse), enabled=progress) as bar:
        for c in coarse.itertuples(index=False):
            t0 = time.perf_counter()
            obj_id = int(c.obj_id)
            if obj_id not in models:
                models[obj_id] = load_arrays(plan["model_features"].item_dir(obj_item(obj_id)) / "features.zarr",
                                             ["points", "normals"])
            m = models[obj_id]
            i = pos[int(c.cand_id)]
            k = int(scene["n_points"][i])
            res = refine_icp(m["points"], m["normals"], scene["points"][i, :k],
                             np.asarray(c.R, float).reshape(3, 3), np.asarray(c.t, float), infos[obj_id].diameter,
                             max_corr_dist_frac=p.max_corr_frac, iterations=p.iterations, point_to_plane=p.point_to_plane)
            rows.append({"scene_id": scene_id, "im_id": int(c.im_id), "obj_id": obj_id, "cand_id": int(c.cand_id),
                         "R": np.asarray(res.R, float).reshape(9).tolist(), "t": np.asarray(res.t, float).reshape(3).tolist(),
                         "score": estimate_score(c.inlier_ratio, res.fitness),
                         "fitness": float(res.fitness), "inlier_rmse": float(res.inlier_rmse),
                         "n_inliers": int(c.n_inliers), "time_s": time.perf_counter() - t0})
            bar.advance()
    poses = pd.DataFrame(rows, columns=["scene_id", "im_id", "obj_id", "cand_id", "R", "t", "score", "fitness",
                                        "inlier_rmse", "n_inliers", "time_s"])
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        write_table(poses, w.dir / "poses.parquet", metadata={"key": sp.key})
        w.summary.update({"scene_id": scene_id, "n_poses": int(len(poses)),
                          "mean_fitness": float(poses.fitness.mean()) if len(poses) else None})


def _collect(plan: DatasetPlan) -> None:
    """Gather every scene's refined poses into the BOP results CSV."""
    from pipeline.bop.results import write_results_csv

    sp = plan["refine"]
    poses, times = [], []
    for scene_id in plan.scene_ids:
        item = scene_item(scene_id)
        poses.append(read_table(sp.item_dir(item) / "poses.parquet"))
        for stage in ("scene_features", "register"):
            times.append(read_table(plan[stage].item_dir(item) / "images.parquet")[["scene_id", "im_id", "time_s"]])
    poses = pd.concat(poses, ignore_index=True) if poses else pd.DataFrame()
    times.append(poses[["scene_id", "im_id", "time_s"]] if len(poses) else pd.DataFrame(columns=["scene_id", "im_id", "time_s"]))
    cands = read_table(plan["segment_prior"].item_dir("all") / "candidates.parquet")
    prior_time = cands.groupby(["scene_id", "im_id"]).prior_time.first().clip(lower=0.0)
    per_image = pd.concat(times, ignore_index=True).groupby(["scene_id", "im_id"]).time_s.sum()
    per_image = per_image.add(prior_time, fill_value=0.0)
    rows = []
    for r in poses.itertuples(index=False):
        rows.append({"scene_id": r.scene_id, "im_id": r.im_id, "obj_id": r.obj_id, "score": r.score,
                     "R": np.asarray(r.R).reshape(3, 3), "t": np.asarray(r.t), "time": float(per_image.loc[(r.scene_id, r.im_id)])})
    with publish(sp.item_dir("all"), **sp.publish_kwargs("all")) as w:
        write_results_csv(w.dir / plan.results_csv_name, rows)
        w.summary.update({"results_csv": plan.results_csv_name, "n_estimates": len(rows),
                          "n_images": int(per_image.size),
                          "mean_time_per_image_s": float(per_image.mean()) if per_image.size else None})

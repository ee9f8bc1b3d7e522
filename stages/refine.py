"""Stage refine: ICP of every registered candidate, choice of the estimates per target,
symmetry-aware refinement (SAR), and (item ``all``) the BOP results CSV
``<method>_<dataset>-<split>.csv`` of the whole dataset.

Per scene:

- ``candidates.parquet``: every registered candidate with its refined pose (R as 9
  row-major floats, t mm), ICP fitness and inlier_rmse (mm), the RANSAC n_inliers and
  inlier_ratio, prior_score, ``evidence`` (inlier ratio x ICP fitness), and the choice:
  selected, rank (0 = best kept), note (why not kept).
- ``poses.parquet``: the kept estimates (up to ``inst_count`` distinct ones per target,
  ranked by ``refine.select_by``): scene_id, im_id, obj_id, cand_id, R, t, score (the
  ranking value, written to the CSV), evidence, fitness, inlier_rmse, n_inliers,
  sar_variant (index of the chosen symmetric variant, 0 = the ICP pose, -1 = no SAR)
  and sar_reason (why SAR did not run, if it did not).
- ``sar.parquet``: per estimate that went through SAR, one row per symmetric variant
  with its pose, similarity and whether it was chosen.
- ``images.parquet``: this stage's time per image (s).

The CSV's ``time`` is, per image, the prior's time plus this pipeline's scene-side time
(scene_features + register + refine) for that image, in seconds (BOP: the time to
produce all estimates of the image, excluding model onboarding).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from pipeline.plan import DatasetPlan, item_id, obj_item, scene_item
from pipeline.store import load_arrays, publish, read_table, write_table

CODE_VERSION = 2

CANDIDATE_COLUMNS = ["cand_id", "scene_id", "im_id", "obj_id", "prior_score", "n_inliers", "inlier_ratio", "R", "t",
                     "fitness", "inlier_rmse", "evidence", "time_s"]
POSE_COLUMNS = ["scene_id", "im_id", "obj_id", "cand_id", "R", "t", "score", "evidence", "fitness", "inlier_rmse",
                "n_inliers", "sar_variant", "sar_reason"]
SAR_COLUMNS = ["scene_id", "im_id", "obj_id", "cand_id", "variant", "R", "t", "similarity", "chosen"]


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    if item == "all":
        return _collect(plan)
    from pipeline.geometry.icp import refine_icp
    from pipeline.progress import progress_bar
    from pipeline.registration.selection import RANK_COLUMNS, estimate_score, select_estimates

    scene_id = item_id(item, "scene", "refine")
    sp = plan["refine"]
    p = plan.run.stages.refine
    bop = plan.bop()
    infos = bop.models_info()
    targets = [t for t in bop.targets(plan.root / plan.dataset.targets_file) if t.scene_id == scene_id]
    registered = read_table(plan["register"].item_dir(item) / "candidates.parquet")
    registered = registered[registered.status == "ok"]
    scene = load_arrays(plan["scene_features"].item_dir(item) / "features.zarr", ["points", "n_points", "cand_id"])
    pos = {int(c): i for i, c in enumerate(scene["cand_id"])}
    models: dict[int, dict] = {}
    image_time: dict[int, float] = {}
    rows = []
    with progress_bar(f"refine {item}", total=len(registered), enabled=progress) as bar:
        for c in registered.itertuples(index=False):
            t0 = time.perf_counter()
            obj_id = int(c.obj_id)
            R, t = np.asarray(c.R, float).reshape(3, 3), np.asarray(c.t, float)
            fitness, rmse = float(c.fitness), float("nan")
            if p.icp:
                if obj_id not in models:
                    models[obj_id] = load_arrays(plan["model_features"].item_dir(obj_item(obj_id)) / "features.zarr",
                                                 ["points", "normals"])
                m = models[obj_id]
                i = pos[int(c.cand_id)]
                res = refine_icp(m["points"], m["normals"], scene["points"][i, :int(scene["n_points"][i])], R, t,
                                 infos[obj_id].diameter, max_corr_dist_frac=p.max_corr_frac, iterations=p.iterations,
                                 point_to_plane=p.point_to_plane)
                R, t, fitness, rmse = res.R, res.t, float(res.fitness), float(res.inlier_rmse)
            dt = time.perf_counter() - t0
            image_time[int(c.im_id)] = image_time.get(int(c.im_id), 0.0) + dt
            rows.append({"cand_id": int(c.cand_id), "scene_id": scene_id, "im_id": int(c.im_id), "obj_id": obj_id,
                         "prior_score": float(c.prior_score), "n_inliers": int(c.n_inliers),
                         "inlier_ratio": float(c.inlier_ratio), "R": np.asarray(R, float).reshape(9).tolist(),
                         "t": np.asarray(t, float).reshape(3).tolist(), "fitness": fitness, "inlier_rmse": rmse,
                         "evidence": estimate_score(c.inlier_ratio, fitness), "time_s": dt})
            bar.advance()
    table = select_estimates(pd.DataFrame(rows, columns=CANDIDATE_COLUMNS), targets,
                             {o: i.diameter for o, i in infos.items()}, by=p.select_by, duplicate_frac=p.duplicate_frac)
    chosen = table[table.selected].sort_values(["im_id", "obj_id", "rank"])
    # The CSV score is the ranking value, so that BOP's matching order agrees with ours.
    poses = chosen.assign(score=chosen[RANK_COLUMNS[p.select_by]].astype(float), sar_variant=-1, sar_reason="")
    sar_rows = _symmetry_aware_refinement(plan, bop, item, poses, image_time, progress) if len(poses) else []
    images = pd.DataFrame([{"scene_id": scene_id, "im_id": k, "time_s": v} for k, v in sorted(image_time.items())],
                          columns=["scene_id", "im_id", "time_s"])
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        write_table(table, w.dir / "candidates.parquet", metadata={"key": sp.key})
        write_table(poses[POSE_COLUMNS].reset_index(drop=True), w.dir / "poses.parquet", metadata={"key": sp.key})
        write_table(pd.DataFrame(sar_rows, columns=SAR_COLUMNS), w.dir / "sar.parquet", metadata={"key": sp.key})
        write_table(images, w.dir / "images.parquet", metadata={"key": sp.key})
        w.summary.update({
            "scene_id": scene_id, "n_candidates": int(len(table)), "n_poses": int(len(poses)),
            "mean_fitness": float(poses.fitness.mean()) if len(poses) else None,
            "n_duplicates": int(table.note.str.startswith("duplicate").sum()),
            "n_sar": int((poses.sar_variant >= 0).sum()), "n_sar_changed": int((poses.sar_variant > 0).sum()),
            "targets_without_pose": len({(t.im_id, t.obj_id) for t in targets} - set(zip(poses.im_id, poses.obj_id))),
        })


def _symmetry_aware_refinement(plan: DatasetPlan, bop, item: str, poses: pd.DataFrame, image_time: dict[int, float],
                               progress: bool) -> list[dict]:
    """Run SAR on the kept estimates of symmetric objects, updating ``poses`` in place
    (R, t, sar_variant, sar_reason) and ``image_time``; returns the per-variant rows."""
    from pipeline.plan import build_encoders
    from pipeline.progress import progress_bar
    from pipeline.refinement.sar import symmetry_aware_refinement
    from pipeline.render import Renderer
    from pipeline.bop.detections import rle_decode
    from pipeline.geometry.symmetry import SymmetrySet, distinct_under
    from stages.symmetries import load_symmetries

    p = plan.run.stages.refine
    if not p.sar:
        poses["sar_reason"] = "sar off"
        return []
    _, vis_enc = build_encoders(plan.run)
    if vis_enc.dim == 0:
        poses["sar_reason"] = "no visual encoder"
        return []
    infos = bop.models_info()
    transforms: dict[int, np.ndarray] = {}
    for obj_id in sorted(set(poses.obj_id.astype(int))):
        sym = load_symmetries(plan, obj_id)
        variants = sym.transforms(p.sar_step_deg) if not sym.is_trivial else [np.eye(4)]
        if p.sar_skip_declared:
            variants = distinct_under(variants, SymmetrySet.from_model_info(infos[obj_id]),
                                      max_trans_mm=max(1.0, 0.01 * infos[obj_id].diameter))
        transforms[obj_id] = np.stack(variants)
    todo = [i for i in poses.index if len(transforms[int(poses.at[i, "obj_id"])]) > 1]
    poses.loc[[i for i in poses.index if i not in set(todo)], "sar_reason"] = (
        "no symmetry" + (" beyond the declared ones" if p.sar_skip_declared else ""))
    if not todo:
        return []
    scene_id = item_id(item, "scene", "refine")
    cams = bop.scene_camera(scene_id)
    boxes = read_table(plan["segment_prior"].item_dir("all") / "candidates.parquet")
    boxes = boxes[boxes.scene_id == scene_id].set_index("cand_id")
    S = vis_enc.input_size
    margin = plan.run.stages.scene_features.crop_margin
    rows: list[dict] = []
    images: dict[int, np.ndarray] = {}
    with Renderer(S, S, znear=1.0, zfar=100000.0) as renderer, \
            progress_bar(f"SAR {item}", total=len(todo), enabled=progress) as bar:
        added: set[int] = set()
        for i in todo:
            t0 = time.perf_counter()
            obj_id, im_id, cand_id = int(poses.at[i, "obj_id"]), int(poses.at[i, "im_id"]), int(poses.at[i, "cand_id"])
            if obj_id not in added:
                renderer.add_mesh(obj_id, bop.load_model(obj_id))
                added.add(obj_id)
            if im_id not in images:
                images = {im_id: bop.load_rgb(scene_id, im_id)}  # estimates come sorted by image
            b = boxes.loc[cand_id]
            mask = (rle_decode({"counts": list(b.rle_counts), "size": [int(b.height), int(b.width)]})
                    if p.sar_use_mask else None)
            res = symmetry_aware_refinement(
                renderer, obj_id, vis_enc, images[im_id], cams[im_id].K, (b.bbox_x, b.bbox_y, b.bbox_w, b.bbox_h),
                np.asarray(poses.at[i, "R"], float).reshape(3, 3), np.asarray(poses.at[i, "t"], float),
                transforms[obj_id], margin=margin, min_cover=p.sar_min_cover, min_gain=p.sar_min_gain,
                centre=p.sar_centre, scene_mask=mask, image_mode=plan.dataset.image_mode)
            k = int(res.index)
            poses.at[i, "R"] = np.asarray(res.Rs[k], float).reshape(9).tolist()
            poses.at[i, "t"] = np.asarray(res.ts[k], float).reshape(3).tolist()
            poses.at[i, "sar_variant"] = k
            for v, (Rv, tv, s) in enumerate(zip(res.Rs, res.ts, res.scores)):
                rows.append({"scene_id": scene_id, "im_id": im_id, "obj_id": obj_id, "cand_id": cand_id, "variant": v,
                             "R": np.asarray(Rv, float).reshape(9).tolist(), "t": np.asarray(tv, float).reshape(3).tolist(),
                             "similarity": float(s), "chosen": v == k})
            image_time[im_id] = image_time.get(im_id, 0.0) + time.perf_counter() - t0
            bar.advance()
    return rows


def _collect(plan: DatasetPlan) -> None:
    """Gather every scene's refined poses into the BOP results CSV."""
    from pipeline.bop.results import write_results_csv

    sp = plan["refine"]
    poses, times = [], []
    for scene_id in plan.scene_ids:
        item = scene_item(scene_id)
        poses.append(read_table(sp.item_dir(item) / "poses.parquet"))
        for stage in ("scene_features", "register", "refine"):
            times.append(read_table(plan[stage].item_dir(item) / "images.parquet")[["scene_id", "im_id", "time_s"]])
    poses = pd.concat(poses, ignore_index=True) if poses else pd.DataFrame(columns=POSE_COLUMNS)
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
                          "mean_time_per_image_s": float(per_image.mean()) if per_image.size else None,
                          "n_sar_changed": int((poses.sar_variant > 0).sum()) if len(poses) else 0})

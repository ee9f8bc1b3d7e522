"""Stage register: coarse pose of every candidate of one scene by RANSAC on fused features.

``candidates.parquet``: one row per candidate with status, the RANSAC pose (R as 9
row-major floats, t mm), n_inliers, inlier_ratio, fitness, n_correspondences, time_s.
``poses.parquet``: per target (scene, image, object) the ``inst_count`` candidates with
the most inliers (as in the paper, the candidate with the most inliers wins).
``images.parquet``: registration time per image (s).
``pca.zarr``: the per-object PCA bases used (obj_id (K,), mean (K, C), components
(K, V, C), explained_variance (K, V), informative (K,) bool: False when the visual
features carried no variance and the visual part was dropped); empty in geometry-only
runs.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from pipeline.plan import DatasetPlan, obj_item, item_id
from pipeline.store import item_seed, load_arrays, publish, read_table, save_arrays, write_table

CODE_VERSION = 3


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.progress import progress_bar
    from pipeline.registration.fusion import apply_pca, fit_pca, fuse
    from pipeline.registration.ransac import RansacParams, register
    from pipeline.registration.selection import select_per_target

    scene_id = item_id(item, "scene", "register")
    sp = plan["register"]
    p = plan.run.stages.register
    bop = plan.bop()
    infos = bop.models_info()
    targets = [t for t in bop.targets(plan.root / plan.dataset.targets_file) if t.scene_id == scene_id]
    sf_dir = plan["scene_features"].item_dir(item)
    scene = load_arrays(sf_dir / "features.zarr")
    cands = read_table(sf_dir / "candidates.parquet")
    pos = {int(c): i for i, c in enumerate(scene["cand_id"])}
    params = RansacParams(inlier_frac=p.inlier_frac, max_iterations=p.max_iterations,
                          confidence=p.confidence, mutual=p.mutual)

    models: dict[int, dict] = {}

    def model(obj_id: int) -> dict:
        if obj_id not in models:
            m = load_arrays(plan["model_features"].item_dir(obj_item(obj_id)) / "features.zarr")
            # geometry-only runs (visual encoder 'none') have no visual channels to reduce
            basis = fit_pca(m["visual"], n_components=p.pca_dim) if m["visual"].shape[1] else None
            m["basis"] = basis
            m["fused"] = fuse(m["geometric"], apply_pca(basis, m["visual"]) if basis is not None else None)
            models[obj_id] = m
        return models[obj_id]

    rows = []
    image_time: dict[int, float] = {}
    with progress_bar(f"register {item}", total=len(cands), enabled=progress) as bar:
        for c in cands.itertuples(index=False):
            row = {"cand_id": int(c.cand_id), "scene_id": scene_id, "im_id": int(c.im_id), "obj_id": int(c.obj_id),
                   "prior_score": float(c.score), "status": c.status, "reason": c.reason}
            if c.status == "ok":
                t0 = time.perf_counter()
                m = model(int(c.obj_id))
                i, k = pos[int(c.cand_id)], int(c.n_points)
                basis = m["basis"]
                fused = fuse(scene["geometric"][i, :k], apply_pca(basis, scene["visual"][i, :k]) if basis is not None else None)
                reg = register(m["points"], m["fused"], scene["points"][i, :k], fused, infos[int(c.obj_id)].diameter,
                               params=params, seed=item_seed(sp.key, f"{item}/{c.cand_id}", p.seed))
                dt = time.perf_counter() - t0
                image_time[int(c.im_id)] = image_time.get(int(c.im_id), 0.0) + dt
                row.update({"R": np.asarray(reg.R, float).reshape(9).tolist(), "t": np.asarray(reg.t, float).reshape(3).tolist(),
                            "n_inliers": int(reg.n_inliers), "inlier_ratio": float(reg.inlier_ratio),
                            "fitness": float(reg.fitness), "n_correspondences": int(reg.n_correspondences), "time_s": dt})
            rows.append(row)
            bar.advance()

    table = pd.DataFrame(rows, columns=["cand_id", "scene_id", "im_id", "obj_id", "prior_score", "status", "reason", "R", "t",
                                        "n_inliers", "inlier_ratio", "fitness", "n_correspondences", "time_s"])
    poses = select_per_target(table[table.status == "ok"], targets)
    images = pd.DataFrame([{"scene_id": scene_id, "im_id": k, "time_s": v} for k, v in sorted(image_time.items())],
                          columns=["scene_id", "im_id", "time_s"])
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        write_table(table, w.dir / "candidates.parquet", metadata={"key": sp.key})
        write_table(poses, w.dir / "poses.parquet", metadata={"key": sp.key})
        write_table(images, w.dir / "images.parquet", metadata={"key": sp.key})
        ids = sorted(o for o in models if models[o]["basis"] is not None)
        bases = [models[o]["basis"] for o in ids]
        save_arrays(w.dir / "pca.zarr", {
            "obj_id": np.asarray(ids, np.int64),
            "mean": np.stack([b.mean for b in bases]) if bases else np.zeros((0, 0), np.float32),
            "components": np.stack([b.components for b in bases]) if bases else np.zeros((0, 0, 0), np.float32),
            "explained_variance": np.stack([b.explained_variance for b in bases]) if bases else np.zeros((0, 0), np.float32),
            "informative": np.asarray([b.informative for b in bases], bool),
        }, attrs={"key": sp.key, "pca_dim": p.pca_dim})
        w.summary.update({"scene_id": scene_id, "n_candidates": int(len(table)),
                          "n_registered": int((table.status == "ok").sum()), "n_poses": int(len(poses)),
                          "targets_without_pose": int(len({(t.im_id, t.obj_id) for t in targets})
                                                      - len(set(zip(poses.im_id, poses.obj_id))))})

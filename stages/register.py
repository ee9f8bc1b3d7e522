"""Stage register: coarse pose hypotheses of every candidate of one scene, by RANSAC on
each modality's own matches, on the paper's fused matches and on the matches fused with
each modality's measured weight.

``coarse_hypotheses.parquet``: one row per hypothesis (a skipped candidate: one row with its
status and reason): cand_id, hyp (0, 1, ...), source (geometric, visual, fused,
weighted), source_rank, the candidate's fusion weights w_geometric, w_visual and the
held-out signals (z-scores) they came from, signal_geometric, signal_visual, the RANSAC
pose (R as 9 row-major floats, t mm), n_inliers, inlier_ratio, fitness,
n_correspondences, time_s (the candidate's, on its first row).
``image_times.parquet``: registration time per image (s).
``pca.zarr``: the per-object PCA bases used (obj_id (K,), mean (K, C), components
(K, V, C), explained_variance (K, V), informative (K,) bool: False when the visual
features carried no variance and the visual part was dropped); empty in geometry-only
runs. Algorithm: :meth:`pipeline.method.estimator.Estimator.register`
(:func:`pipeline.method.scene_side.register_candidates`).

The candidates go to the dask cluster the run names (``dask_scheduler``, else
``$DASK_SCHEDULER_ADDRESS``), else run in this process (:mod:`pipeline.common.parallel`).
"""

from __future__ import annotations

from pipeline.workflow.plan import DatasetPlan

THREADS_HELP = True
"""The candidates run on the job's threads (dask's threaded scheduler) when no dask scheduler is
named: faster here (``benchmarks/results/dask.md``). Snakemake's rule gives the job one
thread (``stage_graph``), so there they run one after the other; ``freeze stage``
without ``--threads`` and ``freeze estimate`` use every core."""


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.common.parallel import job_mapper
    from pipeline.common.progress import progress_bar
    from pipeline.method.estimator import Estimator
    from pipeline.method.scene_side import path_name, time_table
    from pipeline.workflow.plan import scene_device
    from pipeline.workflow.prepared import prepared_objects

    io = plan.io("register", item)
    scene_id, p = io.item_id(), io.params
    scene = io.arrays("scene_features", "features")
    cands = io.table("scene_features", "candidate_status")
    # no encoder: registration matches the features both sides already hold
    estimator = Estimator(prepared_objects(io, io.bop(), features=()), plan.run.stages,
                          scene_device=scene_device(plan.run))
    with progress_bar(f"register {item}", total=len(cands), enabled=progress) as bar, \
            job_mapper(plan.run.dask_scheduler, THREADS_HELP) as mapper:
        registered = estimator.register(cands, scene, lambda cand_id: io.candidate_seed(int(cand_id), p.seed),
                                        bar.advance, mapper)
    table = registered.table
    with io.publish() as w:
        # Where RANSAC's loop and the feature matching ran (recorded, not keyed).
        w.manifest["runtime"] = {"ransac": path_name(estimator.scene_device)}
        w.write("coarse_hypotheses", table)
        w.write("image_times", time_table(scene_id, registered.image_time))
        w.write("pca", registered.pca, attrs={"pca_dim": p.pca_dim})
        w.summary.update({"scene_id": scene_id, "n_candidates": int(len(table)),
                          "n_registered": int((table.status == "ok").sum())})

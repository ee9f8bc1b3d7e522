"""Stage refine: ICP and verification of every coarse hypothesis, each candidate's best,
the choice of the estimates per target, symmetry-aware refinement (SAR), and (item
``all``) the BOP results CSV ``<method>_<dataset>-<split>.csv`` of the whole dataset.

Per scene (algorithm: :meth:`pipeline.method.estimator.Estimator.refine`, then
:meth:`~pipeline.method.estimator.Estimator.refine_by_symmetry`; every column: ``docs/artifacts.md``):

- ``hypotheses.parquet``: every hypothesis after ICP (register's, and the turns of each
  candidate's best one, source ``turn`` with its ``parent``): its pose, ICP fitness and
  inlier_rmse (mm), the RANSAC n_inliers and inlier_ratio, ``evidence`` (inlier ratio x
  ICP fitness), the verification terms (silhouette, depth_fit, coverage, free_space)
  and score (``verification``), and ``chosen`` (its candidate's best).
- ``candidate_choices.parquet``: every registered candidate with its chosen hypothesis (hyp,
  source), its pose after the fine ICP (``fine_icp``: whether that pose was kept), the
  same columns, prior_score, and the choice: selected, rank (0 = best kept), note (why
  not kept).
- ``poses.parquet``: the kept estimates (up to ``inst_count`` distinct ones per target,
  ranked by ``refine.select_by``): scene_id, im_id, obj_id, cand_id, hyp, source, R, t,
  score (the ranking value, written to the CSV), evidence, verification, fitness,
  inlier_rmse, n_inliers,
  sar_variant (index of the chosen symmetric variant, 0 = the ICP pose, -1 = no SAR)
  and sar_reason (why SAR did not run, if it did not).
- ``sar.parquet``: per estimate that went through SAR, one row per symmetric variant
  with its pose, similarity and whether it was chosen.
- ``image_times.parquet``: this stage's time per image (s).

The CSV's ``time`` is, per image, the prior's time plus this pipeline's scene-side time
(scene_features + register + refine) for that image, in seconds (BOP: the time to
produce all estimates of the image, excluding model onboarding; algorithm:
:func:`pipeline.formats.bop.results.image_times`).
"""

from __future__ import annotations

import pandas as pd

from pipeline.workflow.plan import DatasetPlan

THREADS_HELP = False
"""Whether the candidates run on the job's threads when no dask scheduler is named: not by
default, since two threads were not faster here (0.83x median, 0.76-2.17x paired,
``benchmarks/results/dask.md``): Mesa's software rasteriser already spreads each
verification render over the cores, and the rest holds the GIL often enough. A dask
scheduler named by the run still gets the candidates (:func:`pipeline.common.parallel.job_mapper`)."""


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    if item == "all":
        return _collect(plan)
    from pipeline.common.parallel import job_mapper
    from pipeline.common.progress import progress_bar
    from pipeline.formats.bop.detections import prior_row_mask
    from pipeline.method.estimator import Estimator
    from pipeline.method.scene_side import SceneImages, packed_points, path_name, time_table
    from pipeline.workflow.plan import build_encoders, encoder_runtime, scene_device, warm_imports
    from pipeline.workflow.prepared import prepared_objects

    io = plan.io("refine", item)
    scene_id = io.item_id()
    bop = io.bop()
    im_ids = io.images()  # the scene's, or this chunk's (images_per_job)
    targets = [t for t in bop.targets(plan.root / plan.dataset.targets_file)
               if t.scene_id == scene_id and t.im_id in im_ids]
    registered = io.table("register", "coarse_hypotheses")
    registered = registered[registered.status == "ok"]
    scene = io.arrays("scene_features", "features", names=["points", "n_points", "cand_id"])
    boxes = io.table("segment_prior", "prior_candidates")
    boxes = boxes[boxes.scene_id == scene_id].set_index("cand_id")
    cams = bop.scene_camera(scene_id)

    def candidate(cand_id: int):
        b = boxes.loc[cand_id]
        return (b.bbox_x, b.bbox_y, b.bbox_w, b.bbox_h), prior_row_mask(b)

    images = SceneImages(rgb=lambda im_id: bop.load_rgb(scene_id, im_id),
                         depth=lambda im_id: bop.load_depth(scene_id, im_id), K=lambda im_id: cams[im_id].K,
                         mesh=bop.load_model, candidate=candidate)
    estimator = Estimator(prepared_objects(io, bop, features=("points", "normals"), symmetries=True),
                          plan.run.stages, lambda: build_encoders(plan.run), image_mode=plan.dataset.image_mode,
                          scene_device=scene_device(plan.run))
    warm_imports("pyrender", "pipeline.method.render.renderer", "pipeline.method.refinement.sar",
                 "pipeline.method.refinement.verification", "pipeline.method.refinement.icp")
    with progress_bar(f"refine {item}", total=registered.cand_id.nunique(), enabled=progress) as bar, \
            job_mapper(plan.run.dask_scheduler, THREADS_HELP) as mapper:
        refined = estimator.refine(registered, packed_points(scene), images, targets, bar.advance, mapper)
    with progress_bar(f"SAR {item}", total=len(refined.poses), enabled=progress) as bar:
        pca = io.arrays("register", "pca", names=["obj_id", "informative"])
        untextured = {int(o) for o, ok in zip(pca["obj_id"], pca["informative"]) if not ok}
        refined = estimator.refine_by_symmetry(refined, images, lambda n: bar.set_total(n) or bar.advance, untextured)
    table, poses = refined.candidates, refined.poses
    with io.publish() as w:
        # Where the ICP and the verification's comparisons ran, and SAR's encoder passes in what precision (recorded, not keyed).
        w.manifest["runtime"] = {"icp": path_name(estimator.scene_device),
                                 "verification": path_name(estimator.scene_device)}
        if refined.sar_encoder is not None:
            w.manifest["runtime"]["visual"] = encoder_runtime(refined.sar_encoder)
        w.write("candidate_choices", table)
        w.write("hypotheses", refined.hypotheses)
        w.write("poses", poses)
        w.write("sar", refined.sar)
        w.write("image_times", time_table(scene_id, refined.image_time))
        w.summary.update({
            "scene_id": scene_id, "n_candidates": int(len(table)), "n_hypotheses": int(len(refined.hypotheses)),
            "n_poses": int(len(poses)),
            "mean_fitness": float(poses.fitness.mean()) if len(poses) else None,
            "n_duplicates": int(table.note.str.startswith("duplicate").sum()),
            "n_sar": int((poses.sar_variant >= 0).sum()), "n_sar_changed": int((poses.sar_variant > 0).sum()),
            "targets_without_pose": len({(t.im_id, t.obj_id) for t in targets} - set(zip(poses.im_id, poses.obj_id))),
        })


def _collect(plan: DatasetPlan) -> None:
    """Gather every scene's refined poses into the BOP results CSV."""
    from pipeline.formats.bop.results import estimates_rows, image_times, write_results_csv
    from pipeline.method.scene_side import POSE_COLUMNS
    from pipeline.workflow.stage_graph import stages_writing

    io = plan.io("refine", "all")
    poses, times = [], []
    for item in plan.scene_items:
        poses.append(io.table("refine", "poses", item))
        times.extend(io.table(stage, "image_times", item) for stage in stages_writing("image_times", "scene"))
    poses = pd.concat(poses, ignore_index=True) if poses else pd.DataFrame(columns=POSE_COLUMNS)
    prior = io.table("segment_prior", "prior_candidates")
    per_image = image_times(times, prior.groupby(["scene_id", "im_id"]).prior_time.first())
    rows = estimates_rows(poses, per_image)
    notes = [] if rows else [_no_estimate_note(io, plan)]
    for note in notes:
        print(f"warning: {plan.name}: {note}", flush=True)
    with io.publish() as w:
        write_results_csv(w.path("results"), rows)
        w.summary.update({"results_csv": plan.results_csv_name, "n_estimates": len(rows),
                          "n_images": int(per_image.size),
                          "mean_time_per_image_s": float(per_image.mean()) if per_image.size else None,
                          "n_sar_changed": int((poses.sar_variant > 0).sum()) if len(poses) else 0,
                          "notes": notes})


def _no_estimate_note(io, plan: DatasetPlan) -> str:
    """Why a dataset got no estimate at all, from what each stage recorded: the
    candidates the prior had and those segment_prior dropped, scene_features skipped (by
    reason, numbers stripped) and register or refine kept none of."""
    import re
    from collections import Counter

    from pipeline.common.store import read_manifest

    prior = read_manifest(io.input_dir("segment_prior")).get("summary", {})
    reasons = Counter({f"segment_prior: {k}": int(v) for k, v in (prior.get("dropped") or {}).items()})
    for item in plan.scene_items:
        summary = read_manifest(io.input_dir("scene_features", item)).get("summary", {})
        for why in (summary.get("skipped") or {}).values():
            reasons[f"scene_features: {re.sub(r'^[0-9.]+ ', '', str(why))}"] += 1
    n_det = prior.get("n_detections", "?")
    counts = ", ".join(f"{k} ({v})" for k, v in reasons.most_common()) or "no stage recorded a reason"
    return (f"no estimate: every candidate was dropped ({n_det} detections, {prior.get('n_candidates', '?')} "
            f"candidates after segment_prior); reasons: {counts}")

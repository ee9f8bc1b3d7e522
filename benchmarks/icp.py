"""ICP from known starts on real and semi-real frames (run by hand): the pipeline's ICP
against variants of Open3D's ICP, side by side from the same starts.

    .venv/bin/python benchmarks/icp.py [--datasets tyol,semilmo] [--perturb 0:0,5:10,10:20] [--per-image 3]

Starts: each target instance's ground-truth pose rotated by A degrees about a random
axis and shifted by T mm (``--perturb A:T,...``; 0:0 is the ground truth itself). The
scene points are the instance's candidate points as ``scene_features`` lifts them from
its ground-truth visible mask (outliers removed), M = 1000 of them sampled as the
pipeline does. Variants:

- ``hypothesis-icp``: :func:`pipeline.method.refinement.icp.refine_icp` as the refine stage calls
  it on every hypothesis (5000 points sampled on the model with their face normals, the
  M scene points, point-to-plane, correspondence distance 0.1, 0.05, 0.025 d, 30
  iterations each);
- ``pipeline``: ``hypothesis-icp`` followed by the fine ICP that refine runs on each
  candidate's chosen pose (:class:`pipeline.method.scene_side.FineIcp`, for objects without
  shape symmetries): 2000 of the candidate points against 20000 model surface samples,
  same schedule;
- ``open3d-hypothesis-icp``, ``open3d-pipeline``: the same two with Open3D's
  ``registration_icp`` (point-to-plane, its default convergence test, 30 iterations per
  threshold), which the pipeline used before its own ICP (:mod:`pipeline.method.refinement.icp`);
- ``dense-scene``: the same with every candidate point instead of M;
- ``tukey``: the same with a Tukey robust kernel (k = the current correspondence distance / 2);
- ``dense-model``: the model's own vertices with their vertex normals (Open3D's ICP "on
  the dense model"), every candidate point, point-to-plane, same schedule;
- ``model-vertices``: the model's vertices and vertex normals, the M scene points;
- ``samples-20k``: the pipeline's ICP on 20000 surface samples instead of 5000;
- ``samples-20k-dense-scene``: the same with every candidate point;
- ``point-to-point``: the pipeline's ICP with point-to-point error;
- ``gicp``: Open3D's generalized ICP (plane-to-plane, covariances from the points'
  neighbourhoods), the pipeline's points and schedule.

Errors: rotation (deg), translation (mm) and MSSD in diameters (BOP's, with the
declared symmetries), medians and the share of starts ending below 0.1 d. Writes
``benchmarks/results/icp.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def dataset_root(name: str) -> Path:
    """The built semi-real dataset ``name`` (the synth stage is run here if needed)."""
    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.stage_graph import run_stage

    rp = RunPlan(cfg.load_run({"datasets": name}))
    ok, why = rp.available(name)
    if not ok:
        raise SystemExit(why)
    plan = rp[name]
    if not plan["synth"].manifest("dataset").exists():
        run_stage(plan, "synth", "dataset", progress=True)
    return plan.root


def icp_variants(model_mesh, diameter: float, seed: int):
    """name -> function(scene_all, scene_m, R0, t0) -> (R, t)."""
    import open3d as o3d

    from pipeline.method.refinement.icp import IcpModel, refine_icp
    from pipeline.method.geometry.sampling import sample_surface

    pts, nrm = sample_surface(model_mesh, 5000, seed=seed)
    pts20, nrm20 = sample_surface(model_mesh, 20000, seed=seed)
    # Built once per object, as refine does (its k-d tree serves every ICP on the object).
    model5k, model20k = IcpModel(pts, nrm), IcpModel(pts20, nrm20)
    verts = np.array(model_mesh.vertices, np.float64)
    vnrm = np.array(model_mesh.vertex_normals, np.float64)

    def hypothesis_icp(points_all, points_m, R0, t0):
        r = refine_icp(model5k, None, points_m, R0, t0, diameter)
        return r.R, r.t

    def ours(points_all, points_m, R0, t0):
        from pipeline.method.scene_side import sample_candidate

        r = refine_icp(model5k, None, points_m, R0, t0, diameter)
        fine = points_all[sample_candidate(len(points_all), 2000, 0)]
        r = refine_icp(model20k, None, fine, r.R, r.t, diameter)
        return r.R, r.t

    def open3d_hypothesis_icp(points_all, points_m, R0, t0):
        return _o3d(pts, nrm, points_m, R0, t0, kernel=False)

    def open3d_pipeline(points_all, points_m, R0, t0):
        from pipeline.method.scene_side import sample_candidate

        R, t = _o3d(pts, nrm, points_m, R0, t0, kernel=False)
        return _o3d(pts20, nrm20, points_all[sample_candidate(len(points_all), 2000, 0)], R, t, kernel=False)

    def dense_scene(points_all, points_m, R0, t0):
        r = refine_icp(pts, nrm, points_all, R0, t0, diameter)
        return r.R, r.t

    def _o3d(target_pts, target_nrm, source, R0, t0, kernel):
        from pipeline.method.geometry.transforms import invert, matrix_to_rt, rt_to_matrix

        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(target_pts, np.float64)))
        target.normals = o3d.utility.Vector3dVector(np.asarray(target_nrm, np.float64))
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(source, np.float64)))
        T = rt_to_matrix(*invert(R0, t0))
        o3d.utility.set_max_threads(1)
        for scale in (1.0, 0.5, 0.25):
            d = 0.1 * diameter * scale
            reg = o3d.pipelines.registration
            est = (reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=d / 2)) if kernel
                   else reg.TransformationEstimationPointToPlane())
            T = np.asarray(o3d.pipelines.registration.registration_icp(
                src, target, d, T, est, o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30)).transformation)
        return invert(*matrix_to_rt(T))

    def tukey(points_all, points_m, R0, t0):
        return _o3d(pts, nrm, points_m, R0, t0, kernel=True)

    def dense_model(points_all, points_m, R0, t0):
        return _o3d(verts, vnrm, points_all, R0, t0, kernel=False)

    def model_vertices(points_all, points_m, R0, t0):
        return _o3d(verts, vnrm, points_m, R0, t0, kernel=False)

    def dense_samples(points_all, points_m, R0, t0):
        r = refine_icp(pts20, nrm20, points_m, R0, t0, diameter)
        return r.R, r.t

    def dense_both(points_all, points_m, R0, t0):
        r = refine_icp(pts20, nrm20, points_all, R0, t0, diameter)
        return r.R, r.t

    def fine(n_scene):
        def run(points_all, points_m, R0, t0):
            from pipeline.method.scene_side import sample_candidate

            dense = points_all[sample_candidate(len(points_all), n_scene, 0)]
            r = refine_icp(pts20, nrm20, dense, R0, t0, diameter)
            return r.R, r.t
        return run

    def point_to_point(points_all, points_m, R0, t0):
        r = refine_icp(pts, nrm, points_m, R0, t0, diameter, point_to_plane=False)
        return r.R, r.t

    def gicp(points_all, points_m, R0, t0):
        from pipeline.method.geometry.transforms import invert, matrix_to_rt, rt_to_matrix

        reg = o3d.pipelines.registration
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts, np.float64)))
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_m, np.float64)))
        T = rt_to_matrix(*invert(R0, t0))
        o3d.utility.set_max_threads(1)
        for scale in (1.0, 0.5, 0.25):
            T = np.asarray(reg.registration_generalized_icp(
                src, target, 0.1 * diameter * scale, T, reg.TransformationEstimationForGeneralizedICP(),
                reg.ICPConvergenceCriteria(max_iteration=30)).transformation)
        return invert(*matrix_to_rt(T))

    return {"pipeline": ours, "hypothesis-icp": hypothesis_icp, "open3d-pipeline": open3d_pipeline,
            "open3d-hypothesis-icp": open3d_hypothesis_icp, "dense-scene": dense_scene, "tukey": tukey, "dense-model": dense_model,
            "point-to-point": point_to_point, "gicp": gicp, "model-vertices": model_vertices,
            "samples-20k": dense_samples, "samples-20k-dense-scene": dense_both, "fine-2000": fine(2000),
            "fine-5000": fine(5000)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default="tyol,semilmo")
    ap.add_argument("--perturb", default="0:0,5:10,10:20")
    ap.add_argument("--per-image", type=int, default=3, help="instances per image (semilmo: 40 images)")
    ap.add_argument("--variants", default="", help="comma-separated variants to run (default: all)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "icp.md")
    args = ap.parse_args()

    from pipeline.formats.bop import BopDataset
    from pipeline.method.geometry.transforms import perturb_pose, rotation_angle_deg
    from pipeline.evaluation.metrics.bop_symmetries import model_symmetries
    from pipeline.evaluation.metrics.pose_errors import mssd
    from pipeline.method.scene_side import candidate_points, sample_candidate

    starts = [tuple(float(v) for v in p.split(":")) for p in args.perturb.split(",")]
    lines = ["# ICP from known starts", "", f"`benchmarks/icp.py {' '.join(sys.argv[1:])}`", ""]
    for name in args.datasets.split(","):
        ds = BopDataset(dataset_root(name))
        infos = ds.models_info()
        variants, syms, verts = {}, {}, {}
        results: dict[tuple[str, float], list[tuple[float, float, float]]] = {}
        seconds: dict[str, float] = {}
        n_cases = 0
        for scene_id in ds.scene_ids():
            cams, gts = ds.scene_camera(scene_id), ds.scene_gt(scene_id)
            for im_id in ds.image_ids(scene_id):
                depth = ds.load_depth(scene_id, im_id)
                order = np.argsort([-i.visib_fract for i in ds.scene_gt_info(scene_id)[im_id]]) \
                    if (ds.scene_dir(scene_id) / "scene_gt_info.json").is_file() else range(len(gts[im_id]))
                for gt_id in list(order)[:args.per_image]:
                    g = gts[im_id][gt_id]
                    d = infos[g.obj_id].diameter
                    if g.obj_id not in variants:
                        mesh = ds.load_model(g.obj_id)
                        variants[g.obj_id] = icp_variants(mesh, d, seed=g.obj_id)
                        syms[g.obj_id] = model_symmetries(infos[g.obj_id])
                        verts[g.obj_id] = np.asarray(ds.load_model(g.obj_id, eval=True).vertices)
                    pts, _ = candidate_points(depth, cams[im_id].K, ds.load_mask(scene_id, im_id, gt_id), d)
                    if len(pts) < 50:
                        continue
                    pts_m = pts[sample_candidate(len(pts), 1000, seed=n_cases)]
                    n_cases += 1
                    for angle, shift in starts:
                        R0, t0 = perturb_pose(g.R, g.t, angle, shift, rng=n_cases) if angle or shift else (g.R, g.t)
                        for vname, fn in variants[g.obj_id].items():
                            if args.variants and vname not in args.variants.split(","):
                                continue
                            t_start = time.perf_counter()
                            R, t = fn(pts, pts_m, R0, t0)
                            seconds[vname] = seconds.get(vname, 0.0) + time.perf_counter() - t_start
                            err = mssd(R, t, g.R, g.t, verts[g.obj_id], *syms[g.obj_id]) / d
                            results.setdefault((vname, angle), []).append(
                                (rotation_angle_deg(R, g.R), float(np.linalg.norm(t - g.t)), err))
        lines += [f"## {name}: {n_cases} instances x {len(starts)} starts", "",
                  "| variant | start (deg, mm) | median rot (deg) | median trans (mm) | median MSSD / d | MSSD < 0.1 d | ms / run |",
                  "|---|---|---|---|---|---|---|"]
        for (vname, angle), rows in results.items():
            shift = dict(starts)[angle]
            a = np.array(rows)
            lines.append(f"| {vname} | {angle:g}, {shift:g} | {np.median(a[:, 0]):.2f} | {np.median(a[:, 1]):.1f} | "
                         f"{np.median(a[:, 2]):.3f} | {np.mean(a[:, 2] < 0.1):.2f} | "
                         f"{1000 * seconds[vname] / (n_cases * len(starts)):.0f} |")
        lines.append("")
        print("\n".join(lines[-len(results) - 4:]), flush=True)
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()

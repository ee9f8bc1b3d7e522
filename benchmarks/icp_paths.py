"""refine's hypothesis ICP on its two paths, replayed on a run's cached hypotheses (run by hand,
and by scripts/gpu_check.sh on a CUDA machine).

    .venv/bin/python benchmarks/icp_paths.py --dataset synthtiny [--device cuda] [--cache DIR]
        [--geometric gedi --visual dinov2-vitg14 --weights DIR] [--limit N]

Reads register's coarse hypotheses (status ``ok``), scene_features' points and
model_features' points and normals of every scene of the dataset's current plan in the
cache (the run must have reached register), and aligns each candidate's hypotheses

- by the numpy ICP, one hypothesis at a time (``refine_icp``, the CPU path), and
- together by the torch ICP on ``--device`` (``refine_icp_batch``, the path of a CUDA run),

with refine's parameters. Prints, and writes with ``--out``, the time of each path, their
ratio, and how far the poses are apart (largest rotation and translation difference,
iteration counts that differ). The first batch is run once before the clock (CUDA's
start-up).

A hypothesis far from any fit wanders, and there the two paths part: their first
steps agree to 1e-13 degrees, and the difference grows about 30-fold an iteration
(float rounding in another order, amplified by the weakly constrained directions), as
it would between two BLAS builds. ``--stages`` therefore also runs refine and score again
on the path the cached run did not take (torch after a CPU run, numpy after a CUDA
one), on a copy of the cache, and compares what matters: the choices and the AR.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def replay(dataset: str, config: dict[str, str], device: str, limit: int) -> dict:
    """Both paths on every candidate of ``dataset`` (at most ``limit``, 0: all)."""
    import torch

    from pipeline.common.config import load_run
    from pipeline.method.geometry.transforms import rotation_angle_deg
    from pipeline.method.refinement.icp import IcpModel, refine_icp
    from pipeline.method.refinement.icp_torch import refine_icp_batch
    from pipeline.method.scene_side import packed_points
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.prepared import prepared_objects

    plan = RunPlan(load_run({"datasets": dataset, **config}))[dataset]
    p = plan.run.stages.refine
    if not plan["register"].manifest(plan.scene_items[0]).exists():
        raise SystemExit(f"{dataset}: register has not run in the cache; run the pipeline first")
    work = []
    for item in plan.scene_items:
        io = plan.io("refine", item)
        bop = io.bop()
        reg = io.table("register", "coarse_hypotheses")
        reg = reg[reg.status == "ok"]
        points = packed_points(io.arrays("scene_features", "features", names=["points", "n_points", "cand_id"]))
        objects = prepared_objects(io, bop, features=("points", "normals"))
        models = {}
        for cand_id, g in reg.groupby("cand_id", sort=True):
            o = int(g.obj_id.iloc[0])
            if o not in models:
                f = objects[o].features
                models[o] = (IcpModel(f["points"], f["normals"]), objects[o].diameter)
            R0 = np.stack([np.reshape(r, (3, 3)) for r in g.R]).astype(np.float64)
            t0 = np.stack([np.reshape(t, 3) for t in g.t]).astype(np.float64)
            work.append((*models[o], points(int(cand_id)), R0, t0))
    work = work[:limit] if limit else work
    kw = {"max_corr_dist_frac": p.max_corr_frac, "iterations": p.iterations, "point_to_plane": p.point_to_plane}
    m, d, s, R0, t0 = work[0]
    refine_icp_batch(m, s, R0, t0, d, device=device, **kw)  # CUDA's start-up, not timed
    t = time.perf_counter()
    ref = [[refine_icp(m, None, s, R0[i], t0[i], d, **kw) for i in range(len(R0))] for m, d, s, R0, t0 in work]
    numpy_s = time.perf_counter() - t
    t = time.perf_counter()
    got = [refine_icp_batch(m, s, R0, t0, d, device=device, **kw) for m, d, s, R0, t0 in work]
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    torch_s = time.perf_counter() - t
    pairs = [(a, b) for ra, rb in zip(ref, got) for a, b in zip(ra, rb)]
    return {"dataset": dataset, "device": device, "candidates": len(work), "hypotheses": len(pairs),
            "scene_points": int(np.median([len(w[2]) for w in work])),
            "model_points": int(np.median([len(w[0].points) for w in work])),
            "numpy_s": numpy_s, "torch_s": torch_s,
            "max_deg": max(rotation_angle_deg(a.R, b.R) for a, b in pairs),
            "max_mm": max(float(np.abs(a.t - b.t).max()) for a, b in pairs),
            "iteration_mismatches": sum(a.iterations != b.iterations for a, b in pairs),
            "gpu": torch.cuda.get_device_name(device) if device.startswith("cuda") else None}


def stages_on_the_other_path(dataset: str, config: dict[str, str], device: str) -> dict:
    """refine (every scene, then the collection) and score of ``dataset`` again on the
    ICP path the cached run did not take (torch on ``device`` after a numpy run, numpy
    after a torch one: its refine manifest's ``runtime.icp``), on a copy of the cache:
    AR of both, the candidates whose chosen hypothesis differs, the kept poses' largest
    rotation difference."""
    import json
    import shutil
    import tempfile

    import pipeline.workflow.plan as plan_module
    from pipeline.common.config import load_run
    from pipeline.method.geometry.transforms import rotation_angle_deg
    from pipeline.workflow.plan import RunPlan
    from stages import run_stage

    run_plan = RunPlan(load_run({"datasets": dataset, **config}))
    source = run_plan[dataset]
    if not source["score"].manifest("all").exists():
        raise SystemExit(f"{dataset}: score has not run in {run_plan.cache}; run the pipeline first")
    cached = json.loads(source["refine"].manifest(source.scene_items[0]).read_text()).get("runtime", {})
    cached_path = cached.get("icp", "numpy")  # refine manifests before issue 31 ran numpy
    other = device if cached_path == "numpy" else None
    copy = Path(tempfile.mkdtemp(prefix="icp_paths-"))
    try:
        shutil.copytree(run_plan.cache / dataset, copy / dataset, symlinks=True)
        for stage in ("refine", "score"):
            shutil.rmtree(copy / dataset / stage)
        os.environ["FREEZE_CACHE"] = str(copy)
        plan_module.icp_device = lambda run: other  # read by the refine stage when it runs
        plan = RunPlan(load_run({"datasets": dataset, **config}))[dataset]
        t = time.perf_counter()
        for item in plan.scene_items:
            run_stage(plan, "refine", item, progress=False)
        refine_s = time.perf_counter() - t
        run_stage(plan, "refine", "all", progress=False)
        run_stage(plan, "score", "all", progress=False)
        ar = [json.loads((p["score"].item_dir("all") / "scores.json").read_text())["summary"]["AR"]
              for p in (source, plan)]
        rerun_path = json.loads(plan["refine"].manifest(plan.scene_items[0]).read_text())["runtime"]["icp"]
        changed, candidates, worst = 0, 0, 0.0
        for item in plan.scene_items:
            a = source["refine"].table(item, "candidate_choices").set_index("cand_id")
            b = plan["refine"].table(item, "candidate_choices").set_index("cand_id")
            changed += int((a.hyp != b.hyp.reindex(a.index)).sum())
            candidates += len(a)
            pa, pb = source["refine"].table(item, "poses"), plan["refine"].table(item, "poses")
            for ra, rb in zip(pa.itertuples(), pb.itertuples()):
                worst = max(worst, rotation_angle_deg(np.reshape(ra.R, (3, 3)), np.reshape(rb.R, (3, 3))))
        return {"cached_path": cached_path, "ar_cached": ar[0], "rerun_path": rerun_path, "ar_rerun": ar[1],
                "choices_changed": changed, "candidates": candidates, "pose_max_deg": worst, "refine_s": refine_s}
    finally:
        shutil.rmtree(copy, ignore_errors=True)


def report(r: dict) -> str:
    """The measurements as Markdown."""
    where = f"{r['device']} ({r['gpu']})" if r["gpu"] else r["device"]
    return "\n".join([
        f"### refine's hypothesis ICP, both paths: `{r['dataset']}` on {where}",
        "",
        f"{r['candidates']} candidates, {r['hypotheses']} hypotheses (median {r['scene_points']} scene points, "
        f"{r['model_points']} model points).",
        "",
        "| path | s | s per hypothesis | numpy / torch |",
        "|---|---|---|---|",
        f"| numpy, one hypothesis at a time (CPU) | {r['numpy_s']:.3f} | {r['numpy_s'] / r['hypotheses'] * 1e3:.1f} ms | |",
        f"| torch, a candidate's hypotheses together ({r['device']}) | {r['torch_s']:.3f} | "
        f"{r['torch_s'] / r['hypotheses'] * 1e3:.1f} ms | {r['numpy_s'] / r['torch_s']:.2f}x |",
        "",
        f"Poses apart by at most {r['max_deg']:.2e} deg and {r['max_mm']:.2e} mm; "
        f"{r['iteration_mismatches']} of {r['hypotheses']} iteration counts differ.",
        ""] + ([
        f"refine and score again on the other path: {r['stages']['rerun_path']} (refine "
        f"{r['stages']['refine_s']:.1f} s) gives AR {r['stages']['ar_rerun']:.4f}, the cached run's "
        f"{r['stages']['cached_path']} {r['stages']['ar_cached']:.4f}; {r['stages']['choices_changed']} of "
        f"{r['stages']['candidates']} candidates chose another hypothesis; the kept poses apart by at most "
        f"{r['stages']['pose_max_deg']:.2e} deg.", ""]
        if r.get("stages") else []))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthtiny")
    ap.add_argument("--device", default="cpu", help="the torch path's device (cpu or cuda)")
    ap.add_argument("--cache", type=Path, help="cache folder (default: $FREEZE_CACHE or <project>/cache)")
    ap.add_argument("--geometric", help="the run's geometric encoder (default: the run manifest's)")
    ap.add_argument("--visual", help="the run's visual encoder (default: the run manifest's)")
    ap.add_argument("--weights", type=Path, help="the run's weights folder")
    ap.add_argument("--limit", type=int, default=0, help="at most this many candidates (0: all)")
    ap.add_argument("--stages", action="store_true",
                    help="also run refine and score again on the path the cached run did not take (on a copy "
                         "of the cache) and compare")
    ap.add_argument("--out", type=Path, help="also write the report here")
    args = ap.parse_args()
    if args.cache:
        os.environ["FREEZE_CACHE"] = str(args.cache)
    config = {k: v for k, v in (("geometric", args.geometric), ("visual", args.visual),
                                ("weights_dir", str(args.weights) if args.weights else None)) if v}
    result = replay(args.dataset, config, args.device, args.limit)
    if args.stages:
        result["stages"] = stages_on_the_other_path(args.dataset, config, args.device)
    text = report(result)
    if args.out:
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""The scene side's two paths, replayed on a run's cache (run by hand, and by
scripts/gpu_check.sh on a CUDA machine): numpy on the CPU, and torch on ``--device``
(the paths of a CUDA run, ``docs/gpu.md``).

    .venv/bin/python benchmarks/scene_paths.py --dataset synthtiny [--device cuda] [--cache DIR]
        [--geometric gedi --visual dinov2-vitg14 --weights DIR] [--limit N] [--replays register,icp]
        [--stages [--stages-only]] [--out FILE]

The run must have reached refine in the cache (register's coarse hypotheses, scene_features'
points and features, model_features' points and normals). Two replays, each path timed
on the same inputs, the torch one after one untimed warm-up call (CUDA's start-up):

- **register** (RANSAC's loop and the feature matching): every scene's candidates
  registered by ``register_candidates`` with ``device=None`` and with ``--device``; the
  tables compared row by row (hypotheses, sources, weights, counts, and how far the
  poses are apart);
- **refine's hypothesis ICP**: each candidate's cached hypotheses aligned by the numpy ICP,
  one at a time (``refine_icp``), and together by the torch ICP (``refine_icp_batch``):
  how far the poses are apart, iteration counts that differ.

A hypothesis far from any fit wanders, and there the two ICPs part: their first steps
agree to 1e-13 degrees, and the difference grows about 30-fold an iteration (float
rounding in another order, amplified by the weakly constrained directions), as it would
between two BLAS builds. ``--stages`` therefore also runs register, refine and score
again on the paths the cached run did not take (torch after a CPU run, numpy after a
CUDA one), on a copy of the cache, and compares what matters: the coarse hypotheses, the
choices and the AR; and BOP's time per image of both runs, split by stage (each
scene-side stage's own ``image_times``). ``--replays register`` runs only the first
replay (the torch ICP on a CPU takes minutes a candidate's turns on a large set);
``--stages-only`` skips both (a large dataset in a short budget, as in
scripts/gpu_check.sh's semilmo step).
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


def replay_register(dataset: str, config: dict[str, str], device: str) -> dict:
    """register's candidates of every scene of ``dataset`` on both paths."""
    import pandas as pd
    import torch

    from pipeline.common.config import load_run
    from pipeline.method.estimator import Estimator
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.prepared import prepared_objects

    plan = RunPlan(load_run({"datasets": dataset, **config}))[dataset]
    jobs = []
    for item in plan.scene_items:
        io = plan.io("register", item)
        cands = io.table("scene_features", "candidate_status")
        estimator = Estimator(prepared_objects(io, io.bop(), features=()), plan.run.stages)
        for o in sorted(set(cands[cands.status == "ok"].obj_id)):
            estimator._matchable_model(int(o))  # the PCA bases, built before either clock
        seed = io.params.seed
        jobs.append((estimator, cands, io.arrays("scene_features", "features"),
                     lambda c, io=io, seed=seed: io.candidate_seed(int(c), seed)))

    def run_all(on: str | None) -> tuple[list, float]:
        t = time.perf_counter()
        out = []
        for estimator, cands, arrays, seed_of in jobs:
            estimator.scene_device = on
            out.append(estimator.register(cands, arrays, seed_of).table)
        if on is not None and on.startswith("cuda"):
            torch.cuda.synchronize()
        return out, time.perf_counter() - t

    estimator, cands, arrays, seed_of = jobs[0]
    estimator.scene_device = device
    estimator.register(cands.head(1), arrays, seed_of)  # CUDA's start-up, not timed
    ref, numpy_s = run_all(None)
    got, torch_s = run_all(device)
    a, b = pd.concat(ref, ignore_index=True), pd.concat(got, ignore_index=True)
    ok = (a.status == "ok").to_numpy()
    same_shape = len(a) == len(b) and (a[["cand_id", "hyp"]].to_numpy() == b[["cand_id", "hyp"]].to_numpy()).all()
    cols = [c for c in a.columns if c not in ("R", "t", "time_s")]
    differ = int((~np.all([(a[c] == b[c]) | (a[c].isna() & b[c].isna()) for c in cols], axis=0)).sum()) \
        if same_shape else None
    deg = mm = 0.0
    if same_shape and ok.any():
        from pipeline.method.geometry.transforms import rotation_angle_deg

        for ra, rb, ta, tb in zip(a.R[ok], b.R[ok], a.t[ok], b.t[ok]):
            deg = max(deg, rotation_angle_deg(np.reshape(ra, (3, 3)), np.reshape(rb, (3, 3))))
            mm = max(mm, float(np.abs(np.subtract(ta, tb)).max()))
    return {"candidates": int((cands_ok := a[ok]).cand_id.nunique()), "hypotheses": int(len(cands_ok)),
            "numpy_s": numpy_s, "torch_s": torch_s, "same_rows": same_shape, "rows_differ": differ,
            "max_deg": deg, "max_mm": mm}


def replay(dataset: str, config: dict[str, str], device: str, limit: int) -> dict:
    """refine's hypothesis ICP on both paths, on every candidate of ``dataset`` (at most
    ``limit``, 0: all)."""
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
    return {"candidates": len(work), "hypotheses": len(pairs),
            "scene_points": int(np.median([len(w[2]) for w in work])),
            "model_points": int(np.median([len(w[0].points) for w in work])),
            "numpy_s": numpy_s, "torch_s": torch_s,
            "max_deg": max(rotation_angle_deg(a.R, b.R) for a, b in pairs),
            "max_mm": max(float(np.abs(a.t - b.t).max()) for a, b in pairs),
            "iteration_mismatches": sum(a.iterations != b.iterations for a, b in pairs)}


def per_image_split(plan) -> dict[str, float]:
    """BOP's time per image of a dataset plan's run (mean s over its images: refine's
    collection's ``mean_time_per_image_s``) and the mean per image of each scene-side
    stage's own ``image_times`` (the prior's time is the remainder)."""
    import json

    from pipeline.workflow.stage_graph import stages_writing

    out = {}
    for stage in stages_writing("image_times", "scene"):
        t = [plan[stage].table(item, "image_times") for item in plan.scene_items]
        out[stage] = float(np.mean([x for tab in t for x in tab.groupby("im_id").time_s.sum()]))
    out["total"] = json.loads(plan["refine"].manifest("all").read_text())["summary"]["mean_time_per_image_s"]
    return out


def stages_on_the_other_path(dataset: str, config: dict[str, str], device: str) -> dict:
    """register (every scene), refine (every scene, then the collection) and score of
    ``dataset`` again on the paths the cached run did not take (torch on ``device``
    after a numpy run, numpy after a torch one: its refine manifest's ``runtime.icp``),
    on a copy of the cache: the coarse hypotheses that differ, AR of both, the candidates
    whose chosen hypothesis differs, the kept poses' largest rotation difference."""
    import json
    import shutil
    import tempfile

    import pipeline.workflow.plan as plan_module
    from pipeline.common.config import load_run
    from pipeline.method.geometry.transforms import rotation_angle_deg
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.stage_graph import run_stage

    run_plan = RunPlan(load_run({"datasets": dataset, **config}))
    source = run_plan[dataset]
    if not source["score"].manifest("all").exists():
        raise SystemExit(f"{dataset}: score has not run in {run_plan.cache}; run the pipeline first")
    cached = json.loads(source["refine"].manifest(source.scene_items[0]).read_text()).get("runtime", {})
    cached_path = cached.get("icp", "numpy")  # refine manifests before issue 31 ran numpy
    other = device if cached_path == "numpy" else None
    copy = Path(tempfile.mkdtemp(prefix="scene_paths-"))
    try:
        shutil.copytree(run_plan.cache / dataset, copy / dataset, symlinks=True)
        for stage in ("register", "refine", "score"):
            shutil.rmtree(copy / dataset / stage)
        os.environ["FREEZE_CACHE"] = str(copy)
        plan_module.scene_device = lambda run: other  # read by the register and refine stages when they run
        plan = RunPlan(load_run({"datasets": dataset, **config}))[dataset]
        seconds = {}
        for stage in ("register", "refine"):
            t = time.perf_counter()
            for item in plan.scene_items:
                run_stage(plan, stage, item, progress=False)
            seconds[stage] = time.perf_counter() - t
        run_stage(plan, "refine", "all", progress=False)
        run_stage(plan, "score", "all", progress=False)
        ar = [json.loads((p["score"].item_dir("all") / "scores.json").read_text())["summary"]["AR"]
              for p in (source, plan)]
        first = plan.scene_items[0]
        rerun_path = {stage: json.loads(plan[stage].manifest(first).read_text())["runtime"][key]
                      for stage, key in (("register", "ransac"), ("refine", "icp"))}
        changed = candidates = hyps = hyps_changed = 0
        worst = 0.0
        for item in plan.scene_items:
            ra, rb = source["register"].table(item, "coarse_hypotheses"), plan["register"].table(item, "coarse_hypotheses")
            hyps += len(ra)
            cols = ["cand_id", "hyp", "source", "n_inliers", "ransac_fitness"]
            hyps_changed += len(ra) if len(ra) != len(rb) else int(
                (ra[cols].astype(str).to_numpy() != rb[cols].astype(str).to_numpy()).any(axis=1).sum())
            a = source["refine"].table(item, "candidate_choices").set_index("cand_id")
            b = plan["refine"].table(item, "candidate_choices").set_index("cand_id")
            changed += int((a.hyp != b.hyp.reindex(a.index)).sum())
            candidates += len(a)
            pa, pb = source["refine"].table(item, "poses"), plan["refine"].table(item, "poses")
            for ra_, rb_ in zip(pa.itertuples(), pb.itertuples()):
                worst = max(worst, rotation_angle_deg(np.reshape(ra_.R, (3, 3)), np.reshape(rb_.R, (3, 3))))
        return {"cached_path": cached_path, "ar_cached": ar[0], "rerun_path": rerun_path, "ar_rerun": ar[1],
                "per_image": [per_image_split(p) for p in (source, plan)],
                "hypotheses": hyps, "hypotheses_changed": hyps_changed,
                "choices_changed": changed, "candidates": candidates, "pose_max_deg": worst,
                "register_s": seconds["register"], "refine_s": seconds["refine"]}
    finally:
        shutil.rmtree(copy, ignore_errors=True)


def report(r: dict) -> str:
    """The measurements as Markdown."""
    where = f"{r['device']} ({r['gpu']})" if r["gpu"] else r["device"]
    lines = [f"### The scene side's two paths: `{r['dataset']}` on {where}", ""]
    rows = []
    if "register" in r:
        g = r["register"]
        rows_note = ("the same rows (candidates, hypotheses); " + (
            f"{g['rows_differ']} of {g['hypotheses']} rows differ in a column other than the pose; "
            f"poses apart by at most {g['max_deg']:.2e} deg and {g['max_mm']:.2e} mm.")) if g["same_rows"] else \
            "the tables have different rows (another number of hypotheses for some candidate)."
        lines += [f"register: {g['candidates']} candidates, {g['hypotheses']} coarse hypotheses; on both paths "
                  f"{rows_note}", ""]
        rows.append(f"| register (RANSAC's loop, feature matching; per candidate) | {g['numpy_s']:.3f} | "
                    f"{g['torch_s']:.3f} | {g['numpy_s'] / g['torch_s']:.2f}x |")
    if "icp" in r:
        c = r["icp"]
        lines += [f"refine's hypothesis ICP: {c['candidates']} candidates, {c['hypotheses']} hypotheses (median "
                  f"{c['scene_points']} scene points, {c['model_points']} model points); poses apart by at most "
                  f"{c['max_deg']:.2e} deg and {c['max_mm']:.2e} mm; {c['iteration_mismatches']} of "
                  f"{c['hypotheses']} iteration counts differ.", ""]
        rows.append(f"| refine's hypothesis ICP (numpy one at a time, torch a candidate's together) | "
                    f"{c['numpy_s']:.3f} | {c['torch_s']:.3f} | {c['numpy_s'] / c['torch_s']:.2f}x |")
    if rows:
        lines += ["| part | numpy (CPU) s | torch s | numpy / torch |", "|---|---|---|---|", *rows, ""]
    if r.get("stages"):
        st = r["stages"]
        lines += [
            f"register, refine and score again on the other paths (register {st['rerun_path']['register']}, "
            f"{st['register_s']:.1f} s; refine {st['rerun_path']['refine']}, {st['refine_s']:.1f} s): "
            f"{st['hypotheses_changed']} of {st['hypotheses']} coarse hypotheses differ (count, fitness or "
            f"source); AR {st['ar_rerun']:.4f} against the cached run's ({st['cached_path']}) {st['ar_cached']:.4f}; "
            f"{st['choices_changed']} of {st['candidates']} candidates chose another hypothesis; the kept poses "
            f"apart by at most {st['pose_max_deg']:.2e} deg.", "",
            "Time per image (BOP's: the scene-side stages' own per-image times and the prior's), s:", "",
            "| run | " + " | ".join(k for k in st["per_image"][0] if k != "total") + " | per image |",
            "|---" * (len(st["per_image"][0]) + 1) + "|"]
        for name, split in zip((f"cached ({st['cached_path']})", f"rerun ({st['rerun_path']['refine']})"),
                               st["per_image"]):
            lines.append(f"| {name} | " + " | ".join(f"{v:.3f}" for k, v in split.items() if k != "total")
                         + f" | **{split['total']:.3f}** |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthtiny")
    ap.add_argument("--device", default="cpu", help="the torch path's device (cpu or cuda)")
    ap.add_argument("--cache", type=Path, help="cache folder (default: $FREEZE_CACHE or <project>/cache)")
    ap.add_argument("--geometric", help="the run's geometric encoder (default: the run manifest's)")
    ap.add_argument("--visual", help="the run's visual encoder (default: the run manifest's)")
    ap.add_argument("--weights", type=Path, help="the run's weights folder")
    ap.add_argument("--limit", type=int, default=0, help="the ICP replay: at most this many candidates (0: all)")
    ap.add_argument("--replays", default="register,icp",
                    help="which replays to run, comma-separated (register, icp; default both)")
    ap.add_argument("--stages", action="store_true",
                    help="also run register, refine and score again on the paths the cached run did not take "
                         "(on a copy of the cache) and compare")
    ap.add_argument("--stages-only", action="store_true",
                    help="with --stages: skip the two replays (a large dataset in a short budget)")
    ap.add_argument("--out", type=Path, help="also write the report here")
    args = ap.parse_args()
    if args.cache:
        os.environ["FREEZE_CACHE"] = str(args.cache)
    config = {k: v for k, v in (("geometric", args.geometric), ("visual", args.visual),
                                ("weights_dir", str(args.weights) if args.weights else None)) if v}
    replays = [x for x in args.replays.split(",") if x]
    if set(replays) - {"register", "icp"}:
        ap.error(f"--replays: unknown {sorted(set(replays) - {'register', 'icp'})} (register, icp)")
    if args.stages_only and not args.stages:
        ap.error("--stages-only needs --stages")
    result = {"dataset": args.dataset, "device": args.device, "gpu": None}
    if args.device.startswith("cuda"):
        import torch

        result["gpu"] = torch.cuda.get_device_name(args.device)
    if not args.stages_only:
        if "icp" in replays:
            result["icp"] = replay(args.dataset, config, args.device, args.limit)
        if "register" in replays:
            result["register"] = replay_register(args.dataset, config, args.device)
    if args.stages:
        result["stages"] = stages_on_the_other_path(args.dataset, config, args.device)
    text = report(result)
    if args.out:
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""Cost per object and per candidate on each BOP core dataset's layout, and the run
time it implies for the real datasets (run by hand).

    .venv/bin/python benchmarks/bop_layouts.py [--datasets lmo,itodd] [--cores 1] [--work DIR]

For each dataset, a tiny synthetic dataset is written in its exact layout and image
size (``pipeline/evaluation/synth/layouts.py``: 3 objects, 1 scene, 2 images) and ``bop_all``
runs on it with the default run manifest. From the artifact manifests:

- per object: the summed job time of render_templates + symmetries + model_features,
  divided by the objects;
- per candidate: the summed job time of scene_features + register + refine (scene
  jobs), divided by the candidate masks segment_prior kept.

With ``--cores 1`` (the default) jobs run one at a time, so job times are not inflated
by a second job on the other core. The estimate for a real dataset multiplies these
by its BOP19 test subset: objects, instances and ``top_k`` (3) candidates per instance
(CNOS proposes many masks per object, so top-k is usually full; the synthetic prior
gives fewer). "One machine" divides the summed job time by the cores (jobs pack
perfectly: an optimistic bound); "cluster" assumes a node per job, so its wall time is
one object job plus the largest scene-side job: a whole scene (the dataset's instances
spread evenly over its test scenes), or, with ``--images-per-job N`` (default 20, the
run manifest's ``images_per_job``), a chunk of N images of it. Writes
``benchmarks/results/bop_layouts.md`` and the measured costs to ``bop_layouts.json``;
``--reuse`` recomputes the estimates from that file without running anything.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CORE = ("lmo", "tless", "tudl", "icbin", "itodd", "hb", "ycbv")
# BOP19 test subsets as given in the BOP Challenge 2020 paper (Hodan et al.), not checked
# against the data here: objects onboarded (the target objects), test images, instances to
# localise, test scenes. --counts-from BOP_ROOT takes them from your copy instead.
BOP19 = {
    "lmo": (8, 200, 1445, 1), "tless": (30, 1000, 6423, 20), "tudl": (3, 600, 600, 3), "icbin": (2, 150, 1786, 3),
    "itodd": (28, 721, 3041, 1), "hb": (16, 300, 1630, 13), "ycbv": (21, 900, 4123, 12),
}
MODEL_SIDE = ("render_templates", "symmetries", "model_features")
SCENE_SIDE = ("scene_features", "register", "refine")


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


def measure(name: str, work: Path, cores: int) -> dict:
    """Write the layout of ``name`` under ``work/bop`` and run bop_all on it; the costs."""
    import os

    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan
    from pipeline.common.store import read_manifest
    from pipeline.evaluation.synth.layouts import write_layout

    bop_root = work / "bop"
    if not (bop_root / name).exists():
        write_layout(cfg.load_dataset_manifest(name), bop_root)
    env = {**os.environ, "FREEZE_CACHE": str(work / "cache"), "PYOPENGL_PLATFORM": "egl", "HF_HUB_OFFLINE": "1"}
    env.pop("FREEZE_RUN_JSON", None)
    cmd = [str(Path(sys.executable).parent / "snakemake"), "-s", str(ROOT / "Snakefile"), "--directory", str(work),
           "--cores", str(cores), "bop_all", "--config", f"datasets={name}", f"bop_root={bop_root}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-3000:] + proc.stderr[-3000:])
        raise SystemExit(f"{name}: snakemake failed ({proc.returncode})")
    plan = RunPlan(cfg.load_run({"datasets": name, "bop_root": str(bop_root)}), cache=work / "cache")[name]
    secs = {}
    for stage, sp in plan.stages.items():
        secs[stage] = sum(read_manifest(m)["wall_time_s"] for m in sp.dir.glob("*/_manifest.json"))
    n_cand = read_manifest(plan["segment_prior"].manifest("all"))["summary"]["n_candidates"]
    scores = read_manifest(plan["score"].manifest("all"))["summary"]
    return {"wall": wall, "objects": len(plan.obj_ids), "candidates": n_cand, "instances": scores["n_targets"],
            "per_object": sum(secs[s] for s in MODEL_SIDE) / len(plan.obj_ids),
            "per_candidate": sum(secs[s] for s in SCENE_SIDE) / max(1, n_cand),
            "size": "x".join(map(str, plan.dataset.image_size)), "AR": scores.get("AR")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default=",".join(CORE))
    ap.add_argument("--cores", type=int, default=1, help="snakemake --cores for the measured runs")
    ap.add_argument("--machine-cores", type=int, default=2, help="cores of the 'one machine' estimate")
    ap.add_argument("--work", type=Path, default=Path("/tmp/freeze-bop-layouts"))
    ap.add_argument("--fresh", action="store_true", help="delete --work first")
    ap.add_argument("--images-per-job", type=int, default=20,
                    help="images of one scene-side job in the chunked cluster estimate (run manifest images_per_job)")
    ap.add_argument("--reuse", action="store_true",
                    help="take the measured costs from benchmarks/results/bop_layouts.json instead of measuring")
    ap.add_argument("--counts-from", type=Path, default=None,
                    help="bop_root of downloaded datasets: take objects, images, instances and scenes from them "
                         "(as freeze datasets check reports them) instead of the BOP19 figures")
    args = ap.parse_args()
    counts = dict(BOP19)
    if args.counts_from:
        from pipeline.common.config import load_dataset_manifest
        from pipeline.commands.datasets import check_dataset

        for name in CORE:
            if (args.counts_from / name).is_dir():
                s = check_dataset(args.counts_from, load_dataset_manifest(name)).summary
                counts[name] = (s["objects"], s["images"], s["instances"], s["scenes"])
    if args.fresh:
        shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True, exist_ok=True)
    from pipeline.common.config import SegmentPriorParams

    top_k = SegmentPriorParams().top_k
    import json

    store = ROOT / "benchmarks" / "results" / "bop_layouts.json"
    rows = {}
    if args.reuse:
        saved = json.loads(store.read_text())
        rows = {name: saved["rows"][name] for name in args.datasets.split(",") if name in saved["rows"]}
        measured_on = saved["date"]
    else:
        for name in [d for d in args.datasets.split(",") if d]:
            rows[name] = m = measure(name, args.work, args.cores)
            print(f"{name}: {m['per_object']:.1f} s/object, {m['per_candidate']:.2f} s/candidate "
                  f"({m['candidates']} candidates, {m['instances']} instances), run {m['wall']:.0f} s", flush=True)
        measured_on = time.strftime("%Y-%m-%d")
        store.write_text(json.dumps({"date": measured_on, "cores": args.cores, "rows": rows}, indent=1))
    lines = [
        "# Cost on each BOP core dataset's layout, and the run time it implies",
        "",
        f"`benchmarks/bop_layouts.py --cores {args.cores}`: default run manifest (FPFH + colortex), a tiny synthetic "
        "dataset in each layout at the dataset's image size (3 objects, 1 scene, 2 images); jobs one at a time.",
        "",
        "| dataset | image size | s / object (onboarding) | s / candidate (scene side) | measured on |",
        "|---|---|---|---|---|",
    ]
    for name, m in rows.items():
        lines.append(f"| {name} | {m['size']} | {m['per_object']:.1f} | {m['per_candidate']:.2f} | "
                     f"{m['objects']} objects, {m['candidates']} candidates |")
    lines += [
        "",
        f"Estimated for the BOP19 test subsets ({'counted in ' + str(args.counts_from) if args.counts_from else 'figures of the BOP Challenge 2020 paper'}), "
        f"{top_k} candidates per instance (segment_prior.top_k):",
        "",
        f"| dataset | objects | images | instances | scenes | job time | one machine ({args.machine_cores} cores) | "
        f"cluster, a job per scene | cluster, {args.images_per_job} images per job | s / image (BOP) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, m in rows.items():
        objs, images, inst, scenes = counts[name]
        model = objs * m["per_object"]
        scene = inst * top_k * m["per_candidate"]
        cluster = m["per_object"] + scene / scenes
        # a chunk holds images_per_job of a scene's images (the last may hold fewer)
        chunk_images = min(args.images_per_job, -(-images // scenes)) if args.images_per_job else images / scenes
        chunked = m["per_object"] + scene / images * chunk_images
        lines.append(f"| {name} | {objs} | {images} | {inst} | {scenes} | {_hours(model + scene)} | "
                     f"{_hours((model + scene) / args.machine_cores)} | {_hours(cluster)} | {_hours(chunked)} | "
                     f"{scene / images:.0f} |")
    lines += ["", "Job time excludes the score stage (BOP's VSD renders every estimate; see score_speed.md). "
              "The one-machine column assumes perfect packing of jobs; the cluster columns assume a node per job "
              "and are bound by one object job plus the largest scene-side job: a whole scene (LM-O and ITODD "
              f"have a single test scene), or {args.images_per_job} images of it with "
              f"`--config images_per_job={args.images_per_job}` (instances spread evenly over images; each "
              "chunk job also pays the job start-up, included in the per-candidate cost). "
              "s / image (BOP) is the scene-side time per test image, what BOP's time column measures "
              "(onboarding excluded).", "",
              f"Costs measured {measured_on} (`--reuse` recomputes this table from `bop_layouts.json`)."]
    text = "\n".join(lines) + "\n"
    out = ROOT / "benchmarks" / "results" / "bop_layouts.md"
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

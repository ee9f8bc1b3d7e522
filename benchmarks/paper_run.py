"""The paper's configuration run on one dataset in one process, timed per stage (run by hand).

    .venv/bin/python benchmarks/paper_run.py [--dataset synthtiny] [--device cuda] [--weights DIR]
        [--cache DIR] [--geometric gedi] [--visual dinov2-vitg14] [--out report.md]

Every stage of ``bop_all`` runs for every item of the dataset, in the stage graph's
order, in this process (``run_stage``, as ``freeze stage`` and ``freeze estimate``
run them), so that a machine without Snakemake can run it: ``scripts/gpu_check.sh``
runs it on a bare GPU machine. Each stage's wall time is summed over its items;
``torch.cuda.synchronize`` closes each item on CUDA. Weights: the weights folder
``--weights`` when it holds the encoders' files, else random full-size ones written
there in the official layouts (GeDi's checkpoint dict, DINOv2's state dict; drawn on
``--device``): they cost what real ones do, and the AR means nothing then.

The report (``--out``, and the standard output) gives the time per stage, the scene
side per image (segment_prior + scene_features + register + refine, over the dataset's
target images: BOP's time per image counts everything after onboarding, model loads
included as they happen here) beside the paper's 2.72 s per image (FreeZe, one A40), the
onboarding per object, peak GPU memory (``torch.cuda.max_memory_allocated``) and this
process's peak RSS, the encoders' device and precision, the paths the scene side took
(register's and refine's manifests' ``runtime``: numpy, or torch on the device, for
RANSAC, the ICP and the verification), and the AR.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

PAPER_S_PER_IMAGE = 2.72  # FreeZe (ECCV 2024), whole method per image on one A40
SCENE_STAGES = ("segment_prior", "scene_features", "register", "refine")


def ensure_weights(folder: Path, geometric: str, visual: str, device: str) -> list[str]:
    """Write random full-size weights where the manifests ``geometric`` and ``visual``
    look for them, unless a file is there already; the files written."""
    from gpu_agreement import dinov2_official_weights

    from pipeline.common.config import load_encoder_manifest
    from pipeline.method.encoders.dinov2 import find_weights, official_filename
    from pipeline.method.encoders.gedi import DEFAULT_WEIGHTS, save_random_checkpoint

    written = []
    for name in (geometric, visual):
        man = load_encoder_manifest(name)
        if man.encoder == "gedi":
            path = folder / str(man.params.get("weights") or DEFAULT_WEIGHTS)
            if not path.exists():
                save_random_checkpoint(path)
                written.append(str(path))
        elif man.encoder == "dinov2":
            model = str(man.params["model"])
            if find_weights(model, man.params.get("weights"), folder)[0] is None:
                written.append(str(dinov2_official_weights(folder / official_filename(model), model, device=device)))
    return written


def items_of(plan, stage: str) -> list[str]:
    """Every item ``stage`` runs for in the dataset plan, in the order of its item kinds."""
    from pipeline.workflow.plan import obj_item
    from pipeline.workflow.stage_graph import STAGES

    out: list[str] = []
    for kind in STAGES[stage].items:
        out += {"dataset": ["dataset"], "obj": [obj_item(o) for o in plan.obj_ids], "scene": list(plan.scene_items),
                "all": ["all"]}[kind]
    return out


def run(dataset: str, geometric: str, visual: str, device: str, weights: Path, cache: Path) -> dict:
    """Run every stage of ``dataset`` (skipping those already in ``cache``) and return
    the measurements (see the module doc)."""
    os.environ["FREEZE_CACHE"] = str(cache)
    from pipeline.common import store
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan, build_encoders, encoder_runtime
    from pipeline.workflow.stage_graph import STAGES
    from pipeline.workflow.stage_graph import run_stage

    config = {"datasets": dataset, "geometric": geometric, "visual": visual, "device": device,
              "weights_dir": str(weights)}
    run_manifest = load_run(config)
    on_cuda = device.startswith("cuda")
    if on_cuda:
        torch.cuda.reset_peak_memory_stats()
    seconds: dict[str, float] = {}
    skipped: list[str] = []
    plan = RunPlan(run_manifest)[dataset]
    for stage, spec in STAGES.items():
        if stage == "render_templates":  # planned again once synth has written the dataset: its layout is known
            plan = RunPlan(run_manifest)[dataset]
        if spec.synthetic_only and stage not in plan.stages:
            continue
        for item in items_of(plan, stage):
            if plan[stage].manifest(item).exists():
                skipped.append(f"{stage}/{item}")
                continue
            t0 = time.perf_counter()
            store.mark_job_start()
            run_stage(plan, stage, item, progress=False)
            if on_cuda:
                torch.cuda.synchronize()
            seconds[stage] = seconds.get(stage, 0.0) + time.perf_counter() - t0
            print(f"  {stage} {item}: {time.perf_counter() - t0:.1f} s", flush=True)
    scores = json.loads((plan["score"].item_dir("all") / "scores.json").read_text())["summary"]
    n_images = sum(len(v) for v in plan.scene_images.values())
    encoders = dict(zip(("geometric", "visual"), map(encoder_runtime, build_encoders(run_manifest))))
    first = plan.scene_items[0]
    paths = {key: json.loads(plan[stage].manifest(first).read_text()).get("runtime", {}).get(key, "numpy")
             for stage, key in (("register", "ransac"), ("refine", "icp"), ("refine", "verification"))}
    return {
        "dataset": dataset, "geometric": geometric, "visual": visual, "device": device,
        "gpu": torch.cuda.get_device_name(device) if on_cuda else None,
        "torch": torch.__version__, "seconds": seconds, "skipped": skipped,
        "n_objects": len(plan.obj_ids), "n_images": n_images, "n_targets": int(scores.get("n_targets", 0)),
        "scene_s_per_image": sum(seconds.get(s, 0.0) for s in SCENE_STAGES) / max(1, n_images),
        "onboarding_s_per_object": sum(seconds.get(s, 0.0) for s in ("render_templates", "symmetries",
                                                                       "model_features")) / max(1, len(plan.obj_ids)),
        "peak_gpu_gb": torch.cuda.max_memory_allocated() / 2**30 if on_cuda else None,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "encoders": encoders, "scene_paths": paths, "AR": scores.get("AR"),
    }


def report(m: dict, written: list[str]) -> str:
    """The measurements as a Markdown section."""
    lines = [f"## {m['geometric']} + {m['visual']} on {m['dataset']}, device {m['device']}"
             + (f" ({m['gpu']})" if m["gpu"] else ""), "",
             f"torch {m['torch']}; {m['n_objects']} objects, {m['n_images']} images, {m['n_targets']} targets; "
             f"weights: {'random, written by this run' if written else 'the weights folder given'}; "
             f"encoders: {json.dumps(m['encoders'], sort_keys=True)}; scene side's paths: register's RANSAC "
             f"{m['scene_paths']['ransac']}, refine's ICP {m['scene_paths']['icp']} and verification "
             f"{m['scene_paths']['verification']}.", "",
             "| stage | seconds |", "|---|---|"]
    lines += [f"| {s} | {v:.1f} |" for s, v in m["seconds"].items()]
    paper = m["scene_s_per_image"] / PAPER_S_PER_IMAGE
    lines += ["", f"- scene side per image: **{m['scene_s_per_image']:.2f} s** ({' + '.join(SCENE_STAGES)}, "
              f"model loads included), the paper's {PAPER_S_PER_IMAGE} s per image (one A40) x {paper:.2f}",
              f"- onboarding per object: {m['onboarding_s_per_object']:.1f} s (render_templates + symmetries + "
              "model_features)",
              f"- peak GPU memory: {m['peak_gpu_gb']:.1f} GB" if m["peak_gpu_gb"] is not None else "- peak GPU memory: -",
              f"- peak RSS of this process: {m['peak_rss_gb']:.1f} GB",
              f"- AR {m['AR']:.3f}" + (" (random weights: meaningless)" if written else "")]
    if m["skipped"]:
        lines.append(f"- already in the cache, not timed: {', '.join(m['skipped'])}")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="synthtiny")
    ap.add_argument("--geometric", default="gedi")
    ap.add_argument("--visual", default="dinov2-vitg14")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--weights", type=Path, help="weights folder (default: a temporary one with random weights)")
    ap.add_argument("--cache", type=Path, help="cache folder (default: a temporary, fresh one)")
    ap.add_argument("--out", type=Path, help="also write the report here")
    ap.add_argument("--json", type=Path, help="also write the measurements here")
    args = ap.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print(f"paper_run: --device {args.device}, but no CUDA device is visible to torch here", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        weights = (args.weights or Path(tmp) / "weights").resolve()
        t0 = time.perf_counter()
        written = ensure_weights(weights, args.geometric, args.visual, args.device)
        if written:
            print(f"paper_run: random weights written in {time.perf_counter() - t0:.0f} s: {', '.join(written)}")
        m = run(args.dataset, args.geometric, args.visual, args.device, weights,
                (args.cache or Path(tmp) / "cache").resolve())
    text = report(m, written)
    print(text)
    if args.out:
        args.out.write_text(text)
    if args.json:
        args.json.write_text(json.dumps(m, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

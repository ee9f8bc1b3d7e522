"""Where the scene side's time goes, per target (run by hand).

    .venv/bin/python benchmarks/scene_side_profile.py [--dataset synthtiny] [--visual dinov2-vits14]
        [--repeat 3] [--trees before=/tmp/wt_before,after=.]

Runs the scene-side stages (``scene_features``, ``register``, ``refine``) of every scene
item of one dataset in-process, with the run's encoders (DINOv2 with random weights made
here, as ``benchmarks/encoders.py`` makes them: same cost as real weights, meaningless
features), and splits each job's wall time into parts by wrapping the library functions
that do the work (crop, DINOv2 forward, lifting, FPFH, RANSAC, ICP, verification
renders, turns, SAR's renders and encoder passes...). Times are *exclusive*: a part
nested in another (the ICP inside the fine ICP) is subtracted from its parent, so the
parts add up to the job time. ``other`` is whatever no wrapper covers (reading inputs,
mask decoding, publishing).

The first run of each tree in a process pays imports and the model load; the table
reports the median of the later runs (steady state: what every further target costs
once a job is warm) and, separately, the one-time parts (encoder build and weight
load, renderer context) that a job pays once whatever its size.

With ``--trees NAME=DIR,...`` each tree (a checkout of the repository, e.g. a
``git worktree`` of HEAD as "before") is measured in its own subprocess on its own copy
of the cache, alternating between trees for ``--rounds`` rounds on the same inputs, so
that the trees share the machine's load (the order flips every round: use an even
number); the report gives each part per tree and the
ratio. Writes ``benchmarks/results/scene_side_profile.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent

# (module or class path, attribute, part label or a function of (args, kwargs) -> label).
# Labels are prefixed with the stage being run. Missing attributes are skipped, so that
# older trees can be measured with the same list.
WRAPPED: list[tuple[str, str, Any]] = [
    ("pipeline.workflow.plan", "build_encoders", "encoder build (one-time)"),
    ("pipeline.method.encoders.dinov2:Dinov2Encoder", "_load", "DINOv2 weight load (one-time)"),
    ("pipeline.method.render.renderer:Renderer", "__init__", "renderer context (one-time)"),
    ("pipeline.method.render.renderer:Renderer", "add_mesh", "renderer mesh upload"),
    ("pipeline.method.scene_side", "candidate_points", "depth lift + outlier removal"),
    ("pipeline.method.encoders.fpfh:FpfhEncoder", "encode", "FPFH + normals"),
    ("pipeline.method.encoders.lifting", "crop_and_resize", "crop + resize"),
    ("pipeline.method.refinement.sar", "crop_and_resize", "crop + resize"),
    ("pipeline.method.encoders.dinov2:Dinov2Encoder", "encode", "DINOv2 forward"),
    ("pipeline.method.encoders.colortex:ColorTexEncoder", "encode", "colortex"),
    ("pipeline.method.encoders.lifting", "sample_features_at_pixels", "lifting at the points"),
    ("pipeline.method.encoders.lifting", "upsample_to_crop", "upsampling whole maps"),
    ("pipeline.method.scene_side", "matchable_model", "model PCA"),
    ("pipeline.method.registration.ransac", "ransac_hypotheses", "RANSAC"),
    ("pipeline.method.registration.ransac", "feature_neighbours", "feature matching"),
    ("pipeline.method.refinement.icp", "refine_icp",
     lambda a, k: "ICP quick (turns)" if k.get("iterations") == 10 and tuple(k.get("schedule", ())) == (1.0,)
     else "ICP"),
    ("pipeline.method.refinement.turns", "model_turns", "turns set-up"),
    ("pipeline.method.render.renderer:Renderer", "render_depth_crop", "verification render"),
    ("pipeline.method.refinement.verification", "compare_depth", "verification compare"),
    ("pipeline.method.scene_side:FineIcp", "__call__", "fine ICP (points, samples)"),
    ("pipeline.method.geometry.sampling", "sample_surface", "model surface samples"),
    ("pipeline.method.refinement.sar", "symmetry_aware_refinement", "SAR other"),
    ("pipeline.method.refinement.sar", "render_in_crop", "SAR renders"),
    ("pipeline.method.refinement.sar", "sar_similarity", "SAR similarity"),
    ("pipeline.formats.bop.detections", "rle_decode", "mask decode"),
]
ONE_TIME = ("encoder build (one-time)", "DINOv2 weight load (one-time)", "renderer context (one-time)")
SCENE_STAGES = ("scene_features", "register", "refine")


class Clock:
    """Exclusive time per label: each wrapped call's time goes to its label minus the
    time of the wrapped calls nested in it."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.stage = ""
        self._stack: list[float] = []  # nested time of the open calls

    def wrap(self, fn: Callable, label: Any) -> Callable:
        clock = self

        def timed(*args, **kwargs):
            name = label(args, kwargs) if callable(label) else label
            # SAR's encoder passes are DINOv2 forwards too, but a separate part.
            if name == "DINOv2 forward" and clock.stage == "refine":
                name = "SAR encoder passes"
            clock._stack.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                nested = clock._stack.pop()
                key = f"{clock.stage}: {name}"
                clock.seconds[key] += dt - nested
                clock.calls[key] += 1
                if clock._stack:
                    clock._stack[-1] += dt
        timed.__wrapped__ = fn
        return timed


def _install(clock: Clock) -> None:
    import importlib

    for where, attr, label in WRAPPED:
        mod_name, _, cls = where.partition(":")
        try:
            owner = importlib.import_module(mod_name)
            if cls:
                owner = getattr(owner, cls)
        except (ImportError, AttributeError):
            continue
        fn = owner.__dict__.get(attr) if cls else getattr(owner, attr, None)
        if fn is None:
            continue
        setattr(owner, attr, clock.wrap(fn, label))


def measure(dataset: str, config: dict[str, str], repeat: int) -> dict[str, Any]:
    """Run the scene-side stages of every scene item ``repeat`` times in this process;
    returns per run the exclusive seconds per part and the stages' totals, and the
    number of targets."""
    try:
        from pipeline.workflow.stage_graph import run_stage
    except ImportError:  # a tree from before run_stage moved into the workflow layer (--trees)
        from stages import run_stage
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.stage_graph import STAGES
    from pipeline.common.threads import use_threads

    clock = Clock()
    _install(clock)
    plan = RunPlan(load_run(config))[dataset]
    runs = []
    for _ in range(repeat):
        clock.seconds.clear()
        clock.calls.clear()
        totals: dict[str, float] = defaultdict(float)
        for item in plan.scene_items:
            for stage in SCENE_STAGES:
                clock.stage = stage
                use_threads(STAGES[stage].threads)  # as Snakemake's job of that stage would
                t0 = time.perf_counter()
                run_stage(plan, stage, item, progress=False)
                totals[stage] += time.perf_counter() - t0
        parts = dict(clock.seconds)
        for stage in SCENE_STAGES:
            covered = sum(v for k, v in parts.items() if k.startswith(stage + ":"))
            parts[f"{stage}: other (inputs, publish, loops)"] = totals[stage] - covered
        runs.append({"parts": parts, "calls": dict(clock.calls), "totals": dict(totals)})
    return {"runs": runs}


def _targets(dataset: str, config: dict[str, str], cache: Path) -> int:
    """The dataset's number of targets, from a score of the prepared run (any version of
    the method: the targets are the dataset's)."""
    found = sorted((cache / dataset / "score").glob("*/all/scores.json"))
    if not found:
        raise SystemExit(f"scene_side_profile: no score under {cache / dataset / 'score'}; run bop_all there first")
    return int(json.loads(found[0].read_text())["summary"]["n_targets"])


def _prepare(cache: Path, weights: Path, config: dict[str, str]) -> None:
    """Random DINOv2 weights and a cache holding every stage of the run (``bop_all``)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from encoders import _dinov2_weights

    from pipeline.method.encoders.dinov2 import hf_dirname

    if not (weights / hf_dirname("vits14")).exists():
        weights.mkdir(parents=True, exist_ok=True)
        _dinov2_weights(weights, "vits14", hf_dirname("vits14"))
    env = {**os.environ, "FREEZE_CACHE": str(cache), "PYOPENGL_PLATFORM": "egl", "HF_HUB_OFFLINE": "1"}
    env.pop("FREEZE_RUN_JSON", None)
    cmd = [str(Path(sys.executable).parent / "snakemake"), "--cores", "2", "bop_all", "--config",
           *(f"{k}={v}" for k, v in config.items())]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode:
        sys.stderr.write(proc.stdout[-3000:] + proc.stderr[-3000:])
        raise SystemExit("bop_all failed")


def _table(results: dict[str, dict], n_targets: int) -> list[str]:
    """Markdown rows: part, seconds per target per tree (median over the warm runs of
    every round), share of the last tree's total, ratio first/last tree."""
    names = list(results)
    med: dict[str, dict[str, float]] = {}
    calls: dict[str, dict[str, int]] = {}
    for name, rounds in results.items():
        runs = [run for r in rounds for run in r["runs"][1:]] or [run for r in rounds for run in r["runs"]]
        warm = [run["parts"] for run in runs]
        calls[name] = runs[-1]["calls"]
        keys = set().union(*warm)
        med[name] = {k: statistics.median(w.get(k, 0.0) for w in warm) / n_targets for k in keys}
    keys = sorted(set().union(*(m.keys() for m in med.values())),
                  key=lambda k: (SCENE_STAGES.index(k.split(":")[0]), -med[names[-1]].get(k, 0.0)))
    last = names[-1]
    steady = {n: sum(v for k, v in med[n].items() if not any(o in k for o in ONE_TIME)) for n in names}
    head = "| part | calls | " + " | ".join(f"{n} s/target" for n in names) + f" | share ({last}) |" + (
        f" {names[0]}/{last} |" if len(names) > 1 else "")
    lines = [head, "|" + "---|" * (len(names) + 3 + (len(names) > 1))]
    for k in keys:
        vals = [med[n].get(k, 0.0) for n in names]
        if max(vals) < 0.0005:
            continue
        share = f"{100 * med[last].get(k, 0.0) / steady[last]:.1f}%" if not any(o in k for o in ONE_TIME) else "-"
        ratio = "" if len(names) == 1 else f" {vals[0] / vals[-1]:.2f}x |" if vals[-1] > 0.0005 else " - |"
        n_calls = calls[last].get(k, "")
        lines.append(f"| {k} | {n_calls} | " + " | ".join(f"{v:.3f}" for v in vals) + f" | {share} |" + ratio)
    for stage in SCENE_STAGES:
        vals = [sum(v for k, v in med[n].items() if k.startswith(stage + ":") and not any(o in k for o in ONE_TIME))
                for n in names]
        ratio = f" {vals[0] / vals[-1]:.2f}x |" if len(names) > 1 else ""
        lines.append(f"| **{stage} (steady)** | | " + " | ".join(f"**{v:.3f}**" for v in vals) +
                     f" | {100 * vals[-1] / steady[last]:.1f}% |" + ratio)
    vals = [steady[n] for n in names]
    ratio = f" **{vals[0] / vals[-1]:.2f}x** |" if len(names) > 1 else ""
    lines.append("| **scene side, steady state** | | " + " | ".join(f"**{v:.3f}**" for v in vals) + " | 100% |" + ratio)
    once = [sum(v for k, v in med[n].items() if any(o in k for o in ONE_TIME)) for n in names]
    lines.append("| one-time parts (per job, spread over its targets) | | " + " | ".join(f"{v:.3f}" for v in once) +
                 " | - |" + (" - |" if len(names) > 1 else ""))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthtiny")
    ap.add_argument("--geometric", default="fpfh")
    ap.add_argument("--visual", default="dinov2-vits14")
    ap.add_argument("--repeat", type=int, default=3, help="runs per process (the first is cold)")
    ap.add_argument("--rounds", type=int, default=2, help="alternations between the trees (even: the order flips)")
    ap.add_argument("--trees", default="", help="NAME=DIR,... checkouts to compare (default: this one)")
    ap.add_argument("--work", default="", help="folder for weights and caches (default: a temporary one)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "scene_side_profile.md"))
    ap.add_argument("--table-only", action="store_true", help="rewrite the table from --work's results.json")
    ap.add_argument("--measure", default="", help=argparse.SUPPRESS)  # internal: JSON output path
    args = ap.parse_args()

    work = Path(args.work or tempfile.mkdtemp(prefix="scene_side_profile-"))
    config = {"datasets": args.dataset, "geometric": args.geometric, "visual": args.visual,
              "weights_dir": str(work / "weights")}
    if args.measure:
        Path(args.measure).write_text(json.dumps(measure(args.dataset, config, args.repeat)))
        return

    trees = dict(t.split("=", 1) for t in args.trees.split(",")) if args.trees else {"this": str(ROOT)}
    trees = {n: str(Path(d).resolve()) for n, d in trees.items()}
    base = work / "cache"
    if not (base / args.dataset).exists():
        _prepare(base, work / "weights", config)
    n_targets = _targets(args.dataset, config, base)
    results: dict[str, list] = {n: [] for n in trees}
    if args.table_only:
        results = json.loads((work / "results.json").read_text())
    # Each tree runs on its own copy of the cache: its outputs feed its own next stage.
    for name in trees if not args.table_only else []:
        if not (work / f"cache-{name}").exists():
            shutil.copytree(base, work / f"cache-{name}", symlinks=True)
    # The order flips every round (A B, B A, ...): whichever tree ran first in a round ran
    # 4-7 % faster, with either order (2026-12-05, HEAD against 0d43830, two runs).
    for round_no in range(args.rounds if not args.table_only else 0):
        order = list(trees.items())
        for name, tree in (order if round_no % 2 == 0 else order[::-1]):
            out = work / f"{name}.json"
            env = {**os.environ, "FREEZE_CACHE": str(work / f"cache-{name}"), "PYTHONPATH": tree,
                   "PYOPENGL_PLATFORM": "egl", "HF_HUB_OFFLINE": "1"}
            env.pop("FREEZE_RUN_JSON", None)
            subprocess.run([sys.executable, str(Path(__file__).resolve()), "--dataset", args.dataset, "--geometric",
                            args.geometric, "--visual", args.visual, "--repeat", str(args.repeat), "--work",
                            str(work), "--measure", str(out)], cwd=tree, env=env, check=True)
            results[name].append(json.loads(out.read_text()))
            print(f"{name}: done a round", flush=True)
    cmd = " ".join(["benchmarks/scene_side_profile.py", f"--dataset {args.dataset}", f"--geometric {args.geometric}",
                    f"--visual {args.visual}", f"--repeat {args.repeat}", f"--rounds {args.rounds}"] +
                   ([f"--trees {args.trees}"] if args.trees else []))
    lines = ["# Scene-side time per target, by part", "",
             f"`{cmd}`: the scene-side stages of `{args.dataset}` ({n_targets} targets) run in-process, "
             f"{args.geometric} + {args.visual} (DINOv2 with random weights: the cost of real ones), "
             f"on {os.cpu_count()} shared cores, each stage with its Snakemake job's threads. Exclusive seconds "
             "per target, the median over the warm runs (every run after a process's first) of every round; "
             "trees measured alternately, each on its own copy of the same cache.", ""]
    lines += _table(results, n_targets)
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text)
    if not args.table_only:
        (work / "results.json").write_text(json.dumps(results))
    print(text)


if __name__ == "__main__":
    main()

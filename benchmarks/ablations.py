"""Encoder ablations: AR and cost of the main job per (geometric, visual) pair (run by hand).

    .venv/bin/python benchmarks/ablations.py --dataset synthbench \\
        --pairs fpfh+colortex,fpfh+none,none+colortex,fpfh-r02+colortex,fpfh-r03+colortex,fpfh-r04+colortex

For each pair ``GEO+VIS`` (encoder manifest names; ``none`` switches a part off) this
runs ``snakemake --cores N bop_all --config datasets=D geometric=GEO visual=VIS``
(stages already in the cache are reused, so the stages that do not depend on the
encoders run once), then reads the artifacts of that pair's plan and reports:

- AR, AR_VSD, AR_MSSD, AR_MSPD over all targets, and AR over the textured and the
  texture-less objects of the synthetic set (:data:`GREY_OBJECTS`);
- cost, from the job manifests (each job's whole wall time): onboarding seconds per
  object (model_features) and scene-side seconds per target (scene_features +
  register + refine, summed over the dataset's jobs and divided by its targets).
  Jobs that came from the cache report the time they took when they ran.

Writes ``benchmarks/results/ablations_<dataset>.md``. ``--weights-dir`` is passed on as
``weights_dir`` (see ``benchmarks/encoders.py --pipeline`` for pairs with random
weights). ``--cache DIR`` runs in another artifact store (``FREEZE_CACHE``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

GREY_OBJECTS = {3, 4, 5}
"""Texture-less synthetic objects (U-channel, L-bracket, hex nut); the others are textured."""

SCENE_SIDE = ("scene_features", "register", "refine")


@dataclass
class PairResult:
    pair: str
    scores: dict
    per_object: list[dict]
    onboarding_s_per_object: float
    scene_s_per_target: float
    n_targets: int
    wall_s: float
    peak_rss_mb: dict[str, float] = field(default_factory=dict)  # stage -> the largest job's peak RSS (MB)


def run_pair(dataset: str, geometric: str, visual: str, *, cores: int = 2, weights_dir: str | None = None,
             cache: Path | None = None) -> PairResult:
    """Run ``bop_all`` for one encoder pair and read its scores and job times."""
    config = {"datasets": dataset, "geometric": geometric, "visual": visual}
    if weights_dir:
        config["weights_dir"] = weights_dir
    return run_config(config, f"{geometric}+{visual}", cores=cores, cache=cache)


def run_config(config: dict[str, str], label: str, *, cores: int = 2, cache: Path | None = None) -> PairResult:
    """Run ``bop_all --config`` with ``config`` (one dataset) and read its scores and job times."""
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan
    from pipeline.common.store import read_manifest

    dataset = config["datasets"]
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    if cache:
        env["FREEZE_CACHE"] = str(cache)
    env.setdefault("PYOPENGL_PLATFORM", "egl")
    env.setdefault("HF_HUB_OFFLINE", "1")
    cmd = [str(Path(sys.executable).parent / "snakemake"), "--cores", str(cores), "bop_all", "--config",
           *(f"{k}={v}" for k, v in config.items())]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-3000:] + proc.stderr[-3000:])
        raise SystemExit(f"{label}: snakemake failed ({proc.returncode})")

    old = os.environ.get("FREEZE_CACHE")
    if cache:
        os.environ["FREEZE_CACHE"] = str(cache)
    try:
        plan = RunPlan(load_run(config))[dataset]
    finally:
        if cache:
            if old is None:
                os.environ.pop("FREEZE_CACHE", None)
            else:
                os.environ["FREEZE_CACHE"] = old

    def job_seconds(stage: str) -> float:
        return sum(read_manifest(m)["wall_time_s"] for m in plan[stage].dir.glob("*/_manifest.json"))

    def peak_rss(stage: str) -> float:
        return max((float(read_manifest(m).get("peak_rss_mb") or 0.0) for m in plan[stage].dir.glob("*/_manifest.json")),
                   default=0.0)

    scores = json.loads((plan["score"].item_dir("all") / "scores.json").read_text())
    n_targets = int(scores["summary"]["n_targets"])
    return PairResult(
        pair=label,
        scores=scores["summary"],
        per_object=scores["per_object"],
        onboarding_s_per_object=job_seconds("model_features") / max(1, len(plan.obj_ids)),
        scene_s_per_target=sum(job_seconds(s) for s in SCENE_SIDE) / max(1, n_targets),
        n_targets=n_targets,
        wall_s=wall,
        peak_rss_mb={s: peak_rss(s) for s in ("model_features", *SCENE_SIDE)},
    )


def group_ar(per_object: list[dict], grey: bool) -> float:
    """AR over the targets of the grey (or textured) objects: per-object ARs weighted by
    their target counts, which equals the AR of that subset of targets."""
    rows = [r for r in per_object if (int(r["obj_id"]) in GREY_OBJECTS) == grey and r["n_targets"]]
    n = sum(r["n_targets"] for r in rows)
    return sum(r["AR"] * r["n_targets"] for r in rows) / n if n else float("nan")


def table(results: list[PairResult], title: str, command: str) -> str:
    lines = [f"# {title}", "", f"`{command}`", "",
             "| geometric + visual | AR | VSD | MSSD | MSPD | AR textured | AR texture-less | onboarding s/object | scene-side s/target |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        s = r.scores
        lines.append(f"| {r.pair} | {s['AR']:.3f} | {s['AR_VSD']:.3f} | {s['AR_MSSD']:.3f} | {s['AR_MSPD']:.3f} | "
                     f"{group_ar(r.per_object, False):.3f} | {group_ar(r.per_object, True):.3f} | "
                     f"{r.onboarding_s_per_object:.1f} | {r.scene_s_per_target:.2f} |")
    n = {r.n_targets for r in results}
    lines += ["", f"{'/'.join(map(str, sorted(n)))} targets; texture-less objects: {sorted(GREY_OBJECTS)}. "
              "Costs are job wall times from the artifact manifests (2 parallel jobs on 2 cores)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthbench")
    ap.add_argument("--pairs", default="fpfh+colortex,fpfh+none,none+colortex",
                    help="comma-separated GEO+VIS encoder manifest names")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--weights-dir", default=None)
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    results = []
    for pair in args.pairs.split(","):
        geo, vis = pair.split("+")
        r = run_pair(args.dataset, geo, vis, cores=args.cores, weights_dir=args.weights_dir, cache=args.cache)
        print(f"{r.pair}: AR {r.scores['AR']:.3f} ({r.wall_s:.0f} s)", flush=True)
        results.append(r)
    text = table(results, f"Encoder ablations on `{args.dataset}`", "benchmarks/ablations.py " + " ".join(sys.argv[1:]))
    out = args.out or ROOT / "benchmarks" / "results" / f"ablations_{args.dataset}.md"
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""Time the main job on one dataset and split the time by stage (run by hand).

    .venv/bin/python benchmarks/pipeline_run.py --dataset synthmini [--fresh] [--cores 2]

Runs ``snakemake --cores N bop_all --config datasets=D`` (after deleting that dataset's
cache with ``--fresh``), then reads every artifact manifest of the dataset's current
plan and prints: total wall time and peak memory of the run, and per stage the number
of jobs, the summed job wall time (each job's whole run, inputs to publish), its share
and the largest peak RSS of one job. Writes the table to
``benchmarks/results/pipeline_<dataset>.md``.

Job wall times are summed over jobs that ran in parallel, so their sum exceeds the
run's wall time on more than one core.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthmini")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--fresh", action="store_true", help="delete the dataset's cache (and the AR table) first")
    args = ap.parse_args()

    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan
    from pipeline.common.store import read_manifest

    rp = RunPlan(load_run({"datasets": args.dataset}))
    if args.fresh:
        shutil.rmtree(rp.cache / args.dataset, ignore_errors=True)
        (rp.cache.parent / "results" / "ar_table.md").unlink(missing_ok=True)
    cmd = [str(Path(sys.executable).parent / "snakemake"), "--cores", str(args.cores), "bop_all",
           "--config", f"datasets={args.dataset}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-3000:] + proc.stderr[-3000:])
        raise SystemExit(f"snakemake failed ({proc.returncode})")
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024

    plan = rp[args.dataset]
    jobs: dict[str, int] = defaultdict(int)
    secs: dict[str, float] = defaultdict(float)
    rss: dict[str, float] = defaultdict(float)
    for sp in plan.stages.values():
        for manifest in sorted(sp.dir.glob("*/_manifest.json")):
            m = read_manifest(manifest)
            jobs[sp.stage] += 1
            secs[sp.stage] += m["wall_time_s"]
            rss[sp.stage] = max(rss[sp.stage], m["peak_rss_mb"])
    total = sum(secs.values())
    scores = read_manifest(plan["score"].manifest("all"))["summary"]
    lines = [
        f"# Main job on `{args.dataset}` ({args.cores} cores)",
        "",
        f"`{' '.join(cmd[1:])}`: wall time {wall:.1f} s, largest process peak RSS {peak_mb:.0f} MiB.",
        f"AR {scores['AR']:.3f} (VSD {scores['AR_VSD']:.3f}, MSSD {scores['AR_MSSD']:.3f}, "
        f"MSPD {scores['AR_MSPD']:.3f}), {scores['n_targets']} targets.",
        "",
        "| stage | jobs | job time (s) | share | peak RSS of one job (MiB) |",
        "|---|---|---|---|---|",
    ]
    for stage in plan.stages:
        if jobs[stage]:
            lines.append(f"| {stage} | {jobs[stage]} | {secs[stage]:.1f} | {100 * secs[stage] / total:.0f}% | {rss[stage]:.0f} |")
    lines.append(f"| all | {sum(jobs.values())} | {total:.1f} | 100% | {max(rss.values()):.0f} |")
    text = "\n".join(lines) + "\n"
    out = ROOT / "benchmarks" / "results" / f"pipeline_{args.dataset}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

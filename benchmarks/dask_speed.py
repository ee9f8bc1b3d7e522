"""Register, refine and score in a job: serially, on dask threads, and on a loopback
dask cluster of processes, side by side (run by hand).

    .venv/bin/python benchmarks/dask_speed.py --cache DIR [--dataset synthmini] [--scenes 1]
        [--repeat 2] [--threads 2] [--workers 2] [--out benchmarks/results/dask.md]

DIR is a cache in which ``bop_all`` has run on the dataset (every upstream artifact of
the default run; e.g. ``FREEZE_CACHE=DIR snakemake --cores 2 bop_all --config
datasets=synthmini``). Each repeat runs, for each configuration in turn (so that all
see the same machine load), the stages ``register`` and ``refine`` on the first
``--scenes`` scene items, refine's ``all`` item and ``score``, in this process through
``run_stage``, as ``freeze stage`` runs them:

- ``serial``: the default, one candidate (image) after the other in the job's thread;
- ``threads``: dask's threaded scheduler on ``--threads`` threads (the stages'
  ``THREADS_HELP`` switched on, ``FREEZE_THREADS`` set);
- ``cluster``: a ``distributed.LocalCluster`` of ``--workers`` processes of one thread
  each on 127.0.0.1, reached as an external scheduler (``dask_scheduler``); started
  once before the repeats (its start-up is reported apart).

Each stage's wall time is the median over the repeats; speed-up = serial / other. The
artifacts of every configuration are compared with the serial one (every Parquet
table but its time columns, and the results CSV but its time column) and must be
identical.

The score stage has little to do on a small dataset's own results (one estimate per
target), so the scorer is also timed on a heavier file (``--score-scale`` > 0): the
estimates ``benchmarks/score_speed.py`` builds around every ground-truth instance of
the dataset (near, duplicated, symmetric, wrong, shifted, far and random poses), every
one of them scored (targets with ``inst_count`` raised), through
``score_results_file`` with each configuration's mapper, interleaved the same way; the
errors must be identical. Writes the tables to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

TIME_COLUMNS = ("time_s", "time")
NOTES_MARKER = "<!-- notes: kept by benchmarks/dask_speed.py -->"


def _snapshot(plan, stages: list[tuple[str, str]]) -> dict[str, object]:
    """The artifacts the stages wrote, without their time columns (for comparison)."""
    import pandas as pd

    out: dict[str, object] = {}
    for stage, item in stages:
        folder = plan[stage].item_dir(item)
        for path in sorted(folder.rglob("*.parquet")):
            df = pd.read_parquet(path)
            out[f"{stage}/{item}/{path.name}"] = df.drop(columns=[c for c in TIME_COLUMNS if c in df.columns])
        for path in sorted(folder.glob("*.csv")):
            out[f"{stage}/{item}/{path.name}"] = [ln.split(",")[:-1] for ln in path.read_text().splitlines()]
    return out


def _same(a: dict[str, object], b: dict[str, object]) -> bool:
    import pandas as pd

    if a.keys() != b.keys():
        return False
    for k, v in a.items():
        if isinstance(v, pd.DataFrame):
            try:
                pd.testing.assert_frame_equal(v, b[k], check_exact=True)
            except AssertionError:
                return False
        elif v != b[k]:
            return False
    return True


def _heavy_results(plan, scale: int, work: Path) -> tuple[Path, Path, Path, int]:
    """score_speed's estimates around every GT instance of the plan's dataset, written to
    ``work``: (results CSV, dataset root, targets file scoring every estimate, number of
    estimates scored)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from score_speed import build_estimates, write_all_targets

    from pipeline.formats.bop import write_results_csv

    work.mkdir(parents=True, exist_ok=True)
    rows, counts = build_estimates(plan.root, scale)
    csv = work / f"heavy_{plan.name}-test.csv"
    write_results_csv(csv, rows)
    targets = work / "targets_all.json"
    write_all_targets(plan.root, counts, targets)
    return csv, plan.root, targets, sum(counts.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--dataset", default="synthmini")
    ap.add_argument("--scenes", type=int, default=1, help="scene items run by register and refine")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "dask.md")
    ap.add_argument("--score-scale", type=int, default=1, help="per_gt_scale of score_speed's estimates (0: skip)")
    args = ap.parse_args()

    from distributed import LocalCluster

    import stages.refine
    import stages.register
    import stages.score
    from pipeline.common import config as cfg
    from pipeline.evaluation.metrics import score_results_file
    from pipeline.common.parallel import job_mapper
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.stage_graph import run_stage

    modules = (stages.register, stages.refine, stages.score)
    t0 = time.perf_counter()
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None)
    cluster_start = time.perf_counter() - t0
    configs = {
        "serial": ({}, False),
        "threads": ({}, True),
        "cluster": ({"dask_scheduler": cluster.scheduler_address}, False),
    }
    times: dict[str, dict[str, list[float]]] = {c: {} for c in configs}
    heavy, heavy_label = None, ""
    heavy_errors: dict[str, object] = {}
    heavy_same: dict[str, bool] = {c: True for c in configs}
    if args.score_scale > 0:
        heavy = _heavy_results(RunPlan(cfg.load_run({"datasets": args.dataset}), cache=args.cache)[args.dataset],
                               args.score_scale, args.cache.parent / "dask_speed")
        heavy_label = f"scorer, {heavy[3]} estimates scored"
    snapshots: dict[str, dict[str, object]] = {}
    os.environ["FREEZE_THREADS"] = str(args.threads)
    try:
        for r in range(args.repeat):
            for name, (overrides, threads) in configs.items():
                plan = RunPlan(cfg.load_run({"datasets": args.dataset, **overrides}), cache=args.cache)[args.dataset]
                for m in modules:
                    m.THREADS_HELP = threads
                items = plan.scene_items[:args.scenes]
                runs = [("register", i) for i in items] + [("refine", i) for i in items] + \
                    [("refine", "all"), ("score", "all")]
                for stage, item in runs:
                    t = time.perf_counter()
                    run_stage(plan, stage, item, progress=False)
                    dt = time.perf_counter() - t
                    label = stage if item != "all" or stage == "score" else "refine all (CSV)"
                    times[name].setdefault(label, []).append(dt)
                    print(f"repeat {r} {name:8s} {stage:8s} {item:14s} {dt:7.1f} s", flush=True)
                snap = _snapshot(plan, runs)
                snapshots.setdefault(name, snap)
                if not _same(snapshots["serial"], snap):
                    print(f"!! {name}: artifacts differ from serial", flush=True)
                    snapshots[name] = {}
                if heavy is not None:
                    t = time.perf_counter()
                    with job_mapper(overrides.get("dask_scheduler"), threads) as mapper:
                        scores = score_results_file(heavy[0], heavy[1], targets_file=heavy[2], mapper=mapper)
                    dt = time.perf_counter() - t
                    times[name].setdefault(heavy_label, []).append(dt)
                    print(f"repeat {r} {name:8s} scorer   {heavy_label} {dt:7.1f} s", flush=True)
                    errors = scores.errors.sort_values(["scene_id", "im_id", "obj_id", "est_id", "gt_id"])
                    heavy_errors.setdefault(name, errors.reset_index(drop=True))
                    if not heavy_errors[name].equals(errors.reset_index(drop=True)) or \
                            not heavy_errors["serial"].equals(errors.reset_index(drop=True)):
                        print(f"!! {name}: scorer errors differ from serial", flush=True)
                        heavy_same[name] = False
    finally:
        cluster.close()
    same = {name: _same(snapshots["serial"], snap) for name, snap in snapshots.items()}

    stages_seen = list(times["serial"])
    lines = [
        "# Dask inside a job: register, refine and score",
        "",
        "`" + ' '.join(shlex.quote(a) for a in ['.venv/bin/python', *sys.argv]) + "`",
        "",
        f"Dataset `{args.dataset}`, register and refine on {args.scenes} scene item(s), refine's CSV and score on the "
        f"whole dataset; wall time of each stage job in this process (inputs read, work, publish), median of "
        f"{args.repeat} interleaved repeats; 2 cores shared with other work (load average "
        f"{os.getloadavg()[0]:.1f} at the end). `threads`: dask's threaded scheduler on {args.threads} threads; "
        f"`cluster`: a loopback `LocalCluster` of {args.workers} processes x 1 thread, started once in "
        f"{cluster_start:.1f} s (not counted). Speed-up = serial / other.",
        "",
        "| stage | serial (s) | threads (s) | cluster (s) | threads speed-up | cluster speed-up | "
        "threads, paired (min-max) | cluster, paired (min-max) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label in stages_seen:
        med = {c: statistics.median(times[c][label]) for c in configs}
        # Paired: serial / other within each repeat (the two ran a minute apart), then
        # the median over repeats; less exposed to the load drifting between repeats.
        paired = {c: [a / b for a, b in zip(times["serial"][label], times[c][label])] for c in ("threads", "cluster")}
        lines.append(f"| {label} | {med['serial']:.1f} | {med['threads']:.1f} | {med['cluster']:.1f} | "
                     f"{med['serial'] / med['threads']:.2f}x | {med['serial'] / med['cluster']:.2f}x | " + " | ".join(
                         f"{statistics.median(v):.2f}x ({min(v):.2f}-{max(v):.2f})" for v in paired.values()) + " |")
    lines += ["", "Artifacts identical to serial (all columns but the times): "
              + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in same.items())
              + ("; the scorer's errors on the heavier file: "
                 + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in heavy_same.items()) if heavy else ""), "",
              "Every repeat (s): " + "; ".join(f"{c} {label} " + "/".join(f"{t:.1f}" for t in times[c][label])
                                              for c in configs for label in stages_seen), ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    # The notes written by hand below the marker stay when the table is measured again.
    kept = args.out.read_text().partition(NOTES_MARKER) if args.out.exists() else ("", "", "")
    args.out.write_text("\n".join(lines) + ("\n" + NOTES_MARKER + kept[2] if kept[1] else ""))
    print("\n".join(lines))


if __name__ == "__main__":
    main()

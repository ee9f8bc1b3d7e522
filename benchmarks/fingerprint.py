"""Cost of the content fingerprints when planning (run by hand): the first plan of a BOP
dataset on disk reads every byte the stages read; later plans only ``stat`` the files.

    .venv/bin/python benchmarks/fingerprint.py [--dataset synthbench] [--repeats 3]

The dataset is a synthetic one (built by its synth stage if needed) planned as a BOP
dataset on disk (a ``kind: bop`` manifest pointing at the generated folder), with a new
hash database for the first plan. Prints and writes a table to
``benchmarks/results/fingerprint.md``: files, bytes, the first plan's time, the later
plans' time (median of ``--repeats``), and their ratio.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthbench")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "fingerprint.md")
    args = ap.parse_args()

    from pipeline.common import config as cfg
    from pipeline.common.file_hashes import files_under
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.stage_graph import run_stage

    plan = RunPlan(cfg.load_run({"datasets": args.dataset}))[args.dataset]
    if not plan["synth"].manifest("dataset").exists():
        run_stage(plan, "synth", "dataset", progress=True)
    src = plan.root  # <synth item>/<name>: a BOP dataset folder
    ds = plan.dataset
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        manifest = tmp / f"{args.dataset}disk.yaml"
        manifest.write_text(f"name: {args.dataset}disk\nkind: bop\nfolder: {src.name}\nsplit: {ds.split}\n"
                            f"prior: {src.name}/{ds.prior}\n")
        run = cfg.load_run({"datasets": str(manifest), "bop_root": str(src.parent)})

        def plan_once() -> float:
            t0 = time.perf_counter()
            RunPlan(run, cache=tmp / "cache")[f"{args.dataset}disk"]
            return time.perf_counter() - t0

        first = plan_once()
        later = [plan_once() for _ in range(args.repeats)]
    files = files_under(src)
    size = sum(os.stat(p).st_size for p in files)
    text = ["# Planning cost of the content fingerprints", "",
            f"`benchmarks/fingerprint.py {' '.join(sys.argv[1:])}`: `{args.dataset}` planned as a BOP dataset on disk "
            "(every file of its folder is read by some stage; the first plan hashes them all, later plans compare "
            "size, mtime and inode with the remembered ones).", "",
            "| dataset | files | MB | first plan (s) | later plans (s, median) | first / later |", "|---|---|---|---|---|---|",
            f"| {args.dataset} | {len(files)} | {size / 1e6:.1f} | {first:.2f} | {statistics.median(later):.3f} | "
            f"{first / statistics.median(later):.0f}x |", ""]
    print("\n".join(text))
    args.out.write_text("\n".join(text))


if __name__ == "__main__":
    main()

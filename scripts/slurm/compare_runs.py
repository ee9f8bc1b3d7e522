#!/usr/bin/env python3
"""Compare the results of two runs of the pipeline on one dataset, each in its own
cache folder (FREEZE_CACHE): the BOP results CSV, every column but ``time``, and the
scores (AR, AR_VSD, AR_MSSD, AR_MSPD, the target and estimate counts, the recalls,
per object and per visibility) must be identical.

    compare_runs.py CACHE_A CACHE_B --dataset synthtiny

CACHE_A must hold exactly one scored configuration of the dataset (a fresh run); the
same artifact folders (same signatures) are then looked up in CACHE_B. Prints one line
and exits 0 when identical, else prints the first difference and exits 1.
scripts/cluster_check.sh uses it (the SLURM run against the local run). Stdlib only.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

IGNORED_COLUMNS = ("time",)
SUMMARY_KEYS = ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "n_targets", "n_estimates")
TABLE_KEYS = ("recalls", "per_object", "per_visibility")


class Different(Exception):
    """The two runs' results differ (the message says where)."""


def only_one(cache: Path, pattern: str, what: str) -> Path:
    found = sorted(cache.glob(pattern))
    if len(found) != 1:
        raise Different(f"{cache}: expected one {what} ({pattern}), found {len(found)}")
    return found[0]


def read_results(path: Path) -> tuple[list[str], list[list[str]]]:
    """Header and rows of a BOP results CSV without the ignored columns."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise Different(f"{path}: empty file")
    header, body = rows[0], rows[1:]
    keep = [i for i, name in enumerate(header) if name.strip() not in IGNORED_COLUMNS]
    return [header[i] for i in keep], [[row[i] for i in keep] for row in body]


def compare_results(a: Path, b: Path) -> int:
    """Number of rows; raises Different at the first difference."""
    ha, ra = read_results(a)
    hb, rb = read_results(b)
    if ha != hb:
        raise Different(f"results CSV columns differ: {ha} vs {hb}")
    if len(ra) != len(rb):
        raise Different(f"results CSV: {len(ra)} rows vs {len(rb)} rows")
    for n, (x, y) in enumerate(zip(ra, rb), start=2):
        if x != y:
            cols = [h for h, u, v in zip(ha, x, y) if u != v]
            raise Different(f"results CSV line {n} differs in {', '.join(cols)}: {x} vs {y}")
    return len(ra)


def compare_scores(a: Path, b: Path) -> float:
    """The AR; raises Different at the first difference."""
    sa, sb = json.loads(a.read_text()), json.loads(b.read_text())
    for key in SUMMARY_KEYS:
        va, vb = sa.get("summary", {}).get(key), sb.get("summary", {}).get(key)
        if va != vb:
            raise Different(f"scores.json summary.{key}: {va!r} vs {vb!r}")
    for key in TABLE_KEYS:
        if sa.get(key) != sb.get(key):
            raise Different(f"scores.json {key} differs")
    ar = sa.get("summary", {}).get("AR")
    if ar is None:
        raise Different(f"{a}: no summary.AR")
    return float(ar)


def compare_runs(cache_a: Path, cache_b: Path, dataset: str) -> str:
    """One line saying what was found identical; raises Different otherwise."""
    scores_a = only_one(cache_a, f"{dataset}/score/*/all/scores.json", "scores.json")
    csv_a = only_one(cache_a, f"{dataset}/refine/*/all/*.csv", "results CSV")
    scores_b = cache_b / scores_a.relative_to(cache_a)
    csv_b = cache_b / csv_a.relative_to(cache_a)
    for path in (scores_b, csv_b):
        if not path.is_file():
            raise Different(f"{path} is missing: the second run has not produced the same "
                            "configuration (other code, manifest or options?)")
    rows = compare_results(csv_a, csv_b)
    ar = compare_scores(scores_a, scores_b)
    return (f"identical: results CSV ({rows} rows, every column but time) and scores "
            f"(AR {ar:.4f}, AR_VSD/MSSD/MSPD, recalls, per object, per visibility)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cache_a", type=Path)
    ap.add_argument("cache_b", type=Path)
    ap.add_argument("--dataset", required=True)
    args = ap.parse_args(argv)
    try:
        print(compare_runs(args.cache_a, args.cache_b, args.dataset))
    except Different as e:
        print(f"different: {e}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

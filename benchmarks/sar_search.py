"""SAR's coarse-to-fine search replayed on exhaustive runs (run by hand).

    .venv/bin/python benchmarks/sar_search.py CACHE_DIR... [--coarse 60,90] [--leads 1,2,3]
        [--min-gain 0.005] [--out benchmarks/results/sar_search.md]

Reads every ``refine/*/*/sar.parquet`` under the given caches (``$FREEZE_CACHE`` folders
or a dataset's folder in one) and keeps the estimates whose every variant was scored
(runs with ``refine.sar_coarse_deg=0``, or made before the coarse-to-fine search); an
estimate found again with the same similarities (another refine version) counts once.
A variant's similarity does not depend on which other variants are scored, so the
coarse-to-fine search (:func:`pipeline.method.refinement.sar.coarse_variants`, then
:func:`~pipeline.method.refinement.sar.fine_variants`: those within ``coarse`` of the ``leads``
best) can be replayed exactly on those numbers, with the functions SAR itself calls
and SAR's rule (a variant replaces the ICP pose only when it beats it by more than
``min_gain``). Reported per setting: estimates, how many end with the same
variant as the exhaustive search, and the renders (= encoder images) needed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def choice(similarities: np.ndarray, min_gain: float) -> int:
    """SAR's choice among scored variants (NaN: not scored), variant 0 the ICP pose."""
    s = np.where(np.isnan(similarities), -np.inf, similarities)
    best = int(np.argmax(s))
    return best if s[best] > s[0] + min_gain else 0


def exhaustive_estimates(caches: list[Path]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, angles (V, V) deg, similarities (V,)) of every estimate scored exhaustively."""
    import pandas as pd

    from pipeline.method.refinement.sar import variant_angles

    out, seen = [], set()
    for cache in caches:
        for f in sorted(cache.glob("**/refine/*/*/sar.parquet")):
            df = pd.read_parquet(f)
            for cand_id, g in df.groupby("cand_id"):
                g = g.sort_values("variant")
                if len(g) < 3 or g.variant.tolist() != list(range(len(g))):
                    continue
                R = np.stack([np.reshape(r, (3, 3)) for r in g.R])
                S = np.zeros((len(R), 4, 4))
                S[:, :3, :3] = np.einsum("ji,vjk->vik", R[0], R)  # R_v = R_0 S_v
                label = f"{f.relative_to(cache).parts[0]} cand {cand_id}"
                sim = g.similarity.to_numpy(float)
                if (label, sim.tobytes()) in seen:  # the same estimate in another refine version
                    continue
                seen.add((label, sim.tobytes()))
                out.append((label, variant_angles(S), sim))
    return out


def replay(angles: np.ndarray, sim: np.ndarray, coarse: float, leads: int) -> np.ndarray:
    """The similarities the coarse-to-fine search would have (NaN where not scored)."""
    from pipeline.method.refinement.sar import coarse_variants, fine_variants

    first = coarse_variants(angles, coarse)
    fine = fine_variants(angles, first, sim, coarse, leads)
    out = np.full(len(sim), np.nan)
    out[first + fine] = sim[first + fine]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("caches", nargs="+", type=Path)
    ap.add_argument("--coarse", default="60,90")
    ap.add_argument("--leads", default="1,2,3")
    ap.add_argument("--min-gain", type=float, default=0.005)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sar_search.md")
    args = ap.parse_args()

    estimates = exhaustive_estimates(args.caches)
    if not estimates:
        raise SystemExit("sar_search: no exhaustively scored SAR estimate under " + ", ".join(map(str, args.caches)))
    sizes = sorted({len(s) for _, _, s in estimates})
    lines = ["# SAR: coarse-to-fine search against every variant", "",
             f"`benchmarks/sar_search.py {' '.join(sys.argv[1:])}`", "",
             f"{len(estimates)} estimates scored on every variant ({', '.join(map(str, sizes))} variants), "
             f"from: " + ", ".join(sorted({lab.split(' cand')[0] for lab, _, _ in estimates})) + ".", "",
             "| coarse (deg) | leads | same variant as every-variant search | renders | renders saved |",
             "|---|---|---|---|---|"]
    total = sum(len(s) for _, _, s in estimates)
    misses: list[str] = []
    for coarse in (float(c) for c in args.coarse.split(",")):
        for leads in (int(k) for k in args.leads.split(",")):
            same, renders = 0, 0
            for label, angles, sim in estimates:
                cf = replay(angles, sim, coarse, leads)
                a, b = choice(sim, args.min_gain), choice(cf, args.min_gain)
                same += a == b
                renders += int(np.isfinite(cf).sum() + np.isinf(cf).sum())
                if a != b:
                    misses.append(f"- coarse {coarse:g}, {leads} lead(s): {label}: variant {b} instead of {a} "
                                  f"({angles[a, b]:.0f} deg apart, similarity {sim[b]:.4f} against {sim[a]:.4f})")
            lines.append(f"| {coarse:g} | {leads} | {same} / {len(estimates)} | {renders} / {total} | "
                         f"{100 * (1 - renders / total):.0f} % |")
    lines += ["", "Different choices:" if misses else "No setting chose differently.", *misses]
    text = "\n".join(lines) + "\n"
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""Could a cheaper ranking choose refine's turns? (run by hand)

    .venv/bin/python benchmarks/turn_ranking.py --sets semilmo,realycbv,realycbv:faulty,tyol \\
        [--cache DIR] [--out benchmarks/results/turn_ranking.md]

refine aligns every turn of a candidate's best hypothesis
(:mod:`pipeline.method.refinement.turns`: its near-symmetries and the cube's quarter,
half and third turns, about 26 a candidate on semi-real LM-O) by a quick ICP (10
iterations at the coarsest correspondence distance), and keeps the ``refine.turns`` best
by that ICP's fitness, distinct from each other and from the parent
(:func:`pipeline.method.scene_side.kept_turns`). Those quick ICPs are about
a fifth of the scene side's time on semi-real LM-O
(``benchmarks/results/scene_side_profile_semilmo.md``).

This replays, on a run's cache (``bop_all`` of each set done there: refine's
``hypotheses.parquet`` names each turn's parent), every candidate's turns exactly as
refine makes them, and ranks them three cheaper ways: by the fitness of the turned start
before any iteration (one nearest-neighbour query), and after the first 1 and 3 of the
quick ICP's iterations. For each it reports where the turns refine keeps rank: were they
always among the first K, the full quick ICP of only those K would keep refine's choices.
The tables give, per set and ranking, the candidates whose kept turns all rank within K,
and, of the candidates whose chosen pose is a turn, those whose winning turn does (a
weaker test: another kept turn could then win).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

RANKINGS = {"start": 0, "1 iteration": 1, "3 iterations": 3}
"""The cheaper rankings: quick-ICP iterations run before the fitness is read (0: the turned start)."""
KS = (3, 5, 8, 10, 12, 16)


def replay(name: str, prior: str | None) -> list[dict]:
    """Every candidate with turns in the set's cached refine: its number of turns and, per
    ranking, the worst rank (0-based) of a turn refine kept."""
    from pipeline.common.config import load_run
    from pipeline.method.geometry.transforms import invert
    from pipeline.method.refinement.icp import IcpModel, refine_icp
    from pipeline.method.refinement.turns import model_turns, turned
    from pipeline.method.scene_side import icp_options, kept_turns, packed_points
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.prepared import prepared_objects

    config = {"datasets": name, **({"prior": prior} if prior else {})}
    plan = RunPlan(load_run(config))[name]
    p = plan.run.stages.refine
    rows = []
    for item in plan.scene_items:
        found = plan["refine"].item_dir(item) / "hypotheses.parquet"
        if not found.exists():
            raise SystemExit(f"turn_ranking: {found} is missing; run bop_all --config datasets={name} there first")
        hypotheses = pd.read_parquet(found)
        io = plan.io("refine", item)
        objects = prepared_objects(io, io.bop(), features=("points", "normals"), symmetries=True)
        scene = packed_points(io.arrays("scene_features", "features", names=["points", "n_points", "cand_id"]))
        prepared: dict[int, tuple] = {}
        for cand_id, g in hypotheses.groupby("cand_id"):
            turns_rows = g[g.source == "turn"]
            if not len(turns_rows):
                continue
            parent = g[g.hyp == int(turns_rows.parent.iloc[0])].iloc[0]
            obj_id = int(parent.obj_id)
            if obj_id not in prepared:
                o = objects[obj_id]
                T = model_turns(o.near_symmetries, o.features["points"], o.symmetries, o.diameter)
                prepared[obj_id] = (IcpModel(o.features["points"], o.features["normals"]), o.diameter, T)
            model, diameter, T = prepared[obj_id]
            points = np.asarray(scene(int(cand_id)), dtype=np.float64)
            R0, t0 = np.reshape(parent.R, (3, 3)), np.asarray(parent.t, dtype=np.float64)
            quick_options = icp_options(p, quick=True)

            def fitness_after(R, t, iterations: int) -> float:
                if iterations == 0:
                    Rc, tc = invert(R, t)
                    dist, _ = model.tree.query(points @ Rc.T + tc, distance_upper_bound=p.max_corr_frac * diameter)
                    return float((dist < np.inf).mean())
                return float(refine_icp(model, None, points, R, t, diameter,
                                        **(quick_options | {"iterations": iterations})).fitness)

            starts = [turned(R0, t0, Ti) for Ti in T]
            quick = [(res.R, res.t, res.fitness) for res in
                     (refine_icp(model, None, points, R, t, diameter, **quick_options) for R, t in starts)]
            kept = kept_turns(quick, R0, t0, p.turns, diameter)  # refine's own choice
            if len(kept) != len(turns_rows):  # the replay must be refine's own
                raise SystemExit(f"turn_ranking: {name} candidate {cand_id}: the replay keeps {len(kept)} turns, "
                                 f"refine kept {len(turns_rows)}")
            # The turn rows are numbered from first_hyp in the order of ``kept``.
            chosen = g[g.chosen & (g.source == "turn")]
            won = [kept[int(h) - int(turns_rows.hyp.min())] for h in chosen.hyp]
            row = {"cand_id": int(cand_id), "obj_id": obj_id, "n_turns": len(T), "n_kept": len(kept),
                   "turn_chosen": bool(won)}
            for label, iterations in RANKINGS.items():
                ranked = np.argsort([-fitness_after(R, t, iterations) for R, t in starts], kind="stable")
                position = {int(j): r for r, j in enumerate(ranked)}
                row[label] = max((position[j] for j in kept), default=-1)
                row[label + " (chosen)"] = position[won[0]] if won else -1
            rows.append(row)
    return rows


def section(label: str, rows: list[dict]) -> list[str]:
    with_kept = [r for r in rows if r["n_kept"]]
    turns = np.mean([r["n_turns"] for r in rows]) if rows else float("nan")
    out = [f"### {label}: {len(rows)} candidates with turns, {turns:.1f} turns each", "",
           "| ranking | " + " | ".join(f"kept within {k}" for k in KS) + " |",
           "|---|" + "---|" * len(KS)]
    for ranking in RANKINGS:
        cells = [f"{sum(r[ranking] < k for r in with_kept)} / {len(with_kept)}" for k in KS]
        out.append(f"| {ranking} | " + " | ".join(cells) + " |")
    won = [r for r in rows if r["turn_chosen"]]
    out += ["", f"The {len(won)} candidates whose pose is a turn: that turn within K", "",
            "| ranking | " + " | ".join(f"within {k}" for k in KS) + " |", "|---|" + "---|" * len(KS)]
    for ranking in RANKINGS:
        cells = [f"{sum(r[ranking + ' (chosen)'] < k for r in won)} / {len(won)}" for k in KS]
        out.append(f"| {ranking} | " + " | ".join(cells) + " |")
    return out + [""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", default="semilmo,realycbv,realycbv:faulty,tyol")
    ap.add_argument("--cache", type=Path, default=None, help="the runs' cache (default: FREEZE_CACHE's)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "turn_ranking.md")
    args = ap.parse_args()
    if args.cache:
        os.environ["FREEZE_CACHE"] = str(args.cache)
    lines = ["# Could a cheaper ranking choose refine's turns?", "",
             f"`benchmarks/turn_ranking.py {' '.join(sys.argv[1:])}` (see its docstring): for each candidate, the worst "
             "rank of a turn that refine keeps (by the full quick ICP's fitness) under a cheaper ranking; "
             "'kept within K' counts the candidates whose kept turns all rank among the first K.", ""]
    for entry in args.sets.split(","):
        name, _, prior = entry.partition(":")
        lines += section(entry, replay(name, prior or None))
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()

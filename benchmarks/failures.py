"""Why the estimates of a run are wrong (run by hand, after the run): each ground-truth
instance of each target classified by the first failure on its way through the method.

    .venv/bin/python benchmarks/failures.py --datasets realycbv,semilmo [--config prior=faulty] \\
        [--label NAME] [--out benchmarks/results/failures.md]

For each target instance (the kept estimate nearest to it by MSSD, with the dataset's
declared symmetries, as the scorer does), in this order:

- ``right``: MSSD at most 0.1 d (d: the object's diameter);
- ``no estimate``: the target got none (no candidate, or every candidate skipped);
- ``prior: no mask on it``: no candidate of the target covers the instance (mask IoU
  with its visible mask below 0.5): the prior's fault;
- ``wrong candidate chosen``: one did, but the estimate came from another;
- ``wrong symmetric twin chosen``: a refined hypothesis of the chosen candidate was
  right, but the one chosen is its (near-)symmetric twin: the shape fits (ADD-S, the mean
  closest-point distance, at most 0.05 d) in a pose the declared symmetries do not forgive;
- ``wrong hypothesis chosen``: a refined hypothesis was right, the one chosen is no twin;
- ``only a symmetric twin found``: no refined hypothesis was right, the estimate is a twin;
- ``ICP drift``: a coarse hypothesis was near (MSSD at most 0.2 d), no refined one right;
- ``coarse pose never found``: no coarse hypothesis came near.

The visible masks are the dataset's ``mask_visib`` where it has them, else its exact
prior (``detections/gtmask_*``, realycbv's label masks). Writes the section ``## <label>``
of ``--out`` (replacing an older section of that label): counts per kind, per object,
and the worst estimates.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

RIGHT = 0.1
"""MSSD / d at most which an estimate is right (the report's threshold)."""
NEAR = 0.2
"""MSSD / d at most which a coarse hypothesis is near enough for ICP to reach."""
TWIN = 0.05
"""ADD-S / d at most which a wrong pose still fits the shape: a symmetric twin. On
realycbv the twins lie at 0.016-0.027 d and the next wrong pose (the mustard bottle
turned upside down, standing out into free space) at 0.071 d."""
COVERS = 0.5
"""Mask IoU at least which a candidate covers an instance."""
KINDS = ["right", "no estimate", "prior: no mask on it", "wrong candidate chosen", "wrong symmetric twin chosen",
         "wrong hypothesis chosen", "only a symmetric twin found", "ICP drift", "coarse pose never found"]


def _scene_tables(plan, stage: str, name: str) -> pd.DataFrame:
    frames = [plan[stage].table(item, name) for item in plan.scene_items if plan[stage].path(item, name).exists()]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _pose(row) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(row.R, np.float64).reshape(3, 3), np.asarray(row.t, np.float64).reshape(3)


class Judge:
    """MSSD (declared symmetries) and ADD-S of poses against a ground-truth pose, in d."""

    def __init__(self, bop, plan, obj_id: int):
        from scipy.spatial import cKDTree

        from pipeline.evaluation.metrics.bop_symmetries import symmetry_transformations
        from pipeline.evaluation.metrics.pose_errors import hull_indices

        info = plan.model_info(bop, obj_id)
        pts = np.asarray(bop.load_model(obj_id, eval=True).vertices, np.float64)
        self.d = float(info.diameter)
        self.hull = pts[hull_indices(pts)]
        self.sym = symmetry_transformations(info.symmetries_discrete, info.symmetries_continuous)
        rng = np.random.default_rng(0)
        self.sample = pts[rng.choice(len(pts), min(len(pts), 1500), replace=False)]
        self._tree = cKDTree

    def mssd(self, R, t, gt) -> float:
        from pipeline.evaluation.metrics.pose_errors import mssd

        return mssd(R, t, gt.R, gt.t, self.hull, *self.sym) / self.d

    def adds(self, R, t, gt) -> float:
        est = self.sample @ R.T + t
        ref = self.sample @ gt.R.T + gt.t
        return float(self._tree(ref).query(est)[0].mean()) / self.d


def _visible_masks(plan, bop) -> dict[tuple[int, int, int], np.ndarray]:
    """(scene, image, obj) -> the exact prior's mask, when the dataset ships one (realycbv)."""
    from pipeline.formats.bop import load_detections

    out = {}
    for path in sorted((plan.root / "detections").glob("gtmask_*.json")):
        for d in load_detections(path):
            out[(d.scene_id, d.image_id, d.category_id)] = d.mask()
    return out


def classify(plan) -> pd.DataFrame:
    """One row per target instance: scene_id, im_id, obj_id, gt_id, kind, mssd (in d, of
    the estimate; NaN without one), score, cand_id."""
    from pipeline.evaluation.synth.priors import mask_iou
    from pipeline.formats.bop.detections import prior_row_mask

    bop = plan.bop()
    poses = _scene_tables(plan, "refine", "poses")
    hyps = _scene_tables(plan, "refine", "hypotheses")
    coarse = _scene_tables(plan, "register", "coarse_hypotheses")
    if not coarse.empty:
        coarse = coarse[coarse.status == "ok"]
    cands = plan["segment_prior"].table("all", "prior_candidates")
    shipped = _visible_masks(plan, bop)
    judges: dict[int, Judge] = {}
    rows = []
    targets = bop.targets(plan.root / plan.dataset.targets_file)
    for t in targets:
        gts = [(k, g) for k, g in enumerate(bop.scene_gt(t.scene_id)[t.im_id]) if g.obj_id == t.obj_id]
        judge = judges.setdefault(t.obj_id, Judge(bop, plan, t.obj_id))
        mine = poses[(poses.scene_id == t.scene_id) & (poses.im_id == t.im_id) & (poses.obj_id == t.obj_id)] \
            if not poses.empty else poses
        tc = cands[(cands.scene_id == t.scene_id) & (cands.im_id == t.im_id) & (cands.obj_id == t.obj_id)]
        cand_masks = {int(r.cand_id): prior_row_mask(r) for r in tc.itertuples()}
        if len(gts) > t.inst_count:  # the target counts the visible ones: keep the most visible
            infos = bop.scene_gt_info(t.scene_id)[t.im_id]
            gts = sorted(gts, key=lambda kg: -infos[kg[0]].visib_fract)[:t.inst_count]
        for gt_id, gt in gts:
            row = {"scene_id": t.scene_id, "im_id": t.im_id, "obj_id": t.obj_id, "gt_id": gt_id, "mssd": np.nan,
                   "score": np.nan, "cand_id": -1}
            if mine.empty:
                rows.append({**row, "kind": "no estimate"})
                continue
            errs = [judge.mssd(*_pose(p), gt) for p in mine.itertuples()]
            best = int(np.argmin(errs))
            est = mine.iloc[best]
            row.update(mssd=errs[best], score=float(est.score), cand_id=int(est.cand_id))
            if errs[best] <= RIGHT:
                rows.append({**row, "kind": "right"})
                continue
            visible = _gt_visible(bop, shipped, t, gt_id)
            if visible is not None and cand_masks:
                covers = {c: mask_iou(m, visible) for c, m in cand_masks.items()}
                if max(covers.values()) < COVERS:
                    rows.append({**row, "kind": "prior: no mask on it"})
                    continue
                if covers.get(int(est.cand_id), 0.0) < COVERS:
                    rows.append({**row, "kind": "wrong candidate chosen"})
                    continue
            twin = judge.adds(*_pose(est), gt) <= TWIN
            ch = hyps[hyps.cand_id == est.cand_id] if not hyps.empty else hyps
            if any(judge.mssd(*_pose(h), gt) <= RIGHT for h in ch.itertuples()):
                rows.append({**row, "kind": "wrong symmetric twin chosen" if twin else "wrong hypothesis chosen"})
                continue
            if twin:
                rows.append({**row, "kind": "only a symmetric twin found"})
                continue
            cc = coarse[coarse.cand_id == est.cand_id] if not coarse.empty else coarse
            near = any(judge.mssd(*_pose(h), gt) <= NEAR for h in cc.itertuples())
            rows.append({**row, "kind": "ICP drift" if near else "coarse pose never found"})
    return pd.DataFrame(rows)


def _gt_visible(bop, shipped, t, gt_id: int) -> np.ndarray | None:
    path = bop.scene_dir(t.scene_id) / "mask_visib" / f"{t.im_id:06d}_{gt_id:06d}.png"
    if path.exists():
        return bop.load_mask(t.scene_id, t.im_id, gt_id, visib=True)
    return shipped.get((t.scene_id, t.im_id, t.obj_id))


def section(label: str, command: str, results: dict[str, pd.DataFrame]) -> str:
    lines = [f"## {label}", "", f"`{command}`", ""]
    for name, df in results.items():
        n = len(df)
        counts = df.kind.value_counts()
        lines += [f"### {name} ({n} target instances)", "",
                  "| kind | instances | share |", "|---|---|---|"]
        lines += [f"| {k} | {int(counts.get(k, 0))} | {counts.get(k, 0) / max(1, n):.0%} |" for k in KINDS
                  if counts.get(k, 0)]
        objs = sorted(df.obj_id.unique())
        lines += ["", "| object | " + " | ".join(k for k in KINDS if counts.get(k, 0)) + " |",
                  "|---|" + "---|" * sum(1 for k in KINDS if counts.get(k, 0))]
        for o in objs:
            c = df[df.obj_id == o].kind.value_counts()
            lines.append(f"| {o} | " + " | ".join(str(int(c.get(k, 0))) for k in KINDS if counts.get(k, 0)) + " |")
        worst = df[df.kind != "right"].sort_values("mssd", ascending=False, na_position="first").head(8)
        if len(worst):
            lines += ["", "The worst: " + "; ".join(
                f"obj {r.obj_id} scene {r.scene_id} image {r.im_id} ({r.kind}, MSSD {r.mssd:.2f} d)"
                for r in worst.itertuples())]
        lines.append("")
    return "\n".join(lines) + "\n"


def write_section(out: Path, label: str, text: str) -> None:
    old = out.read_text() if out.exists() else "# Failure kinds\n\nMade by `benchmarks/failures.py` (see its docstring).\n\n"
    pattern = re.compile(rf"^## {re.escape(label)}\n.*?(?=^## |\Z)", re.S | re.M)
    new = pattern.sub(lambda _: text, old) if pattern.search(old) else old.rstrip("\n") + "\n\n" + text
    out.write_text(new)


def main() -> None:
    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", required=True)
    ap.add_argument("--config", action="append", default=[], help="run override key=value (repeatable)")
    ap.add_argument("--label", default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "failures.md")
    args = ap.parse_args()
    overrides = dict(c.split("=", 1) for c in args.config)
    results = {}
    for name in args.datasets.split(","):
        plan = RunPlan(cfg.load_run({"datasets": name, **overrides}))[name]
        if not plan["score"].manifest("all").exists():
            raise SystemExit(f"{name}: not scored yet with {overrides or 'the default run'}: run "
                             f"snakemake --cores 2 bop_all --config datasets={name} first")
        results[name] = classify(plan)
        print(name, results[name].kind.value_counts().to_dict())
    label = args.label or (" ".join(f"{k}={v}" for k, v in overrides.items()) or "default")
    command = "benchmarks/failures.py " + shlex.join(sys.argv[1:])
    write_section(args.out, label, section(label, command, results))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Realistic benchmarks (run by hand): AR per object on the real and semi-real sets, under
several seed sets, with the geometry-only and vision-only ablations.

    .venv/bin/python benchmarks/real.py --label before --datasets tyol,semilmo --seeds 0,1,2 \\
        --configs default,visual=none,geometric=none

For each configuration and seed set this runs ``snakemake --cores N bop_all --config
datasets=D run=<seed manifest> [KEY=VALUE]`` (a run manifest extending the default with
``scene_features.seed`` and ``register.seed`` set to the seed; seed 0 is the default
run; artifacts already in the cache are reused) and reads the score artifacts: AR and
its parts, AR per object, and, for a dataset with a single target (the TYO-L frame),
the pose's rotation and translation errors and its MSSD in diameters (right: MSSD below
0.1 d). Writes the section ``## <label>`` of ``benchmarks/results/real.md`` (replacing
an older section of that label, keeping the others).

The semi-real datasets are built from ../shared/realdata by the ``synth`` stage
(``manifests/datasets/semilmo.yaml``, ``tyol.yaml``); without ../shared they are skipped
and this script stops.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ablations import run_config  # noqa: E402

RIGHT_MSSD = 0.1
"""A single pose is right when its MSSD is below this fraction of the diameter."""


def tyol_frame():
    """The TYO-L dataset's one frame, built by its synth stage when needed: (reader
    (:class:`pipeline.formats.bop.BopDataset`), scene id, image id, ground-truth pose
    (:class:`pipeline.formats.bop.GtPose`), diameter mm). Stops with the reason when
    ../shared is absent."""
    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan
    from pipeline.workflow.stage_graph import run_stage

    rp = RunPlan(cfg.load_run({"datasets": "tyol"}))
    ok, why = rp.available("tyol")
    if not ok:
        raise SystemExit(why)
    plan = rp["tyol"]
    if not plan["synth"].manifest("dataset").exists():
        run_stage(plan, "synth", "dataset", progress=True)
    ds = plan.bop()
    (scene_id,) = ds.scene_ids()
    (im_id,) = ds.image_ids(scene_id)
    gt = ds.scene_gt(scene_id)[im_id][0]
    return ds, scene_id, im_id, gt, ds.models_info()[gt.obj_id].diameter


def seed_manifest(folder: Path, seed: int) -> Path:
    """A run manifest: the default one with the scene-side seeds set to ``seed``."""
    path = folder / f"seed{seed}.yaml"
    path.write_text(f"extends: {ROOT / 'manifests' / 'runs' / 'default.yaml'}\n"
                    f"stages:\n  scene_features: {{seed: {seed}}}\n  register: {{seed: {seed}}}\n")
    return path


def single_pose_errors(config: dict[str, str]) -> dict[str, float]:
    """Rotation (deg), translation (mm) and MSSD (diameters) of the estimate of a
    dataset's single target, from the refine and score artifacts of ``config``'s plan."""
    from pipeline.common.config import load_run
    from pipeline.method.geometry.transforms import rotation_angle_deg
    from pipeline.workflow.plan import RunPlan
    from pipeline.common.store import read_table

    plan = RunPlan(load_run(config))[config["datasets"]]
    bop = plan.bop()
    (scene_id,) = plan.scene_ids
    (item,) = plan.items_of_scene(scene_id)
    poses = read_table(plan["refine"].item_dir(item) / "poses.parquet")
    if len(poses) != 1:
        return {"rot_deg": float("nan"), "trans_mm": float("nan"), "mssd_d": float("nan")}
    p = poses.iloc[0]
    gt = bop.scene_gt(scene_id)[int(p.im_id)][0]
    errors = read_table(plan["score"].item_dir("all") / "errors.parquet")
    diameter = bop.models_info()[gt.obj_id].diameter
    return {"rot_deg": rotation_angle_deg(np.reshape(p.R, (3, 3)), gt.R),
            "trans_mm": float(np.linalg.norm(np.asarray(p.t) - gt.t)),
            "mssd_d": float(errors.mssd.min() / diameter)}


def section(label: str, command: str, rows: list[dict]) -> str:
    """The markdown section of one run of this script."""
    out = [f"## {label}", "", f"`{command}`", ""]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        sel = [r for r in rows if r["dataset"] == dataset]
        objs = sorted({int(o["obj_id"]) for r in sel for o in r["per_object"]})
        single = all("rot_deg" in r for r in sel)
        head = ["config", "seed", "AR", "VSD", "MSSD", "MSPD"] + (["rot err (deg)", "trans err (mm)", "MSSD / d", "right"]
                                                                 if single else [f"AR obj {o}" for o in objs])
        out += [f"### {dataset} ({sel[0]['n_targets']} targets)", "", "| " + " | ".join(head) + " |",
                "|" + "---|" * len(head)]
        for r in sel:
            s = r["scores"]
            cells = [r["config"], str(r["seed"]), f"{s['AR']:.3f}", f"{s['AR_VSD']:.3f}", f"{s['AR_MSSD']:.3f}",
                     f"{s['AR_MSPD']:.3f}"]
            if single:
                cells += [f"{r['rot_deg']:.1f}", f"{r['trans_mm']:.1f}", f"{r['mssd_d']:.3f}",
                          "yes" if r["mssd_d"] < RIGHT_MSSD else "no"]
            else:
                per = {int(o["obj_id"]): o["AR"] for o in r["per_object"]}
                cells += [f"{per[o]:.3f}" if o in per else "-" for o in objs]
            out.append("| " + " | ".join(cells) + " |")
        for config in dict.fromkeys(r["config"] for r in sel):
            ars = [r["scores"]["AR"] for r in sel if r["config"] == config]
            out.append(f"\n{config}: mean AR {np.mean(ars):.3f}, spread over seeds {min(ars):.3f}-{max(ars):.3f}"
                       + (f"; right in {sum(r['mssd_d'] < RIGHT_MSSD for r in sel if r['config'] == config)} of "
                          f"{len(ars)} seeds" if single else ""))
        out.append("")
    return "\n".join(out) + "\n"


def write_section(path: Path, label: str, text: str) -> None:
    """Replace or add the section ``## label`` of ``path``."""
    head = ("# Realistic benchmarks\n\nMade by `benchmarks/real.py` (see its docstring). Semi-real LM-O: real images, "
            "depth rendered from the ground truth; TYO-L: one real RGB-D frame with the exact mask as its prior.\n\n")
    old = path.read_text() if path.exists() else head
    parts = re.split(r"(?m)^(?=## )", old)
    kept = [p for p in parts if not p.startswith(f"## {label}\n")]
    path.write_text("".join(kept).rstrip("\n") + "\n\n" + text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", required=True, help="the section's title, e.g. 'before' or a commit")
    ap.add_argument("--datasets", default="tyol,semilmo")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--configs", default="default,visual=none,geometric=none",
                    help="comma-separated: 'default' or KEY=VALUE overrides (visual=none, ...)")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "real.md")
    args = ap.parse_args()

    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for dataset in args.datasets.split(","):
            ok, why = RunPlan(cfg.load_run({"datasets": dataset})).available(dataset)
            if not ok:
                raise SystemExit(why)
            for config in args.configs.split(","):
                extra = dict([config.split("=", 1)]) if config != "default" else {}
                for seed in (int(s) for s in args.seeds.split(",")):
                    conf = {"datasets": dataset, "run": str(seed_manifest(Path(tmp), seed)), **extra}
                    r = run_config(conf, f"{dataset} {config} seed {seed}", cores=args.cores)
                    row = {"dataset": dataset, "config": config, "seed": seed, "scores": r.scores,
                           "per_object": r.per_object, "n_targets": r.n_targets}
                    if r.n_targets == 1:
                        row.update(single_pose_errors(conf))
                    rows.append(row)
                    print(f"{dataset} {config} seed {seed}: AR {r.scores['AR']:.3f}"
                          + (f", {row['rot_deg']:.1f} deg, {row['trans_mm']:.1f} mm" if "rot_deg" in row else ""),
                          flush=True)
    text = section(args.label, "benchmarks/real.py " + " ".join(sys.argv[1:]), rows)
    write_section(args.out, args.label, text)
    print(text)


if __name__ == "__main__":
    main()

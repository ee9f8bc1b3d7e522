"""``freeze estimate`` on the real TYO-L frame, as a user runs it (run by hand): with the
ground-truth mask and with the ground-truth box alone, over seeds.

    .venv/bin/python benchmarks/estimate_tyol.py --label "after" [--seeds 0,1,2]

The frame is ``../shared/realdata/tyol-obj19-frame10`` (a wicker basket; one real RGB-D
image with its ground-truth pose). Its mask is the model rendered at the ground-truth
pose where it agrees with the sensor's depth (as the ``tyol`` dataset's prior, built by
the synth stage); the box is that mask's bounding box. For each mode and seed this runs
``freeze estimate --model --rgb --depth --camera --mask|--bbox -c scene_features.seed=S
-c register.seed=S [-c KEY=VALUE ...]`` and reads ``pose.json``: rotation and translation errors, MSSD in
diameters (right: below 0.1 d). Box mode also reports the share of the kept depth points
within 5 mm of the model at the ground-truth pose. Writes the section ``## <label>:
freeze estimate on the TYO-L frame`` of ``benchmarks/results/real.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from real import RIGHT_MSSD, tyol_frame, write_section  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", required=True)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("-c", "--config", action="append", default=[],
                    help="more run overrides for freeze estimate, KEY=VALUE (e.g. symmetries.threshold=0.005)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "real.md")
    args = ap.parse_args()

    from scipy.spatial import cKDTree

    from pipeline.common import config as cfg
    from pipeline.formats.bop import load_detections
    from pipeline.formats.bop.dataset import save_mask_png
    from pipeline.method.geometry.depth import lift_depth
    from pipeline.method.geometry.crops import mask_to_bbox
    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.geometry.transforms import rotation_angle_deg
    from pipeline.evaluation.metrics.pose_errors import mssd

    ds, scene_id, im_id, gt, diameter = tyol_frame()
    mask = ds.load_mask(scene_id, im_id, 0)
    bbox = mask_to_bbox(mask)
    mesh = ds.load_model(gt.obj_id)
    surface = cKDTree(sample_surface(mesh, 200000, seed=0)[0] @ gt.R.T + gt.t)
    K = ds.scene_camera(scene_id)[im_id].K
    src = cfg.shared_root() / "realdata" / "tyol-obj19-frame10"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_mask_png(tmp / "mask.png", mask)
        camera = tmp / "camera.json"
        camera.write_text(json.dumps({"cam_K": K.reshape(9).tolist(), "depth_scale": 1.0}))
        common = ["--model", str(src / "models" / f"obj_{gt.obj_id:06d}.ply"),
                  "--rgb", str(src / "test" / f"{scene_id:06d}" / "rgb" / f"{im_id:06d}.png"),
                  "--depth", str(src / "test" / f"{scene_id:06d}" / "depth" / f"{im_id:06d}.png"),
                  "--camera", str(camera), "--no-progress"]
        env = dict(os.environ, FREEZE_CACHE=str(tmp / "cache"))
        for mode, prior in (("mask", ["--mask", str(tmp / "mask.png")]),
                            ("box", ["--bbox", ",".join(str(int(v)) for v in bbox)])):
            for seed in (int(s) for s in args.seeds.split(",")):
                out = tmp / f"{mode}{seed}"
                cmd = [str(Path(sys.executable).parent / "freeze"), "estimate", *common, *prior, "--out", str(out),
                       "-c", f"scene_features.seed={seed}", "-c", f"register.seed={seed}",
                       *[a for kv in args.config for a in ("-c", kv)]]
                proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
                if proc.returncode != 0:
                    raise SystemExit(f"{mode} seed {seed}: freeze estimate failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
                rec = json.loads((out / "pose.json").read_text())
                R, t = np.asarray(rec["R"]), np.asarray(rec["t"])
                row = {"mode": mode, "seed": seed, "rot": rotation_angle_deg(R, gt.R),
                       "trans": float(np.linalg.norm(t - gt.t)),
                       "mssd": mssd(R, t, gt.R, gt.t, np.asarray(mesh.vertices)) / diameter,
                       "source": rec["hypothesis"]["source"], "near": float("nan")}
                if mode == "box":  # the kept points are the prior estimate wrote: the box rule's pixels
                    (det,) = load_detections(next((out / "bop" / "detections").glob("*.json")))
                    pts, _ = lift_depth(ds.load_depth(scene_id, im_id), K, det.mask())
                    row["near"] = float(np.mean(surface.query(pts)[0] < 5.0))
                rows.append(row)
                print(f"{mode} seed {seed}: {row['rot']:.1f} deg, {row['trans']:.1f} mm, MSSD {row['mssd']:.3f} d",
                      flush=True)
    title = f"{args.label}: freeze estimate on the TYO-L frame"
    text = [f"## {title}", "", f"`benchmarks/estimate_tyol.py {' '.join(sys.argv[1:])}`", "",
            "| prior | seed | rot err (deg) | trans err (mm) | MSSD / d | right | chosen hypothesis | kept points within 5 mm |",
            "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        text.append(f"| {r['mode']} | {r['seed']} | {r['rot']:.1f} | {r['trans']:.1f} | {r['mssd']:.3f} | "
                    f"{'yes' if r['mssd'] < RIGHT_MSSD else 'no'} | {r['source']} | "
                    + ("-" if np.isnan(r["near"]) else f"{100 * r['near']:.0f} %") + " |")
    for mode in ("mask", "box"):
        n = sum(r["mssd"] < RIGHT_MSSD for r in rows if r["mode"] == mode)
        text.append(f"\n{mode}: right in {n} of {sum(r['mode'] == mode for r in rows)} seeds")
    write_section(args.out, title, "\n".join(text) + "\n")


if __name__ == "__main__":
    main()

"""How far the TYO-L frame can tell its basket from the basket turned half a turn about
its vertical axis (run by hand; the measurement behind the issue-13 notes).

    .venv/bin/python benchmarks/tyol_flip.py

For the ground-truth pose and the same pose turned 180 degrees about the model's z axis
(the best-fitting turn, found by ICP of the model onto itself), each refined by the
pipeline's ICP on the frame's depth, it reports:

- the turn's own fit: the model's surface mean / 90th percentile / max distance to
  itself after the turn (mm), and its MSSD (the error BOP charges for it, in diameters);
- the verification terms (silhouette, depth fit, coverage, free space) against the
  sensor's depth and the ground-truth mask, as refine computes them;
- the photometric agreement of the textured model rendered at the pose with the real
  image inside the mask: zero-mean normalised cross-correlation of the grey levels
  (raw and blurred by 4 px) and the mean |cos| of the gradient directions.

Writes the section ``## TYO-L: the basket and its half turn`` of
``benchmarks/results/real.md``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from real import tyol_frame, write_section  # noqa: E402


def _zncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def main() -> None:
    import cv2
    from scipy.spatial import cKDTree

    from pipeline.method.refinement.icp import refine_icp
    from pipeline.method.geometry.depth import lift_depth
    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.geometry.transforms import rotation_angle_deg
    from pipeline.evaluation.metrics.pose_errors import mssd
    from pipeline.method.refinement.verification import verification_window, verify_pose
    from pipeline.method.geometry.crops import mask_to_bbox
    from pipeline.method.render.renderer import Renderer

    ds, scene_id, im_id, gt, d = tyol_frame()
    mesh = ds.load_model(gt.obj_id)
    K = ds.scene_camera(scene_id)[im_id].K
    depth = ds.load_depth(scene_id, im_id)
    mask = ds.load_mask(scene_id, im_id, 0)
    grey = cv2.cvtColor(ds.load_rgb(scene_id, im_id), cv2.COLOR_RGB2GRAY).astype(np.float32)
    pts, normals = sample_surface(mesh, 20000, seed=0)

    # The half turn about z that fits the model best: ICP of the model onto itself.
    Rz = np.diag([-1.0, -1.0, 1.0])
    turn = refine_icp(pts, normals, pts, Rz, np.zeros(3), d)
    Rt, tt = turn.R, turn.t  # model -> model: x -> Rt x + tt, near the half turn
    self_dist = cKDTree(pts).query(pts @ Rt.T + tt)[0]
    verts = np.asarray(mesh.vertices)

    scene_pts, _ = lift_depth(depth, K, mask)
    window = verification_window(mask_to_bbox(mask), depth.shape)
    tol = max(5.0, 0.05 * d)
    rows = []
    with Renderer(depth.shape[1], depth.shape[0]) as renderer:
        renderer.add_mesh("m", mesh)
        for name, R0, t0 in (("ground truth", gt.R, gt.t), ("half turn about z", gt.R @ Rt, gt.R @ tt + gt.t)):
            icp = refine_icp(pts, normals, scene_pts, R0, t0, d)
            v = verify_pose(renderer, "m", icp.R, icp.t, K, depth, mask, window, tol)
            colour, rendered = renderer.render([("m", icp.R, icp.t)], K)
            on = (rendered > 0) & mask
            r = cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY).astype(np.float32)
            blur = lambda im: cv2.GaussianBlur(im, (0, 0), 4)  # noqa: E731
            gr = [cv2.Sobel(cv2.GaussianBlur(im, (0, 0), 1.5), cv2.CV_32F, *o) for im in (r, grey)
                  for o in ((1, 0), (0, 1))]
            cos = np.abs(gr[0] * gr[2] + gr[1] * gr[3]) / (np.hypot(gr[0], gr[1]) * np.hypot(gr[2], gr[3]) + 1e-6)
            rows.append((name, rotation_angle_deg(icp.R, gt.R), mssd(icp.R, icp.t, gt.R, gt.t, verts) / d, v,
                         _zncc(r[on], grey[on]), _zncc(blur(r)[on], blur(grey)[on]), float(cos[on].mean())))
    text = ["## TYO-L: the basket and its half turn", "", "`benchmarks/tyol_flip.py`", "",
            f"The model turned by {rotation_angle_deg(Rt, np.eye(3)):.1f} deg about its z axis (and shifted "
            f"{np.linalg.norm(tt):.1f} mm) lies on itself: surface distance mean {self_dist.mean():.1f} mm, 90th "
            f"percentile {np.percentile(self_dist, 90):.1f} mm, max {self_dist.max():.1f} mm (diameter {d:.0f} mm; "
            "no symmetry is declared in models_info.json, so BOP counts the turn as wrong).", "",
            "| pose (then ICP on the frame) | rot err (deg) | MSSD / d | silhouette | depth fit | coverage | free space "
            "| grey NCC | grey NCC, 4 px blur | gradient |cos| |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name, rot, m, v, ncc, ncc4, cos in rows:
        text.append(f"| {name} | {rot:.1f} | {m:.3f} | {v.silhouette:.3f} | {v.depth_fit:.3f} | {v.coverage:.3f} | "
                    f"{v.free_space:.3f} | {ncc:+.3f} | {ncc4:+.3f} | {cos:.3f} |")
    print("\n".join(text))
    write_section(ROOT / "benchmarks" / "results" / "real.md", "TYO-L: the basket and its half turn",
                  "\n".join(text) + "\n")


if __name__ == "__main__":
    main()

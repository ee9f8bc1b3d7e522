"""Coarse registration side by side with Open3D's feature-matching RANSAC (run by hand).

    PYOPENGL_PLATFORM=egl HF_HUB_OFFLINE=1 .venv/bin/python benchmarks/coarse_vs_open3d.py \
        --views 10 --threads 1,2 [--write]

Cases: the views of ``benchmarks/registration.py`` (the 3 procedural objects, 10 random
views each, normal and ``--hard``: other lighting, 1 mm depth noise, 20-40 % occlusion),
FPFH radii (0.3, 0.4) on 5000 model surface samples and M = 1000 scene points, with
two feature sets: ``fused`` (FPFH + colortex through the per-object PCA, the paper's
fusion) and ``geometric`` (FPFH alone). Both backends get exactly the same points and
features of a case (computed once, cached in ``--cases``):

- ``ours``: :func:`pipeline.method.registration.ransac.ransac_hypotheses` as
  ``scene_side.coarse_hypotheses`` calls it (inlier 0.05 d, 50000 iterations at most,
  confidence 0.999, no mutual filter, k = 3 hypotheses, NMS 30 deg / 0.2 d), including
  its feature matching, refits and scores; its first hypothesis is the pose;
- ``open3d``: ``registration_ransac_based_on_feature_matching`` with the scene as the
  source and the model as the target (so its correspondences are, like ours, each scene
  point's nearest model point in feature space), no mutual filter (the pipeline's
  default), max correspondence distance 0.05 d, point-to-point estimation, ransac_n 3,
  checkers edge length 0.9 and distance 0.05 d, ``RANSACConvergenceCriteria(50000,
  0.999)``; its scene-to-model transform is inverted.

The two run interleaved per case (the order alternating from case to case), each in a
worker process limited to the same number of threads (OpenMP / OpenBLAS environment and
``o3d.utility.set_max_threads``). Success: ADD of the coarse pose below 0.1 d (mean
distance of the model samples under the estimate and the ground truth; the objects are
asymmetric), and below 0.2 d. ``--write`` writes ``benchmarks/results/coarse_registration.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

ROOT = Path(__file__).resolve().parent.parent


def build_cases(views: int, cache: Path) -> dict[str, Any]:
    """Models and cases of the registration benchmark, normal and hard views; cached."""
    if cache.exists():
        with open(cache, "rb") as f:
            return pickle.load(f)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "tests"))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import numpy as np
    from registration import prepare_model
    from registration_scenes import OBJECT_KINDS, SCENE_WH, harden_view, make_object, random_scene_pose, \
        render_scene, scene_inputs

    from pipeline.method.encoders.colortex import ColorTexEncoder
    from pipeline.method.encoders.fpfh import FpfhEncoder
    from pipeline.method.encoders.lifting import lift_scene_visual_features, mask_to_bbox
    from pipeline.method.registration.fusion import apply_pca, fuse
    from pipeline.method.render.renderer import Light, Lighting, Renderer

    enc, vis = FpfhEncoder(radii=(0.3, 0.4)), ColorTexEncoder()
    scene_r, tmpl_r = Renderer(*SCENE_WH), Renderer(vis.input_size, vis.input_size)
    models, cases = {}, []
    for kind in OBJECT_KINDS:
        mesh = make_object(kind, seed=1)
        scene_r.add_mesh(kind, mesh)
        tmpl_r.add_mesh(kind, mesh)
        model = prepare_model(mesh, tmpl_r, kind, [enc], vis)
        g_model = model.geometric[tuple(enc.radii)]
        models[kind] = {"points": model.points, "diameter": model.diameter,
                        "fused": fuse(g_model, apply_pca(model.pca, model.visual)), "geometric": fuse(g_model, None)}
        for hard in (False, True):
            # The registration benchmark's views: same generator seed, same lighting.
            rng = np.random.default_rng(123)
            if hard:
                light = Lighting(ambient=(0.2, 0.2, 0.2), lights=[Light(direction=(0.6, 0.5, 0.6), intensity=2.5)])
                vs = [harden_view(render_scene(scene_r, kind, *random_scene_pose(rng), lighting=light), rng)
                      for _ in range(views)]
            else:
                vs = [render_scene(scene_r, kind, *random_scene_pose(rng)) for _ in range(views)]
            for i, v in enumerate(vs):
                pts, nrm, pix = scene_inputs(v, model.diameter, 1000, i)
                g = enc.encode(pts, nrm, model.diameter)
                vf = lift_scene_visual_features(v.rgb, mask_to_bbox(v.mask), pix, vis)
                cases.append({"kind": kind, "hard": hard, "view": i, "points": pts, "R": v.R, "t": v.t,
                              "fused": fuse(g, apply_pca(model.pca, vf)), "geometric": fuse(g, None)})
        print(f"{kind}: {len(cases)} cases so far", flush=True)
    data = {"models": models, "cases": cases}
    cache.parent.mkdir(parents=True, exist_ok=True)
    with open(cache, "wb") as f:
        pickle.dump(data, f)
    return data


def worker(cases_path: Path, threads: int, repeats: int, out: Path, baseline: Path | None = None) -> None:
    """Time both backends on every case with ``threads`` threads; JSON rows to ``out``.
    ``baseline``: an older copy of ``ransac.py`` timed as a third backend, ``before``."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(threads)
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import open3d as o3d

    from pipeline.method.registration.ransac import RansacParams, ransac_hypotheses

    o3d.utility.set_max_threads(threads)
    reg = o3d.pipelines.registration
    with open(cases_path, "rb") as f:
        data = pickle.load(f)
    params = RansacParams(inlier_frac=0.05, max_iterations=50000, confidence=0.999, mutual=False)

    def ours(m: dict, c: dict, feats: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
        h = ransac_hypotheses(m["points"], m[feats], c["points"], c[feats], m["diameter"], params=params,
                              seed=seed, k=3, nms_deg=30.0, nms_frac=0.2)
        return h[0].R, h[0].t

    def open3d(m: dict, c: dict, feats: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
        thr = 0.05 * m["diameter"]
        o3d.utility.random.seed(seed)
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(c["points"], np.float64)))
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(m["points"], np.float64)))
        fs, ft = reg.Feature(), reg.Feature()
        fs.data = np.asarray(c[feats], np.float64).T
        ft.data = np.asarray(m[feats], np.float64).T
        res = reg.registration_ransac_based_on_feature_matching(
            source, target, fs, ft, False, thr, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(thr)],
            reg.RANSACConvergenceCriteria(50000, 0.999))
        T = np.linalg.inv(np.asarray(res.transformation))  # scene -> model, inverted
        return T[:3, :3], T[:3, 3]

    backends = {"ours": ours, "open3d": open3d}
    if baseline is not None:
        import importlib.util

        spec = importlib.util.spec_from_file_location("ransac_before", baseline)
        before_mod = importlib.util.module_from_spec(spec)
        sys.modules["ransac_before"] = before_mod  # dataclasses look their module up
        spec.loader.exec_module(before_mod)

        def before(m: dict, c: dict, feats: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
            known = before_mod.RansacParams.model_fields
            p = before_mod.RansacParams(**{k: v for k, v in params.model_dump().items() if k in known})
            h = before_mod.ransac_hypotheses(m["points"], m[feats], c["points"], c[feats], m["diameter"], params=p,
                                             seed=seed, k=3, nms_deg=30.0, nms_frac=0.2)
            return h[0].R, h[0].t

        backends["before"] = before
    rows = []
    for i, c in enumerate(data["cases"]):
        m = data["models"][c["kind"]]
        for feats in ("fused", "geometric"):
            # Rotate the order from case to case so that no backend always runs first.
            names = list(backends)
            shift = (2 * i + (feats == "geometric")) % len(names)
            order = names[shift:] + names[:shift]
            for name in order:
                times = []
                for r in range(repeats):
                    t0 = time.perf_counter()
                    R, t = backends[name](m, c, feats, c["view"])
                    times.append(time.perf_counter() - t0)
                mp = m["points"]
                add = float(np.mean(np.linalg.norm(mp @ R.T + t - (mp @ c["R"].T + c["t"]), axis=1)))
                rows.append({"backend": name, "feats": feats, "hard": c["hard"], "kind": c["kind"], "view": c["view"],
                             "time": min(times), "add_d": add / m["diameter"]})
    out.write_text(json.dumps(rows))


def summarise(rows: list[dict], threads: int) -> list[str]:
    """Markdown table rows: per feature set and view set, per backend."""
    import numpy as np

    lines = []
    for feats in ("fused", "geometric"):
        for hard in (False, True):
            sel = {b: [r for r in rows if r["feats"] == feats and r["hard"] == hard and r["backend"] == b]
                   for b in ("ours", "open3d", "before")}
            before = sel.pop("before")
            med = {b: float(np.median([r["time"] for r in s])) * 1e3 for b, s in sel.items()}
            tot = {b: float(np.sum([r["time"] for r in s])) for b, s in sel.items()}
            ok1 = {b: sum(r["add_d"] < 0.1 for r in s) for b, s in sel.items()}
            ok2 = {b: sum(r["add_d"] < 0.2 for r in s) for b, s in sel.items()}
            n = len(sel["ours"])
            extra = ""
            if before:
                extra = (f" {np.median([r['time'] for r in before]) * 1e3:.1f} ms,"
                         f" {np.sum([r['time'] for r in before]) / tot['ours']:.2f}x,"
                         f" {sum(r['add_d'] < 0.1 for r in before)} |")
            lines.append(f"| {threads} | {feats} | {'hard' if hard else 'normal'} | {n} "
                         f"| {med['ours']:.1f} / {med['open3d']:.1f} | {tot['ours']:.2f} / {tot['open3d']:.2f} "
                         f"| {tot['open3d'] / tot['ours']:.2f}x "
                         f"| {ok1['ours']} / {ok1['open3d']} | {ok2['ours']} / {ok2['open3d']} |" + extra)
    return lines


HEADER = ["| threads | features | views | cases | median ms ours / open3d | total s ours / open3d "
          "| open3d / ours (total) | ADD < 0.1 d ours / open3d | ADD < 0.2 d ours / open3d |",
          "|---|---|---|---|---|---|---|---|---|"]


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=10, help="random views per object and view set")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts, one worker process each")
    ap.add_argument("--repeats", type=int, default=1, help="runs per backend and case (the fastest is kept)")
    ap.add_argument("--cases", type=Path, default=None,
                    help="case cache (default /tmp/freeze_coarse_cases_<views>.pkl)")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/coarse_registration.md")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="an older ransac.py, timed as a third backend 'before' (median ms, total / ours, ADD < 0.1 d)")
    ap.add_argument("--worker", nargs=2, metavar=("THREADS", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cases = args.cases or Path(f"/tmp/freeze_coarse_cases_{args.views}.pkl")
    if args.worker:
        worker(cases, int(args.worker[0]), args.repeats, Path(args.worker[1]), args.baseline)
        return
    build_cases(args.views, cases)
    lines = [HEADER[0] + (" before: median, total / ours, ADD < 0.1 d |" if args.baseline else ""),
             HEADER[1] + ("---|" if args.baseline else "")]
    for n in [int(x) for x in args.threads.split(",")]:
        out = cases.with_suffix(f".rows{n}.json")
        subprocess.run([sys.executable, __file__, "--views", str(args.views), "--cases", str(cases),
                        "--repeats", str(args.repeats), "--worker", str(n), str(out)]
                       + (["--baseline", str(args.baseline)] if args.baseline else []), check=True)
        lines += summarise(json.loads(out.read_text()), n)
        print("\n".join(lines), flush=True)
    if args.write:
        cmd = "PYOPENGL_PLATFORM=egl HF_HUB_OFFLINE=1 .venv/bin/python benchmarks/coarse_vs_open3d.py " + " ".join(
            sys.argv[1:] if argv is None else argv)
        path = ROOT / "benchmarks" / "results" / "coarse_registration.md"
        path.write_text("# Coarse registration: ours vs Open3D's feature-matching RANSAC\n\n"
                        f"`{cmd}`\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()

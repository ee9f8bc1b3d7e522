"""Benchmark of the registration chain on synthetic scenes (run by hand): procedural textured
objects, rendered partial views, features -> fusion -> RANSAC -> ICP as in FreeZe.

    PYOPENGL_PLATFORM=egl .venv/bin/python benchmarks/registration.py --views 10 [--hard]

Measures success rates and timings per object, FPFH radius set and with or without the
colortex visual features. The objects and views come from tests/registration_scenes.py
(the fixtures of tests/test_registration_e2e.py and tests/test_geometry_icp.py): each
view renders the object under a random pose in a 640x480 LM-like camera. Model-side
features are computed once per object, the visual ones lifted from templates rendered
as the render_templates stage renders them (pipeline.method.render.templates, default views).

``--hard`` lights the scene differently from the templates, adds 1 mm depth noise and
hides 20-40 % of the object behind a grey occluder.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from pipeline.method.encoders.colortex import ColorTexEncoder  # noqa: E402
from pipeline.method.encoders.fpfh import FpfhEncoder  # noqa: E402
from pipeline.method.encoders.lifting import (  # noqa: E402
    lift_model_visual_features,
    lift_scene_visual_features,
    mask_to_bbox,
)
from pipeline.method.encoders.registry import VisualEncoder  # noqa: E402
from pipeline.formats.bop.extent import point_cloud_diameter  # noqa: E402
from pipeline.method.refinement.icp import refine_icp  # noqa: E402
from pipeline.method.geometry.sampling import sample_surface  # noqa: E402
from pipeline.method.geometry.transforms import rotation_angle_deg  # noqa: E402
from pipeline.method.registration.fusion import PcaBasis, apply_pca, fit_pca, fuse  # noqa: E402
from pipeline.method.registration.ransac import RansacParams, ransac_align  # noqa: E402
from pipeline.method.render.templates import render_templates, template_views  # noqa: E402
from registration_scenes import (  # noqa: E402
    OBJECT_KINDS,
    SCENE_WH,
    SceneView,
    harden_view,
    make_object,
    random_scene_pose,
    render_scene,
    scene_inputs,
)


@dataclass
class ModelData:
    """Model-side inputs: points (N, 3) mm, normals (N, 3), diameter mm, geometric
    features per FPFH radius set, visual features (N, C) or None."""

    points: np.ndarray
    normals: np.ndarray
    diameter: float
    geometric: dict[tuple[float, ...], np.ndarray] = field(default_factory=dict)
    visual: np.ndarray | None = None
    pca: PcaBasis | None = None


@dataclass
class CaseResult:
    """Pose errors (deg, mm) after RANSAC (coarse) and after ICP, and stage times (s)."""

    rot_err_coarse: float
    trans_err_coarse: float
    rot_err: float
    trans_err: float
    n_inliers: int
    t_features: float
    t_ransac: float
    t_icp: float


def run_case(
    model: ModelData,
    view: SceneView,
    geometric: FpfhEncoder,
    visual: VisualEncoder | None,
    *,
    m: int = 1000,
    seed: int = 0,
    n_pca: int = 64,
    ransac: RansacParams | None = None,
) -> CaseResult:
    """Register one view: scene features, fusion, RANSAC, ICP; errors against ground truth."""
    t0 = time.perf_counter()
    pts, nrm, pix = scene_inputs(view, model.diameter, m, seed)
    g_scene = geometric.encode(pts, nrm, model.diameter)
    g_model = model.geometric[tuple(geometric.radii)]
    if visual is not None and model.visual is not None:
        basis = model.pca if model.pca is not None else fit_pca(model.visual, n_pca)
        v_scene = lift_scene_visual_features(view.rgb, mask_to_bbox(view.mask), pix, visual)
        f_model = fuse(g_model, apply_pca(basis, model.visual))
        f_scene = fuse(g_scene, apply_pca(basis, v_scene))
    else:
        f_model, f_scene = fuse(g_model, None), fuse(g_scene, None)
    t1 = time.perf_counter()
    reg = ransac_align(model.points, f_model, pts, f_scene, model.diameter, params=ransac, seed=seed)
    t2 = time.perf_counter()
    icp = refine_icp(model.points, model.normals, pts, reg.R, reg.t, model.diameter)
    t3 = time.perf_counter()
    return CaseResult(
        rot_err_coarse=rotation_angle_deg(reg.R, view.R),
        trans_err_coarse=float(np.linalg.norm(reg.t - view.t)),
        rot_err=rotation_angle_deg(icp.R, view.R),
        trans_err=float(np.linalg.norm(icp.t - view.t)),
        n_inliers=reg.n_inliers,
        t_features=t1 - t0,
        t_ransac=t2 - t1,
        t_icp=t3 - t2,
    )


def prepare_model(mesh: trimesh.Trimesh, renderer: Any, key: str, encoders: Sequence[FpfhEncoder],
                  visual: VisualEncoder | None, *, n: int = 5000, n_templates: int = 42,
                  seed: int = 0) -> ModelData:
    """Sample the model, compute its geometric features for each encoder and (if
    ``visual``) lift visual features from ``n_templates`` templates rendered with a
    ``visual.input_size`` renderer ``renderer`` holding the mesh under ``key``."""
    pts, nrm = sample_surface(mesh, n, seed)
    model = ModelData(points=pts, normals=nrm, diameter=point_cloud_diameter(mesh.vertices))
    for enc in encoders:
        model.geometric[tuple(enc.radii)] = enc.encode(pts, nrm, model.diameter)
    if visual is not None:
        tpl = render_templates(renderer, key, template_views(n_templates, model.diameter, visual.input_size))
        views = list(zip(tpl["rgb"], tpl["depth"], tpl["K"], tpl["R"], tpl["t"]))
        model.visual, _ = lift_model_visual_features(pts, views, visual, diameter=model.diameter)
        model.pca = fit_pca(model.visual, 64)
    return model


def main(argv: Sequence[str] | None = None) -> None:
    from pipeline.method.render.renderer import Light, Lighting, Renderer

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=10, help="random views per object")
    ap.add_argument("--radii", default="0.3,0.4;0.1,0.15;0.15,0.25", help="';'-separated radius sets")
    ap.add_argument("--objects", default=",".join(OBJECT_KINDS))
    ap.add_argument("--backend", default="numpy", choices=["numpy", "open3d"])
    ap.add_argument("--inlier-frac", type=float, default=0.05)
    ap.add_argument("--no-visual", action="store_true", help="skip the colortex-fused runs")
    ap.add_argument("--visual-params", default="{}", help="colortex params as JSON")
    ap.add_argument("--hard", action="store_true",
                    help="scene lit differently from the templates, 1 mm depth noise, 20-40%% occlusion")
    args = ap.parse_args(argv)

    radius_sets = [tuple(float(r) for r in s.split(",")) for s in args.radii.split(";")]
    encoders = [FpfhEncoder(radii=r) for r in radius_sets]
    visual = ColorTexEncoder(**json.loads(args.visual_params))
    ransac = RansacParams(backend=args.backend, inlier_frac=args.inlier_frac)
    scene_r = Renderer(*SCENE_WH)
    tmpl_r = Renderer(visual.input_size, visual.input_size)
    rows = []
    for kind in args.objects.split(","):
        mesh = make_object(kind, seed=1)
        scene_r.add_mesh(kind, mesh)
        tmpl_r.add_mesh(kind, mesh)
        tm = time.perf_counter()
        model = prepare_model(mesh, tmpl_r, kind, encoders, None if args.no_visual else visual)
        print(f"{kind}: diameter {model.diameter:.1f} mm, model features {time.perf_counter() - tm:.1f} s")
        rng = np.random.default_rng(123)
        if args.hard:
            # Dimmer ambient and a key light from the upper left instead of the headlight.
            light = Lighting(ambient=(0.2, 0.2, 0.2), lights=[Light(direction=(0.6, 0.5, 0.6), intensity=2.5)])
            views = [harden_view(render_scene(scene_r, kind, *random_scene_pose(rng), lighting=light), rng)
                     for _ in range(args.views)]
        else:
            views = [render_scene(scene_r, kind, *random_scene_pose(rng)) for _ in range(args.views)]
        for enc in encoders:
            for vis in ([None] if args.no_visual else [None, visual]):
                results = [run_case(model, v, enc, vis, seed=i, ransac=ransac) for i, v in enumerate(views)]
                ok = [r.rot_err < 5 and r.trans_err < 10 for r in results]
                ok_strict = [r.rot_err < 2 and r.trans_err < 3 for r in results]
                rows.append((kind, str(enc.radii), "colortex" if vis else "-", sum(ok), sum(ok_strict), len(results),
                             np.median([r.rot_err_coarse for r in results]),
                             np.median([r.trans_err_coarse for r in results]),
                             np.median([r.t_features for r in results]) * 1e3,
                             np.median([r.t_ransac for r in results]) * 1e3,
                             np.median([r.t_icp for r in results]) * 1e3))
                print("%-7s radii=%-11s visual=%-8s ok(5deg,10mm)=%d strict(2deg,3mm)=%d /%d  "
                      "coarse med %.1f deg %.1f mm  feat %.0f ms ransac %.0f ms icp %.0f ms" % rows[-1], flush=True)
    print("\ntotal over objects: radii, visual -> ok(5deg,10mm) / strict(2deg,3mm) / views")
    for key in dict.fromkeys((r[1], r[2]) for r in rows):
        sel = [r for r in rows if (r[1], r[2]) == key]
        print("  %-11s %-8s %3d %3d /%d" % (*key, sum(r[3] for r in sel), sum(r[4] for r in sel), sum(r[5] for r in sel)))


if __name__ == "__main__":
    main()

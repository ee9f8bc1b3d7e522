"""Synthetic registration benchmark: procedural textured objects, rendered partial views,
and the full FreeZe registration chain (features -> fusion -> RANSAC -> ICP).

The tests use its objects and rendering helpers (tests/test_registration_e2e.py,
tests/test_geometry_icp.py); as a script it measures success rates and timings::

    PYOPENGL_PLATFORM=egl python -m pipeline.registration.benchmark --views 10 [--hard]

``--hard`` lights the scene differently from the templates, adds 1 mm depth noise and
hides 20-40 % of the object behind a grey occluder.

Objects are built from trimesh primitives, deliberately without rotational symmetry,
and coloured per vertex by a smooth seeded pattern (finely subdivided so that colour
varies within faces). Model-side features are computed once per object; each view
renders the object under a random pose in a 640x480 LM-like camera.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from pipeline.encoders.colortex import ColorTexEncoder  # noqa: E402
from pipeline.encoders.fpfh import FpfhEncoder  # noqa: E402
from pipeline.encoders.lifting import (  # noqa: E402
    View,
    lift_model_visual_features,
    lift_scene_visual_features,
    mask_to_bbox,
)
from pipeline.encoders.registry import VisualEncoder  # noqa: E402
from pipeline.geometry.depth import lift_depth  # noqa: E402
from pipeline.geometry.icp import refine_icp  # noqa: E402
from pipeline.geometry.normals import estimate_normals  # noqa: E402
from pipeline.geometry.sampling import sample_points, sample_surface  # noqa: E402
from pipeline.geometry.transforms import look_at_rotation, random_rotation, rotation_angle_deg  # noqa: E402
from pipeline.registration.fusion import PcaBasis, apply_pca, fit_pca, fuse  # noqa: E402
from pipeline.registration.ransac import RansacParams, register  # noqa: E402

SCENE_K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
SCENE_WH = (640, 480)
OBJECT_KINDS = ("rock", "kettle", "blocks")


def _colour_pattern(points: np.ndarray, seed: int) -> np.ndarray:
    """Smooth seeded RGB pattern (P, 4) uint8 of model points (P, 3) mm: a few plane
    waves per channel with random directions plus colour blobs."""
    rng = np.random.default_rng(seed)
    p = np.asarray(points, dtype=np.float64)
    rgb = np.full((len(p), 3), 0.5)
    for c in range(3):
        for _ in range(3):
            k = rng.normal(size=3)
            k *= rng.uniform(0.02, 0.08) / np.linalg.norm(k)  # wavelength ~80-300 mm
            rgb[:, c] += 0.2 * np.sin(p @ k + rng.uniform(0, 2 * np.pi))
    for _ in range(6):
        centre = p[rng.integers(len(p))]
        colour = rng.uniform(0, 1, size=3)
        w = np.exp(-np.sum((p - centre) ** 2, axis=1) / (2 * rng.uniform(8, 20) ** 2))
        rgb = rgb * (1 - w[:, None]) + colour * w[:, None]
    rgba = np.concatenate([np.clip(rgb, 0, 1) * 255, np.full((len(p), 1), 255)], axis=1)
    return rgba.astype(np.uint8)


def make_object(kind: str = "blocks", seed: int = 0, max_edge: float = 3.0) -> trimesh.Trimesh:
    """A vertex-coloured asymmetric test object (mm), centred on its bounding box.

    kind: ``"rock"`` (a stretched sphere with smooth seeded bumps, ~150 mm: curved
    everywhere, easy for local shape descriptors), ``"kettle"`` (a cylinder body with a
    spout, a handle and a knob, ~140 mm) or ``"blocks"`` (an L of boxes with a tilted
    plate and a post, ~170 mm: mostly planar, hard for local shape descriptors).
    """
    T = trimesh.transformations
    if kind == "rock":
        rng = np.random.default_rng(seed + 1000)
        sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
        v = np.asarray(sphere.vertices)
        radius = np.ones(len(v))
        for _ in range(6):
            k = rng.normal(size=3)
            k *= rng.uniform(1.5, 4.0) / np.linalg.norm(k)
            radius += rng.uniform(0.05, 0.12) * np.sin(v @ k + rng.uniform(0, 2 * np.pi))
        parts = [trimesh.Trimesh(v * radius[:, None] * np.array([75.0, 50.0, 40.0]), sphere.faces)]
    elif kind == "blocks":
        parts = [
            trimesh.creation.box((120, 40, 30), transform=T.translation_matrix((0, 0, 0))),
            trimesh.creation.box((40, 70, 30), transform=T.translation_matrix((-40, 45, 0))),
            trimesh.creation.box((30, 30, 50), transform=T.translation_matrix((45, 0, 35))),
            trimesh.creation.box(
                (50, 8, 40),
                transform=T.translation_matrix((10, -25, 25)) @ T.rotation_matrix(0.5, (1, 0, 0)),
            ),
        ]
    elif kind == "kettle":
        parts = [
            trimesh.creation.cylinder(radius=40, height=90, sections=48),
            trimesh.creation.cylinder(
                radius=8, height=60, sections=24,
                transform=T.translation_matrix((50, 0, 15)) @ T.rotation_matrix(1.0, (0, 1, 0)),
            ),
            trimesh.creation.box((12, 15, 60), transform=T.translation_matrix((-52, 0, 5))),
            trimesh.creation.box((25, 15, 10), transform=T.translation_matrix((-40, 0, 32))),
            trimesh.creation.icosphere(subdivisions=2, radius=10).apply_translation((10, 15, 48)),
        ]
    else:
        raise ValueError(f"make_object: unknown kind {kind!r} (known: {', '.join(OBJECT_KINDS)})")
    mesh = trimesh.util.concatenate(parts)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=_colour_pattern(mesh.vertices, seed))
    return mesh


def mesh_diameter(mesh: trimesh.Trimesh) -> float:
    """Largest vertex-to-vertex distance (mm), via the convex hull."""
    from scipy.spatial.distance import pdist

    return float(pdist(np.asarray(mesh.convex_hull.vertices)).max())


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def render_templates(renderer: Any, key: str, diameter: float, n_views: int, size: int = 224,
                     margin: float = 0.1) -> list[View]:
    """Object-centred square template renders ``(rgb, depth, K, R_m2c, t_m2c)`` from
    ``n_views`` viewpoints evenly spread around the object (model origin at the
    centre). ``renderer`` is a :class:`pipeline.render.Renderer` of size ``size``."""
    dist = 3.0 * diameter
    f = size * dist / (diameter * (1 + 2 * margin))
    c = (size - 1) / 2.0
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    views = []
    for direction in fibonacci_sphere(n_views):
        R = look_at_rotation(direction * dist)
        t = np.array([0.0, 0.0, dist])
        rgb, depth = renderer.render([(key, R, t)], K)
        views.append((rgb, depth, K, R, t))
    return views


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
class SceneView:
    """One rendered partial view: rgb (H, W, 3) uint8, depth (H, W) mm, mask, ground truth."""

    rgb: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    R: np.ndarray
    t: np.ndarray


def random_scene_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random rotation and a translation keeping the object well inside the image."""
    R = random_rotation(rng)
    t = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(550, 800)])
    return R, t


def render_scene(renderer: Any, key: str, R: np.ndarray, t: np.ndarray, lighting: Any = None) -> SceneView:
    """Render the object alone in the LM-like camera (default lighting: headlight)."""
    rgb, depth = renderer.render([(key, R, t)], SCENE_K, lighting=lighting)
    return SceneView(rgb=rgb, depth=depth, mask=depth > 0, R=R, t=t)


def harden_view(view: SceneView, rng: np.random.Generator, *, noise_mm: float = 1.0,
                occlusion: tuple[float, float] = (0.2, 0.4)) -> SceneView:
    """A harder copy of ``view``: Gaussian depth noise (``noise_mm``) and a straight-edged
    grey occluder hiding a random share (in ``occlusion``) of the object's pixels, which
    leave the mask and the depth."""
    v, u = np.nonzero(view.mask)
    direction = rng.normal(size=2)
    proj = u * direction[0] + v * direction[1]
    cut = np.quantile(proj, 1.0 - rng.uniform(*occlusion))
    occluded = np.zeros_like(view.mask)
    occluded[v[proj > cut], u[proj > cut]] = True
    rgb = view.rgb.copy()
    rgb[occluded] = (110, 110, 110)
    depth = view.depth + rng.normal(scale=noise_mm, size=view.depth.shape).astype(np.float32) * view.mask
    depth[occluded] = 0
    return SceneView(rgb=rgb, depth=depth, mask=view.mask & ~occluded, R=view.R, t=view.t)


def scene_inputs(view: SceneView, diameter: float, m: int, seed: int,
                 normal_radius_frac: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lift the view's masked depth; normals estimated on the dense cloud (oriented to the
    camera) then ``m`` points sampled. Returns (points (m, 3), normals (m, 3), pixels (m, 2))."""
    pts, pix = lift_depth(view.depth, SCENE_K, view.mask)
    nrm = estimate_normals(pts, normal_radius_frac * diameter, viewpoint=np.zeros(3))
    idx = sample_points(pts, m, seed)
    return pts[idx], nrm[idx], pix[idx]


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
    reg = register(model.points, f_model, pts, f_scene, model.diameter, params=ransac, seed=seed)
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
    ``visual``) lift visual features from templates rendered with a ``visual.input_size``
    renderer ``renderer`` holding the mesh under ``key``."""
    pts, nrm = sample_surface(mesh, n, seed)
    model = ModelData(points=pts, normals=nrm, diameter=mesh_diameter(mesh))
    for enc in encoders:
        model.geometric[tuple(enc.radii)] = enc.encode(pts, nrm, model.diameter)
    if visual is not None:
        views = render_templates(renderer, key, model.diameter, n_templates, size=visual.input_size)
        model.visual, _ = lift_model_visual_features(pts, views, visual, diameter=model.diameter)
        model.pca = fit_pca(model.visual, 64)
    return model


def main(argv: Sequence[str] | None = None) -> None:
    from pipeline.render.renderer import Light, Lighting, Renderer

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

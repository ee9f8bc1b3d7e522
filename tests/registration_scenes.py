"""Synthetic registration scenes: procedural textured objects and rendered partial views.

Used by tests/test_registration_e2e.py and tests/test_geometry_icp.py, and by the
benchmark script benchmarks/registration.py.

Objects are built from trimesh primitives, deliberately without rotational symmetry,
and coloured per vertex by a smooth seeded pattern (finely subdivided so that colour
varies within faces). Each view renders the object under a random pose in a 640x480
LM-like camera.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from pipeline.method.geometry.depth import lift_depth  # noqa: E402
from pipeline.method.geometry.normals import estimate_normals  # noqa: E402
from pipeline.method.geometry.sampling import sample_points  # noqa: E402
from pose_helpers import random_rotation  # noqa: E402

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

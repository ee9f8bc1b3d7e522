"""Headless pyrender wrapper in BOP / OpenCV conventions.

Poses are model-to-camera (``R_m2c`` (3, 3), ``t_m2c`` (3,) in mm), intrinsics are the
OpenCV ``K`` (3, 3) with pixel centres at integer coordinates, and depth images are
(H, W) float32 distances along the optical axis in mm, 0 where nothing was hit.

Masks are taken from depth (``depth > 0``), never from colour: EGL renders with 4x
multisampling, so colour (and pyrender's segmentation colours) are blended at
silhouettes, while the depth blit keeps a single sample per pixel.

An EGL context must not be inherited across ``fork``; create a ``Renderer`` inside the
worker process that uses it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Hashable, Sequence

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

# pyrender is imported lazily so that importing this module stays cheap.

# OpenCV camera (x right, y down, z forward) expressed in OpenGL camera axes
# (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Light:
    """A light in the camera frame (OpenCV axes).

    kind: ``"directional"`` (``direction`` is where the light travels), ``"point"``
    (``position`` in mm) or ``"spot"`` (both, plus cone half-angles in rad). Point and
    spot intensities fall off as 1 / distance^2 with distance in mm.

    pyrender sums the lights of one kind in set order, which changes from run to run;
    with two lights of the same kind, images differ by 1 grey level at a few pixels.
    Use at most one light per kind where bit-identical renders matter.
    """

    kind: str = "directional"
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 3.0
    inner_cone: float = 0.0
    outer_cone: float = 0.7853981633974483


@dataclass
class Lighting:
    """Ambient term plus a list of lights; the default is a headlight."""

    ambient: tuple[float, float, float] = (0.35, 0.35, 0.35)
    lights: list[Light] = field(default_factory=lambda: [Light()])


def _light_pose(light: Light) -> np.ndarray:
    """4x4 pose of a pyrender light in the OpenCV camera frame used as world frame."""
    pose = np.eye(4)
    if light.kind in ("directional", "spot"):
        d = np.asarray(light.direction, dtype=float)
        d = d / np.linalg.norm(d)
        # pyrender lights shine along their local -z.
        z = -d
        helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        pose[:3, :3] = np.stack([x, y, z], axis=1)
    if light.kind in ("point", "spot"):
        pose[:3, 3] = light.position
    return pose


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix from ``R`` (3, 3) and ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


class Renderer:
    """Offscreen renderer of one image size, reused across many renders.

    Meshes are registered once with :meth:`add_mesh` (vertex colours or textures are
    kept) and then rendered by key under any pose.
    """

    def __init__(self, width: int, height: int, znear: float = 10.0, zfar: float = 20000.0):
        import pyrender

        self._pyrender = pyrender
        self.width = int(width)
        self.height = int(height)
        self.znear = float(znear)
        self.zfar = float(zfar)
        self._renderer = pyrender.OffscreenRenderer(self.width, self.height)
        self._meshes: dict[Hashable, object] = {}

    def close(self) -> None:
        self._renderer.delete()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def has_mesh(self, key: Hashable) -> bool:
        return key in self._meshes

    def add_mesh(self, key: Hashable, mesh: trimesh.Trimesh, smooth: bool = True) -> None:
        """Register a mesh (vertices in mm) under ``key``."""
        self._meshes[key] = self._pyrender.Mesh.from_trimesh(mesh, smooth=smooth)

    def _camera(self, K: np.ndarray):
        K = np.asarray(K, dtype=float)
        # Depth is blitted from the 4x multisampled buffer by taking sample 0, which the
        # standard 4x pattern puts at (0.375, 0.125) of the pixel in OpenGL window
        # coordinates (y up). Shifting the principal point by that sample's offset makes
        # depth and masks exact for OpenCV pixel centres (measured on Mesa llvmpipe:
        # silhouette rows/columns match the analytic projection of a square to within
        # pixel-centre ties); the resolved colour is then within 0.4 px.
        return self._pyrender.IntrinsicsCamera(
            fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.375, cy=K[1, 2] + 0.875,
            znear=self.znear, zfar=self.zfar,
        )

    def render(
        self,
        items: Sequence[tuple[Hashable, np.ndarray, np.ndarray]],
        K: np.ndarray,
        *,
        rgb: bool = True,
        lighting: Lighting | None = None,
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """Render several posed meshes together.

        items: (key, R_m2c (3, 3), t_m2c (3,) mm) per instance.
        Returns ``(rgb (H, W, 3) uint8 or None, depth (H, W) float32 mm)``.
        """
        pr = self._pyrender
        lighting = lighting or Lighting()
        scene = pr.Scene(bg_color=np.zeros(4), ambient_light=np.asarray(lighting.ambient, dtype=float))
        for key, R, t in items:
            scene.add(self._meshes[key], pose=pose_matrix(R, t))
        scene.add(self._camera(K), pose=_CV_TO_GL)
        if rgb:
            for light in lighting.lights:
                col = np.asarray(light.color, dtype=float)
                if light.kind == "directional":
                    node = pr.DirectionalLight(color=col, intensity=light.intensity)
                elif light.kind == "spot":
                    node = pr.SpotLight(
                        color=col, intensity=light.intensity,
                        innerConeAngle=light.inner_cone, outerConeAngle=light.outer_cone,
                    )
                else:
                    node = pr.PointLight(color=col, intensity=light.intensity)
                scene.add(node, pose=_light_pose(light))
            color, depth = self._renderer.render(scene)
            return np.ascontiguousarray(color[..., :3]), depth.astype(np.float32)
        depth = self._renderer.render(scene, flags=pr.RenderFlags.DEPTH_ONLY)
        return None, depth.astype(np.float32)

    def render_depth(self, key: Hashable, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Depth (H, W) float32 mm of one mesh; 0 off the object."""
        return self.render([(key, R, t)], K, rgb=False)[1]

    def render_object(
        self,
        key: Hashable,
        R: np.ndarray,
        t: np.ndarray,
        K: np.ndarray,
        lighting: Lighting | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RGB (H, W, 3) uint8, depth (H, W) float32 mm and mask (H, W) bool of one mesh."""
        color, depth = self.render([(key, R, t)], K, rgb=True, lighting=lighting)
        assert color is not None
        return color, depth, depth > 0

"""Checks that a declared symmetry really maps a coloured model onto itself.

A rigid transform T is a symmetry of the object when every surface point p, moved
to T p, lands on the surface (geometric residual ~0 mm) at a point of the same colour
(colour residual ~0). Closest points come from Open3D's ray-casting scene (BVH), and
colours are interpolated barycentrically from the vertex colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh


@dataclass
class SymmetryResidual:
    """Distances of transformed points to the surface (mm) and colour differences (0-255)."""

    geom_mean: float
    geom_max: float
    color_mean: float


class SurfaceProbe:
    """Closest-point and colour queries on one mesh (vertices in mm)."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.vertices = np.asarray(mesh.vertices, np.float64)
        self.faces = np.asarray(mesh.faces, np.int64)
        colors = getattr(mesh.visual, "vertex_colors", None)
        self.colors = None if colors is None or len(colors) != len(self.vertices) else np.asarray(colors)[:, :3].astype(np.float64)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)), o3d.core.Tensor(self.faces.astype(np.uint32))
        )

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Distance (N,) mm to the surface and interpolated colour (N, 3) at the closest point."""
        q = o3d.core.Tensor(np.asarray(points, np.float32))
        ans = self._scene.compute_closest_points(q)
        cp = ans["points"].numpy().astype(np.float64)
        dist = np.linalg.norm(cp - points, axis=1)
        if self.colors is None:
            return dist, None
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy().astype(np.float64)
        w = np.column_stack([1.0 - uv.sum(axis=1), uv[:, 0], uv[:, 1]])
        col = np.einsum("nk,nkc->nc", w, self.colors[self.faces[prim]])
        return dist, col

    def sample(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
        """n area-uniform surface points (n, 3) mm with their colours (n, 3) or None."""
        pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(self.vertices, self.faces, process=False), n, seed=seed)
        _, col = self.closest(pts)
        return np.asarray(pts), col


def symmetry_residual(probe: SurfaceProbe, T: np.ndarray, points: np.ndarray, colors: np.ndarray | None = None) -> SymmetryResidual:
    """Residual of the (4, 4) transform T on surface ``points`` (N, 3) with ``colors`` (N, 3)."""
    moved = points @ T[:3, :3].T + T[:3, 3]
    dist, col = probe.closest(moved)
    cdiff = float("nan") if colors is None or col is None else float(np.abs(col - colors).mean())
    return SymmetryResidual(float(dist.mean()), float(dist.max()), cdiff)


def axis_rotation(axis: np.ndarray, offset: np.ndarray, angle: float) -> np.ndarray:
    """(4, 4) rotation by ``angle`` rad about the line through ``offset`` (mm) along ``axis``."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(offset, float) - R @ np.asarray(offset, float)
    return T

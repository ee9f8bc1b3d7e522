"""Multi-scale FPFH geometric encoder (open3d), the weight-free stand-in for GeDi.

For each radius ``r_i * diameter`` one 33-bin FPFH is computed from all neighbours
within that radius, normalised (L2 or L1) on its own, and the scales are
concatenated: ``dim = 33 * len(radii)``. Open3d normalises each FPFH sub-histogram by
its neighbour count, so descriptors of a 5000-point model and a 1000-point scene
sample of the same surface agree in expectation; a neighbour cap (``max_nn``) would
break that by shrinking the effective radius on the denser cloud, so it is off by
default.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from pipeline.method.encoders.registry import GeometricEncoder, register_encoder, with_checked_points

FPFH_BINS = 33


class FpfhEncoder(GeometricEncoder):
    """Multi-scale FPFH.

    radii: neighbourhood radii as fractions of the object diameter.
    normal_radius: radius (fraction of the diameter) for normal estimation when no
    normals are given; ``normal_max_nn`` caps its neighbours.
    max_nn: optional neighbour cap for the FPFH search (None = all within radius).
    norm: ``"l2"`` or ``"l1"`` normalisation of each scale's histogram.
    """

    name = "fpfh"
    version = "1"

    def __init__(
        self,
        radii: Sequence[float] = (0.3, 0.4),
        normal_radius: float = 0.05,
        normal_max_nn: int = 30,
        max_nn: int | None = None,
        norm: str = "l2",
    ) -> None:
        radii = [float(r) for r in radii]
        if not radii or any(r <= 0 for r in radii):
            raise ValueError(f"fpfh: radii must be a non-empty list of positive fractions, got {radii}")
        if norm not in ("l1", "l2"):
            raise ValueError(f"fpfh: norm must be 'l1' or 'l2', got {norm!r}")
        if normal_radius <= 0:
            raise ValueError(f"fpfh: normal_radius must be positive, got {normal_radius}")
        self.radii = radii
        self.normal_radius = float(normal_radius)
        self.normal_max_nn = int(normal_max_nn)
        self.max_nn = None if max_nn is None else int(max_nn)
        self.norm = norm
        self.dim = FPFH_BINS * len(radii)

    def signature(self) -> str:
        return "fpfh-ms" if len(self.radii) > 1 else "fpfh"

    def cache_params(self) -> dict[str, Any]:
        return {
            "radii": self.radii,
            "normal_radius": self.normal_radius,
            "normal_max_nn": self.normal_max_nn,
            "max_nn": self.max_nn,
            "norm": self.norm,
        }

    @with_checked_points
    def encode(
        self,
        points: np.ndarray,
        normals: np.ndarray | None,
        diameter: float,
        *,
        viewpoint: np.ndarray | None = None,
    ) -> np.ndarray:
        """Descriptors (N, dim) float32 of ``points`` (N, 3) float64 mm (N >= 1; see
        :func:`~pipeline.method.encoders.registry.with_checked_points`)."""
        # open3d (0.65 s to import, dash's plotly viewer with it) only here: every job
        # plans the run, which registers this encoder, and most jobs never encode.
        import open3d as o3d

        from pipeline.method.geometry.normals import estimate_normals

        if normals is None:
            normals = estimate_normals(
                points, self.normal_radius * diameter, max_nn=self.normal_max_nn, viewpoint=viewpoint
            )
        elif np.shape(normals) != points.shape:
            raise ValueError(f"fpfh: normals shape {np.shape(normals)} differs from points shape {points.shape}")
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
        parts = []
        for r in self.radii:
            radius = r * diameter
            search = (
                o3d.geometry.KDTreeSearchParamRadius(radius)
                if self.max_nn is None
                else o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=self.max_nn)
            )
            hist = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(pcd, search).data).T
            parts.append(_normalise(hist, self.norm))
        return np.concatenate(parts, axis=1).astype(np.float32)


def _normalise(x: np.ndarray, norm: str) -> np.ndarray:
    """Row-normalise (N, D); all-zero rows (isolated points) stay zero."""
    n = np.abs(x).sum(axis=1, keepdims=True) if norm == "l1" else np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.maximum(n, 1e-12)


register_encoder("fpfh", "geometric", FpfhEncoder)

"""Pose helpers only the tests (and the benchmarks that build the tests' scenes) use;
BOP conventions as :mod:`pipeline.method.geometry.transforms`: a pose ``(R (3, 3)
float64, t (3,) float64 mm)`` maps model points to camera points, ``x_c = R @ x_m + t``."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def compose(
    R_ab: np.ndarray, t_ab: np.ndarray, R_bc: np.ndarray, t_bc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose a->c from a->b followed by b->c: ``x_c = R_bc (R_ab x_a + t_ab) + t_bc``."""
    R_ab = np.asarray(R_ab, dtype=np.float64).reshape(3, 3)
    R_bc = np.asarray(R_bc, dtype=np.float64).reshape(3, 3)
    t_ab = np.asarray(t_ab, dtype=np.float64).reshape(3)
    t_bc = np.asarray(t_bc, dtype=np.float64).reshape(3)
    return R_bc @ R_ab, R_bc @ t_ab + t_bc


def transform_points(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply a pose to points (N, 3); returns (N, 3) in the dtype of ``points``."""
    pts = np.asarray(points)
    out = pts.astype(np.float64) @ np.asarray(R, dtype=np.float64).reshape(3, 3).T
    out += np.asarray(t, dtype=np.float64).reshape(1, 3)
    return out.astype(pts.dtype if pts.dtype.kind == "f" else np.float64)


def random_rotation(rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Uniformly distributed rotation (3, 3) float64 over SO(3)."""
    rng = np.random.default_rng(rng)
    return Rotation.random(random_state=rng).as_matrix()

"""Rigid-transform helpers in BOP conventions.

A pose is a pair ``(R (3, 3) float64, t (3,) float64 mm)`` that maps model points to
camera points: ``x_c = R @ x_m + t``. Functions accept anything array-like and return
float64 arrays. (Helpers only the tests use, such as composing poses or drawing a random
rotation, live in ``tests/pose_helpers.py``.)
"""

from __future__ import annotations

import math

import numpy as np


def rt_to_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 float64 homogeneous matrix from ``R`` (3, 3) and ``t`` (3,) mm."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def matrix_to_rt(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` float64 from a 4x4 homogeneous matrix."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"expected a (4, 4) matrix, got shape {T.shape}")
    return T[:3, :3].copy(), T[:3, 3].copy()


def invert(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse pose: if ``(R, t)`` maps a->b, the result maps b->a."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return R.T.copy(), -R.T @ t


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in degrees of the relative rotation ``R_a^T R_b`` (geodesic distance)."""
    R_rel = np.asarray(R_a, dtype=np.float64).reshape(3, 3).T @ np.asarray(R_b, dtype=np.float64).reshape(3, 3)
    # atan2 of sine and cosine parts stays accurate near 0 and 180 deg, where acos of
    # the trace alone loses precision.
    sin = 0.5 * np.linalg.norm([R_rel[2, 1] - R_rel[1, 2], R_rel[0, 2] - R_rel[2, 0], R_rel[1, 0] - R_rel[0, 1]])
    cos = 0.5 * (np.trace(R_rel) - 1.0)
    return float(np.degrees(np.arctan2(sin, cos)))


def rotation_about_axis(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation (3, 3) of ``angle_deg`` degrees about ``axis`` (any non-zero length)."""
    axis = np.asarray(axis, dtype=np.float64).reshape(3)
    norm = math.sqrt(float(axis @ axis))
    if norm == 0:
        raise ValueError("rotation axis must be non-zero")
    # Rodrigues' formula: for one rotation 2x faster than scipy's Rotation (ICP calls this
    # every iteration), the same matrix to 1e-16.
    x, y, z = axis / norm
    a = math.radians(angle_deg)
    s, c = math.sin(a), math.cos(a)
    C = 1.0 - c
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


def perturb_pose(
    R: np.ndarray,
    t: np.ndarray,
    angle_deg: float,
    translation_mm: float,
    rng: np.random.Generator | int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pose rotated by exactly ``angle_deg`` about a random axis through the model
    origin (applied on the model side) and shifted by exactly ``translation_mm`` in a
    random direction."""
    rng = np.random.default_rng(rng)
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    R_new = np.asarray(R, dtype=np.float64) @ rotation_about_axis(axis, angle_deg)
    return R_new, np.asarray(t, dtype=np.float64).reshape(3) + translation_mm * direction


def look_at_rotation(camera_position: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """``R_m2c`` of an OpenCV camera at ``camera_position`` (model frame, mm) looking at
    the model origin. ``up`` is the model-frame direction that should appear up in the
    image (default +z, or +y when the camera lies on the z axis)."""
    c = np.asarray(camera_position, dtype=np.float64).reshape(3)
    z = -c / np.linalg.norm(c)  # optical axis, towards the origin
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    up = np.asarray(up, dtype=np.float64).reshape(3)
    x = np.cross(z, up)  # image right (OpenCV y points down, so right = z x up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    # Rows are the camera axes expressed in the model frame.
    return np.stack([x, y, z], axis=0)

"""Turns: the rigid motions of a model that a partial, noisy view of it can hardly rule
out, tried on a candidate's best hypothesis so that the verification, not RANSAC's
luck, decides between the pose and its turned twins.

Why: on the real TYO-L frame and on semi-real LM-O almost every wrong estimate is a
candidate none of whose coarse hypotheses was right (on semi-real LM-O 65 of 66; the
verification picks a right hypothesis whenever one exists), and many of them are the
right pose turned: the basket a quarter turn about its axis, an LM-O object upside
down. A turn is applied in the model frame, ``x -> T x``, so that a pose
``(R, t)`` becomes ``(R T_R, R T_t + t)``.

Two sources, both per object and both in the model frame (mm):

- the shape's near-symmetries (:func:`pipeline.method.geometry.symmetry.estimate_symmetries`,
  ``details["near"]``): the turns that move the whole surface least without being
  symmetries;
- the 23 quarter and half turns of the cube's rotation group about the model's axes
  through its bounding-box centre: CAD and BOP models are drawn in a frame aligned with
  their main faces, and what a partial view confuses is typically a box-like shape
  turned about one of those axes, which the whole-surface score ranks low (the basket's
  quarter turn about its axis scores 0.035 d, behind four other near-misses).

Turns that the object's symmetry group already explains are dropped, and so are turns
equal to an earlier one modulo the group: their verification would repeat the pose's.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def axis_turns(points: np.ndarray) -> np.ndarray:
    """The 23 non-identity rotations of the cube's group (quarter, half and
    three-quarter turns about the model's axes, third turns about the diagonals) about
    the bounding-box centre of ``points`` (N, 3) mm, as (23, 4, 4) float64 transforms."""
    from scipy.spatial.transform import Rotation

    pts = np.asarray(points, dtype=np.float64)
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    rotations = Rotation.create_group("O").as_matrix()
    out = []
    for R in rotations:
        if np.allclose(R, np.eye(3), atol=1e-9):
            continue
        T = np.eye(4)
        T[:3, :3] = np.round(R)  # exact signed permutations
        T[:3, 3] = centre - T[:3, :3] @ centre
        out.append(T)
    return np.stack(out)


def model_turns(near: Sequence[np.ndarray], points: np.ndarray, symmetries, diameter: float,
                *, max_angle_deg: float = 10.0, max_trans_frac: float = 0.05) -> np.ndarray:
    """The turns tried on an object's hypotheses, (n, 4, 4) float64, model frame, mm:
    ``near`` (the near-symmetries, (4, 4) each, best first) then :func:`axis_turns` of
    ``points``, without those in ``symmetries`` (a
    :class:`pipeline.method.geometry.symmetry.SymmetrySet`, identity included) and those equal
    to an earlier turn modulo it, within ``max_angle_deg`` and ``max_trans_frac`` of
    ``diameter``."""
    tol_mm = max_trans_frac * float(diameter)
    kept: list[np.ndarray] = []
    for T in [np.asarray(n, dtype=np.float64).reshape(4, 4) for n in near] + list(axis_turns(points)):
        if symmetries.contains(T, max_angle_deg=max_angle_deg, max_trans_mm=tol_mm):
            continue
        if any(symmetries.contains(np.linalg.inv(U) @ T, max_angle_deg=max_angle_deg, max_trans_mm=tol_mm)
               for U in kept):
            continue
        kept.append(T)
    return np.stack(kept) if kept else np.zeros((0, 4, 4))


def turned(R: np.ndarray, t: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model-to-camera pose ``(R (3, 3), t (3,) mm)`` with the model first moved by
    the turn ``T`` (4, 4): ``(R T_R, R T_t + t)``."""
    return R @ T[:3, :3], R @ T[:3, 3] + t

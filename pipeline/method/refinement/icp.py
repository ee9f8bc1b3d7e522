"""ICP refinement of a model-to-camera pose against an observed point cloud.

Our own loop rather than open3d's ``registration_icp``, for reasons measured on the
refine stage's 163 ICP calls of ``synthtiny`` (fpfh + dinov2-vits14), replayed:

- **Shapes that depth does not pin down.** For a surface of revolution (a can, a cup) the
  rotation about its axis moves no point off the surface, so point-to-plane's normal
  matrix is (nearly) singular in that direction, and open3d's solver turned such poses
  by 1-5 degrees at *every* iteration, a random walk that never met its stopping test and
  ran all 3 x 30 iterations. Here each Gauss-Newton step is damped (Levenberg-Marquardt,
  ``weak_frac`` of the largest eigenvalue added to all): a direction the points
  constrain well moves as before, one they barely constrain hardly moves, so the pose
  keeps along it what the start (RANSAC on fused features, which see the texture) gave.
- **A stage stops when the pose stops moving** (a step below ``min_step_frac`` of the
  diameter, or the same correspondences as the previous iteration), instead of
  open3d's test on fitness and RMSE, which jitter with every correspondence switch; and
  when its fit stalls (:data:`STALL_ITERATIONS`): along what the points do not
  constrain, a damped step can still exceed the step test.
- **The model's k-d tree is built once** per :class:`IcpModel` (pykdtree: 7x faster to
  build than scipy's ``cKDTree`` and 1.6x faster to query, the same neighbours) and
  reused by every ICP on the object, where open3d built one per call and per stage.

Per iteration our numpy step costs about twice open3d's C++ one; with 2-4x fewer
iterations a hypothesis' ICP took 9 ms against 20 ms, and with the fine ICP 20 ms
against 83 ms, from the same starts on semi-real LM-O with the same median errors
(``benchmarks/results/icp.md``); in the refine stage the ICP took 2.46x less time.

Conventions: poses are BOP model-to-camera ``R`` (3, 3), ``t`` (3,) mm. The scene is
aligned to the model (scene -> model correspondences), because every observed point has a
true counterpart on the model while most model points are unseen in a partial view; this
also lets point-to-plane use the exact model normals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from pykdtree.kdtree import KDTree

from pipeline.method.geometry.transforms import invert, rotation_about_axis, rotation_angle_deg

WEAK_FRAC = 1e-3
"""Damping of the point-to-plane step, as a fraction of the normal matrix's largest
eigenvalue (rotations scaled by the points' RMS radius, so that every eigenvalue is in
mm^2). Measured on synthtiny's refine calls: a can's axis rotation sits at 0.0006-0.0012
of the largest (its step damped to a half or less), the next direction at 0.03-0.09, a
box's smallest at 0.1 (steps kept to 97-99 %). AR with seed 0, against open3d's ICP
(0.859 on semi-real LM-O, 0.842 on synthhard): 1e-2 gave 0.850 and 0.829 (damping that
strong slows the directions a partial view constrains weakly, such as a box face's
sliding, until the stopping test ends the stage early), 1e-3 gave 0.855 and 0.839, no
damping 0.854 on LM-O and, on synthhard, a pose that diverged to non-finite values.
Truncating the weak directions at 1e-2 instead left a smooth rock 0.76 degrees off."""

MIN_STEP_FRAC = 1e-3
"""A stage stops when an iteration moves the points by less than this fraction of the
diameter (rotation times the points' RMS radius plus translation, mm): 0.1 mm for a
100 mm object, where the steps are the jitter of correspondences switching between
model samples (0.02-0.1 mm, sometimes a cycle of a dozen iterations). On semi-real
LM-O 1e-3 and 1e-4 gave the same AR (0.850), 1e-3 in about 2/3 of the ICP time."""

STALL_ITERATIONS, STALL_GAIN = 3, 1e-3
"""A stage also stops when this many iterations in a row lowered its truncated cost
(squared distance of the inlier pairs, the threshold's for the other points) by less
than this fraction of the best so far: along a direction the points do not constrain
the pose can keep moving by more than the step test without fitting any better."""


@dataclass(frozen=True)
class IcpResult:
    """Refined pose and its fit.

    R (3, 3) float64 and t (3,) float64 mm: model-to-camera.
    fitness: fraction of scene points with a model point within the final threshold.
    inlier_rmse: RMS distance (mm) of those inlier pairs.
    iterations: iterations run, summed over the stages.
    """

    R: np.ndarray
    t: np.ndarray
    fitness: float
    inlier_rmse: float
    iterations: int = 0


class IcpModel:
    """A model prepared for repeated ICP: ``points`` (N, 3) float64 mm, outward unit
    ``normals`` (N, 3) float64 or None, and their k-d tree, built once."""

    def __init__(self, points: np.ndarray, normals: np.ndarray | None = None) -> None:
        self.points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        self.normals = None if normals is None else np.ascontiguousarray(
            np.asarray(normals, dtype=np.float64).reshape(-1, 3))
        if self.normals is not None and self.normals.shape != self.points.shape:
            raise ValueError(f"IcpModel: normals {self.normals.shape} differ from points {self.points.shape}")
        if not len(self.points):
            raise ValueError("IcpModel: the model has no points")
        self.tree = KDTree(self.points)

    # pykdtree's tree does not pickle; a worker process (a dask cluster's) gets the points
    # and builds its own (0.2 ms for 5000 points).
    def __getstate__(self) -> dict:
        return {"points": self.points, "normals": self.normals}

    def __setstate__(self, state: dict) -> None:
        self.points, self.normals = state["points"], state["normals"]
        self.tree = KDTree(self.points)


def _plane_step(q: np.ndarray, m: np.ndarray, n: np.ndarray,
                weak_frac: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One Gauss-Newton step of point-to-plane alignment of the points ``q`` (k, 3) to the
    planes through ``m`` (k, 3) with normals ``n`` (k, 3): the rotation ``Rw`` (3, 3) about
    the centroid ``c`` of ``q`` and the translation ``v`` (3,), so that
    ``q -> Rw (q - c) + c + v``; returned as (Rw, c, v). The step is damped by ``weak_frac``
    times the largest eigenvalue of the normal matrix (see :data:`WEAK_FRAC`). Also
    returns the step's size (mm)."""
    c = q.mean(axis=0)
    qc = (q - c).T  # (3, k): the Jacobian is built and multiplied row-wise, 1.4x faster than (k, 6)
    nt = n.T
    L = max(math.sqrt(float(np.einsum("ij,ij->", qc, qc)) / len(q)), 1e-9)
    Jt = np.empty((6, len(q)))
    np.multiply(qc[1], nt[2], out=Jt[0])  # (q - c) x n, rotation scaled by L:
    Jt[0] -= qc[2] * nt[1]                # both halves of the step in mm
    np.multiply(qc[2], nt[0], out=Jt[1])
    Jt[1] -= qc[0] * nt[2]
    np.multiply(qc[0], nt[1], out=Jt[2])
    Jt[2] -= qc[1] * nt[0]
    Jt[:3] /= L
    Jt[3:] = nt
    r = np.einsum("ij,ij->i", q - m, n)
    A = Jt @ Jt.T
    if not np.isfinite(A).all():
        return np.eye(3), c, np.zeros(3), 0.0  # degenerate input: no step, the stage ends
    lam, V = np.linalg.eigh(A)
    if lam[-1] <= 0.0:
        return np.eye(3), c, np.zeros(3), 0.0
    x = V @ ((V.T @ -(Jt @ r)) / (lam + max(weak_frac * lam[-1], 1e-12 * lam[-1])))
    w = x[:3] / L  # rotation vector, rad
    theta = math.sqrt(float(w @ w))
    Rw = rotation_about_axis(w, math.degrees(theta)) if theta > 0 else np.eye(3)
    return Rw, c, x[3:], math.sqrt(float(x[:3] @ x[:3])) + math.sqrt(float(x[3:] @ x[3:]))


def _point_step(q: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The rigid motion (Kabsch) of ``q`` (k, 3) onto ``m`` (k, 3), as :func:`_plane_step`."""
    c, cm = q.mean(axis=0), m.mean(axis=0)
    U, _, Vt = np.linalg.svd((q - c).T @ (m - cm))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    Rw = Vt.T @ D @ U.T
    v = cm - c
    L = float(np.sqrt(((q - c) ** 2).sum(axis=1).mean()))
    return Rw, c, v, float(np.radians(rotation_angle_deg(np.eye(3), Rw))) * L + float(np.linalg.norm(v))


def checked_inputs(model: IcpModel, scene_points: np.ndarray, schedule: Sequence[float], point_to_plane: bool,
                   caller: str) -> np.ndarray:
    """The scene points as (M, 3) float64 mm, after the checks every ICP entry point
    (``caller``, named in the error) makes of its inputs."""
    if point_to_plane and model.normals is None:
        raise ValueError(f"{caller}: point_to_plane=True needs model_normals")
    scene = np.asarray(scene_points, dtype=np.float64).reshape(-1, 3)
    if len(scene) == 0:
        raise ValueError(f"{caller}: the scene point cloud is empty")
    if not len(schedule):
        raise ValueError(f"{caller}: schedule must not be empty")
    return scene


def refine_icp(
    model: IcpModel | np.ndarray,
    model_normals: np.ndarray | None,
    scene_points: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    diameter: float,
    *,
    max_corr_dist_frac: float = 0.1,
    iterations: int = 30,
    point_to_plane: bool = True,
    schedule: Sequence[float] = (1.0, 0.5, 0.25),
    weak_frac: float = WEAK_FRAC,
    min_step_frac: float = MIN_STEP_FRAC,
) -> IcpResult:
    """Refine ``(R0, t0)`` (model-to-camera, mm) by coarse-to-fine ICP.

    model: an :class:`IcpModel` (its tree reused; ``model_normals`` is then ignored), or
    the model points (N, 3) mm with outward unit ``model_normals`` (N, 3) (required for
    point-to-plane). scene_points (M, 3) mm in the camera frame (a partial view).

    Stages use correspondence thresholds ``max_corr_dist_frac * diameter * s`` for ``s``
    in ``schedule`` (coarse first), at most ``iterations`` iterations each; a stage ends
    early when an iteration moves the points by less than ``min_step_frac * diameter`` or
    finds the previous iteration's correspondences again. Point-to-plane damps the
    directions the depth barely constrains (``weak_frac``, see the module docstring).
    Fitness and inlier RMSE are measured at the final pose with the last threshold.
    """
    if not isinstance(model, IcpModel):
        if point_to_plane and model_normals is None:
            raise ValueError("refine_icp: point_to_plane=True needs model_normals")
        model = IcpModel(model, model_normals if point_to_plane else None)
    scene = checked_inputs(model, scene_points, schedule, point_to_plane, "refine_icp")
    R, t = invert(R0, t0)  # camera -> model
    min_step = float(min_step_frac * diameter)
    done = 0
    for scale in schedule:
        threshold = float(max_corr_dist_frac * diameter * scale)
        previous = None
        best, stalled = np.inf, 0
        for _ in range(int(iterations)):
            q = scene @ R.T + t
            dist, idx = model.tree.query(q, distance_upper_bound=threshold)
            if previous is not None and np.array_equal(idx, previous):
                break  # the step just taken solved this very problem
            previous = idx
            ok = dist < np.inf
            n_ok = int(np.count_nonzero(ok))
            if n_ok < 6:
                break
            # Truncated cost: squared distance of the inliers, the threshold's for the others.
            d_ok = dist[ok]
            cost = float(d_ok @ d_ok) + (len(q) - n_ok) * threshold ** 2
            stalled = stalled + 1 if cost > best * (1.0 - STALL_GAIN) else 0
            best = min(best, cost)
            if stalled >= STALL_ITERATIONS:
                break  # wandering along what the points do not constrain
            near = idx[ok]
            if point_to_plane:
                Rw, c, v, step = _plane_step(q[ok], model.points[near], model.normals[near], weak_frac)
            else:
                Rw, c, v, step = _point_step(q[ok], model.points[near])
            R, t = Rw @ R, Rw @ (t - c) + c + v
            done += 1
            if step < min_step:
                break
    dist, _ = model.tree.query(scene @ R.T + t, distance_upper_bound=threshold)
    ok = dist < np.inf
    fitness = float(ok.mean())
    rmse = float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any() else 0.0
    R_m2c, t_m2c = invert(R, t)
    return IcpResult(R=R_m2c, t=t_m2c, fitness=fitness, inlier_rmse=rmse, iterations=done)

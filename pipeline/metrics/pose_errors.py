"""MSSD and MSPD pose errors (BOP 2019), vectorised over symmetry transformations.

Both compare the model points in the estimated pose with the points in every
symmetric variant ``(R_g R_s, R_g t_s + t_g)`` of the ground-truth pose, take the
maximum over points and the minimum over variants.

Units: points and translations in mm, MSSD in mm, MSPD in pixels.
"""

from __future__ import annotations

import numpy as np

# Work arrays are processed in blocks of about this many (point, symmetry) pairs to
# bound memory (about 10 MB per work array) for models with many vertices and many symmetries.
_BLOCK = 1 << 19


def _as_pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(R, dtype=np.float64).reshape(3, 3), np.asarray(t, dtype=np.float64).reshape(3)


def _identity_syms() -> tuple[np.ndarray, np.ndarray]:
    return np.eye(3)[None], np.zeros((1, 3))


def _max_dist_exact(q: np.ndarray, pts: np.ndarray, sym_R: np.ndarray, sym_t: np.ndarray) -> np.ndarray:
    """``max_v |q_v - (R_s p_v + t_s)|`` for each s; ``(S,)`` float64, computed directly."""
    out = np.empty(len(sym_R))
    step = max(1, _BLOCK // max(1, len(pts)))
    for a in range(0, len(sym_R), step):
        y = pts[None] @ sym_R[a : a + step].transpose(0, 2, 1) + sym_t[a : a + step, None, :]
        out[a : a + step] = np.sqrt(((q[None] - y) ** 2).sum(-1).max(-1))
    return out


def mssd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    pts: np.ndarray,
    sym_R: np.ndarray | None = None,
    sym_t: np.ndarray | None = None,
) -> float:
    """Maximum Symmetry-aware Surface Distance in mm.

    R_*: (3, 3), t_*: (3,) mm, model-to-camera. pts: (V, 3) model vertices in mm.
    sym_R: (S, 3, 3), sym_t: (S, 3) mm from :func:`symmetry_transformations`
    (identity only when omitted).
    """
    R_e, t_e = _as_pose(R_e, t_e)
    R_g, t_g = _as_pose(R_g, t_g)
    pts = np.asarray(pts, dtype=np.float64)
    if sym_R is None:
        sym_R, sym_t = _identity_syms()
    sym_R = np.asarray(sym_R, dtype=np.float64)
    sym_t = np.asarray(sym_t, dtype=np.float64)

    # |R_e p + t_e - R_g(R_s p + t_s) - t_g| = |q - (R_s p + t_s)| with q expressed in
    # the model frame of the GT pose (rotations preserve lengths).
    q = (pts @ R_e.T + (t_e - t_g)) @ R_g
    if len(sym_R) <= 4:
        return float(_max_dist_exact(q, pts, sym_R, sym_t).min())

    # Many symmetries: expand the squared distance so that the (V, S) table is one
    # matrix product, |q|^2 + |p|^2 + |t_s|^2 + 2 p.(R_s^T t_s) - 2 q^T R_s p - 2 q.t_s,
    # then recompute the best candidates exactly (the expansion loses ~1e-12 relative).
    feats = np.concatenate([(q[:, :, None] * pts[:, None, :]).reshape(-1, 9), q, pts], axis=1)
    coefs = np.concatenate(
        [-2.0 * sym_R.reshape(-1, 9), -2.0 * sym_t, 2.0 * np.einsum("sji,sj->si", sym_R, sym_t)], axis=1
    )
    base = (q**2).sum(1) + (pts**2).sum(1)
    tsq = (sym_t**2).sum(1)
    worst = np.full(len(sym_R), -np.inf)
    step = max(1, _BLOCK // len(sym_R))
    for a in range(0, len(pts), step):
        d2 = feats[a : a + step] @ coefs.T + base[a : a + step, None]
        np.maximum(worst, d2.max(0), out=worst)
    worst += tsq
    scale = float(base.max() + tsq.max()) if len(base) else 0.0
    cand = np.flatnonzero(worst <= worst.min() + 1e-9 * (1.0 + scale))
    return float(_max_dist_exact(q, pts, sym_R[cand], sym_t[cand]).min())


def project(pts: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) float64 of points (N, 3) mm under pose (R, t) and K (3, 3)."""
    x = np.asarray(pts, dtype=np.float64) @ (K @ R).T + K @ t
    return x[:, :2] / x[:, 2:3]


def mspd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    K: np.ndarray,
    pts: np.ndarray,
    sym_R: np.ndarray | None = None,
    sym_t: np.ndarray | None = None,
) -> float:
    """Maximum Symmetry-aware Projection Distance in pixels.

    Arguments as :func:`mssd`, plus the intrinsics ``K`` (3, 3).
    """
    R_e, t_e = _as_pose(R_e, t_e)
    R_g, t_g = _as_pose(R_g, t_g)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    pts = np.asarray(pts, dtype=np.float64)
    if sym_R is None:
        sym_R, sym_t = _identity_syms()
    sym_R = np.asarray(sym_R, dtype=np.float64)
    sym_t = np.asarray(sym_t, dtype=np.float64)

    proj_e = project(pts, K, R_e, t_e)
    # Homogeneous image points of variant s: A_s p + b_s with A_s = K R_g R_s and
    # b_s = K (R_g t_s + t_g).
    KR = K @ R_g
    A = KR[None] @ sym_R
    b = sym_t @ KR.T + K @ t_g
    best = np.inf
    step = max(1, _BLOCK // max(1, len(pts)))
    for a in range(0, len(sym_R), step):
        x = pts[None] @ A[a : a + step].transpose(0, 2, 1) + b[a : a + step, None, :]
        uv = x[..., :2] / x[..., 2:3]
        d = np.sqrt(((uv - proj_e[None]) ** 2).sum(-1)).max(-1)
        best = min(best, float(d.min()))
    return best

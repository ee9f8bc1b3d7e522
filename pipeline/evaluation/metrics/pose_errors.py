"""MSSD and MSPD pose errors (BOP 2019), vectorised over symmetry transformations.

Both compare the model points in the estimated pose with the points in every
symmetric variant ``(R_g R_s, R_g t_s + t_g)`` of the ground-truth pose, take the
maximum over points and the minimum over variants.

Objects with a continuous symmetry have hundreds of variants, so the minimum is found
by branch and bound, which gives exactly the brute-force value: the maximum over a
few well-spread "probe" vertices is a lower bound of each variant's error; variants
are then evaluated on all vertices in increasing order of that bound until the bound
reaches the best error found.

Units: points and translations in mm, MSSD in mm, MSPD in pixels.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

# Work arrays hold about this many (variant, point) pairs (~3 MB per float64 array).
_BLOCK = 1 << 17
# Number of probe vertices used for the lower bounds.
N_PROBES = 64


def probe_indices(pts: np.ndarray, n: int = N_PROBES) -> np.ndarray:
    """Indices (<= n,) of well-spread vertices: farthest-point sampling, starting from
    the vertex farthest from the centroid (extreme vertices dominate max-distances)."""
    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) <= n:
        return np.arange(len(pts))
    d = np.linalg.norm(pts - pts.mean(0), axis=1)
    idx = [int(d.argmax())]
    dist = np.linalg.norm(pts - pts[idx[0]], axis=1)
    for _ in range(n - 1):
        i = int(dist.argmax())
        idx.append(i)
        np.minimum(dist, np.linalg.norm(pts - pts[i], axis=1), out=dist)
    return np.asarray(idx)


def hull_indices(pts: np.ndarray) -> np.ndarray:
    """Sorted indices of the vertices of the convex hull of ``pts`` (N, 3); all points
    when the hull is degenerate (flat or too few points).

    MSSD over these vertices equals MSSD over all points: per symmetry variant the
    distance ``|A p + b|`` is a convex function of the model point p, so its maximum
    over the model is attained at a hull vertex. (MSPD divides by depth, so it has no
    such property; there the hull vertices only give a tight lower bound.)
    """
    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) < 5:
        return np.arange(len(pts))
    from scipy.spatial import ConvexHull, QhullError

    try:
        return np.sort(ConvexHull(pts).vertices)
    except (QhullError, ValueError):
        return np.arange(len(pts))


def _min_of_max(
    dists: Callable[[np.ndarray, np.ndarray | slice], np.ndarray],
    n_syms: int,
    n_pts: int,
    probes: np.ndarray,
    mid: np.ndarray | None = None,
) -> float:
    """``min_s max_v dists(s, v)`` by branch and bound.

    dists(sym_idx (k,), pts) -> (k, m) distances for the given variants and points
    (``pts`` an index array or ``slice(None)`` for all points). The maxima over
    ``probes`` and then over ``mid`` (optional, a larger subset such as the hull
    vertices) are lower bounds of a variant's value; a variant is evaluated on all
    points only while its bounds are below the best value found.
    """
    if n_syms <= 2 or len(probes) == 0 or len(probes) >= n_pts:
        best = np.inf
        step = max(1, _BLOCK // max(1, n_pts))
        for a in range(0, n_syms, step):
            best = min(best, float(dists(np.arange(a, min(a + step, n_syms)), slice(None)).max(1).min()))
        return best
    lower = np.empty(n_syms)
    step = max(1, _BLOCK // len(probes))
    for a in range(0, n_syms, step):
        s = np.arange(a, min(a + step, n_syms))
        lower[s] = dists(s, probes).max(1)
    order = np.argsort(lower, kind="stable")
    if mid is not None and not (len(probes) < len(mid) < n_pts):
        mid = None
    # The variant with the lowest bound is evaluated alone first: it is usually the
    # minimum, and then its value prunes most of the others.
    best = float(dists(order[:1], slice(None)).max())
    if mid is None:
        step = max(1, min(16, _BLOCK // n_pts))
    else:
        step = max(1, min(64, _BLOCK // len(mid)))
    for a in range(1, n_syms, step):
        s = order[a : a + step]
        s = s[lower[s] < best]
        if len(s) == 0:
            break  # bounds are sorted: no later variant can beat ``best``
        if mid is None:
            best = min(best, float(dists(s, slice(None)).max(1).min()))
            continue
        # Tighter bounds on the subset, then all points in increasing order of them.
        bound = dists(s, mid).max(1)
        for j in np.argsort(bound, kind="stable"):
            if bound[j] >= best:
                break
            best = min(best, float(dists(s[j : j + 1], slice(None)).max()))
    return best


def _prepare(R_e, t_e, R_g, t_g, pts, sym_R, sym_t):
    R_e = np.asarray(R_e, dtype=np.float64).reshape(3, 3)
    t_e = np.asarray(t_e, dtype=np.float64).reshape(3)
    R_g = np.asarray(R_g, dtype=np.float64).reshape(3, 3)
    t_g = np.asarray(t_g, dtype=np.float64).reshape(3)
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if sym_R is None:
        sym_R, sym_t = np.eye(3)[None], np.zeros((1, 3))
    sym_R = np.asarray(sym_R, dtype=np.float64).reshape(-1, 3, 3)
    sym_t = np.asarray(sym_t, dtype=np.float64).reshape(-1, 3)
    return R_e, t_e, R_g, t_g, pts, sym_R, sym_t


def mssd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    pts: np.ndarray,
    sym_R: np.ndarray | None = None,
    sym_t: np.ndarray | None = None,
    probes: np.ndarray | None = None,
) -> float:
    """Maximum Symmetry-aware Surface Distance in mm.

    R_*: (3, 3), t_*: (3,) mm, model-to-camera. pts: (V, 3) model vertices in mm.
    sym_R: (S, 3, 3), sym_t: (S, 3) mm from :func:`symmetry_transformations`
    (identity only when omitted). probes: :func:`probe_indices` of ``pts`` (computed
    when omitted; pass them to save time on repeated calls). Passing only the convex
    hull vertices of the model as ``pts`` gives the same value (see
    :func:`hull_indices`), much faster.
    """
    R_e, t_e, R_g, t_g, pts, sym_R, sym_t = _prepare(R_e, t_e, R_g, t_g, pts, sym_R, sym_t)
    # |R_e p + t_e - R_g(R_s p + t_s) - t_g| = |q - (R_s p + t_s)| with q in the model
    # frame of the GT pose (rotations preserve lengths).
    q = (pts @ R_e.T + (t_e - t_g)) @ R_g
    pts_T, q_T = np.ascontiguousarray(pts.T), np.ascontiguousarray(q.T)  # (3, V)
    sym_R_rows = sym_R.reshape(-1, 3)  # (3 S, 3): one matrix product for many variants

    def dists(s: np.ndarray, v: np.ndarray | slice) -> np.ndarray:
        rows = (3 * s[:, None] + np.arange(3)).reshape(-1)
        y = (sym_R_rows[rows] @ pts_T[:, v]).reshape(len(s), 3, -1) + sym_t[s][:, :, None]
        return np.sqrt(((q_T[:, v][None] - y) ** 2).sum(1))

    if probes is None:
        probes = probe_indices(pts) if len(sym_R) > 2 else np.arange(0)
    return _min_of_max(dists, len(sym_R), len(pts), probes)


def project(pts: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) float64 of points (N, 3) mm under pose (R, t) and K (3, 3)."""
    K = np.asarray(K, dtype=np.float64)
    x = np.asarray(pts, dtype=np.float64) @ (K @ R).T + K @ np.asarray(t, dtype=np.float64).reshape(3)
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
    probes: np.ndarray | None = None,
    mid: np.ndarray | None = None,
) -> float:
    """Maximum Symmetry-aware Projection Distance in pixels.

    Arguments as :func:`mssd`, plus the intrinsics ``K`` (3, 3), and ``mid``: optional
    indices of a subset of ``pts`` (e.g. :func:`hull_indices`) that bounds the
    variants between the probes and all points (same value, less work).
    """
    R_e, t_e, R_g, t_g, pts, sym_R, sym_t = _prepare(R_e, t_e, R_g, t_g, pts, sym_R, sym_t)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    proj_e = project(pts, K, R_e, t_e)
    # Homogeneous image point of variant s: A_s p + b_s, A_s = K R_g R_s, b_s = K (R_g t_s + t_g).
    KR = K @ R_g
    A_rows = (KR[None] @ sym_R).reshape(-1, 3)  # (3 S, 3): one matrix product for many variants
    b = sym_t @ KR.T + K @ t_g
    pts_T, proj_T = np.ascontiguousarray(pts.T), np.ascontiguousarray(proj_e.T)  # (3, V), (2, V)

    def dists(s: np.ndarray, v: np.ndarray | slice) -> np.ndarray:
        rows = (3 * s[:, None] + np.arange(3)).reshape(-1)
        x = (A_rows[rows] @ pts_T[:, v]).reshape(len(s), 3, -1) + b[s][:, :, None]
        uv = x[:, :2] / x[:, 2:3]
        return np.sqrt(((uv - proj_T[:, v][None]) ** 2).sum(1))

    if probes is None:
        probes = probe_indices(pts) if len(sym_R) > 2 else np.arange(0)
    return _min_of_max(dists, len(sym_R), len(pts), probes, mid)

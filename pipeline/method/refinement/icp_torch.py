"""Batched ICP in torch: many starts of one model against one scene cloud at once, on
the run's device (issue 31's GPU scene side).

:func:`refine_icp_batch` runs, for each of B starts, exactly the loop of
:func:`pipeline.method.refinement.icp.refine_icp` (the same coarse-to-fine stages, damped
point-to-plane or Kabsch steps, and the same stopping tests, each start stopping on its
own): the hypotheses of one candidate share its scene points, so every iteration is a
handful of (B, M, ...) tensor operations instead of B small numpy ones, and the nearest
neighbours are a brute-force distance matrix, where a GPU beats a k-d tree.

On a CPU the numpy path stays the one the pipeline runs: pykdtree's query is linear in
the scene points and needs no (M, N) matrix, and for one hypothesis at a time numpy has
less overhead per operation than torch (20 starts: 0.06 s against 6 s on one core).

Both compute in float64, with the sums in another order: from starts that converge
they give the same poses to 1e-7 degrees and the same iteration counts
(``tests/test_icp_torch.py``, on the CPU). A hypothesis far from any fit wanders, and
there the rounding grows about 30-fold an iteration along the directions the points
barely constrain, so the two part after ten or so iterations (on ``synthtiny`` 9 to 11
of 73 hypotheses ended elsewhere), as two BLAS builds would; the choices and the AR are
the same (0 of 10 candidates chose otherwise, AR 0.8524 both:
``benchmarks/results/scene_paths.md``, which also has ``semilmo``).

Shapes and units: poses are model-to-camera ``R`` (B, 3, 3), ``t`` (B, 3) mm, as BOP's;
the scene is aligned to the model, as in :mod:`pipeline.method.refinement.icp`.
"""

from __future__ import annotations

import math
import weakref
from typing import Sequence

import numpy as np

from pipeline.method.refinement.icp import (
    MIN_STEP_FRAC,
    STALL_GAIN,
    STALL_ITERATIONS,
    WEAK_FRAC,
    IcpModel,
    IcpResult,
    checked_inputs,
)

NN_CHUNK = 1 << 24
"""Largest number of (scene point, model point) distances held at once (128 MiB in
float64): the starts, and for large clouds the scene points, are queried in blocks
small enough for this."""


_ON_DEVICE: "weakref.WeakKeyDictionary[IcpModel, dict]" = weakref.WeakKeyDictionary()
"""IcpModel -> {(device, dtype): (points, normals)}: a model's tensors, copied to a device
once, as IcpModel builds its k-d tree once (every candidate's ICPs on the object reuse
them; a GPU would otherwise receive the model again for each candidate, turn and fine ICP)."""


def _model_tensors(model: IcpModel, kw: dict):
    """``model``'s points and normals (None without) as tensors with ``kw`` (dtype, device)."""
    import torch

    key = (str(kw["device"]), str(kw["dtype"]))
    cached = _ON_DEVICE.setdefault(model, {})
    if key not in cached:
        cached[key] = (torch.as_tensor(model.points, **kw),
                       None if model.normals is None else torch.as_tensor(model.normals, **kw))
    return cached[key]


def _nearest(q, model, threshold: float):
    """Nearest model point of every point of ``q`` (b, M, 3): (distance (b, M), with inf
    beyond ``threshold``, as pykdtree's ``distance_upper_bound`` gives; index (b, M), the
    number of model points where none is within it)."""
    import torch

    b, m = q.shape[:2]
    n = len(model)
    rows = max(1, min(m, NN_CHUNK // max(1, n)))  # scene points per block (the fine ICP: 2000 x 20000)
    per = max(1, NN_CHUNK // max(1, rows * n))    # starts per block
    idx = torch.empty((b, m), dtype=torch.long, device=q.device)
    for s in range(0, b, per):
        for r in range(0, m, rows):
            block = q[s:s + per, r:r + rows]
            idx[s:s + per, r:r + rows] = torch.cdist(block, model.expand(len(block), n, 3)).argmin(dim=2)
    # The distance again from the chosen pair: cdist's matrix-product form loses digits.
    dist = torch.linalg.vector_norm(q - model[idx], dim=2)
    far = dist > threshold
    return dist.masked_fill(far, math.inf), idx.masked_fill(far, n)


def _rodrigues(w):
    """Rotations (b, 3, 3) by the rotation vectors ``w`` (b, 3) rad (identity where 0), as
    :func:`pipeline.method.geometry.transforms.rotation_about_axis`."""
    import torch

    theta = torch.linalg.vector_norm(w, dim=1)
    axis = w / torch.where(theta > 0, theta, torch.ones_like(theta))[:, None]
    x, y, z = axis.unbind(1)
    s, c = torch.sin(theta), torch.cos(theta)
    C = 1.0 - c
    R = torch.stack([c + x * x * C, x * y * C - z * s, x * z * C + y * s,
                     y * x * C + z * s, c + y * y * C, y * z * C - x * s,
                     z * x * C - y * s, z * y * C + x * s, c + z * z * C], dim=1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(R)
    return torch.where((theta > 0)[:, None, None], R, eye)


def _plane_steps(q, m, n, ok, weak_frac: float):
    """Damped point-to-plane steps of :func:`pipeline.method.refinement.icp._plane_step`
    for each start at once: ``q`` (b, M, 3) moved points, ``m``/``n`` (b, M, 3) their
    model points and normals, ``ok`` (b, M) the pairs within the threshold. Returns
    (Rw (b, 3, 3), c (b, 3), v (b, 3), step (b,) mm)."""
    import torch

    w = ok.to(q.dtype)[..., None]
    k = w.sum(dim=1)                                         # (b, 1)
    c = (q * w).sum(dim=1) / k
    qc = (q - c[:, None]) * w
    L = torch.sqrt((qc * qc).sum(dim=(1, 2)) / k[:, 0]).clamp_min(1e-9)
    J = torch.cat([torch.linalg.cross(qc, n, dim=2) / L[:, None, None], n * w], dim=2)  # (b, M, 6)
    r = ((q - m) * n).sum(dim=2) * w[..., 0]
    A = J.transpose(1, 2) @ J
    finite = torch.isfinite(A).all(dim=(1, 2))
    A = torch.where(finite[:, None, None], A, torch.eye(6, dtype=A.dtype, device=A.device))
    lam, V = torch.linalg.eigh(A)
    top = lam[:, -1]
    usable = finite & (top > 0)
    g = -(J.transpose(1, 2) @ r[..., None])[..., 0]          # (b, 6)
    damp = torch.maximum(weak_frac * top, 1e-12 * top)
    x = (V @ (((V.transpose(1, 2) @ g[..., None])[..., 0] / (lam + damp[:, None]))[..., None]))[..., 0]
    x = torch.where(usable[:, None], x, torch.zeros_like(x))
    Rw = _rodrigues(x[:, :3] / L[:, None])
    step = torch.linalg.vector_norm(x[:, :3], dim=1) + torch.linalg.vector_norm(x[:, 3:], dim=1)
    return Rw, c, x[:, 3:], step


def _point_steps(q, m, ok):
    """Kabsch steps of :func:`pipeline.method.refinement.icp._point_step` for each start
    at once (shapes as :func:`_plane_steps`)."""
    import torch

    w = ok.to(q.dtype)[..., None]
    k = w.sum(dim=1)
    c, cm = (q * w).sum(dim=1) / k, (m * w).sum(dim=1) / k
    qc, mc = (q - c[:, None]) * w, (m - cm[:, None]) * w
    U, _, Vt = torch.linalg.svd(qc.transpose(1, 2) @ mc)
    d = torch.sign(torch.linalg.det(Vt.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=1))
    Rw = Vt.transpose(1, 2) @ D @ U.transpose(1, 2)
    v = cm - c
    L = torch.sqrt((qc * qc).sum(dim=(1, 2)) / k[:, 0])
    # The angle as rotation_angle_deg measures it (atan2: accurate near 0 degrees).
    skew = torch.stack([Rw[:, 2, 1] - Rw[:, 1, 2], Rw[:, 0, 2] - Rw[:, 2, 0], Rw[:, 1, 0] - Rw[:, 0, 1]], dim=1)
    angle = torch.atan2(0.5 * torch.linalg.vector_norm(skew, dim=1), 0.5 * (Rw.diagonal(dim1=1, dim2=2).sum(dim=1) - 1.0))
    return Rw, c, v, angle * L + torch.linalg.vector_norm(v, dim=1)


def refine_icp_batch(
    model: IcpModel,
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
    device: str = "cpu",
    dtype: str = "float64",
) -> list[IcpResult]:
    """:func:`pipeline.method.refinement.icp.refine_icp` of B starts ``(R0 (B, 3, 3),
    t0 (B, 3))`` (model-to-camera, mm) of ``model`` against ``scene_points`` (M, 3) mm,
    run together on ``device`` in ``dtype``; the keyword arguments mean what they mean
    there. Returns one :class:`IcpResult` per start, in their order."""
    import torch

    scene_np = checked_inputs(model, scene_points, schedule, point_to_plane, "refine_icp_batch")
    R0 = np.asarray(R0, dtype=np.float64).reshape(-1, 3, 3)
    t0 = np.asarray(t0, dtype=np.float64).reshape(-1, 3)
    if len(R0) != len(t0):
        raise ValueError(f"refine_icp_batch: {len(R0)} rotations but {len(t0)} translations")
    if not len(R0):
        return []
    kw = {"dtype": getattr(torch, dtype), "device": torch.device(device)}
    pts, nrm = _model_tensors(model, kw)
    scene = torch.as_tensor(scene_np, **kw)
    Rm = torch.as_tensor(R0, **kw)
    R = Rm.transpose(1, 2).contiguous()                      # camera -> model
    t = -(R @ torch.as_tensor(t0, **kw)[..., None])[..., 0]
    B, M = len(R), len(scene)
    min_step = float(min_step_frac * diameter)
    done = torch.zeros(B, dtype=torch.long, device=kw["device"])
    for scale in schedule:
        threshold = float(max_corr_dist_frac * diameter * scale)
        active = torch.ones(B, dtype=torch.bool, device=kw["device"])
        previous = None
        best = torch.full((B,), math.inf, **kw)
        stalled = torch.zeros(B, dtype=torch.long, device=kw["device"])
        for _ in range(int(iterations)):
            live = active.nonzero()[:, 0]
            if not len(live):
                break
            Rl, tl = R[live], t[live]
            q = scene @ Rl.transpose(1, 2) + tl[:, None]
            dist, idx = _nearest(q, pts, threshold)
            go = torch.ones(len(live), dtype=torch.bool, device=kw["device"])
            if previous is not None:
                go &= ~(idx == previous[live]).all(dim=1)    # the last step solved this very problem
            else:
                previous = torch.empty((B, M), dtype=torch.long, device=kw["device"])
            previous[live] = idx
            ok = torch.isfinite(dist)
            n_ok = ok.sum(dim=1)
            go &= n_ok >= 6
            d_ok = torch.where(ok, dist, torch.zeros_like(dist))
            cost = (d_ok * d_ok).sum(dim=1) + (M - n_ok).to(dist.dtype) * threshold ** 2
            st = torch.where(cost > best[live] * (1.0 - STALL_GAIN), stalled[live] + 1, torch.zeros_like(n_ok))
            # Only the starts still going count this iteration's cost, as the loop of one does.
            stalled[live] = torch.where(go, st, stalled[live])
            best[live] = torch.where(go, torch.minimum(best[live], cost), best[live])
            go &= stalled[live] < STALL_ITERATIONS
            near = idx.clamp_max(len(pts) - 1)
            if point_to_plane:
                Rw, c, v, step = _plane_steps(q, pts[near], nrm[near], ok, weak_frac)
            else:
                Rw, c, v, step = _point_steps(q, pts[near], ok)
            moved = live[go]
            Rw, c, v, step = Rw[go], c[go], v[go], step[go]
            R[moved] = Rw @ R[moved]
            t[moved] = (Rw @ (t[moved] - c)[..., None])[..., 0] + c + v
            done[moved] += 1
            active[live[~go]] = False
            active[moved[step < min_step]] = False
    dist, _ = _nearest(scene @ R.transpose(1, 2) + t[:, None], pts, threshold)
    ok = torch.isfinite(dist)
    fitness = ok.to(dist.dtype).mean(dim=1)
    sq = torch.where(ok, dist * dist, torch.zeros_like(dist)).sum(dim=1)
    rmse = torch.sqrt(sq / ok.sum(dim=1).clamp_min(1))
    Rc = R.transpose(1, 2)                                   # model -> camera
    tc = -(Rc @ t[..., None])[..., 0]
    Rc, tc, fitness, rmse, done = (x.cpu().numpy() for x in (Rc, tc, fitness, rmse, done))
    return [IcpResult(R=Rc[i].astype(np.float64), t=tc[i].astype(np.float64), fitness=float(fitness[i]),
                      inlier_rmse=float(rmse[i]), iterations=int(done[i])) for i in range(B)]

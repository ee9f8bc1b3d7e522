"""PointNet++ sampling and grouping in plain PyTorch (CPU or CUDA, no compiled ops).

These reproduce the semantics of the reference CUDA operators that GeDi's network was
trained with (``pointnet2_ops``), so that official weights see the same patches:

- :func:`furthest_point_sample`: the first sample is always index 0; each next sample
  is the point whose distance (squared) to the set chosen so far is largest, the
  running distance starting at ``1e10``; ties go to the lowest index. Points with
  ``|p|^2 <= 1e-3`` are never chosen after the first (the kernel skips them; GeDi's
  patches are centred on the keypoint, so this excludes a small ball around it). When
  every point is skipped the kernel returns index 0, and so does this.
- :func:`ball_query`: for each query, the indices of the first ``nsample`` points in
  index order with squared distance strictly below ``radius**2``; when fewer are found
  the remaining slots repeat the first hit; a query with no hit gets all zeros.
- :func:`group_points` / :func:`gather_points`: index gathers with batch dimension.

All functions are batched over the leading dimension ``B`` and keep the input's device.
"""

from __future__ import annotations

import torch

FPS_SKIP_MAG2 = 1e-3  # the reference kernel's `if (mag <= 1e-3) continue;`
FPS_INIT_DIST = 1e10  # the reference wrapper's initial running distance


def _sqdist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances (B, S, N) between a (B, S, 3) and b (B, N, 3), computed as the
    kernels do it: per coordinate difference, squared, summed x + y + z in order."""
    d = a.unsqueeze(2) - b.unsqueeze(1)
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def furthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """Indices (B, npoint) int64 of farthest-point samples of ``xyz`` (B, N, 3)."""
    if xyz.dim() != 3 or xyz.shape[-1] != 3:
        raise ValueError(f"furthest_point_sample: xyz must be (B, N, 3), got {tuple(xyz.shape)}")
    B, N, _ = xyz.shape
    if npoint <= 0:
        return torch.zeros((B, 0), dtype=torch.long, device=xyz.device)
    if N == 0:
        raise ValueError("furthest_point_sample: empty point set")
    xyz = xyz.float()
    out = torch.zeros((B, npoint), dtype=torch.long, device=xyz.device)
    mag = xyz[..., 0] * xyz[..., 0] + xyz[..., 1] * xyz[..., 1] + xyz[..., 2] * xyz[..., 2]
    valid = mag > FPS_SKIP_MAG2  # (B, N)
    temp = torch.full((B, N), FPS_INIT_DIST, dtype=torch.float32, device=xyz.device)
    batch = torch.arange(B, device=xyz.device)
    old = torch.zeros(B, dtype=torch.long, device=xyz.device)
    neg = torch.tensor(-1.0, device=xyz.device)
    for j in range(1, npoint):
        last = xyz[batch, old]  # (B, 3)
        diff = xyz - last.unsqueeze(1)
        d = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]
        # skipped points keep their running distance and can never win (-1 < any d2 >= 0);
        # when all are skipped, argmax of all -1 is index 0, as the kernel's besti = 0
        temp = torch.where(valid, torch.minimum(d, temp), temp)
        old = torch.argmax(torch.where(valid, temp, neg), dim=1)  # first maximal index
        out[:, j] = old
    return out


def ball_query(radius: float, nsample: int, xyz: torch.Tensor, new_xyz: torch.Tensor) -> torch.Tensor:
    """Indices (B, S, nsample) int64 of points of ``xyz`` (B, N, 3) within ``radius`` of
    each query of ``new_xyz`` (B, S, 3): the first hits in index order, padded with the
    first hit (all zeros when there is none)."""
    if xyz.dim() != 3 or new_xyz.dim() != 3 or xyz.shape[0] != new_xyz.shape[0]:
        raise ValueError(f"ball_query: shapes {tuple(xyz.shape)} and {tuple(new_xyz.shape)} do not match (B, N, 3), (B, S, 3)")
    B, N, _ = xyz.shape
    S = new_xyz.shape[1]
    if nsample <= 0:
        raise ValueError(f"ball_query: nsample must be positive, got {nsample}")
    r2 = torch.tensor(float(radius) ** 2, dtype=torch.float32)
    inside = _sqdist(new_xyz.float(), xyz.float()) < r2.to(xyz.device)  # (B, S, N)
    ar = torch.arange(N, device=xyz.device)
    key = torch.where(inside, ar, torch.full_like(ar, N))  # hits keep their index, misses sort last
    k = min(nsample, N)
    first = torch.topk(key, k, dim=-1, largest=False, sorted=True).values  # (B, S, k) ascending
    if k < nsample:
        first = torch.cat([first, torch.full((B, S, nsample - k), N, dtype=first.dtype, device=first.device)], -1)
    head = first[..., :1]
    head = torch.where(head == N, torch.zeros_like(head), head)  # no hit: the kernel's zeros
    return torch.where(first == N, head.expand_as(first), first)


def gather_points(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``points`` (B, N, C) gathered at ``idx`` (B, ...) -> (B, ..., C)."""
    B = points.shape[0]
    flat = idx.reshape(B, -1)
    out = torch.gather(points, 1, flat.unsqueeze(-1).expand(-1, -1, points.shape[-1]))
    return out.reshape(*idx.shape, points.shape[-1])


def group_points(features: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Channel-first ``features`` (B, C, N) gathered at ``idx`` (B, S, K) -> (B, C, S, K),
    the layout of the reference ``grouping_operation``."""
    B, C, _ = features.shape
    S, K = idx.shape[1], idx.shape[2]
    flat = idx.reshape(B, 1, S * K).expand(-1, C, -1)
    return torch.gather(features, 2, flat).reshape(B, C, S, K)

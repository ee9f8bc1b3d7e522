"""PointNet++ sampling and grouping in plain PyTorch (CPU or CUDA, no compiled ops).

These reproduce the semantics of the reference CUDA operators that GeDi's network was
trained with (``pointnet2_ops``), so that official weights see the same patches:

- :func:`furthest_point_sample`: the first sample is always index 0; each next sample
  is the point whose distance (squared) to the set chosen so far is largest, the
  running distance starting at ``1e10``. Points with ``|p|^2 <= 1e-3`` are never chosen
  after the first (the kernel skips them; GeDi's patches are centred on the keypoint,
  so this excludes a small ball around it). The kernel computes ``|p|^2`` in float32 and
  compares it with the double literal ``1e-3`` (the float promoted to double), and so
  does this: a point with ``|p|^2`` equal to ``float32(1e-3)``, which is above 1e-3, is
  kept. When every point is skipped the kernel returns index 0, and so does this.
  Exact ties (equal largest distances, e.g. duplicated points): the kernel's threads
  each keep the first of their own points (thread t scans t, t + T, t + 2T, ...), then
  a tree reduction over the threads keeps the lower slot's candidate on equal values,
  so which tied point wins depends on the threads' places in that tree, not only on
  the index. This one takes the lowest index (``argmax``). The two agree whenever the
  largest distance is unique. GeDi's patches are drawn with replacement, so ties are
  frequent, but between copies of one point (same coordinates: same samples), or, once
  a patch has fewer distinct points than samples, between points already chosen (a
  repeat of another centre: the same distinct centres and groups, and repeats change
  no max-pool). No descriptor changed: in ``tests/test_gedi_official.py`` the encoder
  against the same computation with the kernel's tie rule gives the same descriptors
  on 1600 keypoints (identical bits when written).
  :func:`furthest_point_sample_with_sqdist` also returns the distances it computed on
  its way, which a ball query around the samples can reuse.
- :func:`ball_query`: for each query, the indices of the first ``nsample`` points in
  index order with squared distance strictly below the kernel's ``radius * radius``,
  computed as the kernel computes it: the radius rounded to float32, then squared in
  float32 (for GeDi's radii 0.2 and 0.4 that is one ulp above ``float32(radius**2)``,
  :func:`radius_squared`); when fewer are found the remaining slots repeat the first
  hit; a query with no hit gets all zeros. :func:`ball_query_hits` gives the same hits
  without the padding (a flat list of (query, point) pairs), for callers that only
  max-pool over each group, where the repeats change nothing.
- :func:`group_points` / :func:`gather_points`: index gathers with batch dimension.
- :func:`first_of_each_key`: deduplication of flat rows, for running shared MLPs on
  distinct rows only.

Squared distances are computed as the kernels' source writes them, in float32: per
coordinate difference, squared, summed x + y + z in that order (no fused multiply-add),
so that samples and groups are the same as a float32 transcription of the kernels to
the bit (``tests/test_gedi_official.py`` checks this against such a transcription).
The compiled kernels may differ from their source in the last bit where nvcc fuses a
product and a sum (its default); that is not modelled here, nor checked on a GPU.

All functions are batched over the leading dimension ``B`` and keep the input's device.
"""

from __future__ import annotations

import torch

FPS_SKIP_MAG2 = 1e-3  # the reference kernel's `if (mag <= 1e-3) continue;`: a double literal
FPS_INIT_DIST = 1e10  # the reference wrapper's initial running distance


def radius_squared(radius: float) -> float:
    """The ball query's threshold on squared distances for ``radius``, as the kernel
    computes it: ``radius`` is a float32 there and ``radius * radius`` a float32
    product. (``float32(radius**2)`` is one ulp lower for 0.2 and 0.4, which would drop
    a point whose float32 squared distance is exactly that value.)"""
    r = torch.tensor(float(radius), dtype=torch.float32)
    return float(r * r)


def _planes(xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """x, y, z planes (B, N) float32 of ``xyz`` (B, N, 3), each contiguous so that the
    element-wise work on them runs on dense memory."""
    xyz = xyz.float()
    return xyz[..., 0].contiguous(), xyz[..., 1].contiguous(), xyz[..., 2].contiguous()


def _sqdist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances (B, S, N) between a (B, S, 3) and b (B, N, 3), computed as the
    kernels do it: per coordinate difference, squared, summed x + y + z in order.
    Works one coordinate plane at a time, so no (B, S, N, 3) temporary is made."""
    out: torch.Tensor | None = None
    for ca, cb in zip(_planes(a), _planes(b)):
        d = ca.unsqueeze(2) - cb.unsqueeze(1)
        d.mul_(d)
        out = d if out is None else out.add_(d)
    assert out is not None
    return out


def furthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """Indices (B, npoint) int64 of farthest-point samples of ``xyz`` (B, N, 3)."""
    return _farthest_points(xyz, npoint, keep_sqdist=False)[0]


def furthest_point_sample_with_sqdist(xyz: torch.Tensor, npoint: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`furthest_point_sample` and the squared distances (B, npoint, N) float32
    from each sample to every point: the sampling computes them on its way, bit for bit
    as :func:`ball_query` would around the samples (pass them as its ``sqdist``)."""
    idx, sqdist = _farthest_points(xyz, npoint, keep_sqdist=True)
    assert sqdist is not None
    return idx, sqdist


def _farthest_points(xyz: torch.Tensor, npoint: int, keep_sqdist: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Farthest-point sampling (see the module doc). One loop step per sample, each
    vectorised over the batch and the points: the sequential dependency (each sample
    depends on all before it) is inherent to FPS. Step j computes the distances to
    sample j - 1, which ``keep_sqdist`` keeps (plus those to the last sample)."""
    if xyz.dim() != 3 or xyz.shape[-1] != 3:
        raise ValueError(f"furthest_point_sample: xyz must be (B, N, 3), got {tuple(xyz.shape)}")
    B, N, _ = xyz.shape
    if npoint <= 0:
        empty = torch.zeros((B, 0), dtype=torch.long, device=xyz.device)
        return empty, (torch.zeros((B, 0, N), device=xyz.device) if keep_sqdist else None)
    if N == 0:
        raise ValueError("furthest_point_sample: empty point set")
    x, y, z = _planes(xyz)
    mag = x * x + y * y + z * z  # float32, as the kernel's `float mag`
    # The kernel compares the float mag with the double 1e-3 (promoted to double); a
    # float32 comparison would round 1e-3 up to float32(1e-3) and skip one value more.
    keep = mag.double() > FPS_SKIP_MAG2
    # Skipped points start at -1: min(-1, d >= 0) keeps them at -1, so they never win,
    # and when every point is skipped argmax over all -1 is index 0, as the kernel's
    # besti = 0. Valid points start at the wrapper's 1e10.
    temp = torch.where(keep, FPS_INIT_DIST, -1.0).float()
    out = torch.zeros((B, npoint), dtype=torch.long, device=xyz.device)
    sqdist = torch.empty((B, npoint, N), device=xyz.device) if keep_sqdist else None
    old = torch.zeros((B, 1), dtype=torch.long, device=xyz.device)
    t = torch.empty_like(x)

    def distances_to_old(d: torch.Tensor) -> torch.Tensor:
        """Squared distances (B, N) of every point to the points ``old``, into ``d``."""
        torch.sub(x, x.gather(1, old), out=d)
        d.mul_(d)
        torch.sub(y, y.gather(1, old), out=t)
        d.add_(t.mul_(t))
        torch.sub(z, z.gather(1, old), out=t)
        return d.add_(t.mul_(t))

    d = torch.empty_like(x)
    for j in range(1, npoint):
        d = distances_to_old(sqdist[:, j - 1] if sqdist is not None else d)
        torch.minimum(temp, d, out=temp)
        # first maximal index; the kernel's reduction may pick another of exactly tied
        # points (see the module doc)
        old = temp.argmax(dim=1, keepdim=True)
        out[:, j] = old[:, 0]
    if sqdist is not None:
        distances_to_old(sqdist[:, npoint - 1])
    return out, sqdist


def ball_query_hits(
    radius: float, nsample: int, xyz: torch.Tensor, new_xyz: torch.Tensor, sqdist: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The hits of :func:`ball_query` without its padding, as two flat int64 tensors
    ``(query, point)`` of equal length: ``query`` indexes the flattened (B * S) queries
    of ``new_xyz`` (B, S, 3), ``point`` the points of ``xyz`` (B, N, 3) in the same batch
    element. Each query's hits are its first ``nsample`` points in index order with
    squared distance below :func:`radius_squared` of ``radius``; a query
    with no hit gets point 0 (the kernel's all-zero row). Sorted by query, then point.
    ``sqdist``: the squared distances (B, S, N) when already at hand
    (:func:`furthest_point_sample_with_sqdist`)."""
    if xyz.dim() != 3 or new_xyz.dim() != 3 or xyz.shape[0] != new_xyz.shape[0]:
        raise ValueError(f"ball_query: shapes {tuple(xyz.shape)} and {tuple(new_xyz.shape)} do not match (B, N, 3), (B, S, 3)")
    if nsample <= 0:
        raise ValueError(f"ball_query: nsample must be positive, got {nsample}")
    B, N, _ = xyz.shape
    S = new_xyz.shape[1]
    if sqdist is None:
        sqdist = _sqdist(new_xyz, xyz)
    elif sqdist.shape != (B, S, N):
        raise ValueError(f"ball_query: sqdist must be (B, S, N) = {(B, S, N)}, got {tuple(sqdist.shape)}")
    r2 = torch.tensor(radius_squared(radius), dtype=torch.float32, device=xyz.device)  # exact: a float32 value
    query, point = (sqdist < r2).reshape(B * S, N).nonzero(as_tuple=True)  # row-major: by query, then point
    counts = torch.bincount(query, minlength=B * S)
    if bool((counts == 0).any()):  # no hit: the kernel's zeros, i.e. point 0
        lonely = (counts == 0).nonzero()[:, 0]
        order = torch.cat([query * N + point, lonely * N]).sort().values
        query, point = order // N, order % N
        counts[lonely] = 1
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(query), device=xyz.device) - starts[query]  # position in its row
    keep = rank < nsample
    return query[keep], point[keep]


def ball_query(radius: float, nsample: int, xyz: torch.Tensor, new_xyz: torch.Tensor) -> torch.Tensor:
    """Indices (B, S, nsample) int64 of points of ``xyz`` (B, N, 3) within ``radius`` of
    each query of ``new_xyz`` (B, S, 3): the first hits in index order, padded with the
    first hit (all zeros when there is none)."""
    query, point = ball_query_hits(radius, nsample, xyz, new_xyz)
    B, S = new_xyz.shape[0], new_xyz.shape[1]
    counts = torch.bincount(query, minlength=B * S)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(query), device=xyz.device) - starts[query]
    out = point[starts].unsqueeze(1).repeat(1, nsample)  # every slot the first hit
    out[query, rank] = point
    return out.view(B, S, nsample)


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


def first_of_each_key(group: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
    """Positions (M,) int64, ascending, of the first row of each distinct (group, key)
    pair among flat rows with ``group`` (P,) and ``key`` (P,) non-negative int64.

    Rows with equal group and key are identical inputs to a shared MLP whose outputs are
    max-pooled per group, so only one of them needs computing.
    """
    if len(key) == 0:
        return torch.zeros(0, dtype=torch.long, device=key.device)
    combined = group * (int(key.max()) + 1) + key
    _, inverse = torch.unique(combined, return_inverse=True)
    pos = torch.arange(len(key), device=key.device)
    first = torch.full((int(inverse.max()) + 1,), len(key), dtype=torch.long, device=key.device)
    first.scatter_reduce_(0, inverse, pos, "amin")  # lowest position: deterministic
    return first.sort().values

"""GeDi geometric encoder: pure-PyTorch inference with the official checkpoint layout.

GeDi (Poiesi & Boscaini, "Learning general and distinctive 3D local deep descriptors
for point cloud registration", TPAMI 2022) describes a keypoint by the points around it:

1. neighbours within radius ``r`` of the keypoint (``n_lrf`` = 4000 drawn without
   replacement, or all of them padded with random repeats when fewer);
2. a local reference frame (:func:`local_reference_frame`): z is the eigenvector of the
   smallest eigenvalue of ``sum (p - q)(p - q)^T / n`` over the neighbours q, its sign
   chosen so that ``sum z.(p - q) >= 0``; x is the normalised sum of the neighbours'
   tangent-plane projections weighted by ``(r - |q - p|)^2 (z.(q - p))^2``; the third
   axis is ``x cross z`` (as in the reference code, which makes the frame a reflection;
   the weights were trained with it). When the weighted sum vanishes (all neighbours in
   the tangent plane through the keypoint) x falls back to the largest-variance
   tangent direction, its sign fixed by the third moment of the projections;
3. ``n_patch`` = 512 of those neighbours, in the frame, scaled by ``1/r``;
4. the network (:class:`GeDiNet`, parameter names as in the official
   ``pnet_model_state_dict``): a quaternion network aligns the patch, three PointNet++
   set-abstraction levels (128 centres r=0.2 k=32; 64 centres r=0.4 k=16; global) with
   farthest-point sampling and ball query from :mod:`pipeline.encoders.gedi_ops`, and
   a head to a 32-d L2-normalised descriptor.

Multi-scale as in the paper: radii 0.3 and 0.4 of the object diameter, one 32-d
descriptor each, concatenated (64-d). Everything runs on CPU, or CUDA when present.

Weights: the official checkpoint (``data/chkpts/3dmatch/chkpt.tar`` of the GeDi
repository's ``download_data.py``) is a ``torch.load`` dict whose
``pnet_model_state_dict`` holds the network; it is loaded with ``weights_only=True`` and
a strict key match. Its path is the ``weights`` parameter (from the manifest), relative
to the weights folder (``weights_dir``, by default ``$FREEZE_WEIGHTS`` or
``<project>/weights``) unless absolute; the default is ``gedi/chkpt.tar`` there. A
missing file fails when the encoder is built, naming the path looked in.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from scipy.spatial import cKDTree

from pipeline.encoders.gedi_ops import ball_query, furthest_point_sample, gather_points, group_points
from pipeline.encoders.registry import GeometricEncoder, WeightsNotFound, register_encoder, resolve_weights_path

GEDI_DIM = 32
DEFAULT_WEIGHTS = "gedi/chkpt.tar"  # relative to the weights folder
STATE_KEY = "pnet_model_state_dict"

# --- network ---------------------------------------------------------------------------


def _conv1d_bn(cin: int, cout: int, relu: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv1d(cin, cout, 1, bias=False), nn.BatchNorm1d(cout)]
    if relu:
        layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def _linear_bn(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, cout, bias=False), nn.BatchNorm1d(cout), nn.ReLU())


class QuaternionNet(nn.Module):
    """PointNet regressing a unit quaternion (w, x, y, z) that rotates the patch;
    parameters ``conv1..3``, ``fc1..3`` as the official ``qnet``."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = _conv1d_bn(3, 256)
        self.conv2 = _conv1d_bn(256, 512)
        self.conv3 = _conv1d_bn(512, 1024, relu=False)
        self.fc1 = _linear_bn(1024, 512)
        self.fc2 = _linear_bn(512, 256)
        self.fc3 = nn.Linear(256, 4, bias=True)
        nn.init.zeros_(self.fc3.bias)

    def forward(self, pc: torch.Tensor) -> torch.Tensor:
        """pc (B, 3, N) -> unit quaternions (B, 4), identity-biased."""
        x = self.conv3(self.conv2(self.conv1(pc)))
        x = x.max(dim=2).values
        q = self.fc3(self.fc2(self.fc1(x)))
        q = q + torch.tensor([1.0, 0.0, 0.0, 0.0], device=q.device, dtype=q.dtype)
        return F.normalize(q, p=2, dim=1)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (B, 3, 3) of unit quaternions (B, 4) in (w, x, y, z) order."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


class SetAbstraction(nn.Module):
    """One PointNet++ set-abstraction level (single scale).

    With ``npoint``: FPS centres, ball-query groups (coordinates relative to the centre,
    then the features), shared MLP, max-pool. Without: one group of all points
    (absolute coordinates, then the features). Parameters live in ``mlps.0`` as in the
    official module: Conv2d (no bias) / BatchNorm2d / ReLU triplets.
    """

    def __init__(self, mlp: Sequence[int], npoint: int | None = None, radius: float | None = None, nsample: int | None = None):
        super().__init__()
        self.npoint, self.radius, self.nsample = npoint, radius, nsample
        layers: list[nn.Module] = []
        for cin, cout in zip(mlp[:-1], mlp[1:]):
            layers += [nn.Conv2d(cin, cout, kernel_size=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(True)]
        self.mlps = nn.ModuleList([nn.Sequential(*layers)])

    def forward(self, xyz: torch.Tensor, features: torch.Tensor | None) -> tuple[torch.Tensor | None, torch.Tensor]:
        """xyz (B, N, 3), features (B, C, N) or None -> new_xyz (B, S, 3) or None,
        new features (B, C', S) (S = 1 for the global level)."""
        xyz_t = xyz.transpose(1, 2)
        if self.npoint is None:
            new_xyz = None
            grouped = xyz_t.unsqueeze(2)
            if features is not None:
                grouped = torch.cat([grouped, features.unsqueeze(2)], dim=1)
        else:
            centres = furthest_point_sample(xyz, self.npoint)
            new_xyz = gather_points(xyz, centres)
            idx = ball_query(self.radius, self.nsample, xyz, new_xyz)
            grouped = group_points(xyz_t, idx) - new_xyz.transpose(1, 2).unsqueeze(-1)
            if features is not None:
                grouped = torch.cat([grouped, group_points(features, idx)], dim=1)
        out = self.mlps[0](grouped)
        return new_xyz, out.max(dim=3).values


class GeDiNet(nn.Module):
    """The GeDi descriptor network; ``state_dict()`` keys equal the official
    ``pnet_model_state_dict`` keys (``qnet.*``, ``samodule1..3.mlps.0.*``, ``fc_layer.*``)."""

    def __init__(self, dim: int = GEDI_DIM) -> None:
        super().__init__()
        self.qnet = QuaternionNet()
        self.samodule1 = SetAbstraction([3, 128, 128, 128], npoint=128, radius=0.2, nsample=32)
        self.samodule2 = SetAbstraction([128 + 3, 256, 256, 256], npoint=64, radius=0.4, nsample=16)
        self.samodule3 = SetAbstraction([256 + 3, 512, 512, 1024])
        self.fc_layer = nn.Sequential(
            nn.Linear(1024, 512, bias=False),
            nn.BatchNorm1d(512),
            nn.ReLU(True),
            nn.Linear(512, 256, bias=False),
            nn.BatchNorm1d(256),
            nn.ReLU(True),
            nn.Dropout(0.3),
            nn.Linear(256, dim),
        )

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        """patches (B, 3, N) in the LRF, scaled by 1/r -> descriptors (B, dim), unit norm."""
        rot = quaternion_to_matrix(self.qnet(patches))
        xyz = (rot @ patches).transpose(1, 2).contiguous()
        xyz, feats = self.samodule1(xyz, None)
        xyz, feats = self.samodule2(xyz, feats)
        _, feats = self.samodule3(xyz, feats)
        return F.normalize(self.fc_layer(feats.squeeze(-1)), p=2, dim=1)


def load_gedi_net(path: str | os.PathLike, device: str | torch.device = "cpu") -> GeDiNet:
    """The network with the weights of the checkpoint at ``path`` (strict, weights_only)."""
    path = Path(path)
    if not path.is_file():
        raise WeightsNotFound(_missing_message(path), [path.resolve()])
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or STATE_KEY not in ckpt:
        keys = list(ckpt)[:8] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"gedi: {path} is not a GeDi checkpoint: no {STATE_KEY!r} entry (found {keys})")
    state = ckpt[STATE_KEY]
    # A network saved from inside torch.nn.DataParallel carries a "module." prefix.
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    net = GeDiNet()
    net.load_state_dict(state, strict=True)
    return net.to(device).eval()


def _missing_message(path: Path) -> str:
    return (
        f"gedi: weights file not found: {path.resolve()}. GeDi needs the official checkpoint "
        "(the 3DMatch 'chkpt.tar', fetched by download_data.py of the GeDi repository into "
        "data/chkpts/3dmatch/chkpt.tar). Copy it to that path, or set the encoder's "
        "'weights' parameter in the manifest to where it is (relative paths are taken from the "
        "weights folder: --config weights_dir=DIR, $FREEZE_WEIGHTS, or <project>/weights)."
    )


def _sha1(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# --- local reference frame and patches ---------------------------------------------------


def local_reference_frame(keypoints: torch.Tensor, neighbours: torch.Tensor, radius: float) -> torch.Tensor:
    """Frames (B, 3, 3) with columns x, y = x cross z, z, of ``keypoints`` (B, 3) from
    their ``neighbours`` (B, N, 3) within ``radius`` (see the module doc)."""
    d = neighbours - keypoints.unsqueeze(1)  # q - p, (B, N, 3)
    n = d.shape[1]
    cov = d.transpose(1, 2) @ d / n
    evals, evecs = torch.linalg.eigh(cov)  # ascending
    z = evecs[..., 0]
    s = (d @ z.unsqueeze(-1)).squeeze(-1).sum(1)  # sum z.(q - p); want sum z.(p - q) >= 0
    z = torch.where((s > 0).unsqueeze(-1), -z, z)
    h = (d @ z.unsqueeze(-1)).squeeze(-1)  # heights z.(q - p), (B, N)
    tangent = d - h.unsqueeze(-1) * z.unsqueeze(1)
    alpha = (radius - d.norm(dim=-1)) ** 2
    xsum = ((alpha * h * h).unsqueeze(-1) * tangent).sum(1)
    xnorm = xsum.norm(dim=-1, keepdim=True)
    # planar guard: no height anywhere -> largest-variance tangent direction, sign by skew
    e = evecs[..., 2]
    e = e - (e * z).sum(-1, keepdim=True) * z
    proj = (tangent @ e.unsqueeze(-1)).squeeze(-1)
    skew = (proj**3).sum(1)
    skew = torch.where(skew.abs() > 1e-12 * radius**3 * n, skew, proj.sum(1))
    e = torch.where((skew < 0).unsqueeze(-1), -e, e)
    scale = radius**3 * (radius * radius) * n  # magnitude of xsum for a well-curved patch
    degenerate = xnorm <= 1e-9 * scale
    x = torch.where(degenerate, e, xsum)
    x = F.normalize(x, dim=-1)
    y = torch.cross(x, z, dim=-1)
    return torch.stack([x, y, z], dim=-1)


class GeDiEncoder(GeometricEncoder):
    """GeDi descriptors of every point of a cloud, at several radii (fractions of the
    object diameter), 32-d each, concatenated.

    weights: path of the official checkpoint (see the module doc), relative to
    ``weights_dir`` unless absolute.
    n_lrf / n_patch: neighbours for the frame / points fed to the network.
    batch_size: keypoints per network batch. device: ``auto`` (CUDA when present),
    ``cpu`` or ``cuda``. seed: neighbour sampling seed (outputs are deterministic).
    """

    name = "gedi"
    version = "1"

    def __init__(
        self,
        weights: str = DEFAULT_WEIGHTS,
        radii: Sequence[float] = (0.3, 0.4),
        n_lrf: int = 4000,
        n_patch: int = 512,
        batch_size: int = 64,
        device: str = "auto",
        seed: int = 0,
        weights_dir: str | None = None,
    ) -> None:
        radii = [float(r) for r in radii]
        if not radii or any(r <= 0 for r in radii):
            raise ValueError(f"gedi: radii must be a non-empty list of positive fractions, got {radii}")
        if n_lrf <= 0 or n_patch <= 0 or n_patch > n_lrf or batch_size <= 0:
            raise ValueError(f"gedi: need 0 < n_patch <= n_lrf and batch_size > 0, got {n_patch}, {n_lrf}, {batch_size}")
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.weights = resolve_weights_path(weights, weights_dir)
        self.net = load_gedi_net(self.weights, device)
        self.weights_sha1 = _sha1(self.weights)
        self.device = torch.device(device)
        self.radii = radii
        self.n_lrf, self.n_patch, self.batch_size, self.seed = int(n_lrf), int(n_patch), int(batch_size), int(seed)
        self.dim = GEDI_DIM * len(radii)

    def signature(self) -> str:
        return "gedi-ms" if len(self.radii) > 1 else "gedi"

    def cache_params(self) -> dict[str, Any]:
        return {
            "radii": self.radii,
            "n_lrf": self.n_lrf,
            "n_patch": self.n_patch,
            "seed": self.seed,
            "weights_sha1": self.weights_sha1,
        }

    def encode(
        self,
        points: np.ndarray,
        normals: np.ndarray | None,
        diameter: float,
        *,
        viewpoint: np.ndarray | None = None,
    ) -> np.ndarray:
        """Descriptors (N, dim) of every point; normals and viewpoint are not used (the
        frame comes from the neighbourhood)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if diameter <= 0:
            raise ValueError(f"gedi: diameter must be positive, got {diameter}")
        if len(pts) == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        tree = cKDTree(pts)
        parts = [self._encode_radius(pts, tree, r * diameter) for r in self.radii]
        return np.concatenate(parts, axis=1).astype(np.float32)

    def _encode_radius(self, pts: np.ndarray, tree: cKDTree, radius: float) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        hits = tree.query_ball_point(pts, radius, return_sorted=True)
        out = np.empty((len(pts), GEDI_DIM), dtype=np.float32)
        cloud = torch.from_numpy(pts)
        for start in range(0, len(pts), self.batch_size):
            stop = min(start + self.batch_size, len(pts))
            nbr_idx = np.stack([self._draw(np.asarray(hits[i], dtype=np.int64), rng) for i in range(start, stop)])
            patch_idx = np.stack([rng.choice(self.n_lrf, self.n_patch, replace=False) for _ in range(start, stop)])
            kp = cloud[start:stop]
            nbrs = cloud[torch.from_numpy(nbr_idx)]  # (b, n_lrf, 3) float64
            lrf = local_reference_frame(kp, nbrs, radius)
            sel = torch.gather(nbrs, 1, torch.from_numpy(patch_idx).unsqueeze(-1).expand(-1, -1, 3))
            local = (sel - kp.unsqueeze(1)) / radius
            patches = (lrf.transpose(1, 2) @ local.transpose(1, 2)).float()  # (b, 3, n_patch)
            with torch.inference_mode():
                out[start:stop] = self.net(patches.to(self.device)).cpu().numpy()
        return out

    def _draw(self, hits: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """n_lrf neighbour indices: without replacement, or all hits padded with repeats."""
        if len(hits) >= self.n_lrf:
            return rng.choice(hits, self.n_lrf, replace=False)
        return np.concatenate([hits, rng.choice(hits, self.n_lrf - len(hits), replace=True)])


register_encoder("gedi", "geometric", GeDiEncoder, weights=True)

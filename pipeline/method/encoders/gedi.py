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
   farthest-point sampling and ball query from :mod:`pipeline.method.encoders.gedi_ops`, and
   a head to a 32-d L2-normalised descriptor. The quaternion becomes a rotation as in
   the official code (:func:`official_rotation`: torchgeometry 0.1.2's quaternion ->
   angle-axis -> matrix, whose ``theta + 1e-6`` division and small-angle branch put it
   about 1e-6 off the exact rotation), not by the exact formula: the samples and groups
   of the next levels are decided on the rotated coordinates, and 1e-6 is enough to
   flip a decision on a few keypoints in a thousand (descriptor moved by up to 0.1).

Agreement with the official code (github fabiopoiesi/gedi): frame and its sign, 1/r
scaling, rotation, farthest-point sampling and ball query follow it step by step; the
frame is built in float64 here (float32 there: up to 3e-4 apart), the rotation equals
torchgeometry's to the bit on the CPU, and sampling and grouping equal a float32
transcription of the reference CUDA kernels, apart from which of exactly tied FPS
candidates is taken (the kernel's thread reduction breaks ties by thread position, this
takes the lowest index; it changed no descriptor, :mod:`pipeline.method.encoders.gedi_ops`).
``tests/test_gedi_official.py`` checks each step and runs whole clouds (800 keypoints
of a model and of a scene) against an oracle path built from torchgeometry and the
transcribed kernels.

Multi-scale as in the paper: radii 0.3 and 0.4 of the object diameter, one 32-d
descriptor each, concatenated (64-d).

Device. Everything that is torch runs on the encoder's ``device`` (``auto``: CUDA when
present; the run's ``--config device=cpu|cuda`` replaces the manifest's value): the
local reference frames and patches (float64), farthest-point sampling, ball query and
the network (its folded layers, :class:`GeDiInference`, folded on the CPU so that every
device gets the same weights; the module ``GeDiEncoder.net`` stays on the CPU as the
reference the tests compare with). The neighbour search of step 1 is scipy's k-d tree
and the random draws are numpy's, on the CPU, on every device (they are cheap next to
the network, and keeping them there keeps the draws the same everywhere). Precision is
float32 on every device, with no autocast: sampling and grouping reproduce the
reference kernels' float32 distances bit for bit, and a bf16 network would change the
features the next level groups. The device is not part of ``cache_params()``: CPU and
CUDA give the same descriptors up to float rounding (the stages record the device in
their manifests instead).

Inference (:class:`GeDiInference`) computes the same function as ``GeDiNet.forward``
with less work (``benchmarks/gedi_speed.py``, ``benchmarks/results/gedi_speed.md``):

- batch norms folded into the preceding 1x1 convolutions / linear layers, which run as
  plain matrix products on (rows, channels) tensors, in blocks of rows that stay in
  cache through all the layers of a shared MLP;
- shared MLPs run only on distinct rows: a group's padding repeats (ball query) and a
  patch's repeated neighbours (drawn with replacement when the ball holds fewer than
  ``n_lrf`` points) give identical rows, and the max-pool over a group does not change
  when a row is left out that another row equals. At the second level, the part of
  the first layer that depends on a point's features is computed once per point;
- the ball query reuses the distances that farthest-point sampling computed.

The encoder runs each network call on one thread, and as many calls at once as torch
has threads (``torch.get_num_threads()``): most of the network's steps are small
element-wise ones, and threads inside one step wait for each other at every step (with
other jobs on the cores, version 1's farthest-point sampling took 10x longer on 2
threads than on 1, ``benchmarks/results/gedi_speed.md``); independent calls do not
wait. One thread per call also makes the result independent of the thread count.

Descriptors differ from ``GeDiNet.forward`` by float rounding only (cosine > 0.9999 in
``tests/test_encoders_gedi.py``): both rotate with :func:`official_rotation`, and
sampling and grouping are bit for bit the same on the same input. (The quaternions of
the two paths differ by float rounding, which can itself flip a decision, rarely.)

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
import pickle
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from scipy.spatial import cKDTree

from pipeline.method.encoders.gedi_ops import (
    ball_query,
    ball_query_hits,
    first_of_each_key,
    furthest_point_sample,
    furthest_point_sample_with_sqdist,
    gather_points,
    group_points,
)
from pipeline.formats.weights.formats import WeightsNotFound
from pipeline.method.encoders.registry import (GeometricEncoder, register_encoder, resolve_weights_path,
                                               with_checked_points)
from pipeline.method.encoders.torch_device import resolve_device

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
    """Rotation matrices (B, 3, 3) of unit quaternions (B, 4) in (w, x, y, z) order, by
    the exact closed form. Not what the network uses (:func:`official_rotation`, about
    1e-6 away from this): kept for version 1's path in ``benchmarks/gedi_speed.py`` and
    for the tests that show the difference."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


ROTVEC_EPS = 1e-6  # added to the angle before dividing by it, and the small-angle cut on angle^2


def quaternion_to_rotvec(q: torch.Tensor) -> torch.Tensor:
    """Rotation vectors (B, 3) (axis times angle, radians) of unit quaternions (B, 4)
    (w, x, y, z), with the arithmetic of ``torchgeometry.quaternion_to_angle_axis``
    (version 0.1.2), which the official GeDi code uses.

    With s = |(x, y, z)|: the angle is 2 atan2(s, w), or 2 atan2(-s, -w) when w < 0 (the
    quaternion -q, same rotation, an angle in (-pi, 0]); the vector is (x, y, z) times
    angle / s, or times 2 when s = 0. Each step is one float op in the input's dtype,
    as there: the network's float32.
    """
    # Component views of q, not copies: torch on the CPU evaluates atan2 on strided
    # inputs with the scalar libm function and on contiguous ones with its vectorised
    # one, which can differ in the last bit; the reference reads w as such a view.
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    s2 = x * x + y * y + z * z
    s = torch.sqrt(s2)
    angle = 2.0 * torch.where(w < 0.0, torch.atan2(-s, -w), torch.atan2(s, w))
    k = torch.where(s2 > 0.0, angle / s, torch.full_like(s, 2.0))
    return torch.stack([x * k, y * k, z * k], dim=1)


def rotvec_to_matrix(v: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (B, 3, 3) of rotation vectors ``v`` (B, 3), with the arithmetic
    of ``torchgeometry.angle_axis_to_rotation_matrix`` (version 0.1.2; the top-left 3x3
    of its 4x4 result).

    theta^2 = v.v as a batched (1, 3) @ (3, 1) product. Above ``ROTVEC_EPS`` Rodrigues'
    formula R = cos(t) I + (1 - cos(t)) a a^T + sin(t) [a]_x with the axis
    a = v / (t + ROTVEC_EPS): not v / t, so a is short by a factor 1 - 1e-6 / t and R is
    off the exact rotation by about 1e-6 (what the official network was trained and is
    run with). At or below it the first-order R = I + [v]_x. Each entry is summed in
    the reference's order, e.g. R[1, 0] = a_z sin(t) + (a_x a_y)(1 - cos(t)).
    """
    theta2 = (v.unsqueeze(1) @ v.unsqueeze(2)).reshape(-1)  # (B,): a product, as the reference
    theta = torch.sqrt(theta2)
    a = v / (theta + ROTVEC_EPS).unsqueeze(1)
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    c, sn = torch.cos(theta), torch.sin(theta)
    one_c = 1.0 - c
    rodrigues = torch.stack(
        [
            c + ax * ax * one_c, ax * ay * one_c - az * sn, ay * sn + ax * az * one_c,
            az * sn + ax * ay * one_c, c + ay * ay * one_c, -ax * sn + ay * az * one_c,
            -ay * sn + ax * az * one_c, ax * sn + ay * az * one_c, c + az * az * one_c,
        ],
        dim=1,
    )
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    one = torch.ones_like(vx)
    first_order = torch.stack([one, -vz, vy, vz, one, -vx, -vy, vx, one], dim=1)
    # the cut compares in v's dtype (float32(1e-6) for the network), as the reference's mask
    large = (theta2 > ROTVEC_EPS).unsqueeze(1)
    return torch.where(large, rodrigues, first_order).reshape(-1, 3, 3)


def official_rotation(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (B, 3, 3) that the official GeDi code applies to the patches for
    the network's unit quaternions ``q`` (B, 4) (w, x, y, z): quaternion -> rotation
    vector -> matrix through torchgeometry 0.1.2's formulas (:func:`quaternion_to_rotvec`,
    :func:`rotvec_to_matrix`), equal to it to the bit on the CPU
    (``tests/test_gedi_official.py``). The exact matrix (:func:`quaternion_to_matrix`)
    differs by about 1e-6, enough to flip a sampling or grouping decision on a few
    keypoints in a thousand."""
    return rotvec_to_matrix(quaternion_to_rotvec(q))


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
        rot = official_rotation(self.qnet(patches))
        xyz = (rot @ patches).transpose(1, 2).contiguous()
        xyz, feats = self.samodule1(xyz, None)
        xyz, feats = self.samodule2(xyz, feats)
        _, feats = self.samodule3(xyz, feats)
        return F.normalize(self.fc_layer(feats.squeeze(-1)), p=2, dim=1)


def save_random_checkpoint(path: str | os.PathLike, seed: int = 0, extra: dict | None = None) -> Path:
    """Write random GeDi weights at ``path`` in the official checkpoint layout
    (``{STATE_KEY: state_dict}``, plus ``extra`` entries): stand-in weights for the tests,
    the benchmarks and ``scripts/gpu_check.sh``, which cost what the real ones do.

    The batch-norm statistics are set by one pass over 24 random curved patches (seeded
    by ``seed``), as training would leave them: with the initial statistics a random
    network maps every patch to nearly the same descriptor, and comparisons would say
    little. Returns ``path``."""
    torch.manual_seed(seed)
    net = GeDiNet()
    for m in net.modules():
        if isinstance(m, (nn.BatchNorm1d, nn.BatchNorm2d)):
            m.momentum = None  # the statistics of this one pass, not a running blend with the initial ones
    scales = torch.rand(24, 3, 1) * 1.5 + 0.1
    bend = torch.rand(24, 1, 1) - 0.5
    xy = torch.rand(24, 2, 256) * 2 - 1
    net.train()
    with torch.no_grad():
        net(torch.cat([xy, bend * (xy[:, :1] ** 2 - xy[:, 1:] ** 2)], 1) * scales)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**(extra or {}), STATE_KEY: net.eval().state_dict()}, path)
    return path


def load_gedi_net(path: str | os.PathLike, device: str | torch.device = "cpu") -> GeDiNet:
    """The network with the weights of the checkpoint at ``path`` (strict, weights_only)."""
    from pipeline.formats.weights.formats import check_weights_file, unreadable_checkpoint

    path = Path(path)
    if not path.is_file():
        raise WeightsNotFound(_missing_message(path), [path.resolve()])
    check_weights_file(path, "gedi", "gedi")  # a web page or a truncated download: one line, before torch reads it
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError) as exc:  # torch's message advises weights_only=False
        raise unreadable_checkpoint(path, exc, "gedi", "gedi") from None
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
        "weights folder: --config weights_dir=DIR, $FREEZE_WEIGHTS, or <project>/weights). "
        "`freeze weights fetch gedi` fetches it (--config allow_download=true does not: it only "
        "applies to DINOv2's Hugging Face models)."
    )


def _sha1(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# --- inference path ----------------------------------------------------------------------


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch threads (intra-op), then restore the setting.

    The setting is process-wide: not for blocks that run while other Python threads
    use torch."""
    before = torch.get_num_threads()
    if n == before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@dataclass(frozen=True)
class Dense:
    """One 1x1 convolution or linear layer with the batch norm after it folded in, on
    rows: ``x`` (P, C_in) -> ``x @ weight.T + bias`` (P, C_out), then ReLU if ``relu``."""

    weight: torch.Tensor  # (C_out, C_in) float32
    bias: torch.Tensor  # (C_out,) float32
    relu: bool

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.addmm(self.bias, x, self.weight.t())
        return y.relu_() if self.relu else y


def fold_layers(block: nn.Module) -> list[Dense]:
    """The layers of ``block`` (eval mode) as :class:`Dense` layers: each 1x1 Conv1d /
    Conv2d / Linear with the BatchNorm and ReLU that follow it; Dropout is the identity.

    Folding uses the running statistics, in float64 before rounding to float32:
    ``BN(Wx + c) = s * (Wx + c - mean) + beta`` with ``s = gamma / sqrt(var + eps)``.
    """
    layers: list[dict[str, Any]] = []
    for m in block.modules():
        if list(m.children()):
            continue  # containers: their leaves come next, in execution order
        if isinstance(m, (nn.Conv1d, nn.Conv2d, nn.Linear)):
            if isinstance(m, (nn.Conv1d, nn.Conv2d)) and any(k != 1 for k in m.kernel_size):
                raise ValueError(f"fold_layers: only 1x1 convolutions, got kernel {m.kernel_size}")
            w = m.weight.detach().double().reshape(m.weight.shape[0], -1)
            b = m.bias.detach().double() if m.bias is not None else w.new_zeros(w.shape[0])
            layers.append({"w": w, "b": b, "relu": False})
        elif isinstance(m, (nn.BatchNorm1d, nn.BatchNorm2d)):
            last = layers[-1]
            s = m.weight.detach().double() / torch.sqrt(m.running_var.double() + m.eps)
            last["w"] = last["w"] * s.unsqueeze(1)
            last["b"] = (last["b"] - m.running_mean.double()) * s + m.bias.detach().double()
        elif isinstance(m, nn.ReLU):
            layers[-1]["relu"] = True
        elif not isinstance(m, nn.Dropout):
            raise ValueError(f"fold_layers: unexpected layer {type(m).__name__}")
    return [Dense(d["w"].float().contiguous(), d["b"].float().contiguous(), d["relu"]) for d in layers]


def run_layers(layers: Sequence[Dense], x: torch.Tensor) -> torch.Tensor:
    """Rows ``x`` (P, C_in) through ``layers`` -> (P, C_out)."""
    for layer in layers:
        x = layer(x)
    return x


# Rows per block in pooled_layers: a block's activations (at most 1024 x 1024 float32,
# 4 MB) stay in cache from one layer to the next; the 128- and 256-channel layers are
# memory-bound otherwise (1.7x slower for the first level's MLP, one thread, this CPU).
ROW_BLOCK = 1024


def pooled_layers(
    first: Callable[[int, int], torch.Tensor], rest: Sequence[Dense], group: torch.Tensor, n: int
) -> torch.Tensor:
    """Per-group maxima (n, C_out) of a shared MLP over P rows, computed in blocks of
    ``ROW_BLOCK`` rows: ``first(a, b)`` gives the first layer's outputs (b - a, C) for
    rows a..b, ``rest`` are the remaining layers, ``group`` (P,) int64 in [0, n) the
    group of each row; every group needs a row (an empty one would stay -inf)."""
    P = len(group)
    out: torch.Tensor | None = None
    for a in range(0, P, ROW_BLOCK):
        b = min(a + ROW_BLOCK, P)
        y = run_layers(rest, first(a, b))
        if out is None:
            out = torch.full((n, y.shape[1]), -torch.inf, dtype=y.dtype, device=y.device)
        out.scatter_reduce_(0, group[a:b].unsqueeze(1).expand_as(y), y, "amax")
    assert out is not None, "pooled_layers: no rows"
    return out


class GeDiInference:
    """``GeDiNet.forward`` for inference, restructured for speed on CPU; same function
    up to float rounding (see the module doc). Built from a network in eval mode; the
    weights are copied (folded) at construction.

    Call with ``patches`` (B, 3, N) float32 (in the LRF, scaled by 1/r) and optionally
    ``point_ids`` (B, N) int64 >= 0: equal ids within a patch promise equal points (the
    encoder passes the cloud index of each patch point), so their rows are computed
    once. Returns descriptors (B, 32), unit norm. Fastest with one intra-op thread
    (``torch_threads(1)``), as the encoder calls it: see the module doc.

    device: where the folded layers go (default: the network's device). They are folded
    where the network is, so a network on the CPU gives the same folded weights, bit for
    bit, to every device. Call with inputs on that device.
    """

    def __init__(self, net: GeDiNet, device: str | torch.device | None = None) -> None:
        if net.training:
            raise ValueError("GeDiInference: the network must be in eval mode (batch norms are folded)")
        q = net.qnet
        self.q_points = fold_layers(nn.Sequential(q.conv1, q.conv2, q.conv3))  # per point, then max
        self.q_head = fold_layers(nn.Sequential(q.fc1, q.fc2, q.fc3))
        self.levels = [(sa, fold_layers(sa.mlps[0])) for sa in (net.samodule1, net.samodule2)]
        self.global_level = fold_layers(net.samodule3.mlps[0])
        self.head = fold_layers(net.fc_layer)
        if device is not None:

            def move(layers: list[Dense]) -> list[Dense]:
                return [Dense(d.weight.to(device), d.bias.to(device), d.relu) for d in layers]

            self.q_points, self.q_head = move(self.q_points), move(self.q_head)
            self.levels = [(sa, move(layers)) for sa, layers in self.levels]
            self.global_level, self.head = move(self.global_level), move(self.head)

    def __call__(self, patches: torch.Tensor, point_ids: torch.Tensor | None = None) -> torch.Tensor:
        B, _, N = patches.shape
        patches = patches.float()
        ids = torch.arange(N, device=patches.device).expand(B, N) if point_ids is None else point_ids.long()
        with torch.inference_mode():
            rot = self._rotation(patches, ids)
            xyz = (rot @ patches).transpose(1, 2).contiguous()  # (B, N, 3), as the reference
            feats: torch.Tensor | None = None
            for sa, layers in self.levels:
                xyz, feats, ids = self._grouped_level(sa, layers, xyz, feats, ids)
            assert feats is not None
            S = xyz.shape[1]
            rows = torch.cat([xyz, feats], dim=-1).reshape(B * S, -1)  # absolute xyz, then features
            patch = torch.arange(B, device=rows.device).repeat_interleave(S)
            top = self.global_level[0]
            g = pooled_layers(lambda a, b: top(rows[a:b]), self.global_level[1:], patch, B)  # (B, 1024)
            return F.normalize(run_layers(self.head, g), p=2, dim=1)

    def _rotation(self, patches: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        """Rotations (B, 3, 3) from the quaternion network, run on each patch's distinct
        points only (the max over the points does not see repeats)."""
        B, _, N = patches.shape
        pts = patches.transpose(1, 2).reshape(B * N, 3)
        patch = torch.arange(B, device=patches.device).repeat_interleave(N)
        rows = first_of_each_key(patch, ids.reshape(-1))
        pts, patch = pts[rows], patch[rows]
        top = self.q_points[0]
        pooled = pooled_layers(lambda a, b: top(pts[a:b]), self.q_points[1:], patch, B)  # (B, 1024)
        q = run_layers(self.q_head, pooled)
        q = q + torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device)
        return official_rotation(F.normalize(q, p=2, dim=1))

    def _grouped_level(
        self, sa: SetAbstraction, layers: Sequence[Dense], xyz: torch.Tensor, feats: torch.Tensor | None, ids: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One set-abstraction level with centres: xyz (B, N, 3), feats (B, N, C) or None,
        ids (B, N) -> centres (B, S, 3), their features (B, S, C'), their ids (B, S).

        Rows are (centre, neighbour) pairs: the neighbour relative to the centre, then
        its features; each distinct pair once (the ball query's padding repeats the
        first hit, and equal ids are equal points)."""
        B, N = xyz.shape[0], xyz.shape[1]
        centres, sqdist = furthest_point_sample_with_sqdist(xyz, sa.npoint)  # (B, S), (B, S, N)
        new_xyz = gather_points(xyz, centres)  # (B, S, 3)
        S = new_xyz.shape[1]
        group, point = ball_query_hits(sa.radius, sa.nsample, xyz, new_xyz, sqdist)  # group in [0, B*S)
        batch = torch.div(group, S, rounding_mode="floor")
        keep = first_of_each_key(group, ids[batch, point])
        group, flat = group[keep], batch[keep] * N + point[keep]  # flat: index into (B*N)
        rel = xyz.reshape(B * N, 3)[flat] - new_xyz.reshape(B * S, 3)[group]  # as grouped - centre
        feats_flat = None if feats is None else feats.reshape(B * N, -1)
        pooled = pooled_layers(_pair_layer(layers[0], rel, flat, feats_flat), layers[1:], group, B * S)
        return new_xyz, pooled.view(B, S, -1), ids.gather(1, centres)


def _pair_layer(
    layer: Dense, rel: torch.Tensor, point: torch.Tensor, feats: torch.Tensor | None
) -> Callable[[int, int], torch.Tensor]:
    """The first layer of a grouped level, as ``first`` of :func:`pooled_layers`, on the
    pair rows [rel (P, 3), features (P, C) of ``point`` (P,), an index into ``feats``
    (M, C)] (only rel without features).

    With features, the layer is W_xyz @ rel + W_feat @ f + bias. A point's features are
    the same in every group it is in, so W_feat @ f + bias is computed once per point (M
    rows instead of P, a sixth or fewer at the second level) and gathered per pair."""
    if feats is None:
        return lambda a, b: layer(rel[a:b])
    w_xyz, w_feat = layer.weight[:, :3], layer.weight[:, 3:]
    per_point = torch.addmm(layer.bias, feats, w_feat.t())  # (M, C_out)

    def first(a: int, b: int) -> torch.Tensor:
        y = torch.addmm(per_point[point[a:b]], rel[a:b], w_xyz.t())
        return y.relu_() if layer.relu else y

    return first


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
    batch_size: keypoints per group of random draws. The seeded draws are made group by
    group (each keypoint's neighbours, then each keypoint's patch), as version 1 made
    them with its network batches, so the same value gives the same patches.
    net_batch: keypoints per network call (rounded up to a multiple of ``batch_size``);
    memory grows with it, the descriptors do not change beyond float rounding.
    device: ``auto`` (CUDA when present), ``cpu`` or ``cuda`` (see the module doc; not
    keyed). seed: neighbour sampling seed (outputs are deterministic).
    allow_download: accepted so that a run may allow downloads whatever its encoders;
    ignored (GeDi's checkpoint is not on the Hugging Face hub).
    """

    name = "gedi"
    # 2: the inference path of GeDiInference (same descriptors up to float rounding,
    # cosine > 0.9999); new bits, so a new cache key.
    # 3: the official code's rotation (torchgeometry's formulas, not the exact matrix),
    # the kernel's float32 radius * radius and its double FPS skip test: a few
    # descriptors in a thousand change by up to 0.1.
    version = "3"

    def __init__(
        self,
        weights: str = DEFAULT_WEIGHTS,
        radii: Sequence[float] = (0.3, 0.4),
        n_lrf: int = 4000,
        n_patch: int = 512,
        batch_size: int = 64,
        net_batch: int = 128,
        device: str = "auto",
        seed: int = 0,
        weights_dir: str | None = None,
        allow_download: bool = False,
    ) -> None:
        radii = [float(r) for r in radii]
        if not radii or any(r <= 0 for r in radii):
            raise ValueError(f"gedi: radii must be a non-empty list of positive fractions, got {radii}")
        if n_lrf <= 0 or n_patch <= 0 or n_patch > n_lrf or batch_size <= 0 or net_batch <= 0:
            raise ValueError(
                f"gedi: need 0 < n_patch <= n_lrf, batch_size > 0 and net_batch > 0, got {n_patch}, {n_lrf}, {batch_size}, {net_batch}"
            )
        device = resolve_device(device, "gedi")
        self.weights = resolve_weights_path(weights, weights_dir)
        # the reference module stays on the CPU (tests and benchmarks compare with it);
        # the encoder computes with its folded layers, on the device
        self.net = load_gedi_net(self.weights, "cpu")
        self.inference = GeDiInference(self.net, device=device)
        self.weights_sha1 = _sha1(self.weights)
        self.device = torch.device(device)
        self.precision = "fp32"  # on every device: see the module doc
        self.radii = radii
        self.n_lrf, self.n_patch, self.batch_size, self.seed = int(n_lrf), int(n_patch), int(batch_size), int(seed)
        self.net_batch = -(-int(net_batch) // self.batch_size) * self.batch_size
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

    @with_checked_points
    def encode(
        self,
        points: np.ndarray,
        normals: np.ndarray | None,
        diameter: float,
        *,
        viewpoint: np.ndarray | None = None,
    ) -> np.ndarray:
        """Descriptors (N, dim) float32 of every point of ``points`` (N, 3) float64 mm (N >= 1;
        see :func:`~pipeline.method.encoders.registry.with_checked_points`); normals and
        viewpoint are not used (the frame comes from the neighbourhood)."""
        tree = cKDTree(points)
        parts = [self._encode_radius(points, tree, r * diameter) for r in self.radii]
        return np.concatenate(parts, axis=1).astype(np.float32)

    def _encode_radius(self, pts: np.ndarray, tree: cKDTree, radius: float, count: int | None = None) -> np.ndarray:
        """Descriptors (count, 32) of the first ``count`` (default: all) points of ``pts``
        (N, 3) float64 mm, in the whole cloud, at ``radius`` mm.

        Keypoints go through the network ``net_batch`` at a time. On CPU, as many calls
        run at once as torch has threads, each on one thread (see the module doc); the
        random draws are made in order on this thread, so the result does not depend on
        which call finishes first. On CUDA the calls run one after the other. The k-d
        tree's neighbour lists and the draws (numpy) are made on the CPU on every device;
        the frames, patches and network run on the encoder's device.
        """
        count = len(pts) if count is None else min(int(count), len(pts))
        cloud = torch.from_numpy(pts).to(self.device)
        out = np.empty((count, GEDI_DIM), dtype=np.float32)

        def describe(start: int, nbr_idx: np.ndarray, patch_idx: np.ndarray) -> None:
            with torch.inference_mode():
                patches, ids = self._patches(cloud, start, nbr_idx, patch_idx, radius)
                desc = self.inference(patches, ids)
            out[start : start + len(desc)] = desc.cpu().numpy()

        calls = self._network_calls(pts, tree, radius, count)
        workers = torch.get_num_threads() if self.device.type == "cpu" else 1
        with torch_threads(1):
            if workers == 1:
                for call in calls:
                    describe(*call)
                return out
            with ThreadPoolExecutor(max_workers=workers) as pool:
                pending: deque[Future[None]] = deque()
                for call in calls:
                    pending.append(pool.submit(describe, *call))
                    if len(pending) > workers:  # at most one call waiting: bounded memory
                        pending.popleft().result()
                for future in pending:
                    future.result()
        return out

    def _network_calls(
        self, pts: np.ndarray, tree: cKDTree, radius: float, count: int
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(start, neighbour indices, patch positions) of each network call, in order:
        see :meth:`_draw_patches`. Neighbours are looked up for one call's keypoints at a
        time, so memory does not grow with the cloud."""
        rng = np.random.default_rng(self.seed)
        for start in range(0, count, self.net_batch):
            hits = tree.query_ball_point(pts[start : min(start + self.net_batch, count)], radius, return_sorted=True)
            yield (start, *self._draw_patches(hits, rng))

    def _draw_patches(self, hits: Sequence[list[int]], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """For keypoints with neighbour lists ``hits`` (ascending indices): indices
        (b, n_lrf) of their frame neighbours into the cloud and positions (b, n_patch) of
        their patch points among those, drawn group by group as the class doc says."""
        b = len(hits)
        nbr_idx = np.empty((b, self.n_lrf), dtype=np.int64)
        patch_idx = np.empty((b, self.n_patch), dtype=np.int64)
        for start in range(0, b, self.batch_size):
            group = range(start, min(start + self.batch_size, b))
            for i in group:
                nbr_idx[i] = self._draw(np.asarray(hits[i], dtype=np.int64), rng)
            for i in group:
                patch_idx[i] = rng.choice(self.n_lrf, self.n_patch, replace=False)
        return nbr_idx, patch_idx

    def _patches(
        self, cloud: torch.Tensor, start: int, nbr_idx: np.ndarray, patch_idx: np.ndarray, radius: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Network inputs of keypoints ``start .. start + b`` of ``cloud`` (N, 3) float64:
        patches (b, 3, n_patch) float32 in their frames, scaled by 1/radius, and the cloud
        index (b, n_patch) of each patch point (equal indices: equal points), on the
        device of ``cloud``."""
        nbr = torch.from_numpy(nbr_idx).to(cloud.device)
        pick = torch.from_numpy(patch_idx).to(cloud.device)
        kp = cloud[start : start + len(nbr)]
        nbrs = cloud[nbr]  # (b, n_lrf, 3) float64
        lrf = local_reference_frame(kp, nbrs, radius)
        sel = torch.gather(nbrs, 1, pick.unsqueeze(-1).expand(-1, -1, 3))
        local = (sel - kp.unsqueeze(1)) / radius
        patches = (lrf.transpose(1, 2) @ local.transpose(1, 2)).float()  # (b, 3, n_patch)
        return patches, torch.gather(nbr, 1, pick)

    def _draw(self, hits: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """n_lrf neighbour indices: without replacement, or all hits padded with repeats."""
        if len(hits) >= self.n_lrf:
            return rng.choice(hits, self.n_lrf, replace=False)
        return np.concatenate([hits, rng.choice(hits, self.n_lrf - len(hits), replace=True)])


register_encoder("gedi", "geometric", GeDiEncoder, weights=True)

"""GeDi on CPU: version 1 against the current inference path, side by side (run by hand).

    .venv/bin/python benchmarks/gedi_speed.py [--points 256] [--repeat 3] [--threads 2,1]
                     [--clouds scene,model] [--profile-points 128] [--bf16-points 32]

Both paths compute descriptors of the same keypoints with the same weights and the same
seeded patches. Version 1 (the encoder as it was before issue 15, 45.8 s per 1000 points
in ``results/encoders.md``) is frozen below (``V1``): its per-batch loop, its sampling
and grouping ops and the module forward of ``GeDiNet`` (1x1 convolutions, batch norms).
The current path is ``GeDiEncoder`` (``GeDiInference``).

Runs alternate, v1 / new / v1 / new ..., so that load from other jobs on the machine
falls on both alike; the table gives each pair's ratio and their median. Clouds:

- ``scene``: the setting of ``results/encoders.md``, the first 1000 points of a
  5000-point sample of an annulus (40/100 mm radii, 80 mm high), all of them
  keypoints; a scene candidate has 1000 points (``scene_features.n_points``);
- ``model``: the whole 5000-point sample (``model_features.n_points``), the first
  ``--points`` of them keypoints; denser, so fewer repeated neighbours.

Radii 0.3 and 0.4 of the diameter, n_lrf 4000, n_patch 512 (the defaults). Weights are
random with batch-norm statistics calibrated on random patches (as in the tests), so
descriptors differ between points and the cosine between the paths means something;
the cost is that of real weights. Cosine is per 32-d descriptor (one per radius).

``--threads``: torch threads for each table (both paths alike; version 1 uses them
inside each op, the current path runs that many network calls at once, one thread
each). ``--profile-points``: where the time goes in each path (cProfile, cumulative per
function, one run each). ``--bf16-points``: the inference under bf16 autocast against
fp32 (cost and cosine). Writes ``benchmarks/results/gedi_speed.md`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.method.encoders.gedi import (  # noqa: E402
    GEDI_DIM,
    GeDiEncoder,
    GeDiNet,
    SetAbstraction,
    local_reference_frame,
    quaternion_to_matrix,
    save_random_checkpoint,
)
from pipeline.method.encoders.registry import EncoderSpec, build_encoder  # noqa: E402
from pipeline.method.geometry.sampling import sample_surface  # noqa: E402


class V1:
    """Version 1 of the encoder's computation, frozen as the baseline (same patches,
    same network weights, the ops and loop it had)."""

    @staticmethod
    def sqdist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        d = a.unsqueeze(2) - b.unsqueeze(1)
        return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]

    @staticmethod
    def furthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
        B, N, _ = xyz.shape
        xyz = xyz.float()
        out = torch.zeros((B, npoint), dtype=torch.long)
        mag = xyz[..., 0] * xyz[..., 0] + xyz[..., 1] * xyz[..., 1] + xyz[..., 2] * xyz[..., 2]
        valid = mag > 1e-3
        temp = torch.full((B, N), 1e10, dtype=torch.float32)
        batch = torch.arange(B)
        old = torch.zeros(B, dtype=torch.long)
        neg = torch.tensor(-1.0)
        for j in range(1, npoint):
            last = xyz[batch, old]
            diff = xyz - last.unsqueeze(1)
            d = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]
            temp = torch.where(valid, torch.minimum(d, temp), temp)
            old = torch.argmax(torch.where(valid, temp, neg), dim=1)
            out[:, j] = old
        return out

    @staticmethod
    def ball_query(radius: float, nsample: int, xyz: torch.Tensor, new_xyz: torch.Tensor) -> torch.Tensor:
        B, N, _ = xyz.shape
        S = new_xyz.shape[1]
        r2 = torch.tensor(float(radius) ** 2, dtype=torch.float32)
        inside = V1.sqdist(new_xyz.float(), xyz.float()) < r2
        ar = torch.arange(N)
        key = torch.where(inside, ar, torch.full_like(ar, N))
        k = min(nsample, N)
        first = torch.topk(key, k, dim=-1, largest=False, sorted=True).values
        if k < nsample:
            first = torch.cat([first, torch.full((B, S, nsample - k), N, dtype=first.dtype)], -1)
        head = first[..., :1]
        head = torch.where(head == N, torch.zeros_like(head), head)
        return torch.where(first == N, head.expand_as(first), first)

    @staticmethod
    def group_points(features: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        B, C, _ = features.shape
        S, K = idx.shape[1], idx.shape[2]
        return torch.gather(features, 2, idx.reshape(B, 1, S * K).expand(-1, C, -1)).reshape(B, C, S, K)

    @staticmethod
    def gather_points(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        return torch.gather(points, 1, idx.unsqueeze(-1).expand(-1, -1, points.shape[-1]))

    @staticmethod
    def shared_mlp(sa: SetAbstraction, grouped: torch.Tensor) -> torch.Tensor:
        return sa.mlps[0](grouped).max(dim=3).values

    @staticmethod
    def set_abstraction(sa: SetAbstraction, xyz: torch.Tensor, features: torch.Tensor | None):
        xyz_t = xyz.transpose(1, 2)
        if sa.npoint is None:
            grouped = xyz_t.unsqueeze(2)
            if features is not None:
                grouped = torch.cat([grouped, features.unsqueeze(2)], dim=1)
            return None, V1.shared_mlp(sa, grouped)
        centres = V1.furthest_point_sample(xyz, sa.npoint)
        new_xyz = V1.gather_points(xyz, centres)
        idx = V1.ball_query(sa.radius, sa.nsample, xyz, new_xyz)
        grouped = V1.group_points(xyz_t, idx) - new_xyz.transpose(1, 2).unsqueeze(-1)
        if features is not None:
            grouped = torch.cat([grouped, V1.group_points(features, idx)], dim=1)
        return new_xyz, V1.shared_mlp(sa, grouped)

    @staticmethod
    def forward(net: GeDiNet, patches: torch.Tensor) -> torch.Tensor:
        rot = quaternion_to_matrix(net.qnet(patches))
        xyz = (rot @ patches).transpose(1, 2).contiguous()
        xyz, feats = V1.set_abstraction(net.samodule1, xyz, None)
        xyz, feats = V1.set_abstraction(net.samodule2, xyz, feats)
        _, feats = V1.set_abstraction(net.samodule3, xyz, feats)
        return F.normalize(net.fc_layer(feats.squeeze(-1)), p=2, dim=1)

    @staticmethod
    def encode_radius(enc: GeDiEncoder, pts: np.ndarray, tree: cKDTree, radius: float, count: int) -> np.ndarray:
        rng = np.random.default_rng(enc.seed)
        hits = tree.query_ball_point(pts[:count], radius, return_sorted=True)
        out = np.empty((count, GEDI_DIM), dtype=np.float32)
        cloud = torch.from_numpy(pts)
        for start in range(0, count, enc.batch_size):
            stop = min(start + enc.batch_size, count)
            nbr_idx = np.stack([enc._draw(np.asarray(hits[i], dtype=np.int64), rng) for i in range(start, stop)])
            patch_idx = np.stack([rng.choice(enc.n_lrf, enc.n_patch, replace=False) for _ in range(start, stop)])
            kp = cloud[start:stop]
            nbrs = cloud[torch.from_numpy(nbr_idx)]
            lrf = local_reference_frame(kp, nbrs, radius)
            sel = torch.gather(nbrs, 1, torch.from_numpy(patch_idx).unsqueeze(-1).expand(-1, -1, 3))
            local = (sel - kp.unsqueeze(1)) / radius
            patches = (lrf.transpose(1, 2) @ local.transpose(1, 2)).float()
            with torch.inference_mode():
                out[start:stop] = V1.forward(enc.net, patches).numpy()
        return out


def descriptors(enc: GeDiEncoder, path: str, pts: np.ndarray, diameter: float, count: int) -> np.ndarray:
    """(count, 32 * radii) descriptors of the first ``count`` points of ``pts`` (N, 3) mm by
    ``path`` ``v1`` or ``new``."""
    pts = np.asarray(pts, dtype=np.float64)
    tree = cKDTree(pts)
    if path == "v1":
        parts = [V1.encode_radius(enc, pts, tree, r * diameter, count) for r in enc.radii]
    else:
        parts = [enc._encode_radius(pts, tree, r * diameter, count) for r in enc.radii]
    return np.concatenate(parts, axis=1)


def calibrated_weights(folder: Path) -> Path:
    """Random GeDi weights in the official layout, batch-norm statistics calibrated on
    random curved patches (:func:`pipeline.method.encoders.gedi.save_random_checkpoint`)."""
    return save_random_checkpoint(folder / "chkpt.tar", seed=0)


def clouds() -> tuple[dict[str, np.ndarray], float]:
    """The ``scene`` (1000 points) and ``model`` (5000 points) clouds, mm, and the
    annulus diameter."""
    mesh = trimesh.creation.annulus(r_min=20, r_max=50, height=80, sections=64)
    points, _ = sample_surface(mesh, 5000, seed=0)
    return {"scene": points[:1000], "model": points}, float(np.linalg.norm(mesh.extents))


def cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine similarity of each 32-d descriptor of ``a`` and ``b`` (N, 32 * radii) -> (N * radii,)."""
    a32, b32 = a.reshape(-1, GEDI_DIM), b.reshape(-1, GEDI_DIM)
    return (a32 * b32).sum(1) / (np.linalg.norm(a32, axis=1) * np.linalg.norm(b32, axis=1))


def ab_table(enc: GeDiEncoder, cloud_sets: dict[str, np.ndarray], diameter: float, points: int, repeat: int, threads: int) -> list[str]:
    """Markdown rows: for each cloud, interleaved v1/new timings, their ratios, cosines."""
    torch.set_num_threads(threads)
    rows = []
    for name, pts in cloud_sets.items():
        count = min(points, len(pts))
        descriptors(enc, "new", pts, diameter, 8)  # warm-up (allocator, thread pools)
        times: dict[str, list[float]] = {"v1": [], "new": []}
        outs: dict[str, np.ndarray] = {}
        for rep in range(repeat):
            for path in ("v1", "new"):
                t0 = time.perf_counter()
                outs[path] = descriptors(enc, path, pts, diameter, count)
                times[path].append(time.perf_counter() - t0)
            print(f"{name} {threads}t rep {rep}: v1 {times['v1'][-1]:.1f} s, new {times['new'][-1]:.1f} s, "
                  f"ratio {times['v1'][-1] / times['new'][-1]:.2f}", flush=True)
        ratios = [a / b for a, b in zip(times["v1"], times["new"])]
        cos = cosines(outs["v1"], outs["new"])
        again = descriptors(enc, "new", pts, diameter, min(count, 128))
        same = bool(np.array_equal(again, outs["new"][: len(again)]))
        per_k = {p: 1000 * statistics.median(t) / count for p, t in times.items()}
        rows.append(
            f"| {name} ({len(pts)} points) | {threads} | {count} | {per_k['v1']:.1f} | {per_k['new']:.2f} | "
            f"{' / '.join(f'{r:.1f}' for r in ratios)} | **{statistics.median(ratios):.1f}x** | "
            f"{cos.min():.7f} / {cos.mean():.7f} | {'yes' if same else 'NO'} |"
        )
    return rows


def profile_paths(enc: GeDiEncoder, pts: np.ndarray, diameter: float, count: int) -> str:
    """cProfile of one run of each path: cumulative seconds of the functions that make up
    the work (a function, or the name of built-ins to add up), as a markdown section."""
    from pipeline.method.encoders import gedi, gedi_ops

    parts = {
        "v1": [("neighbour search (cKDTree)", "query_ball_point"), ("random draws", GeDiEncoder._draw),
               ("LRF", local_reference_frame), ("network forward", V1.forward),
               ("  quaternion net (conv1d + BN + ReLU, max)", gedi.QuaternionNet.forward),
               ("  farthest-point sampling", V1.furthest_point_sample), ("  ball query", V1.ball_query),
               ("  grouping", V1.group_points), ("  shared MLPs of the 3 levels (conv2d + BN + ReLU), max", V1.shared_mlp),
               ("  (all 1x1 convolutions, mkldnn)", "conv"), ("  (all batch norms)", "batch_norm")],
        "new": [("neighbour search (cKDTree)", "query_ball_point"), ("random draws", GeDiEncoder._draw_patches),
                ("LRF + patches", GeDiEncoder._patches), ("network forward", gedi.GeDiInference.__call__),
                ("  quaternion net on distinct points, max", gedi.GeDiInference._rotation),
                ("  farthest-point sampling", gedi_ops.furthest_point_sample_with_sqdist),
                ("  ball query", gedi_ops.ball_query_hits),
                ("  distinct rows", gedi_ops.first_of_each_key),
                ("  (all pooled MLPs: dense layers + max per group)", gedi.pooled_layers),
                ("  (all dense layers: addmm + ReLU)", gedi.run_layers)],
    }
    lines = []
    for path, threads in (("v1", torch.get_num_threads()), ("v1", 1), ("new", 1)):
        torch.set_num_threads(threads)
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        descriptors(enc, path, pts, diameter, count)
        prof.disable()
        total = time.perf_counter() - t0
        stats = pstats.Stats(prof, stream=io.StringIO()).stats  # {(file, line, name): (cc, nc, tt, ct, callers)}
        lines += [f"### {path}, {threads} thread{'s' if threads > 1 else ''}: {total:.1f} s for {count} keypoints x {len(enc.radii)} radii "
                  f"({1000 * total / count:.1f} s per 1000 points)", "",
                  "| part | s | % |", "|---|---|---|"]
        for label, fn in parts[path]:
            sec = _cumulative(stats, fn)
            lines.append(f"| {label} | {sec:.2f} | {100 * sec / total:.0f} |")
        lines.append("")
    return "\n".join(lines)


def _cumulative(stats: dict, fn) -> float:
    """Cumulative seconds of Python function ``fn`` in cProfile ``stats``; for a string,
    the summed own time of the built-ins whose name contains it."""
    if isinstance(fn, str):
        return sum(tt for (file, _, name), (_, _, tt, _, _) in stats.items() if file == "~" and fn in name)
    code = fn.__code__
    entry = stats.get((code.co_filename, code.co_firstlineno, code.co_name))
    return entry[3] if entry else 0.0


def bf16_check(enc: GeDiEncoder, pts: np.ndarray, diameter: float, count: int) -> list[str]:
    """Markdown lines: the inference under bf16 autocast against fp32 on the first
    ``count`` keypoints of ``pts`` at the first radius (cost, cosine per descriptor)."""
    tree = cKDTree(np.asarray(pts, dtype=np.float64))
    start, nbr_idx, patch_idx = next(enc._network_calls(tree.data, tree, enc.radii[0] * diameter, count))
    patches, ids = enc._patches(torch.from_numpy(tree.data), start, nbr_idx, patch_idx, enc.radii[0] * diameter)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    fp32 = enc.inference(patches, ids)
    t1 = time.perf_counter()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        bf16 = enc.inference(patches, ids).float()
    t2 = time.perf_counter()
    cos = (fp32 * bf16).sum(1)
    flags = _cpu_flags() & {"avx512_bf16", "amx_bf16"}
    return [
        f"bf16 autocast around the inference against fp32, {count} keypoints of `scene` at radius "
        f"{enc.radii[0]}, 1 thread. CPU bf16 flags: {', '.join(sorted(flags)) or 'none (no avx512_bf16, no amx_bf16)'}.", "",
        "| precision | s | cosine to fp32 min / mean |", "|---|---|---|",
        f"| fp32 | {t1 - t0:.2f} | 1 / 1 |",
        f"| bf16 autocast | {t2 - t1:.2f} | {cos.min():.3f} / {cos.mean():.3f} |", "",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=256, help="keypoints per timed run")
    ap.add_argument("--repeat", type=int, default=3, help="v1/new pairs per table row")
    ap.add_argument("--threads", default=f"{torch.get_num_threads()},1", help="comma-separated thread counts, one table each")
    ap.add_argument("--clouds", default="scene,model")
    ap.add_argument("--profile-points", type=int, default=128, help="keypoints of the profile runs (0: no profile)")
    ap.add_argument("--bf16-points", type=int, default=32, help="keypoints of the bf16 check (0: none)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "gedi_speed.md")
    args = ap.parse_args()
    command = (f"benchmarks/gedi_speed.py --points {args.points} --repeat {args.repeat} --threads {args.threads} "
               f"--clouds {args.clouds} --profile-points {args.profile_points} --bf16-points {args.bf16_points}")
    default_threads = torch.get_num_threads()
    load = os.getloadavg()[0]
    cloud_sets, diameter = clouds()
    with tempfile.TemporaryDirectory() as tmp:
        weights = calibrated_weights(Path(tmp))
        enc = build_encoder(EncoderSpec(name="gedi", params={"weights": str(weights), "radii": [0.3, 0.4]}))
        assert isinstance(enc, GeDiEncoder)
        rows = []
        for threads in [int(t) for t in args.threads.split(",")]:
            rows += ab_table(enc, {k: cloud_sets[k] for k in args.clouds.split(",")}, diameter, args.points, args.repeat, threads)
        lines = [
            "# GeDi: version 1 against the current path, side by side", "",
            f"`.venv/bin/python {command}`, torch {torch.__version__}, {_cpu()} ({os.cpu_count()} cores, "
            f"{default_threads} torch threads by default), load average {load:.1f} at the start, "
            f"{os.getloadavg()[0]:.1f} after the timings (other jobs shared the machine).", "",
            "Runs alternate v1 / new; seconds are medians, the ratio is per pair. 2 radii (0.3, 0.4), "
            "n_lrf 4000, n_patch 512. Cosine: per 32-d descriptor, v1 against new. With more than one "
            "thread, v1 splits each op across the threads, the new path runs that many network calls "
            "at once, one thread each (the encoder's default); the 1-thread rows compare the "
            "computations alone.", "",
            "| cloud | threads | keypoints | v1 s / 1000 pts | new s / 1000 pts | ratio per pair (v1 / new) | median ratio | cosine min / mean | same output twice |",
            "|---|---|---|---|---|---|---|---|---|",
            *rows, "",
        ]
        if args.profile_points > 0:
            torch.set_num_threads(default_threads)
            lines += ["## Where the time goes", "",
                      "cProfile, cumulative seconds, `scene` cloud, one run each; indented rows are part of "
                      "the network forward. The new path is profiled on one thread: with more, its "
                      "network calls run on worker threads, which cProfile does not see.", "",
                      profile_paths(enc, cloud_sets["scene"], diameter, args.profile_points)]
        if args.bf16_points > 0:
            lines += ["## bf16", "", *bf16_check(enc, cloud_sets["scene"], diameter, args.bf16_points)]
    text = "\n".join(lines)
    args.out.write_text(text + "\n")
    print(text)


def _cpu_flags() -> set[str]:
    try:
        for row in Path("/proc/cpuinfo").read_text().splitlines():
            if row.startswith("flags"):
                return set(row.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def _cpu() -> str:
    try:
        for row in Path("/proc/cpuinfo").read_text().splitlines():
            if row.startswith("model name"):
                return row.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


if __name__ == "__main__":
    main()

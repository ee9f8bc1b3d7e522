"""CPU/GPU agreement and time per call of the torch encoders, on random weights.

    .venv/bin/python benchmarks/gpu_agreement.py [--device cuda] [--weights DIR] [--points 500] [--repeat 2]

Writes random weights in the official layouts into ``--weights`` (``gedi/chkpt.tar``,
the GeDi checkpoint dict; ``dinov2_vits14_pretrain.pth``, an official DINOv2 ViT-S/14
state dict; a file already there is kept), where the default manifests look for them, so that a run can use them with
``--config weights_dir=DIR`` (``scripts/gpu_check.sh`` does); a temporary folder when
not given. Then, for GeDi (manifest ``gedi``: radii 0.3 and 0.4) on a bent surface of
``--points`` points and for DINOv2 ViT-S/14 on a batch of 8 random 224 px crops (in
the precision a run resolves on each device, ``auto``, and in fp32), it builds the
encoder on the CPU and on ``--device``, times one call on each (the median of
``--repeat`` calls after a warm-up call) and compares the outputs: the cosine of each
point's descriptor (GeDi, per radius) or of each patch token (DINOv2) between the two
devices. Exits 1 when a lowest cosine is below 0.99.

``--device cpu`` compares the CPU with itself: it checks the code path on a machine
without CUDA (the agreement is then 1).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.method.encoders.registry import EncoderSpec, build_encoder  # noqa: E402

THRESHOLD = 0.99


def gedi_weights(path: Path, seed: int = 0) -> Path:
    """Random GeDi weights as the official checkpoint, batch-norm statistics calibrated
    (:func:`pipeline.method.encoders.gedi.save_random_checkpoint`)."""
    from pipeline.method.encoders.gedi import save_random_checkpoint

    return save_random_checkpoint(path, seed=seed)


def dinov2_official_weights(path: Path, model: str = "vits14", seed: int = 0, device: str = "cpu") -> Path:
    """A random state dict under the official facebookresearch/dinov2 parameter names
    and shapes of ``model`` (any size: the SwiGLU feed-forward of ViT-g, the register
    tokens of the ``_reg`` variants), drawn on ``device`` (ViT-g/14 has 1.1 B
    parameters) and saved from the CPU. The encoder loads it strictly, so a wrong name
    or shape fails there."""
    from pipeline.method.encoders.dinov2 import MODEL_CONFIGS, NUM_REGISTER_TOKENS, PATCH_SIZE, parse_model_name

    arch, reg = parse_model_name(model)
    cfg = MODEL_CONFIGS[arch]
    g = torch.Generator(device=device).manual_seed(seed)
    D, grid = cfg["hidden_size"], cfg["image_size"] // PATCH_SIZE
    # SwiGLU hidden width as the official SwiGLUFFNFused rounds it
    hidden = (int(4 * D * 2 / 3) + 7) // 8 * 8 if cfg["use_swiglu_ffn"] else 4 * D

    def normal(*shape: int, std: float = 0.02) -> torch.Tensor:
        return (torch.randn(*shape, generator=g, device=device) * std).cpu()

    def uniform(n: int) -> torch.Tensor:
        return (0.1 + torch.rand(n, generator=g, device=device)).cpu()

    sd = {"cls_token": normal(1, 1, D), "pos_embed": normal(1, 1 + grid * grid, D), "mask_token": torch.zeros(1, D),
          "patch_embed.proj.weight": normal(D, 3, PATCH_SIZE, PATCH_SIZE), "patch_embed.proj.bias": normal(D),
          "norm.weight": 1 + normal(D, std=0.1), "norm.bias": normal(D)}
    if reg:
        sd["register_tokens"] = normal(1, NUM_REGISTER_TOKENS, D)
    for i in range(cfg["num_hidden_layers"]):
        b = f"blocks.{i}."
        sd.update({
            b + "norm1.weight": 1 + normal(D, std=0.1), b + "norm1.bias": normal(D),
            b + "attn.qkv.weight": normal(3 * D, D), b + "attn.qkv.bias": normal(3 * D),
            b + "attn.proj.weight": normal(D, D), b + "attn.proj.bias": normal(D),
            b + "ls1.gamma": uniform(D),
            b + "norm2.weight": 1 + normal(D, std=0.1), b + "norm2.bias": normal(D),
            b + "ls2.gamma": uniform(D),
        })
        if cfg["use_swiglu_ffn"]:
            sd.update({b + "mlp.w12.weight": normal(2 * hidden, D), b + "mlp.w12.bias": normal(2 * hidden),
                       b + "mlp.w3.weight": normal(D, hidden), b + "mlp.w3.bias": normal(D)})
        else:
            sd.update({b + "mlp.fc1.weight": normal(hidden, D), b + "mlp.fc1.bias": normal(hidden),
                       b + "mlp.fc2.weight": normal(D, hidden), b + "mlp.fc2.bias": normal(D)})
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(sd, path)
    return path


def make_weights(folder: Path) -> Path:
    """The weights folder the default manifests ``gedi`` and ``dinov2-vits14`` load; a
    file already there is kept (a folder of real weights is used as it is)."""
    from pipeline.method.encoders.dinov2 import official_filename

    if not (folder / "gedi" / "chkpt.tar").exists():
        gedi_weights(folder / "gedi" / "chkpt.tar")
    if not (folder / official_filename("vits14")).exists():
        dinov2_official_weights(folder / official_filename("vits14"))
    return folder


def bent_surface(n: int, seed: int = 0) -> tuple[np.ndarray, float]:
    """``n`` points (mm) of a bent, twisted sheet about 100 mm across, and its diameter."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-50, 50, size=(n, 2))
    pts = np.column_stack([uv, 0.01 * uv[:, 0] ** 2 - 0.006 * uv[:, 0] * uv[:, 1] + 3 * np.sin(uv[:, 1] / 9)])
    return pts.astype(np.float32), float(np.linalg.norm(pts.max(0) - pts.min(0)))


def timed(fn, repeat: int) -> tuple[object, float]:
    """(the warm-up call's result, median seconds of ``repeat`` more calls)."""
    out = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times) if times else float("nan")


def cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cosine of (n, d) arrays."""
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return (a * b).sum(1) / np.maximum(den, 1e-12)


def compare(name: str, params: dict, weights: Path, device: str, call, rows: list[tuple], repeat: int) -> None:
    """Build encoder ``name`` with ``params`` on the CPU and on ``device`` (as a run's
    ``--config device=...`` does), time ``call`` on each and append
    ``(label, cpu column, device column, min cosine, mean cosine)`` to ``rows``."""
    out, cols = [], []
    for d in ("cpu", device):  # two encoders, also when device is cpu
        enc = build_encoder(EncoderSpec(name=name, params=params), weights_dir=weights, device=d)
        result, seconds = timed(lambda: call(enc), repeat)
        out.append(result)
        cols.append(f"{enc.device} {getattr(enc, 'precision', '-')} {1000 * seconds:.0f} ms")
    cos = np.concatenate([cosines(x, y) for x, y in zip(*out)])
    label = f"{name} {', '.join(f'{k}={v}' for k, v in params.items())}"
    rows.append((label, *cols, float(cos.min()), float(cos.mean())))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", help="the device compared with the CPU (cpu: the CPU with itself)")
    ap.add_argument("--weights", type=Path, help="weights folder to write (default: a temporary one)")
    ap.add_argument("--points", type=int, default=500, help="points of the GeDi cloud")
    ap.add_argument("--repeat", type=int, default=2, help="timed calls per encoder and device")
    args = ap.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print(f"gpu_agreement: --device {args.device}, but no CUDA device is visible to torch here", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        weights = make_weights((args.weights or Path(tmp) / "weights").resolve())
        pts, diameter = bent_surface(args.points)
        crops = np.random.default_rng(1).integers(0, 256, (8, 224, 224, 3), dtype=np.uint8)
        rows: list[tuple] = []

        def gedi_call(e):  # one descriptor block per radius, compared per point
            d = e.encode(pts, None, diameter)
            return [d[:, i:i + 32] for i in range(0, d.shape[1], 32)]

        def dinov2_call(e):  # one row per patch token
            f = e.encode(crops)
            return [f.transpose(0, 2, 3, 1).reshape(-1, f.shape[1])]

        compare("gedi", {"radii": [0.3, 0.4]}, weights, args.device, gedi_call, rows, args.repeat)
        for precision in ("auto", "fp32"):
            compare("dinov2", {"model": "vits14", "precision": precision}, weights, args.device, dinov2_call, rows,
                    args.repeat)
        print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, device {args.device}"
              + (f" ({torch.cuda.get_device_name(args.device)})" if args.device.startswith("cuda") else "")
              + f"; GeDi on {args.points} points (per call), DINOv2 ViT-S/14 on 8 crops of 224 px (per call)")
        print(f"{'encoder':44} {'cpu: precision, time':24} {'device: precision, time':28} {'min cos':>8} {'mean cos':>9}")
        ok = True
        for label, cpu, dev, lo, mean in rows:
            ok &= lo >= THRESHOLD
            print(f"{label:44} {cpu:24} {dev:28} {lo:8.5f} {mean:9.5f}")
        print(f"gpu_agreement: {'OK' if ok else 'FAILED'}: lowest cosine "
              f"{min(r[3] for r in rows):.5f} ({'>=' if ok else '<'} {THRESHOLD})")
        return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""CPU cost of the encoders, measured side by side in one run (run by hand).

    .venv/bin/python benchmarks/encoders.py [--repeat 3] [--dinov2 vits14,vitb14] [--no-gedi]

Geometric encoders: seconds per 1000 points of a 5000-point model surface sample at the
default radii (0.3 and 0.4 of the diameter), for ``fpfh`` and ``gedi``. Visual
encoders: milliseconds per 224x224 crop in a batch of 8, for ``colortex``, ``rgb`` and
DINOv2 ViT-S/14 and ViT-B/14 in fp32 and (where the CPU supports it) bf16 autocast.
GeDi and DINOv2 run with random weights saved in their official layouts by this
script: the cost is the same as with real weights, the features are meaningless.
Medians over ``--repeat`` runs; writes ``benchmarks/results/encoders.md``.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from pipeline.encoders.registry import EncoderSpec, build_encoder
from pipeline.geometry.sampling import sample_surface

ROOT = Path(__file__).resolve().parent.parent


def _median_time(fn, repeat: int) -> float:
    fn()  # warm-up (lazy loading, allocator, thread pools)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _gedi_weights(folder: Path) -> Path:
    from pipeline.encoders.gedi import STATE_KEY, GeDiNet

    torch.manual_seed(0)
    path = folder / "chkpt.tar"
    torch.save({STATE_KEY: GeDiNet().state_dict()}, path)
    return path


def _dinov2_weights(folder: Path, model: str) -> Path:
    from transformers import Dinov2Model

    from pipeline.encoders.dinov2 import hf_config_for

    torch.manual_seed(0)
    out = folder / f"dinov2-{model}"
    Dinov2Model(hf_config_for(model)).save_pretrained(out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dinov2", default="vits14,vitb14", help="comma-separated DINOv2 sizes ('' for none)")
    ap.add_argument("--no-gedi", action="store_true")
    args = ap.parse_args()

    mesh = trimesh.creation.annulus(r_min=20, r_max=50, height=80, sections=64)
    diameter = float(np.linalg.norm(mesh.extents))
    points, normals = sample_surface(mesh, 5000, seed=0)
    crops = np.random.default_rng(0).integers(0, 256, size=(8, 224, 224, 3), dtype=np.uint8)
    rows: list[tuple[str, str, str]] = []

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        geometric = [("fpfh", {"radii": [0.3, 0.4]})]
        if not args.no_gedi:
            geometric.append(("gedi", {"weights": str(_gedi_weights(tmp)), "radii": [0.3, 0.4]}))
        for name, params in geometric:
            enc = build_encoder(EncoderSpec(name=name, params=params))
            n = 5000 if name == "fpfh" else 1000  # GeDi costs ~1 min per 1000 points on 2 cores
            sec = _median_time(lambda: enc.encode(points[:n], normals[:n], diameter), args.repeat if name == "fpfh" else 1)
            rows.append((f"{name} ({enc.dim}-d)", f"{1000 * sec / n:.3f} s per 1000 points", f"{n} points, 2 radii"))

        visual = [("colortex", {}), ("rgb", {})]
        for model in filter(None, args.dinov2.split(",")):
            weights = str(_dinov2_weights(tmp, model))
            visual.append(("dinov2", {"model": model, "weights": weights, "precision": "fp32"}))
            visual.append(("dinov2", {"model": model, "weights": weights, "precision": "auto"}))
        for name, params in visual:
            enc = build_encoder(EncoderSpec(name=name, params=params))
            sec = _median_time(lambda: enc.encode(crops), args.repeat)
            label = enc.signature() + (f" {enc.cache_params().get('precision')}" if name == "dinov2" else "")
            rows.append((f"{label} ({enc.dim}-d)", f"{1000 * sec / len(crops):.1f} ms per crop", "batch of 8, 224x224"))

    lines = ["# Encoder cost on this CPU", "",
             f"`benchmarks/encoders.py --repeat {args.repeat}`, torch {torch.__version__}, "
             f"{torch.get_num_threads()} threads; medians.", "",
             "| encoder | cost | setting |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    text = "\n".join(lines) + "\n"
    out = ROOT / "benchmarks" / "results" / "encoders.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

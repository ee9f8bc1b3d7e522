"""CPU cost of the encoders, measured side by side in one run (run by hand).

    .venv/bin/python benchmarks/encoders.py [--repeat 3] [--dinov2 vits14,vitb14] [--no-gedi]
    .venv/bin/python benchmarks/encoders.py --precision      # bf16 vs fp32 DINOv2
    .venv/bin/python benchmarks/encoders.py --pipeline       # whole-pipeline cost per pair

Geometric encoders: seconds per 1000 points of a 5000-point model surface sample at the
default radii (0.3 and 0.4 of the diameter), for ``fpfh`` and ``gedi``. Visual
encoders: milliseconds per 224x224 crop in a batch of 8, for ``colortex``, ``rgb`` and
DINOv2 ViT-S/14 and ViT-B/14 in fp32 and (where the CPU supports it) bf16 autocast.
GeDi and DINOv2 run with random weights saved in their official layouts by this
script: the cost is the same as with real weights, the features are meaningless.
Medians over ``--repeat`` runs; writes ``benchmarks/results/encoders.md``.

``--precision``: DINOv2 ViT-S/14 (random weights) in bf16 autocast against fp32, on the
42 rendered templates of two synthetic objects: cost per crop, cosine similarity of the
lifted per-point features, of the fused visual parts (PCA to 64 fitted on the fp32
features, applied to both, L2-normalised) and how often a point's nearest neighbour in
fused-feature space is the same under both precisions; then the AR of the main job on
``synthmini`` with each precision (same random weights, separate cache). Writes
``benchmarks/results/precision.md``.

``--pipeline``: the per-target cost of the whole pipeline with each encoder pair
(``--pairs``), from fresh runs of ``bop_all`` on ``synthtiny`` in a temporary cache with
random weights in a temporary weights folder (AR is meaningless there). Writes
``benchmarks/results/pipeline_pairs.md``.
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
import trimesh

from pipeline.method.encoders.registry import EncoderSpec, build_encoder
from pipeline.method.geometry.sampling import sample_surface

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
    from pipeline.method.encoders.gedi import save_random_checkpoint

    return save_random_checkpoint(folder / "chkpt.tar")


def _dinov2_weights(folder: Path, model: str, name: str | None = None) -> Path:
    from transformers import Dinov2Model

    from pipeline.method.encoders.dinov2 import hf_config_for

    torch.manual_seed(0)
    out = folder / (name or f"dinov2-{model}")
    Dinov2Model(hf_config_for(model)).save_pretrained(out)
    return out


def _random_weights_dir(folder: Path, models: tuple[str, ...] = ("vits14", "vitb14")) -> Path:
    """A weights folder with random GeDi and DINOv2 weights (``models``, default ViT-S/B)
    where the default manifests look for them (gedi/chkpt.tar; dinov2-small, dinov2-base...
    in HF layout)."""
    from pipeline.method.encoders.dinov2 import hf_dirname

    (folder / "gedi").mkdir(parents=True, exist_ok=True)
    _gedi_weights(folder / "gedi")
    for model in models:
        _dinov2_weights(folder, model, hf_dirname(model))
    return folder


def _templates(obj_id: int):
    """A synthetic object and its 42 template views (rgb, depth, K, R, t), rendered as the
    render_templates stage renders them."""
    from pipeline.method.render import Renderer
    from pipeline.method.render.templates import render_templates, template_views
    from pipeline.evaluation.synth.objects import build_object

    obj = build_object(obj_id)
    views = template_views(42, obj.diameter, 224)
    with Renderer(224, 224, znear=1.0, zfar=30 * obj.diameter) as r:
        r.add_mesh(obj_id, obj.model)
        tpl = render_templates(r, obj_id, views)
    return obj, [(tpl["rgb"][i], tpl["depth"][i], tpl["K"][i], tpl["R"][i], tpl["t"][i]) for i in range(len(tpl["rgb"]))]


def precision_check(repeat: int) -> str:
    from scipy.spatial import cKDTree

    from pipeline.method.encoders.lifting import lift_model_visual_features
    from pipeline.method.registration.fusion import apply_pca, fit_pca, l2_normalise

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from ablations import run_pair

    lines = ["# DINOv2 in bf16 autocast against fp32", "",
             f"`benchmarks/encoders.py --precision`, torch {torch.__version__}, {torch.get_num_threads()} threads, "
             "ViT-S/14 with random weights (same weights for both).", "",
             "| object | cost fp32 / bf16 (ms per crop) | lifted features: mean / min cosine | fused visual part: mean / min cosine | same nearest neighbour |",
             "|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        wdir = _random_weights_dir(Path(tmp) / "weights")
        enc = {p: build_encoder(EncoderSpec(name="dinov2", params={"model": "vits14", "precision": p}), weights_dir=wdir)
               for p in ("fp32", "bf16")}
        for obj_id in (1, 8):
            obj, views = _templates(obj_id)
            points, _ = sample_surface(obj.model, 5000, seed=0)
            crops = np.stack([v[0] for v in views[:8]])
            ms = {p: 1000 * _median_time(lambda: e.encode(crops), repeat) / len(crops) for p, e in enc.items()}
            feats = {p: lift_model_visual_features(points, views, e, diameter=obj.diameter)[0] for p, e in enc.items()}
            a, b = l2_normalise(feats["fp32"]), l2_normalise(feats["bf16"])
            cos = (a * b).sum(1)
            basis = fit_pca(feats["fp32"], 64)
            fa, fb = l2_normalise(apply_pca(basis, feats["fp32"])), l2_normalise(apply_pca(basis, feats["bf16"]))
            fcos = (fa * fb).sum(1)
            same = float((cKDTree(fa).query(fb, k=1)[1] == np.arange(len(fb))).mean())
            lines.append(f"| {obj_id} {obj.name} | {ms['fp32']:.1f} / {ms['bf16']:.1f} | {cos.mean():.5f} / {cos.min():.5f} | "
                         f"{fcos.mean():.5f} / {fcos.min():.5f} | {100 * same:.1f}% |")
        lines += ["", "Main job on `synthmini` with each precision (random weights, fresh cache):", "",
                  "| visual encoder | AR | VSD | MSSD | MSPD |", "|---|---|---|---|---|"]
        for manifest in ("dinov2-vits14", "dinov2-vits14-fp32"):
            r = run_pair("synthmini", "fpfh", manifest, weights_dir=str(wdir), cache=Path(tmp) / "cache")
            s = r.scores
            lines.append(f"| {manifest} ({enc['bf16' if manifest == 'dinov2-vits14' else 'fp32'].precision}) | "
                         f"{s['AR']:.3f} | {s['AR_VSD']:.3f} | {s['AR_MSSD']:.3f} | {s['AR_MSPD']:.3f} |")
    return "\n".join(lines) + "\n"


def pipeline_pairs(pairs: list[str]) -> str:
    """The table of ``--pipeline``: per pair, onboarding s/object, scene side s/target,
    the run's wall time, and the largest job's peak RSS on the model side
    (model_features) and on the scene side (scene_features, register, refine)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from ablations import SCENE_SIDE, run_pair

    lines = ["# Whole-pipeline cost per encoder pair", "",
             f"`benchmarks/encoders.py --pipeline --pairs {','.join(pairs)}`: fresh `bop_all` runs on `synthtiny` "
             "(3 objects, 2 images, 7 targets, 10 candidate masks) on 2 cores, random full-size weights "
             "(the cost of real ones; AR not meaningful). Onboarding: model_features job time per object "
             "(5000 points, 42 templates); scene side: scene_features + register + refine job time per target "
             "(3 candidates of 1000 points per target at most). Peak RSS: the largest job's, from the "
             "artifacts' `_manifest.json` (`peak_rss_mb`).", "",
             "| geometric + visual | onboarding s/object | scene-side s/target | run wall time (s) "
             "| peak RSS model side (GB) | peak RSS scene side (GB) |", "|---|---|---|---|---|---|"]
    from pipeline.common.config import load_encoder_manifest

    # the DINOv2 sizes the pairs use (dinov2-vitl14 -> vitl14)
    models = tuple(sorted({str(load_encoder_manifest(p.split("+")[1]).params["model"]) for p in pairs
                           if load_encoder_manifest(p.split("+")[1]).encoder == "dinov2"}))
    with tempfile.TemporaryDirectory() as tmp:
        wdir = _random_weights_dir(Path(tmp) / "weights", models)
        for pair in pairs:
            geo, vis = pair.split("+")
            r = run_pair("synthtiny", geo, vis, weights_dir=str(wdir), cache=Path(tmp) / "cache")
            model_gb = r.peak_rss_mb.get("model_features", 0.0) / 1024
            scene_gb = max(r.peak_rss_mb.get(s, 0.0) for s in SCENE_SIDE) / 1024
            print(f"{pair}: {r.onboarding_s_per_object:.1f} s/object, {r.scene_s_per_target:.2f} s/target, "
                  f"peak RSS {model_gb:.1f} / {scene_gb:.1f} GB", flush=True)
            lines.append(f"| {pair} | {r.onboarding_s_per_object:.1f} | {r.scene_s_per_target:.2f} | {r.wall_s:.0f} "
                         f"| {model_gb:.1f} | {scene_gb:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dinov2", default="vits14,vitb14", help="comma-separated DINOv2 sizes ('' for none)")
    ap.add_argument("--no-gedi", action="store_true")
    ap.add_argument("--precision", action="store_true", help="bf16 vs fp32 check instead of the cost table")
    ap.add_argument("--pipeline", action="store_true", help="whole-pipeline cost per encoder pair instead")
    ap.add_argument("--pairs", default="fpfh+colortex,fpfh+dinov2-vits14,gedi+dinov2-vits14")
    ap.add_argument("--out", type=Path, default=None, help="where --pipeline/--precision write their table "
                    "(default benchmarks/results/pipeline_pairs.md or precision.md)")
    args = ap.parse_args()
    if args.precision or args.pipeline:
        text = precision_check(args.repeat) if args.precision else pipeline_pairs(args.pairs.split(","))
        out = args.out or ROOT / "benchmarks" / "results" / ("precision.md" if args.precision else "pipeline_pairs.md")
        out.write_text(text)
        print(text)
        return

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
            n = 5000 if name == "fpfh" else 1000  # GeDi: one run; gedi_speed.py compares it with version 1
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

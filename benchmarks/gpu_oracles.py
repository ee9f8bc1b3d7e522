"""The encoders on a device against the official computations, same weights (run by hand;
``scripts/gpu_check.sh`` runs it on a GPU).

    .venv/bin/python benchmarks/gpu_oracles.py [--device cuda] [--official DIR] [--out report.md]

DINOv2: each family built by the official facebookresearch/dinov2 code (``--official``,
by default ``../shared/reference/dinov2-official``): ViT-S, -B, -L and -g at full size,
the register variants with 2 blocks (their difference is the tokens and the position
resize, not the depth), every parameter random, on ``--device``. Its patch tokens
(``forward_features(x)["x_norm_patchtokens"]``, float32) are compared with the project's
encoder loading the same state dict from the official file, on the device, in fp32 and
in the precision a run resolves there (``auto``: bf16 on a GPU with it), at 224 and 448
px. Required: fp32 minimum token cosine >= 0.999; bf16 mean cosine >= 0.99 (its
minimum is reported: bf16 keeps 8 bits of mantissa through 40 blocks).

GeDi: 800 keypoints of a model cloud and of a partial scene cloud (those of
``tests/test_gedi_official.py``), the encoder on the device against the oracle path on
the CPU (torchgeometry's rotation and the transcribed PointNet++ kernels, same seeded
patches). Required: minimum descriptor cosine >= 0.999.

Exits 1 when a requirement fails. On a machine without CUDA, ``--device cpu`` runs the
same comparisons on the CPU (slow for ViT-g: minutes).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

FP32_MIN_COS, BF16_MEAN_COS, GEDI_MIN_COS = 0.999, 0.99, 0.999
FULL = ("vits14", "vitb14", "vitl14", "vitg14")
REG_DEPTH = 2


def _token_cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine per patch token of two (B, D, g, g) maps."""
    a = a.transpose(0, 2, 3, 1).reshape(-1, a.shape[1])
    b = b.transpose(0, 2, 3, 1).reshape(-1, b.shape[1])
    return (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)


def dinov2_rows(official_dir: Path, device: str, tmp: Path, reduced: bool = False) -> tuple[list[str], bool]:
    import warnings

    from pipeline.method.encoders import dinov2 as d2
    from test_dinov2_official import HUB_FUNCTIONS, _depth, _images, _randomise

    sys.path.insert(0, str(official_dir))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from dinov2.hub import backbones
        from dinov2.models import vision_transformer as vits
    rows, ok = [], True
    models = [*FULL, *(m + "_reg" for m in FULL)]
    for i, model in enumerate(models):
        arch, reg = d2.parse_model_name(model)
        depth = REG_DEPTH if reg or reduced else None
        saved = dict(d2.MODEL_CONFIGS[arch])
        if depth:
            d2.MODEL_CONFIGS[arch] = dict(saved, num_hidden_layers=depth)
        try:
            t0 = time.perf_counter()
            with _depth(vits, depth), torch.device(device):
                net = getattr(backbones, HUB_FUNCTIONS[arch] + ("_reg" if reg else ""))(pretrained=False)
            _randomise(net.cpu(), seed=i)
            pth = tmp / d2.official_filename(model)
            torch.save(net.state_dict(), pth)
            net = net.to(device).eval()
            encs = {p: d2.Dinov2Encoder(model=model, weights=str(pth), input_size=224, precision=p, device=device)
                    for p in ("fp32", "auto")}
            for size in (224, 448):
                images = _images(4, size, seed=size)
                x = torch.from_numpy(images).to(device).permute(0, 3, 1, 2).float() / 255.0
                mean = torch.tensor(d2.IMAGENET_MEAN, device=device).view(1, 3, 1, 1)
                std = torch.tensor(d2.IMAGENET_STD, device=device).view(1, 3, 1, 1)
                with torch.inference_mode():
                    tok = net.forward_features((x - mean) / std)["x_norm_patchtokens"].float()
                g = size // d2.PATCH_SIZE
                want = tok.reshape(len(images), g, g, -1).permute(0, 3, 1, 2).cpu().numpy()
                for precision, enc in encs.items():
                    enc.input_size = size
                    got = enc.encode(images)
                    cos = _token_cosines(got, want)
                    diff = float(np.abs(got - want).max())
                    good = cos.min() >= FP32_MIN_COS if enc.precision == "fp32" else cos.mean() >= BF16_MEAN_COS
                    ok &= bool(good)
                    rows.append(f"| {model}{f' ({depth} blocks)' if depth else ''} | {size} | {enc.precision} | "
                                f"{diff:.2e} | {cos.min():.5f} | {cos.mean():.5f} | {'ok' if good else 'FAILED'} |")
            print(f"  dinov2 {model}: {time.perf_counter() - t0:.0f} s", flush=True)
            del net, encs
            pth.unlink()
            if device.startswith("cuda"):
                torch.cuda.empty_cache()
        finally:
            d2.MODEL_CONFIGS[arch] = saved
    return rows, ok


def gedi_rows(device: str, tmp: Path) -> tuple[list[str], bool]:
    from scipy.spatial import cKDTree
    from test_gedi_official import _model_cloud, _OraclePath, _scene_cloud

    from pipeline.method.encoders.gedi import GeDiEncoder, save_random_checkpoint

    weights = save_random_checkpoint(tmp / "chkpt.tar", seed=0)
    model = _model_cloud()
    radius = 0.3 * float(np.linalg.norm(model.max(0) - model.min(0)))
    rows, ok = [], True
    for name, pts in (("model", model), ("scene", _scene_cloud())):
        tree = cKDTree(pts)
        oracle_enc = GeDiEncoder(weights=str(weights), radii=[0.3], device="cpu")
        with _OraclePath(oracle_enc):
            want = oracle_enc._encode_radius(pts, tree, radius, 800)
        enc = GeDiEncoder(weights=str(weights), radii=[0.3], device=device)
        t0 = time.perf_counter()
        got = enc._encode_radius(pts, tree, radius, 800)
        seconds = time.perf_counter() - t0
        cos = (got * want).sum(1)
        good = bool(cos.min() >= GEDI_MIN_COS)
        ok &= good
        rows.append(f"| {name} cloud, 800 keypoints | {device} | {seconds:.2f} | {cos.min():.6f} | "
                    f"{int((got == want).all(1).sum())}/800 | {'ok' if good else 'FAILED'} |")
    return rows, ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--official", type=Path, default=ROOT.parent / "shared" / "reference" / "dinov2-official",
                    help="the official DINOv2 code (a folder holding dinov2/)")
    ap.add_argument("--out", type=Path, help="also write the report here")
    ap.add_argument("--skip-dinov2", action="store_true")
    ap.add_argument("--reduced", action="store_true", help=f"every DINOv2 family with {REG_DEPTH} blocks (a quick run "
                    "on a CPU)")
    args = ap.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print(f"gpu_oracles: --device {args.device}, but no CUDA device is visible to torch here", file=sys.stderr)
        return 2
    if not args.skip_dinov2 and not (args.official / "dinov2" / "hub" / "backbones.py").is_file():
        print(f"gpu_oracles: no official DINOv2 code in {args.official} (--official DIR)", file=sys.stderr)
        return 2
    lines = [f"## The encoders on {args.device} against the official computations", ""]
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        grows, gok = gedi_rows(args.device, Path(tmp))
        ok &= gok
        lines += ["GeDi (radius 0.3 d), the encoder on the device against the oracle path on the CPU "
                  f"(required: min cosine >= {GEDI_MIN_COS}):", "",
                  "| cloud | device | seconds | min cosine | identical | |", "|---|---|---|---|---|---|", *grows, ""]
        if not args.skip_dinov2:
            drows, dok = dinov2_rows(args.official.resolve(), args.device, Path(tmp), args.reduced)
            ok &= dok
            lines += ["DINOv2, the project's encoder against the official code's fp32 patch tokens, same random "
                      f"weights, on the device (required: fp32 min cosine >= {FP32_MIN_COS}, bf16 mean cosine >= "
                      f"{BF16_MEAN_COS}):", "",
                      "| model | px | precision | max abs diff | min cosine | mean cosine | |",
                      "|---|---|---|---|---|---|---|", *drows, ""]
    lines.append(f"gpu_oracles: {'OK' if ok else 'FAILED'}")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

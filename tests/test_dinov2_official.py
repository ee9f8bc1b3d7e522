"""DINOv2 equal to the official code (issue 27): every architecture family built by the
official facebookresearch/dinov2 code (``../shared/reference/dinov2-official``, a test
oracle kept outside the repository), every parameter random, saved as the official
checkpoint and loaded through the project's encoder by both routes (the official file,
and a Hugging Face directory converted from it). The patch tokens must equal the
official ``forward_features(x)["x_norm_patchtokens"]`` within 1e-4 (fp32) at 224 px
(the paper's crops), 448 px and 518 px (the 37 x 37 grid the position embeddings were
trained on).

ViT-S and ViT-B are built at full size. ViT-L and ViT-g keep their real width, heads,
block types (MLP; SwiGLU for g) and the hub functions' constructor arguments, with 2
blocks instead of 24 / 40 (so that the test runs in seconds on two cores)."""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from typing import Iterator

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import numpy as np
import pytest
import torch

from pipeline.method.encoders import dinov2 as d2
from shared_data import shared_dir

pytestmark = pytest.mark.slow

SIZES = (224, 448, 518)
TOLERANCE = 1e-4  # fp32 max abs difference, tokens of magnitude up to about 6
REDUCED_DEPTH = {"vitl14": 2, "vitg14": 2}
HUB_FUNCTIONS = {"vits14": "dinov2_vits14", "vitb14": "dinov2_vitb14", "vitl14": "dinov2_vitl14", "vitg14": "dinov2_vitg14"}
MODELS = [arch + reg for arch in HUB_FUNCTIONS for reg in ("", "_reg")]


@pytest.fixture(scope="module")
def official():
    """The official ``dinov2.hub.backbones`` and ``dinov2.models.vision_transformer``
    modules, imported from ../shared (skipped only when ../shared is absent)."""
    root = shared_dir("reference", "dinov2-official",
                      files=["SOURCE.txt", "dinov2/hub/backbones.py", "dinov2/models/vision_transformer.py"])
    sys.path.insert(0, str(root))
    try:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "xFormers is not available": the plain attention is used
            from dinov2.hub import backbones
            from dinov2.models import vision_transformer
    finally:
        sys.path.remove(str(root))
    return backbones, vision_transformer


@contextmanager
def _depth(vits_module, depth: int | None) -> Iterator[None]:
    """While open, the official ViT constructor builds ``depth`` blocks (None: the real
    depth); everything else the hub function and the architecture pass is unchanged."""
    original = vits_module.DinoVisionTransformer
    if depth is not None:
        vits_module.DinoVisionTransformer = lambda **kw: original(**{**kw, "depth": depth})
    try:
        yield
    finally:
        vits_module.DinoVisionTransformer = original


def _randomise(net: torch.nn.Module, seed: int) -> None:
    """Every parameter random, at scales that keep activations of order one: weights
    ~ N(0, 1/fan_in), biases N(0, 0.1), norm scales 1 + N(0, 0.2), layer scales, tokens
    and position embeddings N(0, 0.5) (large enough that a different resize of the
    position embeddings shows)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in net.named_parameters():
            noise = torch.randn(p.shape, generator=g)
            if name.endswith("weight") and p.dim() >= 2:
                p.copy_(noise / float(np.sqrt(p[0].numel())))
            elif "norm" in name and name.endswith("weight"):
                p.copy_(1.0 + 0.2 * noise)
            elif name.endswith("bias"):
                p.copy_(0.1 * noise)
            else:  # cls / register / mask tokens, pos_embed, LayerScale gammas
                p.copy_(0.5 * noise)


def _build_official(official, model: str, seed: int) -> torch.nn.Module:
    backbones, vits = official
    arch, reg = d2.parse_model_name(model)
    with _depth(vits, REDUCED_DEPTH.get(arch)):
        net = getattr(backbones, HUB_FUNCTIONS[arch] + ("_reg" if reg else ""))(pretrained=False)
    _randomise(net, seed)
    return net.eval()


def _official_tokens(net: torch.nn.Module, images: np.ndarray) -> np.ndarray:
    """The official patch tokens as the encoder's (B, D, g, g) map, from uint8 crops
    normalised exactly as the encoder normalises them."""
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    x = (x - torch.tensor(d2.IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(d2.IMAGENET_STD).view(1, 3, 1, 1)
    g = images.shape[1] // d2.PATCH_SIZE
    with torch.inference_mode():
        tok = net.forward_features(x)["x_norm_patchtokens"]
    return tok.reshape(len(images), g, g, -1).permute(0, 3, 1, 2).numpy()


def _images(n: int, size: int, seed: int) -> np.ndarray:
    """Crops with smooth structure and noise (not flat, not pure noise)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = np.stack([np.sin(6 * xx + c) * np.cos(4 * yy - c) for c in range(3)], -1)
    imgs = 127.5 + 90 * base[None] + rng.normal(0, 25, (n, size, size, 3))
    return np.clip(imgs, 0, 255).astype(np.uint8)


@pytest.fixture
def real_shapes(monkeypatch):
    """The project's architecture table with the reduced depths this test builds."""
    for arch, depth in REDUCED_DEPTH.items():
        monkeypatch.setitem(d2.MODEL_CONFIGS, arch, dict(d2.MODEL_CONFIGS[arch], num_hidden_layers=depth))


@pytest.mark.parametrize("model", MODELS)
def test_patch_tokens_equal_official_code(official, model, tmp_path, real_shapes):
    net = _build_official(official, model, seed=MODELS.index(model))
    pth = tmp_path / d2.official_filename(model)
    torch.save(net.state_dict(), pth)
    # the Hugging Face route: a directory converted from the official file
    d2.load_official(pth, model).save_pretrained(tmp_path / "hf")
    n = 2 if d2.parse_model_name(model)[0] in ("vits14", "vitl14") else 1
    for size in SIZES:
        images = _images(n, size, seed=size)
        want = _official_tokens(net, images)
        assert np.abs(want).max() > 1.0  # tokens of a meaningful magnitude
        for route, weights in (("official", pth), ("hf", tmp_path / "hf")):
            enc = d2.Dinov2Encoder(model=model, weights=str(weights), input_size=size, precision="fp32",
                                   device="cpu", batch_size=2)
            assert enc.hf_dir == (route == "hf")
            got = enc.encode(images)
            diff = float(np.abs(got - want).max())
            assert got.shape == want.shape and diff <= TOLERANCE, f"{model} {route} {size}px: max abs diff {diff:.3g}"


def test_a_different_position_resize_would_be_caught(official, tmp_path):
    """The comparison has teeth: the register models' resize (size, antialias) applied
    to a plain model moves its 224 px tokens far beyond the tolerance."""
    net = _build_official(official, "vits14", seed=0)
    pth = tmp_path / d2.official_filename("vits14")
    torch.save(net.state_dict(), pth)
    enc = d2.Dinov2Encoder(model="vits14", weights=str(pth), input_size=224, precision="fp32", device="cpu")
    images = _images(1, 224, seed=1)
    want = _official_tokens(net, images)
    assert float(np.abs(enc.encode(images) - want).max()) <= TOLERANCE
    emb = enc._load().embeddings
    emb.offset, emb.antialias = d2.OFFICIAL_INTERPOLATION[True]
    assert float(np.abs(enc.encode(images) - want).max()) > 100 * TOLERANCE


def test_official_position_resize_formula():
    """Against F.interpolate called as the official code calls it, for the plain models'
    scale factor (g + 0.1) / 37 and the register models' size with antialias; the
    trained 37 x 37 grid is returned unchanged."""
    torch.manual_seed(0)
    pos = torch.randn(1, 1 + 37 * 37, 8)
    grid = pos[:, 1:].reshape(1, 37, 37, 8).permute(0, 3, 1, 2)
    for g in (16, 32):
        plain = torch.nn.functional.interpolate(grid, scale_factor=((g + 0.1) / 37, (g + 0.1) / 37), mode="bicubic")
        reg = torch.nn.functional.interpolate(grid, size=(g, g), mode="bicubic", antialias=True)
        for (offset, antialias), ref in ((d2.OFFICIAL_INTERPOLATION[False], plain), (d2.OFFICIAL_INTERPOLATION[True], reg)):
            out = d2.official_position_embeddings(pos, g, g, offset, antialias)
            assert torch.equal(out[:, 0], pos[:, 0])
            assert torch.equal(out[:, 1:], ref.permute(0, 2, 3, 1).reshape(1, g * g, 8))
    assert d2.official_position_embeddings(pos, 37, 37, 0.1, False) is pos

"""DINOv2 encoder: offline loading of tiny random models (HF layout and official state
dict), output grid, missing weights, precision and cache keys."""

from __future__ import annotations

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import numpy as np
import pytest
import torch

transformers = pytest.importorskip("transformers")

from pipeline.method.encoders import dinov2 as d2
from pipeline.method.encoders.registry import EncoderSpec, build_encoder, known_encoders

TINY = {"hidden_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2, "use_swiglu_ffn": False, "image_size": 56}


@pytest.fixture
def tiny_arch(monkeypatch):
    """Register a tiny architecture 'vitt14' (32-d, 2 layers, 2 heads, 56 px = 4x4 patches)."""
    monkeypatch.setitem(d2.MODEL_CONFIGS, "vitt14", dict(TINY))
    return "vitt14"


def _tiny_hf(registers: bool = False, swiglu: bool = False, seed: int = 0):
    torch.manual_seed(seed)
    kw = dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_ratio=4, patch_size=14,
              image_size=56, layerscale_value=1.0, use_swiglu_ffn=swiglu)
    if registers:
        net = transformers.Dinov2WithRegistersModel(transformers.Dinov2WithRegistersConfig(num_register_tokens=4, **kw))
    else:
        net = transformers.Dinov2Model(transformers.Dinov2Config(**kw))
    # random layer scales and biases, so that a wrong mapping cannot hide behind constants
    with torch.no_grad():
        for name, p in net.named_parameters():
            if "lambda1" in name or name.endswith("bias") or "token" in name:
                p.copy_(torch.randn_like(p) * 0.5)
    return net.eval()


def _to_official(net) -> dict[str, torch.Tensor]:
    """The tiny HF model's weights under the official facebookresearch/dinov2 names."""
    sd = net.state_dict()
    out = {
        "cls_token": sd["embeddings.cls_token"],
        "pos_embed": sd["embeddings.position_embeddings"],
        "mask_token": sd["embeddings.mask_token"],
        "patch_embed.proj.weight": sd["embeddings.patch_embeddings.projection.weight"],
        "patch_embed.proj.bias": sd["embeddings.patch_embeddings.projection.bias"],
        "norm.weight": sd["layernorm.weight"],
        "norm.bias": sd["layernorm.bias"],
    }
    if "embeddings.register_tokens" in sd:
        out["register_tokens"] = sd["embeddings.register_tokens"]
    new_names = "encoder.layer.0.attention.q_proj.weight" in sd
    for i in range(net.config.num_hidden_layers):
        p, b = f"encoder.layer.{i}.", f"blocks.{i}."
        q, k, v, o = (("attention.q_proj", "attention.k_proj", "attention.v_proj", "attention.o_proj") if new_names else
                      ("attention.attention.query", "attention.attention.key", "attention.attention.value",
                       "attention.output.dense"))
        for kind in ("weight", "bias"):
            out[b + "norm1." + kind] = sd[p + "norm1." + kind]
            out[b + "norm2." + kind] = sd[p + "norm2." + kind]
            out[b + "attn.qkv." + kind] = torch.cat([sd[f"{p}{n}.{kind}"] for n in (q, k, v)], 0)
            out[b + "attn.proj." + kind] = sd[f"{p}{o}.{kind}"]
            if net.config.use_swiglu_ffn:
                out[b + "mlp.w12." + kind] = torch.cat([sd[f"{p}mlp.gate_proj.{kind}"], sd[f"{p}mlp.up_proj.{kind}"]], 0)
                out[b + "mlp.w3." + kind] = sd[f"{p}mlp.down_proj.{kind}"]
            else:
                out[b + "mlp.fc1." + kind] = sd[p + "mlp.fc1." + kind]
                out[b + "mlp.fc2." + kind] = sd[p + "mlp.fc2." + kind]
        out[b + "ls1.gamma"] = sd[p + "layer_scale1.lambda1"]
        out[b + "ls2.gamma"] = sd[p + "layer_scale2.lambda1"]
    return {k: v.clone() for k, v in out.items()}


def _images(n: int, size: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, size, size, 3), dtype=np.uint8)


def test_dinov2_is_registered():
    assert known_encoders()["dinov2"] == "visual"


@pytest.mark.parametrize("registers", [False, True])
def test_hf_dir_loads_offline_and_gives_patch_grid(tmp_path, tiny_arch, registers):
    net = _tiny_hf(registers=registers)
    net.save_pretrained(tmp_path / "hf")
    model = tiny_arch + ("_reg" if registers else "")
    enc = build_encoder(EncoderSpec(name="dinov2", params={
        "model": model, "weights": str(tmp_path / "hf"), "input_size": 56, "precision": "fp32",
        "device": "cpu", "batch_size": 2}))
    assert enc.kind == "visual" and enc.dim == 32
    imgs = _images(3, 56)
    out = enc.encode(imgs)
    assert out.shape == (3, 32, 4, 4) and out.dtype == np.float32
    # same as running the model by hand: ImageNet normalisation, patch tokens after the
    # CLS (and register) tokens, reshaped row-major into the grid. At the trained grid
    # (56 px here) no position embedding is resized, so transformers' own embeddings
    # agree with the official ones the encoder uses (other sizes: test_dinov2_official.py)
    x = torch.from_numpy(imgs).permute(0, 3, 1, 2).float() / 255.0
    x = (x - torch.tensor(d2.IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(d2.IMAGENET_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        tok = net(pixel_values=x).last_hidden_state[:, 1 + (4 if registers else 0):]
    ref = tok.reshape(3, 4, 4, 32).permute(0, 3, 1, 2).numpy()
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-5)
    assert enc.signature() == f"dinov2-vitt14{'reg' if registers else ''}-s56-fp32"
    # a 42 px crop resizes the 4 x 4 grid to 3 x 3
    enc42 = d2.Dinov2Encoder(model=model, weights=str(tmp_path / "hf"), input_size=42, precision="fp32", device="cpu")
    assert enc42.encode(_images(1, 42)).shape == (1, 32, 3, 3)


@pytest.mark.parametrize("registers,swiglu", [(False, False), (True, False), (False, True)])
def test_official_state_dict_matches_hf_route(tmp_path, tiny_arch, registers, swiglu, monkeypatch):
    monkeypatch.setitem(d2.MODEL_CONFIGS, "vitt14", dict(TINY, use_swiglu_ffn=swiglu))
    net = _tiny_hf(registers=registers, swiglu=swiglu, seed=1)
    net.save_pretrained(tmp_path / "hf")
    model = tiny_arch + ("_reg" if registers else "")
    pth = tmp_path / d2.official_filename(model)
    torch.save(_to_official(net), pth)
    common = {"model": model, "input_size": 56, "precision": "fp32", "device": "cpu"}
    hf = d2.Dinov2Encoder(weights=str(tmp_path / "hf"), **common)
    off = d2.Dinov2Encoder(weights=str(pth), **common)
    imgs = _images(2, 56, seed=3)
    np.testing.assert_allclose(off.encode(imgs), hf.encode(imgs), rtol=1e-5, atol=1e-5)
    # an extra or missing official parameter is an error, not silently ignored
    sd = _to_official(net)
    sd.pop("blocks.1.ls2.gamma")
    torch.save(sd, pth)
    with pytest.raises(ValueError, match="does not match"):
        d2.load_official(pth, model)


def test_hub_cache_lookup_and_missing_weights(tmp_path, monkeypatch, tiny_arch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("FREEZE_WEIGHTS", str(tmp_path / "no-weights-here"))
    with pytest.raises(FileNotFoundError) as err:
        d2.Dinov2Encoder(model="vits14_reg")
    msg = str(err.value)
    assert "dinov2_vits14_reg4_pretrain.pth" in msg and str(tmp_path / "torch" / "hub" / "checkpoints") in msg
    with pytest.raises(FileNotFoundError, match="nowhere.pth"):
        d2.Dinov2Encoder(weights=str(tmp_path / "nowhere.pth"))
    with pytest.raises(ValueError, match="invalid params"):  # wrapped by the registry
        build_encoder({"name": "dinov2", "params": {"model": "vits14", "wieghts": "x"}})
    # a file in the hub cache is found without 'weights'
    net = _tiny_hf()
    ckpt = tmp_path / "torch" / "hub" / "checkpoints" / "dinov2_vitt14_pretrain.pth"
    ckpt.parent.mkdir(parents=True)
    torch.save(_to_official(net), ckpt)
    enc = d2.Dinov2Encoder(model=tiny_arch, input_size=28, precision="fp32", device="cpu")
    assert enc.weights_path == ckpt.resolve()
    assert enc.encode(_images(1, 28)).shape == (1, 32, 2, 2)
    assert d2.weights_status(tiny_arch)["found"] and not d2.weights_status("vitb14")["found"]


def test_bad_params(tmp_path, tiny_arch):
    net = _tiny_hf()
    net.save_pretrained(tmp_path / "hf")
    with pytest.raises(ValueError, match="multiple of 14"):
        d2.Dinov2Encoder(model=tiny_arch, weights=str(tmp_path / "hf"), input_size=50)
    with pytest.raises(ValueError, match="unknown model"):
        d2.Dinov2Encoder(model="vitx99", weights=str(tmp_path / "hf"))
    with pytest.raises(ValueError, match="needs"):  # config.json is not a ViT-S/14
        d2.Dinov2Encoder(model="vits14", weights=str(tmp_path / "hf"))
    with pytest.raises(ValueError, match="precision"):
        d2.Dinov2Encoder(model=tiny_arch, weights=str(tmp_path / "hf"), precision="fp16")


def test_cache_params_follow_weights_and_precision(tmp_path, tiny_arch):
    hf = tmp_path / "hf"
    _tiny_hf(seed=0).save_pretrained(hf)
    common = {"model": tiny_arch, "weights": str(hf), "device": "cpu"}
    p0 = d2.Dinov2Encoder(precision="fp32", **common).cache_params()
    assert p0 == d2.Dinov2Encoder(precision="fp32", **common).cache_params()
    assert p0["precision"] == "fp32" and p0["model"] == tiny_arch and p0["input_size"] == 224
    assert d2.Dinov2Encoder(precision="fp32", input_size=112, **common).cache_params() != p0
    _tiny_hf(seed=1).save_pretrained(hf)
    p1 = d2.Dinov2Encoder(precision="fp32", **common).cache_params()
    assert p1["weights_sha1"] != p0["weights_sha1"]
    pth = tmp_path / "w.pth"
    torch.save(_to_official(_tiny_hf(seed=0)), pth)
    s0 = d2.weights_checksum(pth)
    torch.save(_to_official(_tiny_hf(seed=2)), pth)
    assert d2.weights_checksum(pth) != s0
    auto = d2.Dinov2Encoder(precision="auto", **common).cache_params()["precision"]
    assert auto == ("bf16" if d2.cpu_supports_bf16() else "fp32")


@pytest.mark.skipif(not d2.cpu_supports_bf16(), reason="CPU has no AMX/AVX-512 BF16")
def test_bf16_close_to_fp32(tmp_path, tiny_arch):
    _tiny_hf(seed=4).save_pretrained(tmp_path / "hf")
    common = {"model": tiny_arch, "weights": str(tmp_path / "hf"), "device": "cpu", "input_size": 56}
    imgs = _images(4, 56, seed=5)
    a = d2.Dinov2Encoder(precision="fp32", **common).encode(imgs)
    b = d2.Dinov2Encoder(precision="bf16", **common).encode(imgs)
    assert a.dtype == b.dtype == np.float32 and not np.array_equal(a, b)
    fa, fb = a.transpose(0, 2, 3, 1).reshape(-1, 32), b.transpose(0, 2, 3, 1).reshape(-1, 32)
    cos = (fa * fb).sum(1) / np.linalg.norm(fa, axis=1) / np.linalg.norm(fb, axis=1)
    assert cos.min() > 0.99


def test_parse_model_names():
    assert d2.parse_model_name("vitg14") == ("vitg14", False)
    assert d2.parse_model_name("vitl14_reg") == ("vitl14", True)
    assert d2.parse_model_name("vitb14-reg4") == ("vitb14", True)
    assert d2.official_filename("vitb14_reg") == "dinov2_vitb14_reg4_pretrain.pth"
    assert d2.official_filename("vits14") == "dinov2_vits14_pretrain.pth"


def test_weights_folder_lookup_order_and_relative_paths(tmp_path, monkeypatch, tiny_arch):
    """Without 'weights', the weights folder is searched before the hub cache: the
    official file first, then the HF directory; relative 'weights' are taken from it;
    the registry passes weights_dir through; the checksum, not the place, is keyed."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("FREEZE_WEIGHTS", raising=False)
    wdir = tmp_path / "w"
    net = _tiny_hf()
    hub = tmp_path / "torch" / "hub" / "checkpoints" / "dinov2_vitt14_pretrain.pth"
    hub.parent.mkdir(parents=True)
    torch.save(_to_official(net), hub)
    kw = dict(model=tiny_arch, input_size=28, precision="fp32", device="cpu")
    assert d2.Dinov2Encoder(weights_dir=str(wdir), **kw).weights_path == hub.resolve()
    net.save_pretrained(wdir / "dinov2" / "dinov2-vitt14")  # the HF name of an unknown arch is the arch
    assert d2.Dinov2Encoder(weights_dir=str(wdir), **kw).weights_path == (wdir / "dinov2" / "dinov2-vitt14").resolve()
    torch.save(_to_official(net), wdir / "dinov2_vitt14_pretrain.pth")
    enc = build_encoder({"name": "dinov2", "params": {k: v for k, v in kw.items()}}, weights_dir=wdir)
    assert enc.weights_path == (wdir / "dinov2_vitt14_pretrain.pth").resolve()
    monkeypatch.setenv("FREEZE_WEIGHTS", str(wdir))  # the environment names the same folder
    assert d2.Dinov2Encoder(**kw).weights_path == enc.weights_path
    rel = d2.Dinov2Encoder(weights="dinov2/dinov2-vitt14", **kw)
    assert rel.weights_path == (wdir / "dinov2" / "dinov2-vitt14").resolve()
    # same weights copied elsewhere: same cache params
    other = tmp_path / "elsewhere"
    other.mkdir()
    torch.save(_to_official(net), other / "dinov2_vitt14_pretrain.pth")
    moved = d2.Dinov2Encoder(weights_dir=str(other), **kw)
    assert moved.weights_path.parent == other.resolve() and moved.cache_params() == enc.cache_params()
    status = d2.weights_status(tiny_arch, weights_dir=tmp_path / "empty")
    assert status["looked_in"][0] == str((tmp_path / "empty" / "dinov2_vitt14_pretrain.pth").resolve())
    assert status["found"] and status["path"] == str(hub)  # the last place: the hub cache
    with pytest.raises(d2.WeightsNotFound) as err:
        d2.Dinov2Encoder(model="vitb14", weights_dir=str(tmp_path / "empty"))
    assert len(err.value.looked_in) == 5 and "dinov2-base" in str(err.value)

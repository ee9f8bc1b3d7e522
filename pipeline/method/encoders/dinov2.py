"""``dinov2``: dense DINOv2 patch tokens (visual encoder), run through ``transformers``.

Models: ``vits14``, ``vitb14``, ``vitl14``, ``vitg14`` and their register variants
``vits14_reg`` ... (``Dinov2WithRegistersModel``, 4 register tokens). Weights are not
downloaded unless the run allows it (``allow_download``, below); ``weights`` is one of

- a local directory in the Hugging Face layout (``config.json`` plus
  ``model.safetensors`` or ``pytorch_model.bin``, e.g. a copy of
  ``facebook/dinov2-small``), loaded with ``local_files_only=True``; its
  ``config.json`` must agree with ``model`` (width, depth, registers);
- an official state-dict file ``dinov2_vits14_pretrain.pth`` (or ``..._reg4_...``) as
  published by facebookresearch/dinov2, whose parameter names are mapped onto the
  transformers model and loaded strictly;
- ``None`` (default): looked up, in order, as the official file or the HF directory
  (``dinov2-small``, ``dinov2-with-registers-base``...) in the weights folder
  (``weights_dir``: ``--config weights_dir=DIR``, else ``$FREEZE_WEIGHTS``, else
  ``<project>/weights``, also under a ``dinov2/`` sub-folder), then as the official file
  in the torch hub cache, ``torch.hub.get_dir()/checkpoints/``
  (``$TORCH_HOME/hub/checkpoints``, by default ``~/.cache/torch/hub/checkpoints``).

Relative ``weights`` paths are taken from the weights folder.

A missing file fails when the encoder is built, naming the file and where to put it,
unless ``allow_download`` is true (``--config allow_download=true``) and ``weights`` is
None: then the model is loaded from the Hugging Face hub through transformers,
``from_pretrained("facebook/<hf_dirname(model)>", cache_dir=<weights folder>/hub)``, at
build time, and later builds find the snapshot in that cache without the network. The
snapshot is a Hugging Face directory like any other, keyed on the checksum of its
``config.json`` and weight files (so a download and a local copy of the same files share
their artifacts).

Encoding: the (B, S, S, 3) uint8 crops are scaled to [0, 1], normalised with the
ImageNet mean and std, and passed through the ViT under ``torch.inference_mode``; the
output is the final-layernorm patch tokens as a (B, D, S/14, S/14) float32 map (the
lifting code upsamples it bilinearly), the official ``x_norm_patchtokens``.

Position embeddings. The checkpoints hold a 37 x 37 grid (518 px); any other input
size resizes it, and the resize changes the features (at 224 px, transformers 5.x's own
``size=(16, 16)`` resize moved tokens by up to 0.45 against the official model, cosine
0.994). Whatever transformers is installed, the embeddings layer of the loaded model is
replaced by :class:`OfficialEmbeddings`, which resizes exactly as the official
backbones' ``interpolate_pos_encoding`` does for that variant
(:data:`OFFICIAL_INTERPOLATION`: the plain models by ``scale_factor=(g + 0.1) / 37``,
bicubic, no antialias; the register models to ``size=g``, bicubic, with antialias).
The rest of the network is transformers'; ``tests/test_dinov2_official.py`` compares
the patch tokens with the official code (``../shared/reference/dinov2-official``) on
random weights for every family at 224, 448 and 518 px (fp32 max abs difference
<= 1e-4). ``precision="bf16"`` runs under bf16 autocast, ``"fp32"``
in float32, ``"auto"`` (default) picks bf16 when the hardware has it (CUDA with bf16,
or a CPU whose ``/proc/cpuinfo`` lists ``amx_bf16`` or ``avx512_bf16``) and fp32
otherwise; bf16 requested on hardware without it falls back to fp32 with a warning.
The precision actually used is part of ``cache_params()``, together with the model,
the input size and a SHA-1 of the weights. The device is not: fp32 on CPU and on CUDA
give the same features up to float rounding (the stages record the device in their
manifests instead, ``pipeline.workflow.plan.encoder_runtime``).

The model itself is loaded lazily on the first :meth:`Dinov2Encoder.encode`, so that
building the encoder at DAG-planning time only checks the files (and hashes them once
per (path, size, mtime)).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import pickle
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from pipeline.formats.weights.formats import WeightsNotFound
from pipeline.method.encoders.registry import VisualEncoder, register_encoder, resolve_weights_dir, resolve_weights_path
from pipeline.method.encoders.torch_device import resolve_device

PATCH_SIZE = 14
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NUM_REGISTER_TOKENS = 4

# Architecture of the official backbones (facebookresearch/dinov2 hub/backbones.py):
# all are trained at 518 px (37x37 patches), mlp_ratio 4, layer scale, qkv bias; ViT-g
# uses a SwiGLU feed-forward.
MODEL_CONFIGS: dict[str, dict[str, Any]] = {
    "vits14": {"hidden_size": 384, "num_hidden_layers": 12, "num_attention_heads": 6, "use_swiglu_ffn": False, "image_size": 518},
    "vitb14": {"hidden_size": 768, "num_hidden_layers": 12, "num_attention_heads": 12, "use_swiglu_ffn": False, "image_size": 518},
    "vitl14": {"hidden_size": 1024, "num_hidden_layers": 24, "num_attention_heads": 16, "use_swiglu_ffn": False, "image_size": 518},
    "vitg14": {"hidden_size": 1536, "num_hidden_layers": 40, "num_attention_heads": 24, "use_swiglu_ffn": True, "image_size": 518},
}

_HF_WEIGHT_PATTERNS = ("*.safetensors", "*.bin")

#: The official backbones' position-embedding resize, per variant (registers or not):
#: ``(interpolate_offset, interpolate_antialias)`` as hub/backbones.py passes them.
OFFICIAL_INTERPOLATION: dict[bool, tuple[float, bool]] = {False: (0.1, False), True: (0.0, True)}


# --- model names and weight files ---------------------------------------------------


def parse_model_name(model: str) -> tuple[str, bool]:
    """``"vits14"`` -> ("vits14", False); ``"vits14_reg"``/``"vits14-reg"``/``"vits14_reg4"``
    -> ("vits14", True)."""
    m = re.fullmatch(r"(vit[a-z]14)(?:[_-]?reg4?)?", str(model))
    if m is None or m.group(1) not in MODEL_CONFIGS:
        known = ", ".join(list(MODEL_CONFIGS) + [f"{k}_reg" for k in MODEL_CONFIGS])
        raise ValueError(f"dinov2: unknown model {model!r}; known: {known}")
    return m.group(1), str(model) != m.group(1)


def official_filename(model: str) -> str:
    """The official checkpoint file name, e.g. ``dinov2_vits14_reg4_pretrain.pth``."""
    arch, reg = parse_model_name(model)
    return f"dinov2_{arch}{'_reg4' if reg else ''}_pretrain.pth"


def hub_checkpoint_dir() -> Path:
    """Where official checkpoints are looked up when ``weights`` is None."""
    return Path(torch.hub.get_dir()) / "checkpoints"


HF_NAMES = {"vits14": "small", "vitb14": "base", "vitl14": "large", "vitg14": "giant"}


def hf_dirname(model: str) -> str:
    """The Hugging Face model name without its owner, e.g. ``dinov2-small`` or
    ``dinov2-with-registers-base``."""
    arch, reg = parse_model_name(model)
    return f"dinov2-{'with-registers-' if reg else ''}{HF_NAMES.get(arch, arch)}"


def default_locations(model: str, weights_dir: str | os.PathLike | None = None) -> list[Path]:
    """Where the weights of ``model`` are looked up when the manifest gives none, in
    order: the official file and the HF directory in the weights folder (also under a
    ``dinov2/`` sub-folder), then the official file in the torch hub cache."""
    wd = resolve_weights_dir(weights_dir)
    official, hf = official_filename(model), hf_dirname(model)
    return [wd / official, wd / "dinov2" / official, wd / hf, wd / "dinov2" / hf, hub_checkpoint_dir() / official]


def _usable(path: Path) -> bool:
    if path.is_dir():
        return (path / "config.json").is_file() and bool(_hf_weight_files(path))
    return path.is_file()


def find_weights(
    model: str, weights: str | os.PathLike | None = None, weights_dir: str | os.PathLike | None = None
) -> tuple[Path | None, list[Path]]:
    """``(the weights to load or None, every path looked in)``. An explicit ``weights``
    (relative to the weights folder unless absolute) is the only place looked in."""
    if weights is not None:
        path = resolve_weights_path(weights, weights_dir)
        return (path if _usable(path) else None), [path]
    places = default_locations(model, weights_dir)
    return next((p for p in places if _usable(p)), None), places


def weights_status(
    model: str = "vits14", weights: str | os.PathLike | None = None, weights_dir: str | os.PathLike | None = None
) -> dict[str, Any]:
    """What the encoder needs and where it looks: ``{"file", "path", "found", "looked_in"}``
    (``path`` is the file found, or the first place looked in)."""
    found, places = find_weights(model, weights, weights_dir)
    return {"file": official_filename(model) if weights is None else Path(weights).name,
            "path": str(found or places[0]), "found": found is not None, "looked_in": [str(p) for p in places]}


def manifest_name(model: str) -> str:
    """The encoder manifest of ``model`` by the naming of ``manifests/encoders/``, e.g.
    ``dinov2-vits14`` or ``dinov2-vitb14-reg`` (for messages naming what to fetch)."""
    arch, reg = parse_model_name(model)
    return f"dinov2-{arch}{'-reg' if reg else ''}"


# --- the Hugging Face hub, only with allow_download ----------------------------------

HUB_SUBDIR = "hub"  # in the weights folder: the transformers cache of downloaded models


def hub_repo(model: str) -> str:
    """The Hugging Face repository of ``model``, e.g. ``facebook/dinov2-small``."""
    return f"facebook/{hf_dirname(model)}"


def hub_cache_dir(weights_dir: str | os.PathLike | None = None) -> Path:
    """Where downloaded models are cached: ``<weights folder>/hub``."""
    return resolve_weights_dir(weights_dir) / HUB_SUBDIR


def hub_snapshot(model: str, weights_dir: str | os.PathLike | None = None) -> Path | None:
    """The snapshot folder of :func:`hub_repo` in the hub cache (the one ``refs/main``
    names, else the newest) when it holds a usable model, else None. Nothing is fetched."""
    repo_dir = hub_cache_dir(weights_dir) / ("models--" + hub_repo(model).replace("/", "--"))
    snapshots = repo_dir / "snapshots"
    if not snapshots.is_dir():
        return None
    candidates = []
    ref = repo_dir / "refs" / "main"
    if ref.is_file():
        candidates.append(snapshots / ref.read_text().strip())
    candidates += sorted((p for p in snapshots.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime, reverse=True)
    return next((p for p in candidates if _usable(p)), None)


def _hub_offline() -> bool:
    """Whether huggingface_hub / transformers are told to stay offline."""
    flags = [os.environ.get(v, "") for v in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")]
    if any(f.strip().lower() in ("1", "true", "yes", "on") for f in flags):
        return True
    try:  # read by huggingface_hub when it was imported
        from huggingface_hub import constants
    except ImportError:
        return False
    return bool(getattr(constants, "HF_HUB_OFFLINE", False))


def download_from_hub(model: str, weights_dir: str | os.PathLike | None = None) -> tuple[Path, torch.nn.Module]:
    """``(snapshot folder, model)``: ``model`` loaded from the hub with transformers'
    ``from_pretrained`` into the weights folder's hub cache. Fails with
    :class:`WeightsNotFound` (saying why and how to fetch the weights otherwise) when the
    hub cannot be reached or the download left no usable snapshot."""
    from transformers import Dinov2Model, Dinov2WithRegistersModel

    _, reg = parse_model_name(model)
    cls = Dinov2WithRegistersModel if reg else Dinov2Model
    repo, cache = hub_repo(model), hub_cache_dir(weights_dir)
    fetch = (f"fetch the weights with `freeze weights fetch {manifest_name(model)}` on a machine with network "
             f"access, or put them in the weights folder yourself (see `freeze encoders`)")
    try:
        net = cls.from_pretrained(repo, cache_dir=str(cache))
    except Exception as exc:  # transformers/huggingface_hub raise OSError, or their HTTP errors
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        where = ("the hub could not be reached: offline mode is on (HF_HUB_OFFLINE or TRANSFORMERS_OFFLINE is set)"
                 if _hub_offline() else f"the hub could not be reached or refused it ({type(exc).__name__}: {why})")
        raise WeightsNotFound(f"dinov2: allow_download is on, but {repo} could not be loaded into {cache}: {where}; "
                              f"{fetch}", [cache]) from None
    snapshot = hub_snapshot(model, weights_dir)
    if snapshot is None:
        raise WeightsNotFound(f"dinov2: {repo} was loaded from the hub, but no snapshot with config.json and weights "
                              f"is in {cache} (transformers cached it elsewhere?); {fetch}", [cache])
    return snapshot, net


def _hf_weight_files(directory: Path) -> list[Path]:
    files: set[Path] = set()
    for pattern in _HF_WEIGHT_PATTERNS:
        files.update(p for p in directory.glob(pattern) if p.is_file())
    return sorted(files)


_CHECKSUMS: dict[tuple, str] = {}


def weights_checksum(path: str | os.PathLike) -> str:
    """SHA-1 of a weights file, or of a HF directory's ``config.json`` and weight files
    (names and contents). Cached per (path, size, mtime) of every file hashed."""
    path = Path(path)
    files = [path] if path.is_file() else [path / "config.json"] + _hf_weight_files(path)
    stats = tuple((str(f.resolve()), f.stat().st_size, f.stat().st_mtime_ns) for f in files)
    if stats not in _CHECKSUMS:
        h = hashlib.sha1()
        for f in files:
            if len(files) > 1:
                h.update(f.name.encode() + b"\0")
            with open(f, "rb") as fh:
                for chunk in iter(functools.partial(fh.read, 1 << 20), b""):
                    h.update(chunk)
        _CHECKSUMS[stats] = h.hexdigest()
    return _CHECKSUMS[stats]


# --- precision and device -----------------------------------------------------------


@functools.lru_cache(maxsize=1)
def cpu_supports_bf16() -> bool:
    """True when /proc/cpuinfo lists ``amx_bf16`` or ``avx512_bf16``."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return bool(flags & {"amx_bf16", "avx512_bf16"})
    except OSError:
        pass
    return False


def bf16_supported(device: str) -> bool:
    """Whether ``device`` (``"cpu"`` or ``"cuda[:i]"``) runs bf16 in hardware."""
    if device.startswith("cuda"):
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return cpu_supports_bf16()


def resolve_precision(precision: str, device: str) -> str:
    """``"auto"``/``"bf16"``/``"fp32"`` -> the precision actually used (``"bf16"`` or ``"fp32"``)."""
    if precision not in ("auto", "bf16", "fp32"):
        raise ValueError(f"dinov2: precision must be 'auto', 'bf16' or 'fp32', got {precision!r}")
    if precision == "fp32":
        return "fp32"
    if bf16_supported(device):
        return "bf16"
    if precision == "bf16":
        warnings.warn(f"dinov2: bf16 is not supported in hardware on {device}; using fp32", stacklevel=3)
    return "fp32"


# --- official state dict -> transformers --------------------------------------------


def _pick(keys: set[str], prefix: str, *candidates: str) -> str:
    """The first ``prefix + candidate`` module name having a parameter in ``keys``."""
    for cand in candidates:
        name = prefix + cand
        if any(k.startswith(name + ".") for k in keys):
            return name
    raise KeyError(f"dinov2: none of {[prefix + c for c in candidates]} in the transformers model")


def official_to_hf(state_dict: dict[str, torch.Tensor], hf_keys: set[str] | list[str]) -> dict[str, torch.Tensor]:
    """Rename an official DINOv2 state dict to the parameter names of a transformers
    ``Dinov2Model``/``Dinov2WithRegistersModel`` whose state-dict keys are ``hf_keys``.

    Handles both the current transformers names (``attention.q_proj``, ``o_proj``,
    ``mlp.gate_proj/up_proj/down_proj``) and the older ones (``attention.attention.query``,
    ``attention.output.dense``, ``mlp.weights_in/weights_out``). The fused ``qkv``
    projection is split in rows (q, k, v); the SwiGLU ``w12`` in (gate, up) halves.
    Unknown official names raise ``KeyError`` (the caller loads strictly).
    """
    hf_keys = set(hf_keys)
    out: dict[str, torch.Tensor] = {}
    top = {
        "cls_token": "embeddings.cls_token",
        "pos_embed": "embeddings.position_embeddings",
        "mask_token": "embeddings.mask_token",
        "register_tokens": "embeddings.register_tokens",
        "patch_embed.proj.weight": "embeddings.patch_embeddings.projection.weight",
        "patch_embed.proj.bias": "embeddings.patch_embeddings.projection.bias",
        "norm.weight": "layernorm.weight",
        "norm.bias": "layernorm.bias",
    }
    for key, value in state_dict.items():
        # chunked checkpoints (block_chunks > 0) name blocks "blocks.<chunk>.<i>."
        key = re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", key)
        if key in top:
            out[top[key]] = value
            continue
        m = re.fullmatch(r"blocks\.(\d+)\.(.+)\.(weight|bias|gamma)", key)
        if m is None:
            raise KeyError(f"dinov2: unexpected parameter {key!r} in the official state dict")
        i, name, kind = m.groups()
        p = f"encoder.layer.{i}."
        if name in ("norm1", "norm2", "mlp.fc1", "mlp.fc2") and kind != "gamma":
            out[f"{p}{name}.{kind}"] = value
        elif name in ("ls1", "ls2") and kind == "gamma":
            out[f"{p}layer_scale{name[-1]}.lambda1"] = value
        elif name == "attn.qkv":
            q, k, v = value.chunk(3, dim=0)
            names = [
                _pick(hf_keys, p, "attention.q_proj", "attention.attention.query"),
                _pick(hf_keys, p, "attention.k_proj", "attention.attention.key"),
                _pick(hf_keys, p, "attention.v_proj", "attention.attention.value"),
            ]
            for n, t in zip(names, (q, k, v)):
                out[f"{n}.{kind}"] = t.contiguous()
        elif name == "attn.proj":
            out[f"{_pick(hf_keys, p, 'attention.o_proj', 'attention.output.dense')}.{kind}"] = value
        elif name == "mlp.w12":
            if any(k.startswith(p + "mlp.weights_in.") for k in hf_keys):
                out[f"{p}mlp.weights_in.{kind}"] = value
            else:
                gate, up = value.chunk(2, dim=0)
                out[f"{_pick(hf_keys, p, 'mlp.gate_proj')}.{kind}"] = gate.contiguous()
                out[f"{_pick(hf_keys, p, 'mlp.up_proj')}.{kind}"] = up.contiguous()
        elif name == "mlp.w3":
            out[f"{_pick(hf_keys, p, 'mlp.down_proj', 'mlp.weights_out')}.{kind}"] = value
        else:
            raise KeyError(f"dinov2: unexpected parameter {key!r} in the official state dict")
    return out


def hf_config_for(model: str, arch: dict[str, Any] | None = None):
    """transformers config of an official backbone (``arch`` overrides MODEL_CONFIGS)."""
    from transformers import Dinov2Config, Dinov2WithRegistersConfig

    name, reg = parse_model_name(model)
    a = dict(MODEL_CONFIGS[name] if arch is None else arch)
    common = dict(
        hidden_size=a["hidden_size"],
        num_hidden_layers=a["num_hidden_layers"],
        num_attention_heads=a["num_attention_heads"],
        use_swiglu_ffn=a["use_swiglu_ffn"],
        image_size=a["image_size"],
        patch_size=PATCH_SIZE,
        mlp_ratio=4,
        layerscale_value=1.0,
        layer_norm_eps=1e-6,
        qkv_bias=True,
        hidden_act="gelu",
    )
    if reg:
        return Dinov2WithRegistersConfig(num_register_tokens=NUM_REGISTER_TOKENS, **common)
    return Dinov2Config(**common)


def official_position_embeddings(
    pos_embed: torch.Tensor, rows: int, cols: int, offset: float, antialias: bool
) -> torch.Tensor:
    """Position embeddings (1, 1 + rows * cols, D) for a rows x cols patch grid, resized
    from the checkpoint's (1, 1 + M * M, D) as the official ``interpolate_pos_encoding``
    does: unchanged for the trained square grid; else the M x M grid resized bicubically
    in float32, by ``scale_factor = (rows + offset) / M`` (and cols) when ``offset`` is
    non-zero, to ``size = (rows, cols)`` otherwise, with ``antialias``; returned in the
    dtype of ``pos_embed``."""
    n = pos_embed.shape[1] - 1
    if n == rows * cols and rows == cols:
        return pos_embed
    m = int(math.sqrt(n))
    if m * m != n:
        raise ValueError(f"dinov2: {n} position embeddings do not form a square grid")
    dim = pos_embed.shape[-1]
    grid = pos_embed[:, 1:].float().reshape(1, m, m, dim).permute(0, 3, 1, 2)
    if offset:
        # Python floats, as the official code computes them (not float32 tensors)
        size_or_scale: dict[str, Any] = {"scale_factor": (float(rows + offset) / m, float(cols + offset) / m)}
    else:
        size_or_scale = {"size": (rows, cols)}
    grid = F.interpolate(grid, mode="bicubic", antialias=antialias, **size_or_scale)
    if grid.shape[-2:] != (rows, cols):
        raise ValueError(f"dinov2: position embeddings resized to {tuple(grid.shape[-2:])}, expected {(rows, cols)}")
    patches = grid.permute(0, 2, 3, 1).reshape(1, rows * cols, dim)
    return torch.cat([pos_embed[:, :1].float(), patches], dim=1).to(pos_embed.dtype)


class OfficialEmbeddings(nn.Module):
    """The embeddings layer of a transformers DINOv2 model, computed as the official
    ``prepare_tokens_with_masks``: patch projection, cls token, position embeddings
    resized by :func:`official_position_embeddings`, then the register tokens after the
    cls token. It holds the original layer's parameters under the same names (so the
    model's state dict is unchanged). Masked tokens (``bool_masked_pos``) are not used
    by the pipeline and are refused."""

    def __init__(self, original: nn.Module, offset: float, antialias: bool) -> None:
        super().__init__()
        self.cls_token = original.cls_token
        self.mask_token = original.mask_token
        self.position_embeddings = original.position_embeddings
        self.patch_embeddings = original.patch_embeddings
        self.register_tokens = getattr(original, "register_tokens", None)
        self.dropout = original.dropout
        self.patch_size = PATCH_SIZE
        self.offset = float(offset)
        self.antialias = bool(antialias)

    def forward(self, pixel_values: torch.Tensor, bool_masked_pos: torch.Tensor | None = None, **_: Any) -> torch.Tensor:
        """pixel_values (B, 3, H, W) -> tokens (B, 1 [+ registers] + H/14 * W/14, D)."""
        if bool_masked_pos is not None:
            raise ValueError("dinov2: masked patch tokens are not supported")
        batch, _, height, width = pixel_values.shape
        proj = self.patch_embeddings.projection
        x = proj(pixel_values.to(proj.weight.dtype)).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls_token.expand(batch, -1, -1), x], dim=1)
        pos = official_position_embeddings(self.position_embeddings, height // PATCH_SIZE, width // PATCH_SIZE,
                                           self.offset, self.antialias)
        x = x + pos.to(x.dtype)
        if self.register_tokens is not None:
            x = torch.cat([x[:, :1], self.register_tokens.expand(batch, -1, -1), x[:, 1:]], dim=1)
        return self.dropout(x)


def with_official_embeddings(net: torch.nn.Module) -> torch.nn.Module:
    """``net`` (a transformers Dinov2Model / Dinov2WithRegistersModel) with its
    embeddings layer replaced by :class:`OfficialEmbeddings` for its variant (in place;
    also returned). Idempotent."""
    if not isinstance(net.embeddings, OfficialEmbeddings):
        registers = bool(getattr(net.config, "num_register_tokens", 0) or 0)
        net.embeddings = OfficialEmbeddings(net.embeddings, *OFFICIAL_INTERPOLATION[registers])
    return net


def load_official(path: str | os.PathLike, model: str) -> torch.nn.Module:
    """A transformers model (float32) with the official state dict ``path`` loaded strictly.

    The model is built on the meta device and takes the loaded tensors as its
    parameters: a random initialisation first would cost 31 s and a second copy of the
    weights for ViT-g/14 (1.1 B parameters) on this CPU."""
    from transformers import Dinov2Model, Dinov2WithRegistersModel

    config = hf_config_for(model)
    cls = Dinov2WithRegistersModel if getattr(config, "num_register_tokens", 0) else Dinov2Model
    from pipeline.formats.weights.formats import check_weights_file, unreadable_checkpoint

    check_weights_file(path, "dinov2", manifest_name(model))  # a web page, a truncated download: one line
    with torch.device("meta"):
        net = cls(config)
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError) as exc:  # torch's message advises weights_only=False
        raise unreadable_checkpoint(path, exc, "dinov2", manifest_name(model)) from None
    if isinstance(sd, dict) and "model" in sd and isinstance(sd["model"], dict):
        sd = sd["model"]
    mapped = {k: v.float() if v.is_floating_point() else v for k, v in official_to_hf(sd, net.state_dict().keys()).items()}
    del sd
    try:
        net.load_state_dict(mapped, strict=True, assign=True)
    except RuntimeError as exc:
        raise ValueError(f"dinov2: {path} does not match model {model!r}: {exc}") from exc
    left = [n for n, t in [*net.named_parameters(), *net.named_buffers()] if t.is_meta]
    if left:  # a buffer outside the state dict (none in the releases tested) would stay empty
        raise ValueError(f"dinov2: {path}: the model's {', '.join(left)} not loaded from the state dict")
    return net


def check_weight_files(path: str | os.PathLike, model: str | None = None) -> None:
    """Raise :class:`~pipeline.formats.weights.formats.NotAWeightsFile` (one line naming the file)
    when the official file, or a Hugging Face folder's ``config.json`` and weights, are
    not of their format (a web page saved under the name, a truncated download). Reads
    a few bytes of each (and a zip's directory), so it runs before any long work.
    ``model`` (e.g. ``vits14``) names the manifest that fetches the file again."""
    from pipeline.formats.weights.formats import check_weights_file

    path = Path(path)
    fetch = manifest_name(model) if model else None
    if not path.is_dir():
        check_weights_file(path, "dinov2", fetch)
        return
    for name in ("config.json", "model.safetensors", "pytorch_model.bin"):
        if (path / name).is_file():
            check_weights_file(path / name, "dinov2", fetch)


def load_hf_dir(path: str | os.PathLike) -> torch.nn.Module:
    """A ``Dinov2Model``/``Dinov2WithRegistersModel`` from a local HF-layout directory."""
    from transformers import Dinov2Model, Dinov2WithRegistersModel

    check_weight_files(path)
    model_type = json.loads((Path(path) / "config.json").read_text()).get("model_type")
    cls = Dinov2WithRegistersModel if model_type == "dinov2_with_registers" else Dinov2Model
    return cls.from_pretrained(str(path), local_files_only=True)


# --- the encoder ----------------------------------------------------------------------


class Dinov2Encoder(VisualEncoder):
    """DINOv2 patch tokens (see module docstring).

    model: ``vits14`` | ``vitb14`` | ``vitl14`` | ``vitg14``, optionally with ``_reg``.
    weights: HF directory or official ``.pth`` file (relative to the weights folder unless
    absolute), or None to look in the default places (:func:`default_locations`).
    weights_dir: the weights folder (default ``$FREEZE_WEIGHTS`` or ``<project>/weights``).
    input_size: crop side S, a multiple of 14 (224 as in FreeZe).
    precision: ``auto`` | ``bf16`` | ``fp32``.
    device: ``auto`` (cuda if available, else cpu), ``cpu``, ``cuda``, ``cuda:1``... (the
    run's ``--config device=cpu|cuda`` replaces the manifest's value); not keyed.
    batch_size: crops per forward pass.
    allow_download: with ``weights`` None and no local weights, load the model from the
    Hugging Face hub into ``<weights folder>/hub`` (the run's ``--config allow_download=true``).
    """

    name = "dinov2"
    # 2: position embeddings resized as the official backbones (OfficialEmbeddings),
    # not by the installed transformers
    version = "2"

    def __init__(
        self,
        model: str = "vits14",
        weights: str | None = None,
        input_size: int = 224,
        precision: str = "auto",
        device: str = "auto",
        batch_size: int = 8,
        weights_dir: str | None = None,
        allow_download: bool = False,
    ) -> None:
        self.arch, self.registers = parse_model_name(model)
        self.model = self.arch + ("_reg" if self.registers else "")
        if int(input_size) != input_size or input_size < PATCH_SIZE or input_size % PATCH_SIZE != 0:
            raise ValueError(f"dinov2: input_size must be a positive multiple of {PATCH_SIZE}, got {input_size}")
        if int(batch_size) < 1:
            raise ValueError(f"dinov2: batch_size must be >= 1, got {batch_size}")
        self.input_size = int(input_size)
        self.batch_size = int(batch_size)
        self.device = resolve_device(device, "dinov2")
        self.precision = resolve_precision(precision, self.device)
        self._fetched: torch.nn.Module | None = None  # a model just loaded from the hub

        path, places = find_weights(self.model, weights, weights_dir)
        if path is None and weights is None and allow_download:
            path = hub_snapshot(self.model, weights_dir)  # downloaded by an earlier run
            if path is None:
                path, self._fetched = download_from_hub(self.model, weights_dir)
        if path is None:
            asked = places[0]
            if weights is None:
                cached = hub_snapshot(self.model, weights_dir)
                raise WeightsNotFound(
                    f"dinov2: weights for {self.model} not found. Fetch them with `freeze weights fetch "
                    f"{manifest_name(self.model)}`, or put the official file "
                    f"{official_filename(self.model)} (from https://dl.fbaipublicfiles.com/dinov2/) or a local "
                    f"Hugging Face copy of {hub_repo(self.model)} in one of: "
                    + ", ".join(str(p) for p in places)
                    + " (the weights folder is --config weights_dir=DIR, $FREEZE_WEIGHTS or <project>/weights; "
                    "the last is the torch hub cache, $TORCH_HOME/hub/checkpoints), or set the encoder param "
                    "'weights'. Nothing is downloaded unless the run says --config allow_download=true (then "
                    f"transformers loads {hub_repo(self.model)} from the Hugging Face hub into "
                    f"{hub_cache_dir(weights_dir)})"
                    + (f"; a copy downloaded earlier is in {cached}, which that option uses" if cached else "")
                    + ".", places)
            if asked.is_dir():
                raise WeightsNotFound(
                    f"dinov2: {asked} is not a Hugging Face model directory: it needs config.json and "
                    f"model.safetensors (or pytorch_model.bin) of a Dinov2 model such as facebook/{hf_dirname(self.model)}", places)
            raise WeightsNotFound(
                f"dinov2: weights file {asked} not found: put the official {official_filename(self.model)} there, "
                f"or point 'weights' at a local Hugging Face model directory (relative paths are taken from the "
                f"weights folder). Nothing is downloaded.", places)
        self.weights_path = path.resolve()
        self.hf_dir = self.weights_path.is_dir()
        check_weight_files(self.weights_path, self.model)  # not a checkpoint: fail now, not at the first encode
        if self.hf_dir:
            self._check_hf_config()
        self.dim = int(self._hidden_size)
        self._net: torch.nn.Module | None = None

    def _check_hf_config(self) -> None:
        cfg = json.loads((self.weights_path / "config.json").read_text())
        arch = MODEL_CONFIGS[self.arch]
        got = (cfg.get("hidden_size"), cfg.get("num_hidden_layers"), int(cfg.get("num_register_tokens", 0) or 0))
        want = (arch["hidden_size"], arch["num_hidden_layers"], NUM_REGISTER_TOKENS if self.registers else 0)
        if cfg.get("model_type") not in ("dinov2", "dinov2_with_registers") or got != want:
            raise ValueError(
                f"dinov2: {self.weights_path}/config.json describes model_type={cfg.get('model_type')!r}, "
                f"hidden_size, layers, registers = {got}, but model {self.model!r} needs {want}"
            )
        if cfg.get("patch_size", PATCH_SIZE) != PATCH_SIZE:
            raise ValueError(f"dinov2: {self.weights_path} has patch_size {cfg.get('patch_size')}, expected {PATCH_SIZE}")

    @property
    def _hidden_size(self) -> int:
        return MODEL_CONFIGS[self.arch]["hidden_size"]

    def signature(self) -> str:
        sig = f"dinov2-{self.arch}" + ("reg" if self.registers else "")
        sig = sig if self.input_size == 224 else f"{sig}-s{self.input_size}"
        return sig if self.precision == "bf16" else f"{sig}-fp32"

    def cache_params(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "input_size": self.input_size,
            "precision": self.precision,
            "weights_format": "hf" if self.hf_dir else "official",
            "weights_sha1": weights_checksum(self.weights_path),
        }

    def _load(self) -> torch.nn.Module:
        if self._net is None:
            if self._fetched is not None:  # loaded from the hub when the encoder was built
                net, self._fetched = self._fetched, None
            else:
                net = load_hf_dir(self.weights_path) if self.hf_dir else load_official(self.weights_path, self.model)
            self._net = with_official_embeddings(net).eval().to(self.device)
        return self._net

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = self.check_images(images)
        S = self.input_size
        net = self._load()
        g = S // PATCH_SIZE
        skip = 1 + int(getattr(net.config, "num_register_tokens", 0) or 0)
        dev = torch.device(self.device)
        mean = torch.tensor(IMAGENET_MEAN, device=dev).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD, device=dev).view(1, 3, 1, 1)
        out = np.empty((len(images), self.dim, g, g), dtype=np.float32)
        with torch.inference_mode(), torch.autocast(
            dev.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"
        ):
            for b0 in range(0, len(images), self.batch_size):
                x = torch.from_numpy(images[b0 : b0 + self.batch_size]).to(dev)
                x = (x.permute(0, 3, 1, 2).float() / 255.0 - mean) / std
                tokens = net(pixel_values=x).last_hidden_state[:, skip:]
                fmap = tokens.float().reshape(len(x), g, g, -1).permute(0, 3, 1, 2)
                out[b0 : b0 + len(x)] = fmap.cpu().numpy()
        return out


register_encoder("dinov2", "visual", Dinov2Encoder, weights=True)

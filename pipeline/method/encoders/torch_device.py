"""Where the torch encoders run: one rule for DINOv2 and GeDi (``device`` param, which
the run's ``--config device=cpu|cuda`` replaces; see ``docs/gpu.md``)."""

from __future__ import annotations

import re

import torch


def resolve_device(device: str, who: str) -> str:
    """``"auto"`` -> ``"cuda"`` when torch sees a CUDA device, else ``"cpu"``; ``"cpu"``,
    ``"cuda"``, ``"cuda:i"`` as given, after checking that a CUDA device is visible
    (``ValueError`` naming the encoder ``who`` and the device otherwise)."""
    device = str(device)
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cpu":
        return device
    if re.fullmatch(r"cuda(:\d+)?", device) is None:
        raise ValueError(f"{who}: device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if not torch.cuda.is_available():
        raise ValueError(f"{who}: device {device!r} was asked for, but no CUDA device is visible to torch "
                         "(torch.cuda.is_available() is false); use device 'auto' or 'cpu'")
    return device

"""``rgb``: each pixel's own colour as a 3-channel visual feature (values in [0, 1]).

The simplest visual encoder there is. It is a baseline (raw colour, no context) and a
known-answer probe of the lifting path: features lifted onto model points must equal
the model's colours there, and scene features must equal the crop's colours at the
lifted pixels (``tests/test_stages_lifting.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.method.encoders.registry import VisualEncoder, register_encoder


class RgbEncoder(VisualEncoder):
    """Feature map (B, 3, S, S) float32 = the crop's RGB / 255 (stride 1)."""

    name = "rgb"
    version = "1"
    dim = 3

    def __init__(self, input_size: int = 224) -> None:
        if input_size < 1:
            raise ValueError(f"rgb: input_size must be positive, got {input_size}")
        self.input_size = int(input_size)

    def cache_params(self) -> dict[str, Any]:
        return {"input_size": self.input_size}

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = self.check_images(images)
        return (images.astype(np.float32) / 255.0).transpose(0, 3, 1, 2).copy()


register_encoder("rgb", "visual", RgbEncoder)

"""The empty encoders, for geometry-only and vision-only runs (the paper's ablations).

``none-geometric`` and ``none-visual`` return features with zero channels (``dim ==
0``). The stages store the empty arrays as usual and fusion then consists of the other
part alone (:func:`pipeline.method.registration.fusion.fuse`), so an ablation is the same
pipeline with one encoder switched off: ``--config visual_encoder=none`` (the run
manifests accept ``none`` for either encoder; both at once is refused).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.method.encoders.registry import GeometricEncoder, VisualEncoder, register_encoder


class NoGeometry(GeometricEncoder):
    """Geometric features with no channels: (N, 0) float32."""

    name = "none-geometric"
    version = "1"
    dim = 0

    def signature(self) -> str:
        return "nogeo"

    def cache_params(self) -> dict[str, Any]:
        return {}

    def encode(self, points, normals, diameter, *, viewpoint=None) -> np.ndarray:
        return np.zeros((len(np.asarray(points).reshape(-1, 3)), 0), np.float32)


class NoVisual(VisualEncoder):
    """Visual feature maps with no channels: (B, 0, 1, 1) float32. Lifting skips it."""

    name = "none-visual"
    version = "1"
    dim = 0

    def __init__(self, input_size: int = 224) -> None:
        self.input_size = int(input_size)

    def signature(self) -> str:
        return "novis"

    def cache_params(self) -> dict[str, Any]:
        return {}

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = self.check_images(images)
        return np.zeros((len(images), 0, 1, 1), np.float32)


register_encoder("none-geometric", "geometric", NoGeometry)
register_encoder("none-visual", "visual", NoVisual)

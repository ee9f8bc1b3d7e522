"""``colortex``: a weight-free dense colour + texture descriptor (visual encoder).

It stands in for DINOv2 when no weights are available. Every channel is computed from
Gaussian-smoothed versions of the image at scales ``sigmas`` (pixels of the
``input_size`` crop), then average-pooled over ``stride x stride`` blocks, so the map is
``(dim, S/stride, S/stride)`` and the lifting code really upsamples it.

Colour is described by chromaticity, opponent colour divided by intensity::

    c1 = (R - G) / (R + G + B + e),   c2 = (R + G - 2B) / (2 (R + G + B) + e)

computed from the smoothed R, G, B. Per scale ``s`` there are 5 colour channels, in
this order:

0-1. ``c1_s``, ``c2_s``: chromaticity of the smoothed colour;
2.   ``s * sqrt(|grad c1_s|^2 + |grad c2_s|^2)``: colour-edge strength;
3-4. ``s^2 * Laplacian(c1_s)``, ``s^2 * Laplacian(c2_s)``: colour blobs (a
     Laplacian-of-Gaussian of the chromaticity, sign = which colour is inside).

With ``intensity_weight > 0`` there are 4 more channels per scale, multiplied by that
weight, describing achromatic texture (printed text, dark marks) on the log intensity
``L = log(mean(R, G, B) + e_L)``: ``s * |grad L_s|``, the two Hessian eigenvalues
``s^2 * (l1 >= l2)`` of ``L_s``, and the standard deviation of ``L`` in the Gaussian
window ``s``. They are off by default. On rendered views of the textured objects of
benchmarks/registration.py, shading and silhouettes, which change with the
viewpoint and the light, dominate them: fused with FPFH, the share of correct top-1
scene-to-model matches on the "rock" object fell from 0.70 to 0.54 when they were
added with weight 0.1 (the colour Laplacian channels raised it from 0.70 to 0.73), and
in the benchmark's hard setting 28/30 poses were recovered with weight 0.1 against
29/30 without. Objects with achromatic print may still want them.

Invariances (tested). Brightness: scaling the image by a factor cancels in the
chromaticity ratios and becomes an additive constant of ``L`` that derivatives and
standard deviations remove, so all channels are unchanged up to uint8 rounding,
clipping and the small offsets ``e``/``e_L`` that keep dark pixels stable. Because
shading of a matte surface under white light scales R, G, B together, the colour
channels are also insensitive to shading. In-plane rotation: Gaussian smoothing,
gradient magnitudes, Laplacians, Hessian eigenvalues and standard deviations are
rotation invariant; on the pixel grid, with symmetric borders (reflect-101) and block
pooling, rotating the input by a multiple of 90 degrees rotates the output map the same
way exactly (up to float round-off).

Not invariant: scale (the crop normalises it), the colour of the illumination, and
near-silhouette pixels at large ``s``, which mix in the background (as with any CNN or
ViT feature). Achromatic (grey, white, black) regions have zero chromaticity and are
told apart only by the optional intensity channels.
"""

from __future__ import annotations

from typing import Any, Sequence

import cv2
import numpy as np

from pipeline.method.encoders.registry import VisualEncoder, register_encoder

COLOUR_CHANNELS_PER_SCALE = 5
INTENSITY_CHANNELS_PER_SCALE = 4
_EPS_CHROMA = 0.03  # on R+G+B in [0, 3]: about 2.5/255 per channel
_EPS_LOG = 0.02  # on mean intensity in [0, 1]


def _dx(a: np.ndarray) -> np.ndarray:
    """Central difference along columns with reflect-101 borders, (H, W) -> (H, W)."""
    p = np.pad(a, ((0, 0), (1, 1)), mode="reflect")
    return 0.5 * (p[:, 2:] - p[:, :-2])


def _dy(a: np.ndarray) -> np.ndarray:
    """Central difference along rows with reflect-101 borders."""
    p = np.pad(a, ((1, 1), (0, 0)), mode="reflect")
    return 0.5 * (p[2:, :] - p[:-2, :])


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of (H, W) or (H, W, C) float32, kernel radius ceil(3 sigma)."""
    radius = int(np.ceil(3.0 * sigma))
    return cv2.GaussianBlur(a, (2 * radius + 1, 2 * radius + 1), sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_REFLECT_101)


def _pool(a: np.ndarray, stride: int) -> np.ndarray:
    """Block average (H, W, C) -> (H/stride, W/stride, C)."""
    H, W, C = a.shape
    return a.reshape(H // stride, stride, W // stride, stride, C).mean(axis=(1, 3))


class ColorTexEncoder(VisualEncoder):
    """Dense chromaticity + rotation-invariant colour texture (see module docstring).

    input_size: side S of the square crops it takes (a multiple of ``stride``).
    stride: pooling block size; the output map is (dim, S/stride, S/stride).
    sigmas: Gaussian scales in pixels of the S x S crop.
    intensity_weight: weight of the optional achromatic texture channels (0 = off).
    """

    name = "colortex"
    version = "1"

    def __init__(
        self,
        input_size: int = 224,
        stride: int = 4,
        sigmas: Sequence[float] = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
        intensity_weight: float = 0.0,
    ) -> None:
        sigmas = [float(s) for s in sigmas]
        if not sigmas or any(s <= 0 for s in sigmas):
            raise ValueError(f"colortex: sigmas must be a non-empty list of positive values, got {sigmas}")
        if stride < 1 or input_size % stride != 0:
            raise ValueError(f"colortex: input_size {input_size} must be a multiple of stride {stride}")
        if 3 * max(sigmas) >= input_size:
            raise ValueError(f"colortex: sigma {max(sigmas)} too large for input_size {input_size}")
        if intensity_weight < 0:
            raise ValueError(f"colortex: intensity_weight must be >= 0, got {intensity_weight}")
        self.input_size = int(input_size)
        self.stride = int(stride)
        self.sigmas = sigmas
        self.intensity_weight = float(intensity_weight)
        per_scale = COLOUR_CHANNELS_PER_SCALE + (INTENSITY_CHANNELS_PER_SCALE if self.intensity_weight > 0 else 0)
        self.dim = per_scale * len(sigmas)

    def cache_params(self) -> dict[str, Any]:
        return {
            "input_size": self.input_size,
            "stride": self.stride,
            "sigmas": self.sigmas,
            "intensity_weight": self.intensity_weight,
        }

    def channel_names(self) -> list[str]:
        """Names of the ``dim`` output channels, e.g. ``c1@s2`` or ``L-grad@s4``."""
        names = []
        for s in self.sigmas:
            tag = f"@s{s:g}"
            names += [n + tag for n in ("c1", "c2", "c-edge", "c1-log", "c2-log")]
            if self.intensity_weight > 0:
                names += [n + tag for n in ("L-grad", "L-hess1", "L-hess2", "L-std")]
        return names

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = self.check_images(images)
        S = self.input_size
        out = np.empty((len(images), self.dim, S // self.stride, S // self.stride), dtype=np.float32)
        for b, img in enumerate(images):
            out[b] = self._encode_one(img).transpose(2, 0, 1)
        return out

    def _encode_one(self, img: np.ndarray) -> np.ndarray:
        """(S, S, 3) uint8 -> (S/stride, S/stride, dim) float32."""
        rgb = img.astype(np.float32) / 255.0
        R, G, B = rgb[..., 0], rgb[..., 1], rgb[..., 2]
        total = R + G + B
        planes = [R - G, R + G - 2.0 * B, total]
        if self.intensity_weight > 0:
            L = np.log(total / 3.0 + _EPS_LOG)
            planes += [L, L * L]
        # Chromaticity is taken from smoothed R, G, B (not smoothed per-pixel ratios):
        # the brightness factor still cancels, and dark, noisy pixels weigh less.
        base = np.stack(planes, axis=-1).astype(np.float32)
        channels = []
        for s in self.sigmas:
            sm = _blur(base, s)
            c1 = sm[..., 0] / (sm[..., 2] + _EPS_CHROMA)
            c2 = sm[..., 1] / (2.0 * sm[..., 2] + _EPS_CHROMA)
            g1x, g1y, g2x, g2y = _dx(c1), _dy(c1), _dx(c2), _dy(c2)
            edge = s * np.sqrt(g1x * g1x + g1y * g1y + g2x * g2x + g2y * g2y)
            log1 = s * s * (_dx(g1x) + _dy(g1y))
            log2 = s * s * (_dx(g2x) + _dy(g2y))
            channels += [c1, c2, edge, log1, log2]
            if self.intensity_weight > 0:
                channels += [self.intensity_weight * ch for ch in self._intensity_texture(sm, s)]
        dense = np.stack(channels, axis=-1).astype(np.float32)
        return _pool(dense, self.stride)

    @staticmethod
    def _intensity_texture(sm: np.ndarray, s: float) -> list[np.ndarray]:
        """Gradient magnitude, Hessian eigenvalues and local std of log intensity."""
        Ls = sm[..., 3]
        gx, gy = _dx(Ls), _dy(Ls)
        grad = s * np.sqrt(gx * gx + gy * gy)
        dxx, dyy, dxy = _dx(gx), _dy(gy), _dy(gx)
        half_trace = 0.5 * (dxx + dyy)
        root = np.sqrt(0.25 * (dxx - dyy) ** 2 + dxy * dxy)
        std = np.sqrt(np.maximum(sm[..., 4] - Ls * Ls, 0.0))
        return [grad, s * s * (half_trace + root), s * s * (half_trace - root), std]


register_encoder("colortex", "visual", ColorTexEncoder)

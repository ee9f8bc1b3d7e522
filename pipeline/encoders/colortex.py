"""``colortex``: a weight-free dense colour + texture descriptor (visual encoder).

It stands in for DINOv2 when no weights are available. Every channel is computed from
Gaussian-smoothed versions of the image at scales ``sigmas`` (pixels of the
``input_size`` crop), then average-pooled over ``stride x stride`` blocks, so the map is
``(dim, S/stride, S/stride)`` and the lifting code really upsamples it.

Per scale ``s`` (7 channels, in this order):

0-1. chromaticity ``(R-G)/(R+G+B+e)`` and ``(R+G-2B)/(2(R+G+B)+e)`` of the smoothed
     colour: opponent colour divided by intensity, so it does not change when the
     illumination intensity is scaled;
2.   scale-normalised gradient magnitude ``s*|grad L_s|`` of the smoothed log
     intensity ``L = log(mean(R,G,B) + e_L)``;
3-4. scale-normalised Hessian eigenvalues ``s^2 * (l1 >= l2)`` of ``L_s`` (blobs,
     ridges, corners; their sum is the Laplacian of Gaussian);
5.   local contrast: standard deviation of ``L`` in the Gaussian window ``s``;
6.   colour-edge strength ``s*sqrt(|grad c1_s|^2 + |grad c2_s|^2)``.

Invariances (tested): log intensity turns a brightness factor into an additive
constant that derivatives and standard deviations remove, and chromaticity ratios
cancel it, so all channels are unchanged when the image is multiplied by a factor, up
to uint8 rounding, clipping and the small offsets ``e``/``e_L`` that keep dark pixels
stable. Gaussian smoothing, gradient magnitudes, Hessian eigenvalues and standard
deviations are rotation invariant; on the pixel grid with symmetric borders
(reflect-101) and block pooling, rotating the input by a multiple of 90 degrees
rotates the output map the same way exactly (up to float round-off).

Not invariant: scale (the crop normalises it), colour of the illumination, and
near-silhouette pixels at large ``s``, which mix in the background (as with any CNN or
ViT feature).
"""

from __future__ import annotations

from typing import Any, Sequence

import cv2
import numpy as np

from pipeline.encoders.registry import VisualEncoder, register_encoder

CHANNELS_PER_SCALE = 7
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
    radius = int(np.ceil(3.0 * sigma))
    return cv2.GaussianBlur(a, (2 * radius + 1, 2 * radius + 1), sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_REFLECT_101)


def _pool(a: np.ndarray, stride: int) -> np.ndarray:
    """Block average (H, W, C) -> (H/stride, W/stride, C)."""
    H, W, C = a.shape
    return a.reshape(H // stride, stride, W // stride, stride, C).mean(axis=(1, 3))


class ColorTexEncoder(VisualEncoder):
    """Dense colour + rotation-invariant texture descriptor (see module docstring).

    input_size: side S of the square crops it takes (must be divisible by ``stride``).
    stride: pooling block size; the output map is (dim, S/stride, S/stride).
    sigmas: Gaussian scales in pixels of the S x S crop.
    """

    name = "colortex"
    version = "1"

    def __init__(self, input_size: int = 224, stride: int = 4, sigmas: Sequence[float] = (1.0, 2.0, 4.0, 8.0, 16.0)) -> None:
        sigmas = [float(s) for s in sigmas]
        if not sigmas or any(s <= 0 for s in sigmas):
            raise ValueError(f"colortex: sigmas must be a non-empty list of positive values, got {sigmas}")
        if stride < 1 or input_size % stride != 0:
            raise ValueError(f"colortex: input_size {input_size} must be a multiple of stride {stride}")
        if 3 * max(sigmas) >= input_size:
            raise ValueError(f"colortex: sigma {max(sigmas)} too large for input_size {input_size}")
        self.input_size = int(input_size)
        self.stride = int(stride)
        self.sigmas = sigmas
        self.dim = CHANNELS_PER_SCALE * len(sigmas)

    def cache_params(self) -> dict[str, Any]:
        return {"input_size": self.input_size, "stride": self.stride, "sigmas": self.sigmas}

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = np.asarray(images)
        S = self.input_size
        if images.ndim != 4 or images.shape[1:] != (S, S, 3):
            raise ValueError(f"colortex: expected images (B, {S}, {S}, 3) uint8, got shape {images.shape}")
        if images.dtype != np.uint8:
            raise ValueError(f"colortex: expected uint8 images, got {images.dtype}")
        out = np.empty((len(images), self.dim, S // self.stride, S // self.stride), dtype=np.float32)
        for b, img in enumerate(images):
            out[b] = self._encode_one(img).transpose(2, 0, 1)
        return out

    def _encode_one(self, img: np.ndarray) -> np.ndarray:
        """(S, S, 3) uint8 -> (S/stride, S/stride, dim) float32."""
        rgb = img.astype(np.float32) / 255.0
        R, G, B = rgb[..., 0], rgb[..., 1], rgb[..., 2]
        total = R + G + B
        L = np.log(total / 3.0 + _EPS_LOG)
        # Smoothed linear quantities: ratios of smoothed values keep the brightness
        # invariance exact, ratios of raw pixels would amplify dark-pixel noise.
        base = np.stack([R - G, R + G - 2.0 * B, total, L, L * L], axis=-1).astype(np.float32)
        channels = []
        for s in self.sigmas:
            sm = _blur(base, s)
            c1 = sm[..., 0] / (sm[..., 2] + _EPS_CHROMA)
            c2 = sm[..., 1] / (2.0 * sm[..., 2] + _EPS_CHROMA)
            Ls = sm[..., 3]
            gx, gy = _dx(Ls), _dy(Ls)
            grad = s * np.sqrt(gx * gx + gy * gy)
            dxx, dyy, dxy = _dx(gx), _dy(gy), _dy(gx)
            half_trace = 0.5 * (dxx + dyy)
            root = np.sqrt(0.25 * (dxx - dyy) ** 2 + dxy * dxy)
            l1 = s * s * (half_trace + root)
            l2 = s * s * (half_trace - root)
            contrast = np.sqrt(np.maximum(sm[..., 4] - Ls * Ls, 0.0))
            cedge = s * np.sqrt(_dx(c1) ** 2 + _dy(c1) ** 2 + _dx(c2) ** 2 + _dy(c2) ** 2)
            channels += [c1, c2, grad, l1, l2, contrast, cedge]
        dense = np.stack(channels, axis=-1).astype(np.float32)
        return _pool(dense, self.stride)


register_encoder("colortex", "visual", ColorTexEncoder)

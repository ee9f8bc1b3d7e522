"""Procedural 2D artwork: printed labels for objects and surface textures for the scene.

Labels are drawn on a canvas in millimetres (x right, y *down*, origin top-left, as a
designer lays out a label) and later read at mesh vertices whose uv is in mm with v
*up* from the label's bottom edge (see ``Label.sample``).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

Color = Sequence[int]


class Label:
    """An RGB canvas of ``width_mm`` x ``height_mm`` at ``ppm`` pixels per mm."""

    def __init__(self, width_mm: float, height_mm: float, background: Color, ppm: float = 4.0):
        self.width_mm = float(width_mm)
        self.height_mm = float(height_mm)
        self.ppm = float(ppm)
        w = int(round(width_mm * ppm))
        h = int(round(height_mm * ppm))
        self.image = np.empty((h, w, 3), np.uint8)
        self.image[:] = np.asarray(background, np.uint8)

    def _px(self, v: float) -> int:
        return int(round(v * self.ppm))

    def rect(self, x: float, y: float, w: float, h: float, color: Color) -> "Label":
        """Filled rectangle, top-left (x, y) mm, size w x h mm."""
        cv2.rectangle(self.image, (self._px(x), self._px(y)), (self._px(x + w) - 1, self._px(y + h) - 1), _c(color), -1)
        return self

    def disc(self, cx: float, cy: float, r: float, color: Color) -> "Label":
        cv2.circle(self.image, (self._px(cx), self._px(cy)), self._px(r), _c(color), -1, lineType=cv2.LINE_AA)
        return self

    def ring(self, cx: float, cy: float, r: float, width: float, color: Color) -> "Label":
        cv2.circle(self.image, (self._px(cx), self._px(cy)), self._px(r), _c(color), max(self._px(width), 1), cv2.LINE_AA)
        return self

    def polygon(self, points_mm: np.ndarray, color: Color) -> "Label":
        pts = np.round(np.asarray(points_mm) * self.ppm).astype(np.int32)
        cv2.fillPoly(self.image, [pts], _c(color), lineType=cv2.LINE_AA)
        return self

    def text(self, s: str, x: float, y: float, height: float, color: Color, bold: float = 0.18) -> "Label":
        """Text whose capitals are ``height`` mm tall, baseline at y mm."""
        font = cv2.FONT_HERSHEY_DUPLEX
        (_, th), _ = cv2.getTextSize("H", font, 1.0, 1)
        scale = height * self.ppm / th
        thick = max(int(round(bold * height * self.ppm / 2)), 1)
        cv2.putText(self.image, s, (self._px(x), self._px(y)), font, scale, _c(color), thick, cv2.LINE_AA)
        return self

    def text_width(self, s: str, height: float, bold: float = 0.18) -> float:
        """Width in mm that ``text`` would use."""
        font = cv2.FONT_HERSHEY_DUPLEX
        (_, th), _ = cv2.getTextSize("H", font, 1.0, 1)
        scale = height * self.ppm / th
        thick = max(int(round(bold * height * self.ppm / 2)), 1)
        (tw, _), _ = cv2.getTextSize(s, font, scale, thick)
        return tw / self.ppm

    def stripes(self, x: float, y: float, w: float, h: float, period: float, colors: Sequence[Color], vertical: bool = False) -> "Label":
        """Bands of width ``period`` cycling through ``colors`` inside a rectangle."""
        n = int(np.ceil((w if vertical else h) / period))
        for i in range(n):
            c = colors[i % len(colors)]
            if vertical:
                self.rect(x + i * period, y, min(period, x + w - (x + i * period)), h, c)
            else:
                self.rect(x, y + i * period, w, min(period, y + h - (y + i * period)), c)
        return self

    def text_block(self, x: float, y: float, w: float, h: float, line: float, color: Color, rng: np.random.Generator) -> "Label":
        """Rows of word-like bars (small print) filling a rectangle; ``line`` = row pitch mm."""
        yy = y
        while yy + 0.6 * line <= y + h:
            xx = x
            end = x + w * rng.uniform(0.6, 1.0)
            while xx < end:
                word = rng.uniform(1.5, 5.0) * line * 0.6
                self.rect(xx, yy, min(word, end - xx), 0.55 * line, color)
                xx += word + 0.5 * line
            yy += line
        return self

    def barcode(self, x: float, y: float, w: float, h: float, rng: np.random.Generator) -> "Label":
        self.rect(x, y, w, h, (255, 255, 255))
        xx = x + 1.5
        while xx < x + w - 2.5:
            bw = rng.choice([0.5, 0.8, 1.2])
            self.rect(xx, y + 1, bw, h - 2, (15, 15, 15))
            xx += bw + rng.choice([0.5, 0.8, 1.2])
        return self

    def sample(self, uv: np.ndarray, feature_mm: float = 1.0) -> np.ndarray:
        """Colours (V, 3) uint8 at uv (V, 2) mm (v up from the bottom edge).

        The canvas is blurred to about ``feature_mm`` first, since a vertex stands for
        a patch of surface, not a point; uv outside the canvas clamps to its border.
        """
        sigma = max(0.4 * feature_mm * self.ppm, 0.01)
        img = cv2.GaussianBlur(self.image, (0, 0), sigma)
        col = (np.asarray(uv[:, 0]) * self.ppm - 0.5).astype(np.float32)
        row = ((self.height_mm - np.asarray(uv[:, 1])) * self.ppm - 0.5).astype(np.float32)
        out = cv2.remap(img, col.reshape(-1, 1), row.reshape(-1, 1), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(-1, 3)


def _c(color: Color) -> tuple[int, int, int]:
    return tuple(int(v) for v in color)  # type: ignore[return-value]


# ---------------------------------------------------------------------------- scene surfaces


def _smooth_noise(rng: np.random.Generator, size: int, scale: float) -> np.ndarray:
    """(size, size) float32 noise with features of ``scale`` px, standardised, tileable."""
    n = rng.standard_normal((size, size)).astype(np.float32)
    f = np.fft.fft2(n)
    k = np.fft.fftfreq(size)
    kk = np.sqrt(k[:, None] ** 2 + k[None, :] ** 2)
    f *= np.exp(-((kk * scale) ** 2))
    out = np.real(np.fft.ifft2(f)).astype(np.float32)
    return (out - out.mean()) / (out.std() + 1e-8)


def wood_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """(size, size, 3) uint8 tileable wood grain (planks along x)."""
    y = np.arange(size, dtype=np.float32)[:, None]
    warp = _smooth_noise(rng, size, 40.0) * 6.0
    grain = np.sin(2 * np.pi * (y + warp) / rng.uniform(9, 16)) * 0.5 + 0.5
    fine = _smooth_noise(rng, size, 2.0) * 0.08
    planks = ((y // (size // 4)) % 2).astype(np.float32) * 0.06
    base = np.array(rng.choice([[150, 100, 60], [185, 140, 90], [110, 70, 45], [200, 170, 120]]), np.float32)
    shade = 0.78 + 0.22 * grain + fine + planks
    return np.clip(base[None, None, :] * shade[..., None], 0, 255).astype(np.uint8)


def cloth_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """(size, size, 3) uint8 tileable gingham tablecloth."""
    period = size // int(rng.choice([8, 16]))
    x = np.arange(size)
    band = ((x // (period // 2)) % 2).astype(np.float32)
    a, b = band[None, :], band[:, None]
    light = np.array([245, 245, 240], np.float32)
    dark = np.array(rng.choice([[190, 40, 40], [40, 80, 170], [40, 130, 70]]), np.float32)
    mix = (a + b) / 2.0
    img = light[None, None] * (1 - mix[..., None]) + dark[None, None] * mix[..., None]
    weave = _smooth_noise(rng, size, 1.0)[..., None] * 6.0
    return np.clip(img + weave, 0, 255).astype(np.uint8)


def speckle_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """(size, size, 3) uint8 tileable speckled laminate."""
    base = np.array(rng.choice([[170, 172, 168], [205, 200, 190], [90, 95, 100]]), np.float32)
    blotch = _smooth_noise(rng, size, 30.0)[..., None] * 8.0
    speck = (rng.random((size, size)) < 0.02)[..., None] * rng.uniform(-60, 60)
    return np.clip(base + blotch + speck + _smooth_noise(rng, size, 1.0)[..., None] * 4.0, 0, 255).astype(np.uint8)


def felt_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """(size, size, 3) uint8 tileable dark felt/mat with a printed grid (like a cutting mat)."""
    base = np.array(rng.choice([[40, 90, 60], [50, 55, 70], [30, 30, 35]]), np.float32)
    img = base + _smooth_noise(rng, size, 3.0)[..., None] * 7.0
    step = size // 20
    img[::step, :, :] += 60
    img[:, ::step, :] += 60
    return np.clip(img, 0, 255).astype(np.uint8)


TABLE_TEXTURES = {"wood": wood_texture, "cloth": cloth_texture, "speckle": speckle_texture, "felt": felt_texture}

"""Pictures of one estimate over its image (``freeze estimate``'s overlay.png and points.png)."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def render_overlay(mesh, R: np.ndarray, t: np.ndarray, K: np.ndarray, rgb: np.ndarray,
                   box: Sequence[float] | None = None, caption: str = "", alpha: float = 0.5) -> np.ndarray:
    """(H, W, 3) uint8: ``mesh`` rendered at (R, t mm) blended over ``rgb`` with its
    contour in green, the prior's box in yellow and a caption."""
    import cv2

    from pipeline.method.render import Renderer
    from pipeline.views.plots import finite_max
    from pipeline.views.sar_figure import overlay

    H, W = rgb.shape[:2]
    v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3) @ R.T + t
    # Far plane beyond the model's farthest finite vertex (an empty or non-finite model
    # gives 1 mm, so the plane stays finite: a renderer cannot take NaN or inf).
    zfar = max(finite_max(v[:, 2], 1.0), 1.0) * 2 + 1000.0
    with Renderer(W, H, znear=1.0, zfar=zfar) as r:
        r.add_mesh("model", mesh)
        color, d = r.render([("model", R, t)], K, rgb=True)
    m = d > 0
    out = overlay(rgb, color, m, alpha=alpha)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 2)
    if box is not None:
        x, y, w, h = (int(round(float(b))) for b in box)
        cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), (255, 220, 0), 1)
    if caption:
        cv2.putText(out, caption, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, caption, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def points_picture(rgb: np.ndarray, kept_pixels: np.ndarray, sampled_pixels: np.ndarray,
                   box: Sequence[float] | None = None) -> np.ndarray:
    """(H, W, 3) uint8: the image darkened, the candidate's object pixels (P, 2) (u, v)
    in green, the M sampled ones in white, the prior's box in yellow."""
    import cv2

    out = (0.5 * np.asarray(rgb)).astype(np.uint8)
    out[kept_pixels[:, 1], kept_pixels[:, 0]] = (0, 200, 0)
    out[sampled_pixels[:, 1], sampled_pixels[:, 0]] = (255, 255, 255)
    if box is not None:
        x, y, w, h = (int(round(float(b))) for b in box)
        cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), (255, 220, 0), 1)
    return out

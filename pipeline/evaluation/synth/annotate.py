"""Ground-truth annotations from depth renders: masks, visibility statistics, targets.

Masks come from depth, never from colour (colour is blended at silhouettes): ``mask``
is the object rendered alone (depth > 0), ``mask_visib`` the part of it whose own depth
equals the depth of the whole scene within ``VISIB_TOL_MM``. Boxes follow the BOP
toolkit: (x_min, y_min, x_max - x_min, y_max - y_min), (-1, -1, -1, -1) when empty.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from pipeline.formats.bop import GtInfo, Target

VISIB_TOL_MM = 2.0
"""Object depth within this of the scene depth counts as visible (both are clean renders)."""

MIN_VISIB_FRACT = 0.1
"""BOP19 targets: instances at least this visible."""


def bbox_from_mask(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of a (H, W) bool mask, BOP-toolkit style; (-1, -1, -1, -1) if empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return (-1, -1, -1, -1)
    return (int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min()))


def projected_bbox(vertices: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> tuple[int, int, int, int]:
    """Box of the pixel centres covered by the projection of a mesh, unclipped by the image.

    vertices (N, 3) mm in the model frame. The silhouette's extreme points are
    vertices, and a pixel is covered when its centre (integer coordinates) is inside,
    so the box runs from ceil(min) to floor(max); this is the BOP ``bbox_obj``, which
    extends past the image for truncated objects.
    """
    pc = vertices @ np.asarray(R).T + np.asarray(t)
    uvw = pc @ np.asarray(K).T
    uv = uvw[:, :2] / uvw[:, 2:3]
    lo = np.ceil(uv.min(axis=0) - 1e-9).astype(int)
    hi = np.floor(uv.max(axis=0) + 1e-9).astype(int)
    return (int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1]))


def silhouette_bbox(mask: np.ndarray, projected: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """BOP ``bbox_obj``: the mask's box, extended by the projection where the mask is cut by the image border.

    Inside the image the rasterised mask is the reference (the projection can differ
    by a pixel where a vertex falls on a pixel centre); at a border the silhouette
    continues, and the projected box says how far.
    """
    h, w = mask.shape
    px, py, pw, ph = projected
    if not mask.any():
        return projected
    x0, y0, bw, bh = bbox_from_mask(mask)
    x1, y1 = x0 + bw, y0 + bh
    x0 = px if x0 == 0 else x0
    y0 = py if y0 == 0 else y0
    x1 = px + pw if x1 == w - 1 else x1
    y1 = py + ph if y1 == h - 1 else y1
    return (x0, y0, x1 - x0, y1 - y0)


@dataclass
class InstanceMasks:
    """Masks (H, W) bool and statistics of one annotated instance."""

    mask: np.ndarray
    mask_visib: np.ndarray
    info: GtInfo


def annotate_instance(
    obj_depth: np.ndarray,
    scene_depth: np.ndarray,
    measured_depth: np.ndarray,
    bbox_obj: tuple[int, int, int, int],
    tol_mm: float = VISIB_TOL_MM,
) -> InstanceMasks:
    """Masks and ``GtInfo`` of one instance.

    bbox_obj: the projected box of the whole object (``projected_bbox``), used
    where the silhouette leaves the image.
    obj_depth: (H, W) float32 mm, the object rendered alone; scene_depth: the clean
    render of the whole scene; measured_depth: the simulated sensor depth (for
    ``px_count_valid``, silhouette pixels with a depth value).
    """
    mask = obj_depth > 0
    visib = mask & (np.abs(obj_depth - scene_depth) <= tol_mm)
    n_all = int(mask.sum())
    n_visib = int(visib.sum())
    info = GtInfo(
        bbox_obj=silhouette_bbox(mask, tuple(int(v) for v in bbox_obj)),
        bbox_visib=bbox_from_mask(visib),
        px_count_all=n_all,
        px_count_valid=int((mask & (measured_depth > 0)).sum()),
        px_count_visib=n_visib,
        visib_fract=float(n_visib / n_all) if n_all > 0 else 0.0,
    )
    return InstanceMasks(mask, visib, info)


def image_targets(scene_id: int, im_id: int, obj_ids: list[int], infos: list[GtInfo], min_visib: float = MIN_VISIB_FRACT) -> list[Target]:
    """BOP19 targets of one image: per object, the number of instances at least ``min_visib`` visible."""
    counts = Counter(o for o, g in zip(obj_ids, infos) if g.visib_fract >= min_visib)
    return [Target(scene_id, im_id, o, n) for o, n in sorted(counts.items())]

"""The SAR figure: what the symmetry-aware refinement saw and chose (like FreeZe's Fig. 5).

One row per estimate: the scene crop, the object rendered at the ICP pose over it, the
object at the pose SAR chose over it, and the similarity of every symmetric variant
(a bar per variant, the chosen one highlighted). Rendered with the same crop geometry
as SAR itself (:func:`pipeline.method.refinement.sar.render_in_crop`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np


@dataclass
class SarCase:
    """One estimate that went through SAR.

    crop: (S, S, 3) uint8 scene crop; icp_render / sar_render: (S, S, 3) uint8 renders
    with masks (S, S) bool; similarities: (V,) per variant (variant 0 = ICP pose);
    chosen: index of the kept variant; title: caption (scene, image, object...).
    """

    crop: np.ndarray
    icp_render: np.ndarray
    icp_mask: np.ndarray
    sar_render: np.ndarray
    sar_mask: np.ndarray
    similarities: np.ndarray
    chosen: int
    title: str


def overlay(crop: np.ndarray, render: np.ndarray, mask: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """The render blended over the crop where ``mask`` is set, with its outline in white."""
    import cv2

    out = crop.astype(np.float32).copy()
    m = mask.astype(bool)
    out[m] = (1 - alpha) * out[m] + alpha * render[m].astype(np.float32)
    edge = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    out[edge] = 255.0
    return out.clip(0, 255).astype(np.uint8)


def _similarity(values: np.ndarray, i: int) -> str:
    """Variant ``i``'s similarity for a title: 3 decimals, "-" when missing or not finite."""
    return f"{values[i]:.3f}" if 0 <= i < len(values) and np.isfinite(values[i]) else "-"


def draw_sar_figure(cases: Sequence[SarCase], out: Path, title: str = "") -> Path:
    """Write the figure of ``cases`` (one row each) to the PNG ``out``. A case whose
    similarities are empty or all non-finite gets "no data" in its bar panel; non-finite
    similarities are left out of the bars and of the axis limits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.views.plots import NO_DATA, finite_or_nan, no_data, save_figure

    n = max(1, len(cases))
    fig, axes = plt.subplots(n, 4, figsize=(13, 3.2 * n), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 1, 1, 1.4]})
    for row, case in zip(axes, cases):
        # Similarities as stored may be empty, NaN or inf (a variant that could not be
        # encoded): only finite ones are drawn and set the limits.
        finite = finite_or_nan(case.similarities)
        row[0].imshow(case.crop)
        row[0].set_title(case.title, fontsize=9)
        row[1].imshow(overlay(case.crop, case.icp_render, case.icp_mask))
        row[1].set_title(f"ICP pose (variant 0): {_similarity(finite, 0)}", fontsize=9)
        row[2].imshow(overlay(case.crop, case.sar_render, case.sar_mask))
        row[2].set_title(f"SAR pose (variant {case.chosen}): {_similarity(finite, case.chosen)}", fontsize=9)
        for ax in row[:3]:
            ax.set_xticks([])
            ax.set_yticks([])
        if not np.isfinite(finite).any():
            no_data(row[3], f"{NO_DATA}: no finite similarity")
            continue
        colors = ["tab:green" if i == case.chosen else "tab:gray" for i in range(len(finite))]
        row[3].bar(np.arange(len(finite)), np.nan_to_num(finite), color=colors)
        lo, hi = float(np.nanmin(finite)), float(np.nanmax(finite))
        pad = max(0.01, 0.1 * (hi - lo))
        row[3].set_ylim(lo - pad, hi + pad)
        row[3].set_xlabel("symmetric variant (no bar: not scored)", fontsize=8)
        row[3].set_ylabel("similarity", fontsize=8)
        row[3].tick_params(labelsize=7)
    for row in axes[len(cases):]:
        for ax in row:
            ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=11)
    return save_figure(fig, out, dpi=80)


def sar_cases(plan, obj_id: int, limit: int = 4) -> list[SarCase]:
    """Up to ``limit`` SAR cases of ``obj_id`` from a dataset plan's refine artifacts:
    those where SAR changed the pose first (largest gain first), then unchanged ones."""
    import pandas as pd

    from pipeline.method.geometry.crops import crop_and_resize, square_crop_box
    from pipeline.workflow.plan import build_encoders
    from pipeline.method.refinement.sar import render_in_crop
    from pipeline.method.render import Renderer
    from pipeline.common.store import read_table

    refine = plan["refine"]
    frames = []
    for item in plan.scene_items:
        path = refine.path(item, "sar")
        if path.exists():
            t = read_table(path)
            frames.append(t[t.obj_id == obj_id])
    sar = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if sar.empty:
        return []
    groups = []
    for (scene_id, im_id, cand_id), g in sar.groupby(["scene_id", "im_id", "cand_id"]):
        g = g.sort_values("variant")
        k = int(g[g.chosen].variant.iloc[0])
        # By variant number: the coarse-to-fine search leaves some variants unscored
        # (no row), which stay NaN (no bar).
        sims = np.full(int(g.variant.max()) + 1, np.nan)
        sims[g.variant.to_numpy(int)] = g.similarity.to_numpy(float)
        gain = float(sims[k] - sims[0])
        groups.append((k > 0, gain, int(scene_id), int(im_id), int(cand_id), g, sims))
    groups.sort(key=lambda x: (not x[0], -x[1]))
    _, vis = build_encoders(plan.run)
    S = vis.input_size
    margin = plan.run.stages.scene_features.crop_margin
    bop = plan.bop()
    cases = []
    with Renderer(S, S, znear=1.0, zfar=100000.0) as r:
        r.add_mesh(obj_id, bop.load_model(obj_id))
        for changed, gain, scene_id, im_id, cand_id, g, sims in groups[:limit]:
            boxes = plan["segment_prior"].table("all", "prior_candidates")
            b = boxes[boxes.cand_id == cand_id].iloc[0]
            rgb = bop.load_rgb(scene_id, im_id)
            K = bop.scene_camera(scene_id)[im_id].K
            box = square_crop_box((b.bbox_x, b.bbox_y, b.bbox_w, b.bbox_h), rgb.shape[:2], margin)
            k = int(g[g.chosen].variant.iloc[0])
            renders = []
            for v in (0, k):
                row = g[g.variant == v].iloc[0]
                renders.append(render_in_crop(r, obj_id, np.asarray(row.R).reshape(3, 3), np.asarray(row.t), K, box, S))
            cases.append(SarCase(crop=crop_and_resize(rgb, box, S), icp_render=renders[0][0], icp_mask=renders[0][1],
                                 sar_render=renders[1][0], sar_mask=renders[1][1],
                                 similarities=sims, chosen=k,
                                 title=f"scene {scene_id} image {im_id} cand {cand_id}" + (" (changed)" if changed else "")))
    return cases

"""The hypotheses figure: every hypothesis of a candidate after ICP (register's coarse
ones and the turns of the best, :mod:`pipeline.method.refinement.turns`), as the
verification saw it (:mod:`pipeline.method.refinement.verification`).

One row per candidate, one panel per hypothesis: the verification window of the image,
darkened, with the model rendered at the hypothesis' pose coloured by how its depth
compares with the sensor's (green: agrees within the tolerance; red: free space, the
camera sees behind the model; blue: occluded, something is in front of it; grey: no
sensor depth), the candidate mask's outline in yellow, and the terms in the title. The
candidate's chosen hypothesis has a green frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

AGREE, FREE, OCCLUDED, NO_DEPTH = (40, 200, 60), (230, 40, 40), (60, 110, 230), (150, 150, 150)


@dataclass
class HypothesisPanel:
    """One hypothesis: the coloured window (h, w, 3) uint8 and its caption."""

    image: np.ndarray
    caption: str
    chosen: bool


@dataclass
class HypothesisCase:
    """A candidate's hypotheses and a title (scene, image, candidate, object)."""

    panels: list[HypothesisPanel]
    title: str


def compare_picture(crop: np.ndarray, rendered: np.ndarray, observed: np.ndarray, mask: np.ndarray,
                    tol: float) -> np.ndarray:
    """(h, w, 3) uint8: ``crop`` darkened, the rendered pixels coloured by the depth
    comparison (see the module docstring), the mask's outline in yellow."""
    import cv2

    out = (0.45 * crop.astype(np.float32)).astype(np.uint8)
    on = rendered > 0
    seen = observed > 0
    diff = observed - rendered
    for sel, colour in ((on & ~seen, NO_DEPTH), (on & seen & (np.abs(diff) <= tol), AGREE),
                        (on & seen & (diff > tol), FREE), (on & seen & (diff < -tol), OCCLUDED)):
        out[sel] = (0.35 * out[sel] + 0.65 * np.asarray(colour)).astype(np.uint8)
    edge = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    out[edge] = (255, 220, 0)
    return out


def caption(row) -> str:
    """The panel title of one row of refine's ``hypotheses.parquet``."""
    turned = f" (of #{int(row.parent)})" if getattr(row, "parent", -1) >= 0 else ""
    return (f"{row.source} #{int(row.hyp)}{turned}: score {row.verification:.2f}\n"
            f"sil {row.silhouette:.2f} fit {row.depth_fit:.2f} cov {row.coverage:.2f} "
            f"free {row.free_space:.2f} ev {row.evidence:.3f}")


def hypothesis_cases(plan, limit: int = 6, scene_id: int | None = None, cand_id: int | None = None,
                     obj_id: int | None = None) -> list[HypothesisCase]:
    """Up to ``limit`` candidates of a dataset plan's refine artifacts, drawn: those whose
    chosen hypothesis is not the paper's fused pose first (largest margin first), then
    the others; or the one candidate ``cand_id`` (with ``scene_id``)."""
    import pandas as pd

    from pipeline.formats.bop.detections import prior_row_mask
    from pipeline.method.refinement.verification import verification_window
    from pipeline.method.render import Renderer
    from pipeline.common.store import read_table

    frames = []
    for item in plan.scene_items if scene_id is None else plan.items_of_scene(scene_id):
        path = plan["refine"].path(item, "hypotheses")
        if not path.exists():
            raise FileNotFoundError(f"{path} missing: run the refine stage first (snakemake --cores 2 bop_all)")
        frames.append(read_table(path))
    if not frames:  # a dataset without scenes: nothing to draw (concat of nothing fails)
        return []
    hyps = pd.concat(frames, ignore_index=True)
    if obj_id is not None:
        hyps = hyps[hyps.obj_id == obj_id]
    if cand_id is not None:
        hyps = hyps[hyps.cand_id == cand_id]
        if hyps.empty:
            raise LookupError(f"{plan.name}: candidate {cand_id} has no hypotheses"
                              + (f" in scene {scene_id}" if scene_id is not None else ""))
    order = []
    for (s, c), g in hyps.groupby(["scene_id", "cand_id"]):
        chosen = g[g.chosen]
        if chosen.empty:
            continue
        fused = g[g.source == "fused"].verification
        margin = float(chosen.verification.iloc[0] - (fused.max() if len(fused) else chosen.verification.iloc[0]))
        order.append((chosen.source.iloc[0] != "fused", margin, int(s), int(c), g.sort_values("hyp")))
    order.sort(key=lambda x: (not x[0], -x[1]))
    bop = plan.bop()
    boxes = plan["segment_prior"].table("all", "prior_candidates").set_index(["scene_id", "cand_id"])
    rp = plan.run.stages.refine
    infos = bop.models_info()
    cases: list[HypothesisCase] = []
    renderer = None
    try:
        for _, _, s, c, g in order[:limit]:
            im_id, o = int(g.im_id.iloc[0]), int(g.obj_id.iloc[0])
            depth, rgb, K = bop.load_depth(s, im_id), bop.load_rgb(s, im_id), bop.scene_camera(s)[im_id].K
            if renderer is None:
                renderer = Renderer(depth.shape[1], depth.shape[0], znear=1.0, zfar=100000.0)
            if not renderer.has_mesh(o):
                renderer.add_mesh(o, bop.load_model(o))
            b = boxes.loc[(s, c)]
            mask = prior_row_mask(b)
            x0, y0, w, h = verification_window((b.bbox_x, b.bbox_y, b.bbox_w, b.bbox_h), depth.shape, rp.verify_margin)
            tol = max(rp.verify_min_tol_mm, rp.verify_tol_frac * infos[o].diameter)
            panels = []
            for row in g.itertuples():
                rendered = renderer.render_depth_crop(o, np.reshape(row.R, (3, 3)), np.asarray(row.t), K,
                                                      (x0, y0, w, h))
                pic = compare_picture(rgb[y0:y0 + h, x0:x0 + w], rendered, depth[y0:y0 + h, x0:x0 + w],
                                      mask[y0:y0 + h, x0:x0 + w], tol)
                panels.append(HypothesisPanel(pic, caption(row), bool(row.chosen)))
            cases.append(HypothesisCase(panels, f"scene {s} image {im_id} candidate {c} (object {o})"))
    finally:
        if renderer is not None:
            renderer.close()
    return cases


def draw_hypotheses_figure(cases: Sequence[HypothesisCase], out: Path) -> Path:
    """Write the figure of ``cases`` (one row each) to the PNG ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.views.plots import save_figure

    n_rows = max(1, len(cases))
    n_cols = max([len(c.panels) for c in cases] + [1])
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(3.3 * n_cols, 3.6 * n_rows), squeeze=False)
    for row, case in zip(axes, cases):
        for ax, panel in zip(row, case.panels):
            ax.imshow(panel.image)
            ax.set_title(panel.caption, fontsize=7.5)
            ax.set_xticks([])
            ax.set_yticks([])
            for spine in ax.spines.values():
                spine.set_edgecolor("tab:green" if panel.chosen else "0.7")
                spine.set_linewidth(4 if panel.chosen else 1)
        row[0].set_ylabel(case.title, fontsize=8)
        for ax in row[len(case.panels):]:
            ax.axis("off")
    for row in axes[len(cases):]:
        for ax in row:
            ax.axis("off")
    fig.suptitle("hypotheses after ICP, as verified: green agrees with the sensor's depth, red stands in free space, "
                 "blue is occluded, grey has no depth; yellow: the candidate's mask; green frame: chosen", fontsize=9)
    return save_figure(fig, out, dpi=80)

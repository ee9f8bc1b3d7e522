"""Pictures of the report page, as PNG bytes: matplotlib charts (Agg) and pose overlays.

Charts: :func:`visibility_figure` (AR per visible-fraction bin, like FreeZe's occlusion
figure) and :func:`timing_figure` (wall time and peak memory per stage). Overlays:
:func:`pose_overlay` draws a rendered object over an image crop (tinted shading plus the
silhouette's contour) and :func:`side_by_side` puts the estimate and the ground truth
next to each other. Nothing here reads artifacts: :mod:`pipeline.views.html` does.

The charts take whatever the artifacts hold: empty inputs, None, NaN and inf are not
errors. A non-finite value is not drawn (a recall or a time cannot be infinite: inf
means "unknown" as much as NaN does), axis limits come from the finite values only, and
a panel with nothing to draw says "no data" instead of failing.
"""

from __future__ import annotations

import io
from typing import Any, Sequence

import numpy as np

#: Outline colours (RGB): a correct estimate, a wrong one, the ground truth.
GREEN = (40, 200, 60)
RED = (230, 40, 40)
BLUE = (40, 110, 255)

METRIC_STYLE = {  # column -> (label, colour, marker)
    "AR": ("AR", "black", "o"),
    "AR_VSD": ("AR_VSD", "tab:blue", "s"),
    "AR_MSSD": ("AR_MSSD", "tab:orange", "^"),
    "AR_MSPD": ("AR_MSPD", "tab:green", "v"),
}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: What a chart panel says when it has nothing finite to draw.
NO_DATA = "no data"


def finite_or_nan(values: Any) -> np.ndarray:
    """``values`` (a scalar or a sequence, possibly nested, possibly holding None) as a
    flat float64 array (a copy) with every non-finite or missing entry (None, NaN,
    +-inf, non-numeric) as NaN."""
    def one(v: Any) -> float:
        try:
            return float(v)
        except (TypeError, ValueError):
            return float("nan")

    try:
        a = np.array(values, dtype=np.float64).ravel()  # None becomes NaN here
    except (TypeError, ValueError):  # strings, ragged lists: one value at a time
        a = np.array([one(v) for v in np.ravel(np.asarray(values, dtype=object))], dtype=np.float64)
    a[~np.isfinite(a)] = np.nan
    return a


def finite_max(values: Any, default: float) -> float:
    """The largest finite value of ``values``, ``default`` when there is none."""
    v = finite_or_nan(values)
    return float(np.nanmax(v)) if np.isfinite(v).any() else float(default)


def no_data(ax, note: str = NO_DATA) -> None:
    """Mark the axes ``ax`` as having nothing to draw: ``note`` in its middle, no ticks."""
    ax.set_xticks([])
    ax.set_yticks([])
    ax.text(0.5, 0.5, note, transform=ax.transAxes, ha="center", va="center", fontsize=11, color="0.45")


def no_data_figure(note: str = NO_DATA, title: str = "", size: tuple[float, float] = (6.0, 2.4)) -> bytes:
    """A small PNG saying ``note`` (a chart without any finite value to draw)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=size)
    no_data(ax, note)
    if title:
        ax.set_title(title, fontsize=10)
    return figure_png(fig)


def figure_png(fig, dpi: int = 90) -> bytes:
    """The figure encoded as PNG (and closed)."""
    plt = _plt()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def save_figure(fig, out, dpi: int = 80, tight: bool = True):
    """Lay the figure out (``tight``: matplotlib's tight layout; False keeps the
    figure's own), write it to the PNG ``out`` atomically (no half-written file under
    that name) with mode ``0o666 & ~umask``, close it; returns the path."""
    from pathlib import Path

    from pipeline.common.published_files import publishable
    from pipeline.common.store import atomic_path

    plt = _plt()
    if tight:
        fig.tight_layout()
    out = Path(out)
    try:
        with atomic_path(out) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
            publishable(tmp)
    finally:
        plt.close(fig)  # also when writing fails: an open figure holds its memory until exit
    return out


def image_png(rgb: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 RGB image encoded as PNG."""
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {rgb.shape}")
    return buf.tobytes()


def visibility_figure(bins: Sequence[dict[str, Any]], title: str = "") -> bytes:
    """AR and its three components per visible-fraction bin, with the target counts.

    bins: rows of ``scores.json``'s ``per_visibility`` (visib_min, visib_max in [0, 1],
    n_targets, AR, AR_VSD, AR_MSSD, AR_MSPD in [0, 1]; None where a bin has no target).
    Lines join the bins that have targets; grey bars (right axis) count the targets per
    bin. Bins without finite edges are left out, non-finite recalls are not drawn and a
    missing or non-finite count is 0; with no bin left, or nothing at all to draw, the
    figure says "no data".
    """
    plt = _plt()
    from matplotlib.ticker import MaxNLocator

    bins = [b for b in bins or [] if isinstance(b, dict)]
    lo = finite_or_nan([b.get("visib_min") for b in bins])
    hi = finite_or_nan([b.get("visib_max") for b in bins])
    keep = np.isfinite(lo) & np.isfinite(hi)
    bins = [b for b, k in zip(bins, keep) if k]
    lo, hi = lo[keep], hi[keep]
    counts = np.nan_to_num(finite_or_nan([b.get("n_targets") for b in bins]), nan=0.0)
    counts = np.maximum(counts, 0).astype(np.int64)
    curves = {col: finite_or_nan([b.get(col) for b in bins]) for col in METRIC_STYLE}
    if not bins or (not counts.any() and not any(np.isfinite(y).any() for y in curves.values())):
        return no_data_figure(f"{NO_DATA}: no target in any visible-fraction bin", title=title)
    centre = (lo + hi) / 2
    fig, ax = plt.subplots(figsize=(8.5, 4.0))
    ax2 = ax.twinx()
    # Counts behind the recall lines: the twin axis is drawn on top, so swap the z-order.
    ax.set_zorder(ax2.get_zorder() + 1)
    ax.patch.set_visible(False)
    bars = ax2.bar(centre, counts, width=0.8 * (hi - lo), color="0.85", edgecolor="0.6", label="targets")
    # Counts written above the frame, where no recall line can hide them.
    for x, n in zip(centre, counts):
        ax.annotate(f"n={n}", (x, 1.0), xycoords=("data", "axes fraction"), xytext=(0, 3),
                    textcoords="offset points", ha="center", va="bottom", fontsize=7.5,
                    color="0.25" if n else "0.7")
    ax2.set_ylabel("targets (GT instances) in the bin", color="0.4")
    ax2.set_ylim(0, max(1, int(counts.max(initial=0))) * 1.25)
    ax2.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax2.tick_params(axis="y", colors="0.4")
    for col, (label, colour, marker) in METRIC_STYLE.items():
        y = curves[col]
        if not np.isfinite(y).any():
            continue
        # NaN (a bin without targets) breaks the line: no recall is drawn across empty bins.
        ax.plot(centre, y, marker=marker, color=colour, label=label,
                lw=2.2 if col == "AR" else 1.3, ms=6 if col == "AR" else 4, alpha=1.0 if col == "AR" else 0.85)
    if not any(np.isfinite(y).any() for y in curves.values()):
        ax.text(0.5, 0.5, f"{NO_DATA}: no finite recall", transform=ax.transAxes, ha="center", va="center",
                fontsize=11, color="0.45")
    ax.set_xlim(min(0.0, float(lo.min())), max(1.0, float(hi.max())))
    ax.set_xticks(np.round(np.unique(np.append(lo, hi)), 2))
    ax.set_ylim(-0.03, 1.05)
    ax.set_xlabel("visible fraction of the target object")
    ax.set_ylabel("average recall")
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles + [bars], labels + ["targets"], loc="lower center", bbox_to_anchor=(0.5, 1.06), fontsize=8,
              ncol=5, frameon=False)
    if title:
        ax.set_title(title, fontsize=10, pad=36)
    return figure_png(fig)


def timing_figure(stages: Sequence[str], wall_s: Sequence[float], peak_mb: Sequence[float]) -> bytes:
    """Two horizontal bar charts: summed job wall time (s) and the largest peak RSS (MB)
    per stage, stages top to bottom in pipeline order.

    A NaN, inf or missing value is unknown: no bar, "-" beside it, and left out of the
    axis limits and of the shares; a panel with no finite value says "no data"; no stage
    at all gives a figure saying so.
    """
    plt = _plt()
    if not len(stages):
        return no_data_figure(f"{NO_DATA}: no stage")
    y = np.arange(len(stages))
    wall = finite_or_nan(wall_s)
    peak = finite_or_nan(peak_mb)
    if len(wall) != len(stages) or len(peak) != len(stages):
        raise ValueError(f"timing_figure: {len(stages)} stages but {len(wall)} wall times and {len(peak)} peaks")
    total = float(np.nansum(wall))
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 0.45 * len(stages) + 1.4), sharey=True,
                               gridspec_kw={"width_ratios": [1.4, 1]})
    a.barh(y, np.nan_to_num(wall), color="tab:blue")
    for yi, w in zip(y, wall):
        if not np.isfinite(w):
            a.annotate("-", (0, yi), xytext=(3, 0), textcoords="offset points", va="center", fontsize=8)
            continue
        share = f"{100 * w / total:.0f}%" if total > 0 else ""
        a.annotate(f"{w:.1f} s  {share}", (w, yi), xytext=(3, 0), textcoords="offset points", va="center", fontsize=8)
    a.set_xlim(0, max(1e-3, finite_max(wall, 0.0)) * 1.3)
    a.set_xlabel("wall time, summed over the stage's jobs (s)")
    b.barh(y, np.nan_to_num(peak), color="tab:purple")
    for yi, m in zip(y, peak):
        if np.isfinite(m):
            b.annotate(f"{m:.0f}", (m, yi), xytext=(3, 0), textcoords="offset points", va="center", fontsize=8)
    b.set_xlim(0, max(1.0, finite_max(peak, 1.0)) * 1.25)
    b.set_xlabel("largest peak RSS of a job (MB)")
    a.set_yticks(y, stages)
    a.invert_yaxis()
    for ax in (a, b):
        ax.grid(axis="x", alpha=0.3)
    for ax, v in ((a, wall), (b, peak)):
        if not np.isfinite(v).any():
            ax.text(0.5, 0.5, NO_DATA, transform=ax.transAxes, ha="center", va="center", fontsize=11, color="0.45")
    fig.tight_layout()
    return figure_png(fig)


def pose_overlay(image: np.ndarray, render: np.ndarray | None, mask: np.ndarray | None,
                 colour: tuple[int, int, int], alpha: float = 0.5, thickness: int = 2) -> np.ndarray:
    """The object drawn over ``image``: its shading tinted with ``colour`` blended in where
    ``mask`` is set, and the silhouette's outline in ``colour``.

    image, render: (H, W, 3) uint8; mask: (H, W) bool. ``render`` None or an empty mask
    (the pose projects outside the crop) leaves the image as it is.
    """
    import cv2

    out = image.astype(np.float32).copy()
    if render is None or mask is None or not mask.any():
        return image.copy()
    m = mask.astype(bool)
    # Tinted shading: the render's brightness modulates one colour, so the object reads
    # as a shape (not as a second copy of its texture) and the colour tells what it is.
    shade = render.astype(np.float32).mean(axis=-1, keepdims=True) / 255.0
    tint = np.asarray(colour, np.float32)[None, None, :] * (0.35 + 0.65 * shade)
    out[m] = (1 - alpha) * out[m] + alpha * tint[m]
    out = out.clip(0, 255).astype(np.uint8)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, tuple(int(c) for c in colour), thickness, lineType=cv2.LINE_AA)
    return out


def _label(img: np.ndarray, text: str, colour: tuple[int, int, int]) -> np.ndarray:
    """``text`` in a dark strip at the top-left corner of ``img`` (in place)."""
    import cv2

    font, scale, th = cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1
    (w, h), base = cv2.getTextSize(text, font, scale, th)
    cv2.rectangle(img, (0, 0), (w + 8, h + base + 6), (20, 20, 20), -1)
    cv2.putText(img, text, (4, h + 3), font, scale, tuple(int(c) for c in colour), th, cv2.LINE_AA)
    return img


def side_by_side(left: np.ndarray, right: np.ndarray | None, left_label: str, right_label: str,
                 left_colour: tuple[int, int, int], gap: int = 6) -> np.ndarray:
    """Two equally sized (S, S, 3) uint8 panels with a white gap, each labelled; a grey
    panel saying so when the right one (the ground truth) is unknown."""
    left = _label(left.copy(), left_label, left_colour)
    if right is None:
        right = np.full_like(left, 235)
        import cv2

        cv2.putText(right, "ground truth unknown", (10, right.shape[0] // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (90, 90, 90), 1, cv2.LINE_AA)
    else:
        right = _label(right.copy(), right_label, BLUE)
    spacer = np.full((left.shape[0], gap, 3), 255, np.uint8)
    return np.concatenate([left, spacer, right], axis=1)

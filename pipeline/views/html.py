"""The report page of one dataset of a run: one self-contained HTML file.

Built from the artifacts only (nothing is recomputed but renders of poses): the AR table
(``score/all/scores.json``), AR against the visible fraction, time and memory per stage
(every ``_manifest.json`` of the dataset's current stages), a sample of estimates drawn
over their images beside the ground truth, and the SAR figures. Images are PNG data
URIs and the style sheet is inline, so the file can be mailed or archived alone.

Entry points: :func:`write_report` (the ``freeze report`` command and Snakemake) and
:func:`build_report` (the page as a string).

Every table and chart takes the artifacts as they are: no rows, None, NaN and inf give
"-" in a cell and "no data" in a chart (:mod:`pipeline.views.plots`), never an error.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from pipeline.views import plots

#: An estimate is drawn as correct when its MSSD to the nearest ground-truth instance of
#: its object is at most this fraction of the object's diameter. BOP's AR_MSSD averages
#: the recall over thresholds 0.05..0.5 of the diameter; 0.2 is a strict middle.
CORRECT_MSSD_FRAC = 0.2

#: Side (px) of each pose panel on the page.
PANEL_SIZE = 256

#: Context around the object in a pose panel: fraction of the box's longer side added on
#: each side.
PANEL_MARGIN = 0.3

#: SAR cases shown per object.
SAR_CASES_PER_OBJECT = 3
HYPOTHESIS_CASES = 4

METRICS = ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")


# ---------------------------------------------------------------------------- data


def default_out(rp, dataset: str) -> Path:
    """``<cache parent>/results/report_<dataset>.html``."""
    return Path(rp.cache).parent / "results" / f"report_{dataset}.html"


def read_scores(plan) -> dict[str, Any]:
    """``scores.json`` of the dataset's score stage; fails naming the file when missing,
    and when the score artifact is damaged (:class:`pipeline.common.store.DamagedArtifact`)."""
    from pipeline.common.store import ensure_sound

    path = plan["score"].path("all", "scores")
    if not path.exists():
        raise FileNotFoundError(f"{path}: not scored yet; run `snakemake --cores 2 bop_all` "
                                f"(with the same --config) first")
    ensure_sound(path.parent)
    return json.loads(path.read_text())


def _finite(v: Any) -> float:
    """``v`` as a float; NaN when it is None, not a number, NaN or +-inf."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return float("nan")
    return f if np.isfinite(f) else float("nan")


@dataclass
class StageTiming:
    """Jobs of one stage: count, summed wall time (s), share of the dataset's total, and
    the largest peak resident memory of a job (MB). A job whose manifest has no finite
    wall time adds nothing to the sum (NaN when no job has one); the peak is NaN when
    no manifest gives a finite one."""

    stage: str
    signature: str
    jobs: int
    wall_s: float
    share: float
    peak_rss_mb: float


def stage_timings(plan) -> list[StageTiming]:
    """One row per stage of the plan (pipeline order), from its items' ``_manifest.json``."""
    from pipeline.common.store import read_manifest

    rows = []
    for sp in plan.stages.values():
        manifests = sorted(sp.dir.glob("*/_manifest.json")) if sp.dir.exists() else []
        walls, peaks = [], []
        for path in manifests:
            m = read_manifest(path)
            # A manifest may say null, NaN or Infinity: an unknown time, not a huge one.
            if np.isfinite(w := _finite(m.get("wall_time_s"))):
                walls.append(w)
            if np.isfinite(pk := _finite(m.get("peak_rss_mb"))):
                peaks.append(pk)
        wall = float(sum(walls)) if walls or not manifests else float("nan")
        rows.append(StageTiming(sp.stage, sp.signature, len(manifests), wall, 0.0,
                                max(peaks) if peaks else float("nan")))
    total = float(np.nansum([r.wall_s for r in rows])) if rows else 0.0
    for r in rows:
        r.share = r.wall_s / total if total > 0 and np.isfinite(r.wall_s) else 0.0
    return rows


def empty_estimate_table() -> pd.DataFrame:
    """An :func:`estimate_table` with no rows."""
    return pd.DataFrame(columns=["scene_id", "im_id", "obj_id", "est_id", "score", "R", "t", "gt_id", "mssd", "mspd",
                                 "visib", "diameter", "mssd_frac", "correct"])


def estimate_table(plan) -> pd.DataFrame:
    """Every evaluated estimate with its pose and the ground-truth instance it is judged by.

    One row per estimate that BOP evaluated (``errors.parquet``): scene_id, im_id,
    obj_id, est_id (position among the image's estimates of the object in the results
    CSV, as in the errors), score, R (3, 3), t (3,) mm, gt_id (the valid GT instance of
    the object with the smallest MSSD, else any; -1 if none), mssd (mm), mspd (px),
    visib (its visible fraction), diameter (mm), mssd_frac (mssd / diameter) and
    correct (mssd_frac <= :data:`CORRECT_MSSD_FRAC`).
    """
    from pipeline.formats.bop import read_results_csv
    from pipeline.common.store import read_table

    score_dir = plan["score"].item_dir("all")
    err_path = score_dir / "errors.parquet"
    if not err_path.exists():
        raise FileNotFoundError(f"{err_path}: not scored yet; run `snakemake --cores 2 bop_all` first")
    csv_path = plan["refine"].item_dir("all") / plan.results_csv_name
    results = read_results_csv(csv_path)
    keys = ["scene_id", "im_id", "obj_id"]
    # est_id as the scorer numbers it: file order within (scene, image, object).
    results["est_id"] = results.groupby(keys, sort=False).cumcount()
    errors = read_table(err_path)
    if errors.empty:
        return empty_estimate_table()
    errors = errors.copy()
    valid = errors["gt_valid"].astype(bool) if "gt_valid" in errors else pd.Series(True, index=errors.index)
    errors["_invalid"] = ~valid & errors["mssd"].notna()
    errors["_mssd"] = errors["mssd"].fillna(np.inf)
    best = (errors.sort_values(["_invalid", "_mssd"], kind="stable")
            .groupby(keys + ["est_id"], sort=True).head(1))
    table = best[keys + ["est_id", "gt_id", "mssd", "mspd", "gt_visib_fract"]].rename(
        columns={"gt_visib_fract": "visib"})
    table = table.merge(results[keys + ["est_id", "score", "R", "t"]], on=keys + ["est_id"], how="left",
                        validate="one_to_one")
    if table["R"].isna().any():
        r = table[table["R"].isna()].iloc[0]
        raise ValueError(f"{err_path}: estimate (scene {r.scene_id}, image {r.im_id}, object {r.obj_id}, "
                         f"est_id {r.est_id}) is not in {csv_path}: errors and results CSV disagree")
    bop = plan.bop()
    table["diameter"] = [plan.model_info(bop, int(o)).diameter for o in table["obj_id"]]
    table["gt_id"] = table["gt_id"].fillna(-1).astype(int)
    table["mssd_frac"] = table["mssd"] / table["diameter"]
    table["correct"] = table["mssd_frac"].fillna(np.inf) <= CORRECT_MSSD_FRAC
    return table.sort_values(keys + ["est_id"]).reset_index(drop=True)


def choose_samples(table: pd.DataFrame, n: int) -> pd.DataFrame:
    """Up to ``n`` estimates of ``table`` (see :func:`estimate_table`), deterministically:
    objects take turns (so the sample spreads over objects), and each turn takes a correct
    estimate when the sample so far has no more correct than incorrect ones, else an
    incorrect one (falling back to the other kind when the object has none left). Within
    an object and kind, estimates come in the order of a hash of (scene, image, est_id),
    which spreads them over images without depending on the file's order.
    Returned sorted by object, scene, image."""
    if n <= 0 or table.empty:
        return table.iloc[0:0]

    def order(df: pd.DataFrame) -> list[int]:
        h = [hashlib.sha1(f"{s}-{i}-{o}-{e}".encode()).hexdigest()
             for s, i, o, e in zip(df.scene_id, df.im_id, df.obj_id, df.est_id)]
        return [idx for _, idx in sorted(zip(h, df.index))]

    queues = {int(o): {True: order(g[g.correct]), False: order(g[~g.correct])}
              for o, g in table.groupby("obj_id", sort=True)}
    picked: list[int] = []
    counts = {True: 0, False: 0}
    while len(picked) < n and any(q[True] or q[False] for q in queues.values()):
        for q in queues.values():
            if len(picked) >= n:
                break
            want = counts[True] <= counts[False]
            kind = want if q[want] else (not want)
            if q[kind]:
                picked.append(q[kind].pop(0))
                counts[kind] += 1
    return table.loc[picked].sort_values(["obj_id", "scene_id", "im_id", "est_id"])


@dataclass
class PosePanel:
    """One drawn estimate: the PNG (estimate | ground truth) and its caption."""

    png: bytes
    caption: str
    correct: bool
    obj_id: int


def _box_of(masks: Sequence[np.ndarray]) -> tuple[float, float, float, float] | None:
    """(x, y, w, h) bounding box of the union of masks (None if all are empty)."""
    union = np.zeros_like(masks[0], dtype=bool)
    for m in masks:
        union |= m
    if not union.any():
        return None
    ys, xs = np.nonzero(union)
    return float(xs.min()), float(ys.min()), float(xs.max() - xs.min() + 1), float(ys.max() - ys.min() + 1)


def _square_box(bbox: tuple[float, float, float, float], margin: float, min_side: int = 48) -> tuple[int, int, int]:
    """Square ``(x0, y0, side)`` px centred on ``bbox`` (x, y, w, h), ``margin`` x its
    longer side added on each side; at least ``min_side`` px. May extend off the image."""
    x, y, w, h = bbox
    side = max(min_side, int(np.ceil(max(w, h) * (1 + 2 * margin))))
    return int(round(x + w / 2 - side / 2)), int(round(y + h / 2 - side / 2)), side


def _crop(image: np.ndarray, box: tuple[int, int, int], size: int) -> np.ndarray:
    """``box`` of ``image`` (H, W[, C]) resized to ``size`` x ``size``; white off the image."""
    from pipeline.method.geometry.crops import crop_and_resize

    return crop_and_resize(image, box, size, fill=255 if image.dtype == np.uint8 else 0)


def _crop_mask(mask: np.ndarray, box: tuple[int, int, int], size: int) -> np.ndarray:
    """(S, S) bool: ``mask`` cropped like the image (float, so off-image pixels pad to 0)."""
    return _crop(mask.astype(np.float32), box, size) > 0.5


def draw_samples(plan, samples: pd.DataFrame, size: int = PANEL_SIZE) -> list[PosePanel]:
    """Each sampled estimate rendered over its image (green if correct, red if not) beside
    the ground truth (blue), cropped around both.

    Renders at the full image size in the image's camera K, then crops the square around
    the union of the two silhouettes (margin :data:`PANEL_MARGIN`) and resizes it to
    ``size`` px.
    """
    from pipeline.method.render import Renderer

    if samples.empty:
        return []
    bop = plan.bop()
    renderers: dict[tuple[int, int], Renderer] = {}
    panels = []
    cams: dict[int, Any] = {}
    gts: dict[int, Any] = {}
    try:
        for row in samples.itertuples(index=False):
            scene_id, im_id, obj_id = int(row.scene_id), int(row.im_id), int(row.obj_id)
            if scene_id not in cams:
                cams[scene_id], gts[scene_id] = bop.scene_camera(scene_id), bop.scene_gt(scene_id)
            K = cams[scene_id][im_id].K
            rgb = bop.load_rgb(scene_id, im_id)
            H, W = rgb.shape[:2]
            r = renderers.get((W, H))
            if r is None:
                r = renderers[(W, H)] = Renderer(W, H, znear=1.0, zfar=100000.0)
            if not r.has_mesh(obj_id):
                r.add_mesh(obj_id, bop.load_model(obj_id))
            est_rgb, _, est_mask = r.render_object(obj_id, np.asarray(row.R).reshape(3, 3), np.asarray(row.t), K)
            gt = None
            if row.gt_id >= 0 and row.gt_id < len(gts[scene_id].get(im_id, [])):
                g = gts[scene_id][im_id][row.gt_id]
                gt = r.render_object(obj_id, g.R, g.t, K)
            masks = [est_mask] + ([gt[2]] if gt is not None else [])
            bbox = _box_of(masks)
            if bbox is None:  # nothing projects into the image: show the whole image
                side = max(H, W)
                box = ((W - side) // 2, (H - side) // 2, side)
            else:
                box = _square_box(bbox, PANEL_MARGIN)
            crop = _crop(rgb, box, size)
            colour = plots.GREEN if row.correct else plots.RED
            left = plots.pose_overlay(crop, _crop(est_rgb, box, size), _crop_mask(est_mask, box, size), colour)
            right = None
            if gt is not None:
                right = plots.pose_overlay(crop, _crop(gt[0], box, size), _crop_mask(gt[2], box, size),
                                           plots.BLUE)
            verdict = "correct" if row.correct else "wrong"
            png = plots.image_png(plots.side_by_side(left, right, f"estimate ({verdict})", "ground truth", colour))
            mssd = (f"MSSD {row.mssd:.1f} mm = {fmt(_finite(row.mssd_frac), 2)} d" if np.isfinite(_finite(row.mssd))
                    else "MSSD -")
            visib = f", {100 * row.visib:.0f}% visible" if np.isfinite(_finite(row.visib)) else ""
            caption = (f"object {obj_id}, scene {scene_id} image {im_id}, estimate {int(row.est_id)} "
                       f"(score {fmt(_finite(row.score))}): {mssd}{visib}")
            panels.append(PosePanel(png, caption, bool(row.correct), obj_id))
    finally:
        for r in renderers.values():
            r.close()
    return panels


def sar_objects(plan) -> list[int]:
    """Objects with at least one estimate that went through SAR (rows in some scene's
    ``refine/scene_*/sar.parquet``)."""
    from pipeline.common.store import read_table

    ids: set[int] = set()
    for item in plan.scene_items:
        path = plan["refine"].path(item, "sar")
        if path.exists():
            t = read_table(path)
            if len(t):
                ids |= set(t["obj_id"].astype(int))
    return sorted(ids)


def sar_figures(plan, limit: int = SAR_CASES_PER_OBJECT) -> list[tuple[int, bytes, int]]:
    """(obj_id, PNG of :func:`pipeline.views.sar_figure.draw_sar_figure`, cases shown)
    per object that went through SAR."""
    from pipeline.views.sar_figure import draw_sar_figure, sar_cases

    out = []
    with tempfile.TemporaryDirectory(prefix="freeze-report-") as tmp:
        for obj_id in sar_objects(plan):
            cases = sar_cases(plan, obj_id, limit=limit)
            if not cases:
                continue
            path = draw_sar_figure(cases, Path(tmp) / f"sar_{obj_id}.png")
            out.append((obj_id, path.read_bytes(), len(cases)))
    return out


def hypothesis_tables(plan) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per hypothesis source: hypotheses, chosen, mean verification score; per object:
    candidates, median signal and mean fusion weight of each modality (from register)."""
    from pipeline.common.store import read_table

    hyps, regs = [], []
    for item in plan.scene_items:
        path = plan["refine"].path(item, "hypotheses")
        if path.exists():
            hyps.append(read_table(path))
        path = plan["register"].path(item, "coarse_hypotheses")
        if path.exists():
            regs.append(read_table(path))
    counts = pd.DataFrame(columns=["source", "hypotheses", "chosen", "mean_score"])
    if hyps:
        h = pd.concat(hyps, ignore_index=True)
        counts = (h.groupby("source").agg(hypotheses=("hyp", "size"), chosen=("chosen", "sum"),
                                          mean_score=("verification", "mean")).reset_index())
    weights = pd.DataFrame()
    if regs:
        r = pd.concat(regs, ignore_index=True)
        r = r[(r.status == "ok") & (r.hyp == 0) & r.signal_geometric.notna()]
        weights = r.groupby("obj_id").agg(
            candidates=("cand_id", "size"), signal_geometric=("signal_geometric", "median"),
            signal_visual=("signal_visual", "median"), w_geometric=("w_geometric", "mean"),
            w_visual=("w_visual", "mean")).reset_index()
    return counts, weights


def hypotheses_png(plan, limit: int = HYPOTHESIS_CASES) -> bytes | None:
    """PNG of :func:`pipeline.views.hypotheses_figure.draw_hypotheses_figure` for up to
    ``limit`` candidates, or None when refine recorded no hypotheses."""
    from pipeline.views.hypotheses_figure import draw_hypotheses_figure, hypothesis_cases

    try:
        cases = hypothesis_cases(plan, limit=limit)
    except FileNotFoundError:
        return None
    if not cases:
        return None
    with tempfile.TemporaryDirectory(prefix="freeze-report-") as tmp:
        return draw_hypotheses_figure(cases, Path(tmp) / "hypotheses.png").read_bytes()


# ---------------------------------------------------------------------------- HTML

CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, "DejaVu Sans", Arial, sans-serif; color: #222;
       max-width: 1120px; margin: 24px auto; padding: 0 20px; line-height: 1.45; background: #fff; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.25em; margin-top: 1.8em; border-bottom: 2px solid #e4e4e4; padding-bottom: 4px; }
h3 { font-size: 1.05em; margin-top: 1.2em; }
p.intro { color: #444; margin-top: 0; }
p.note, figcaption, .small { color: #555; font-size: 0.9em; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 0.92em; }
th, td { padding: 4px 10px; border-bottom: 1px solid #e2e2e2; text-align: right; }
th { background: #f3f4f6; font-weight: 600; }
td.l, th.l { text-align: left; }
tr:nth-child(even) td { background: #fafafa; }
td.ar { font-weight: 600; }
figure { margin: 10px 0; }
figure img { max-width: 100%; height: auto; display: block; }
.grid { display: grid; grid-template-columns: repeat(auto-fill, minmax(500px, 1fr)); gap: 14px; }
.grid figure { margin: 0; padding: 6px; border: 3px solid #ccc; border-radius: 6px; }
.grid figure.correct { border-color: #28c83c; }
.grid figure.wrong { border-color: #e62828; }
.swatch { display: inline-block; width: 0.9em; height: 0.9em; border-radius: 2px; vertical-align: -0.1em; }
details pre { background: #f6f8fa; padding: 10px; overflow-x: auto; font-size: 0.82em; }
code { background: #f3f4f6; padding: 0 3px; border-radius: 3px; }
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def fmt(v: Any, digits: int = 3) -> str:
    """A table cell: floats with ``digits`` decimals, None/NaN as '-'."""
    if v is None:
        return "-"
    if isinstance(v, (float, np.floating)):
        return "-" if not np.isfinite(v) else f"{v:.{digits}f}"
    return str(v)


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _img(png: bytes, alt: str) -> str:
    return f'<img src="{data_uri(png)}" alt="{_e(alt)}">'


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "", left: int = 1,
           keys: Sequence[str] | None = None) -> str:
    """HTML table; the first ``left`` columns left-aligned; ``keys`` name the columns in
    ``data-key`` attributes (what tests and scripts read)."""
    keys = keys or header
    head = "".join(f'<th class="{"l" if i < left else ""}">{_e(h)}</th>' for i, h in enumerate(header))
    body = []
    for row in rows:
        cells = "".join(
            f'<td class="{"l" if i < left else ""}{" ar" if keys[i] == "AR" else ""}" data-key="{_e(keys[i])}">{c}</td>'
            for i, c in enumerate(row))
        body.append(f"<tr>{cells}</tr>")
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def stand_in_note(encoders: dict[str, dict[str, Any]]) -> str:
    """The page's line on encoders that stand in for the paper's (the run's start prints
    the same, :func:`pipeline.common.stand_in.stand_in_notice`); empty when none does.
    ``encoders``: :attr:`pipeline.workflow.plan.RunPlan.encoders`."""
    from pipeline.common.stand_in import stand_in_notice

    notice = stand_in_notice(encoders["geometric"]["manifest"], encoders["visual"]["manifest"])
    return f'<p class="note stand-in">{_e(notice)}</p>' if notice else ""


def _column_means(values: Any, n: int) -> np.ndarray:
    """(n,) mean over the rows of a (rows, n) table of recalls, ignoring NaN/inf/None;
    NaN where a column has no finite value, or everywhere when the shape is not (rows, n)."""
    a = plots.finite_or_nan(values)
    if a.size == 0 or a.size % n:
        return np.full(n, np.nan)
    a = a.reshape(-1, n)
    seen = np.isfinite(a).sum(axis=0)
    # nansum / count instead of nanmean: an all-NaN column is NaN without a RuntimeWarning.
    return np.where(seen > 0, np.nansum(a, axis=0) / np.maximum(seen, 1), np.nan)


def _recall_table(recalls: dict[str, Any]) -> str:
    """Recall per correctness threshold (VSD averaged over its tolerances tau). Missing,
    NaN or inf recalls are shown as "-"; a list of the wrong length as "-" throughout."""
    from pipeline.evaluation.metrics.evaluate import MSPD_THRESHOLDS, MSSD_THRESHOLDS, VSD_THETAS

    rows = []
    if recalls.get("vsd") is not None and len(recalls["vsd"]):
        rows.append(("VSD (mean over τ)", "θ", VSD_THETAS, _column_means(recalls["vsd"], len(VSD_THETAS))))
    if recalls.get("mssd") is not None:
        rows.append(("MSSD", "× diameter", MSSD_THRESHOLDS, _column_means(recalls["mssd"], len(MSSD_THRESHOLDS))))
    if recalls.get("mspd") is not None:
        rows.append(("MSPD", "px at 640 px", MSPD_THRESHOLDS, _column_means(recalls["mspd"], len(MSPD_THRESHOLDS))))
    out = []
    for name, unit, thr, rec in rows:
        header = [f"{name}: threshold ({unit})"] + [f"{t:g}" for t in np.round(thr, 2)]
        out.append(_table(header, [["recall"] + [fmt(float(v), 2) for v in rec]], cls="recall",
                          keys=["metric"] + [f"{name}@{t:g}" for t in np.round(thr, 2)]))
    return "\n".join(out)


def worst_samples(table: pd.DataFrame, n: int) -> pd.DataFrame:
    """The ``n`` wrong estimates of ``table`` (see :func:`estimate_table`) farthest from
    their ground truth: largest MSSD in diameters first (an estimate with no ground
    truth to compare with, infinitely far), ties by the higher score; at most
    ``ceil(n / 2)`` of one object, so one bad object does not fill the sample."""
    if n <= 0 or table.empty:
        return table.iloc[0:0]
    wrong = table[~table["correct"]].copy()
    wrong["_far"] = wrong["mssd_frac"].fillna(np.inf)
    wrong = wrong.sort_values(["_far", "score", "scene_id", "im_id", "obj_id", "est_id"],
                              ascending=[False, False, True, True, True, True], kind="stable")
    cap = -(-n // 2)
    picked = wrong.groupby("obj_id", sort=False).head(cap).head(n)
    return picked.drop(columns="_far")


def build_report(rp, dataset: str, samples: int = 12, run_label: str | None = None, worst: int = 0) -> str:
    """The report page of ``dataset`` under the run plan ``rp`` (a
    :class:`pipeline.workflow.plan.RunPlan`), as an HTML string.

    samples: number of estimates drawn over their images. worst: number of the worst
    estimates (:func:`worst_samples`) drawn in a section of their own. run_label: how
    the run was chosen (e.g. ``manifests/runs/default.yaml + visual=dinov2-vits14``),
    shown in the intro; the resolved run manifest is always at the end of the page.
    """
    t0 = time.perf_counter()
    plan = rp[dataset]
    scores = read_scores(plan)
    summary = scores["summary"]
    # private test ground truth (ITODD, HB): nothing to judge the estimates by
    no_gt = summary.get("status") == "no_ground_truth"
    table = empty_estimate_table() if no_gt else estimate_table(plan)
    chosen = choose_samples(table, samples)
    panels = draw_samples(plan, chosen)
    worst_panels = draw_samples(plan, worst_samples(table, worst))
    sar = sar_figures(plan)
    hyp_png = hypotheses_png(plan)
    timings = stage_timings(plan)
    parts: list[str] = [
        *_header_section(rp, plan, dataset, run_label),
        *_recall_section(dataset, scores, table),
        *_visibility_section(scores),
        *_timing_section(timings),
        *_samples_section(table, panels, no_gt),
        *_worst_section(worst_panels, worst),
        *_hypotheses_section(plan, hyp_png),
        *_sar_section(sar),
    ]
    parts.append("<h2>Run manifest</h2>")
    parts.append(f"<details><summary>resolved run manifest (JSON)</summary><pre>"
                 f"{_e(json.dumps(rp.run.model_dump(), indent=2))}</pre></details>")
    parts.append(f'<p class="small">Page built in {time.perf_counter() - t0:.1f} s by '
                 f'<code>pipeline.views.html</code>.</p>')
    body = "\n".join(parts)
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            f"<title>FreeZe report: {_e(dataset)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n{body}\n</body>\n</html>\n")


def _header_section(rp, plan, dataset: str, run_label: str | None) -> list[str]:
    """The page's title, the intro (method, dataset, encoders, refinement signature, run,
    cache folder, time generated) and the stand-in note: HTML fragments. ``plan``: the
    dataset's plan, ``rp[dataset]``."""
    enc = rp.encoders
    ds = plan.dataset
    generated = time.strftime("%Y-%m-%d %H:%M:%S %Z", time.localtime())
    geo, vis = enc["geometric"], enc["visual"]
    run_txt = f"run manifest <code>{_e(run_label)}</code>" if run_label else "run manifest as resolved below"
    return [
        f"<h1>FreeZe report: {_e(dataset)}</h1>",
        f'<p class="intro">Method <b>{_e(rp.run.method)}</b> on <b>{_e(dataset)}</b> ({_e(ds.kind)}, split '
        f'{_e(ds.split)}, {len(plan.obj_ids)} objects, {len(plan.scene_ids)} scenes); geometric encoder '
        f'<b>{_e(geo["manifest"])}</b> (<code>{_e(geo["signature"])}</code>, v{_e(geo["version"])}), visual encoder '
        f'<b>{_e(vis["manifest"])}</b> (<code>{_e(vis["signature"])}</code>, v{_e(vis["version"])}); refinement '
        f'<code>{_e(plan["refine"].signature)}</code>; {run_txt}. Generated {_e(generated)} from the artifacts in '
        f'<code>{_e(rp.cache / dataset)}</code>.</p>',
        stand_in_note(enc),
    ]


def _recall_section(dataset: str, scores: dict[str, Any], table: pd.DataFrame) -> list[str]:
    """Section 1: the AR table (AR and its parts, targets, estimates, s / image), the
    scorer's notes, AR per object with its correct estimates (``table``: the
    :func:`estimate_table`), and the recall per threshold: HTML fragments."""
    summary = scores["summary"]
    t_img = summary.get("mean_time_per_image")
    out = ["<h2>1. Average recall (BOP19)</h2>"]
    out.append(_table(["dataset", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "targets", "estimates", "s / image"],
                      [[_e(dataset)] + [fmt(summary.get(k)) for k in METRICS]
                       + [fmt(summary.get("n_targets")), fmt(summary.get("n_estimates")),
                          fmt(t_img, 2) if t_img is not None and t_img >= 0 else "-"]],
                      cls="summary",
                      keys=["dataset", *METRICS, "n_targets", "n_estimates", "mean_time_per_image"]))
    out.append(f'<p class="note">targets: valid ground-truth instances to find; estimates: lines of the results CSV '
               f'({fmt(summary.get("n_evaluated"))} evaluated); s / image: mean time per image as written in the CSV '
               f'(prior + scene features + registration + refinement). AR = mean(AR_VSD, AR_MSSD, AR_MSPD).</p>')
    for note in summary.get("notes") or []:
        out.append(f'<p class="note">Note: {_e(note)}</p>')
    out.append("<h3>Per object</h3>")
    out.append(_table(["object", "AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "targets", "correct estimates"],
                      _per_object_rows(scores, table), cls="per-object",
                      keys=["obj_id", *METRICS, "n_targets", "correct"]))
    out.append(f'<p class="note">correct estimates: evaluated estimates whose MSSD to the nearest ground-truth '
               f'instance is at most {CORRECT_MSSD_FRAC:g} × the object\'s diameter (the rule of section 4).</p>')
    if scores.get("recalls"):
        out.append("<h3>Recall per threshold</h3>")
        out.append(_recall_table(scores["recalls"]))
    return out


def _per_object_rows(scores: dict[str, Any], table: pd.DataFrame) -> list[list[str]]:
    """Rows of the per-object table: object id, AR and its parts, targets and "correct /
    evaluated" estimates (from ``table``; "-" when it has none of the object). Rows of
    ``scores["per_object"]`` naming no object are left out."""
    correct_by_obj = table.groupby("obj_id")["correct"].agg(["sum", "count"]) if len(table) else None
    rows = []
    for o in scores.get("per_object") or []:
        if not np.isfinite(_finite(o.get("obj_id"))):
            continue  # a row naming no object has nothing to show
        oid = int(o["obj_id"])
        c = (f"{int(correct_by_obj.loc[oid, 'sum'])} / {int(correct_by_obj.loc[oid, 'count'])}"
             if correct_by_obj is not None and oid in correct_by_obj.index else "-")
        rows.append([str(oid)] + [fmt(o.get(k)) for k in METRICS] + [fmt(o.get("n_targets")), c])
    return rows


def _visibility_section(scores: dict[str, Any]) -> list[str]:
    """Section 2: the figure of AR per visible fraction (or a note that there is none)."""
    out = ["<h2>2. Average recall against visible fraction</h2>"]
    bins = scores.get("per_visibility") or []
    if bins:
        out.append(f'<figure class="plot">{_img(plots.visibility_figure(bins), "AR per visible fraction")}'
                   f'<figcaption>AR and its components per bin of the visible fraction of the ground-truth instance '
                   f'(a found target counts in the bin of the instance it was matched to); grey bars: targets per '
                   f'bin. Bins without targets have no point.</figcaption></figure>')
    else:
        out.append('<p class="note">scores.json has no per-visibility breakdown.</p>')
    return out


def _timing_section(timings: list[StageTiming]) -> list[str]:
    """Section 3: wall time (s) and peak RSS (MB) per stage, as a table and a figure."""
    out = ["<h2>3. Time and memory per stage</h2>"]
    out.append(_table(["stage", "signature", "jobs", "wall time (s)", "share", "peak RSS (MB)"],
                      [[_e(r.stage), f"<code>{_e(r.signature)}</code>", str(r.jobs), fmt(r.wall_s, 1),
                        f"{fmt(100 * r.share, 1)}%", fmt(r.peak_rss_mb, 0)] for r in timings],
                      cls="timing", left=2, keys=["stage", "signature", "jobs", "wall_s", "share", "peak_rss_mb"]))
    total = float(np.nansum([r.wall_s for r in timings])) if timings else 0.0
    out.append(f'<p class="note">From every <code>_manifest.json</code> of the dataset\'s current stage folders: '
               f'{sum(r.jobs for r in timings)} jobs, {total:.1f} s of job wall time in all (jobs may have run in '
               f'parallel); peak RSS is the largest of any one job.</p>')
    if any(r.jobs for r in timings):
        figure = plots.timing_figure([r.stage for r in timings], [r.wall_s for r in timings],
                                     [r.peak_rss_mb for r in timings])
        out.append(f'<figure class="plot">{_img(figure, "time and memory per stage")}</figure>')
    return out


def _samples_section(table: pd.DataFrame, panels: list[PosePanel], no_gt: bool) -> list[str]:
    """Section 4: the chosen estimates drawn over their images (``panels``), framed green
    (correct) or red, with how they were chosen; a note when the ground truth is private."""
    out = ["<h2>4. Estimates drawn over their images</h2>"]
    if no_gt:
        out.append('<p class="note">This dataset\'s test ground truth is not public, so no estimate can be judged '
                   'here; the results CSV named above is the file for the BOP evaluation server.</p>')
    n_correct = int(table["correct"].sum()) if len(table) else 0
    out.append(f'<p class="note">{len(panels)} of {len(table)} evaluated estimates ({n_correct} correct), chosen '
               f'deterministically: objects take turns, alternating correct and wrong ones where both exist. Left: '
               f'the estimate, <span class="swatch" style="background:#28c83c"></span> green if correct, '
               f'<span class="swatch" style="background:#e62828"></span> red if not; right: the ground truth '
               f'<span class="swatch" style="background:#286eff"></span> blue. <b>Correct</b> means: MSSD to the '
               f'nearest ground-truth instance of the object at most {CORRECT_MSSD_FRAC:g} × its diameter (d). '
               f'Renders in the image\'s camera, cropped around both silhouettes.</p>')
    if panels:
        out.append('<div class="grid">')
        for p in panels:
            cls = "correct" if p.correct else "wrong"
            out.append(f'<figure class="sample {cls}">{_img(p.png, p.caption)}<figcaption>{_e(p.caption)}'
                       f'</figcaption></figure>')
        out.append("</div>")
    return out


def _worst_section(panels: list[PosePanel], asked: int) -> list[str]:
    """Section 4b, when asked for: the worst estimates drawn as in section 4."""
    if asked <= 0:
        return []
    out = ["<h3>4b. The worst estimates</h3>",
           f'<p class="note">The {len(panels)} wrong estimates farthest from their ground truth (largest MSSD in '
           f'diameters, at most half of them of one object; {asked} asked for). <code>freeze show hypotheses '
           f'--scene S</code> draws every hypothesis of their candidates.</p>']
    if panels:
        out.append('<div class="grid">')
        for p in panels:
            out.append(f'<figure class="sample wrong">{_img(p.png, p.caption)}<figcaption>{_e(p.caption)}'
                       f'</figcaption></figure>')
        out.append("</div>")
    return out


def _hypotheses_section(plan, hyp_png: bytes | None) -> list[str]:
    """Section 5: hypotheses per source (chosen, mean score), each modality's signal and
    fusion weight per object, and the figure of the hypotheses (``hyp_png``, if any)."""
    out = ["<h2>5. Hypotheses and their verification</h2>"]
    counts, weights = hypothesis_tables(plan)
    if len(counts):
        out.append('<p class="note">Every candidate gets several coarse hypotheses (the RANSAC winners of the '
                   'geometric and of the visual matches, the paper\'s equal fusion, and the fusion weighted by each '
                   'modality\'s signal), each refined by ICP and verified against the sensor\'s depth and the '
                   'candidate\'s mask; the best verified one is the candidate\'s pose.</p>')
        out.append(_table(["source", "hypotheses", "chosen", "mean score"],
                          [[_e(r.source), fmt(r.hypotheses), fmt(r.chosen), fmt(r.mean_score)]
                           for r in counts.itertuples()],
                          cls="hypotheses", keys=["source", "hypotheses", "chosen", "mean_score"]))
    if len(weights):
        out.append("<h3>Signal of each modality, per object</h3>")
        out.append('<p class="note">How far each modality\'s matches agree with a pose beyond chance (median z-score '
                   'over the object\'s candidates, on held-out points) and the mean fusion weight it got (0: '
                   'dropped).</p>')
        out.append(_table(["object", "candidates", "geometric signal", "visual signal", "geometric weight",
                           "visual weight"],
                          [[str(int(r.obj_id)), fmt(r.candidates), fmt(r.signal_geometric, 1),
                            fmt(r.signal_visual, 1), fmt(r.w_geometric, 2), fmt(r.w_visual, 2)]
                           for r in weights.itertuples()],
                          cls="modality-signal",
                          keys=["obj_id", "candidates", "signal_geometric", "signal_visual", "w_geometric",
                                "w_visual"]))
    if hyp_png is not None:
        out.append(f'<figure class="hypotheses">{_img(hyp_png, "hypotheses")}<figcaption>Candidates whose chosen '
                   f'hypothesis is not the paper\'s fused pose come first. Green: the model\'s depth agrees with the '
                   f'sensor\'s; red: free space (the camera sees behind the model); blue: occluded; grey: no depth; '
                   f'yellow: the mask; the chosen hypothesis is framed in green.</figcaption></figure>')
    return out


def _sar_section(sar: list[tuple[int, bytes, int]]) -> list[str]:
    """Section 6: per object with symmetries beyond the declared ones, the SAR figure
    (``sar``: :func:`sar_figures`), or a note that SAR ran on no estimate."""
    out = ["<h2>6. Symmetry-aware refinement</h2>"]
    if sar:
        out.append('<p class="note">Per object whose shape has symmetries beyond the declared ones: the scene crop, '
                   'the ICP pose, the pose SAR chose, and the similarity of every symmetric variant (chosen one in '
                   'green). Cases where SAR changed the pose come first.</p>')
        for obj_id, png, n in sar:
            out.append(f'<h3>Object {obj_id}</h3><figure class="sar">{_img(png, f"SAR object {obj_id}")}'
                       f'<figcaption>{n} case(s) of object {obj_id}.</figcaption></figure>')
    else:
        out.append('<p class="note">SAR ran on no estimate of this dataset (no object with a symmetry beyond the '
                   'declared ones, or SAR switched off).</p>')
    return out


def write_report(rp, dataset: str, out: Path, samples: int = 12, run_label: str | None = None,
                 worst: int = 0) -> Path:
    """Write the report page of ``dataset`` (see :func:`build_report`) to ``out``
    atomically (a temporary sibling renamed into place), with the mode the umask gives a
    new file (0644 under umask 022); returns ``out``."""
    from pipeline.common.published_files import write_text_published

    return write_text_published(Path(out), build_report(rp, dataset, samples=samples, run_label=run_label,
                                                        worst=worst))

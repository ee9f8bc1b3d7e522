"""BOP 2019 evaluation of 6D localisation results: AR = mean(AR_VSD, AR_MSSD, AR_MSPD).

Follows the BOP toolkit (``scripts/eval_bop19_pose.py`` with ``eval_calc_errors.py``
and ``eval_calc_scores.py``):

- Only estimates of (scene, image, object) listed in the targets count; of those, the
  ``inst_count`` with the highest score (ties: earlier in the file first).
- Each estimate is compared with every GT instance of its object in the image.
- Per correctness setting, estimates are matched greedily (see ``matching``); the
  recall is pooled over all valid GT instances of the target images.
- AR_VSD averages 10 tau x 10 theta recalls, AR_MSSD 10 thresholds (0.05..0.5 of the
  diameter), AR_MSPD 10 thresholds (5..50 px at 640 px image width).

Datasets without depth get no VSD: AR_VSD and AR are then None, never an average
over the remaining metrics.

Estimates whose R is not a rotation (see :data:`ROTATION_TOLERANCE`) are refused before
anything is scored (:func:`check_rotations`): the toolkit would score them, but MSSD,
MSPD and VSD of a scaled, sheared or reflected model mean nothing.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import time as _time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from pipeline.formats.bop import BopDataset, BopFormatError, Target, read_results_csv
from pipeline.common.progress import StepTimer
from pipeline.common.store import atomic_path

from .calc_errors import (ErrorCalculator, ErrorParams, ErrorWork, ImageJob, eval_models_info, image_errors_task,
                          init_worker, run_jobs)
from .matching import greedy_match, valid_gt_mask
from .bop_symmetries import DEFAULT_MAX_SYM_DISC_STEP
from .vsd import VSD_TAUS

log = logging.getLogger(__name__)

#: Correctness thresholds of BOP19 (built like the toolkit's, for identical floats).
VSD_THETAS: np.ndarray = np.arange(0.05, 0.51, 0.05)
MSSD_THRESHOLDS: np.ndarray = np.arange(0.05, 0.51, 0.05)  # x object diameter
MSPD_THRESHOLDS: np.ndarray = np.arange(5, 51, 5).astype(np.float64)  # px at 640 px width

#: VSD misalignment tolerance delta (mm) per BOP dataset; 15 mm for any other.
VSD_DELTAS = {"itodd": 5.0}

#: An estimate's R (3, 3) is a rotation when max|R^T R - I| <= ROTATION_TOLERANCE and
#: |det R - 1| <= ROTATION_TOLERANCE (dimensionless). Loose enough for R written with
#: 6 significant digits (deviation about 1e-6) or re-orthonormalised in float32; tight
#: enough to refuse a scale off by 0.1%, any shear, any reflection and an all-zero R.
ROTATION_TOLERANCE: float = 1e-3


def bop_vsd_delta(dataset_name: str) -> float:
    """The BOP19 VSD delta in mm for a dataset name (5 for ITODD, else 15)."""
    return VSD_DELTAS.get(dataset_name, 15.0)


def vsd_column(tau: float) -> str:
    """Name of the errors column holding VSD at tolerance ``tau``, e.g. ``vsd_tau_0.05``."""
    return f"vsd_tau_{tau:.2f}"


@dataclass
class Scores:
    """Result of :func:`evaluate`.

    summary: AR, AR_VSD, AR_MSSD, AR_MSPD (None when not computable), n_targets (valid
      GT instances to find), n_estimates (rows of the results), n_ignored (estimates
      of (scene, image, object) not in the targets), n_evaluated, n_beyond_inst_count,
      mean_time_per_image (s, -1 if not given), vsd_delta, images_without_depth, notes.
    errors: one row per (evaluated estimate, GT instance of its object): scene_id,
      im_id, obj_id, est_id, gt_id, score, gt_visib_fract, gt_valid, mssd (mm), mspd
      (px), vsd_tau_0.05 .. vsd_tau_0.50 (NaN without VSD).
      timing: seconds per part: read (the CSV), prepare (checks, selection, GT
      annotations), load (depth images, models), vsd_render, vsd_compare, mssd, mspd
      (summed over worker processes), errors_wall (wall time of the error
      computation), match (matching, recalls, breakdowns), write (errors.parquet);
      n_renders, n_workers.
    per_object: obj_id, n_targets, AR_VSD, AR_MSSD, AR_MSPD, AR per object.
    recalls: "vsd" (n_tau, n_theta), "mssd" (10,), "mspd" (10,) recall arrays.
    per_visibility: visib_min, visib_max, n_targets, AR_VSD, AR_MSSD, AR_MSPD, AR per
      visible-fraction bin of the valid GT instances ([0, 0.1), ..., [0.9, 1.0]; NaN
      where a bin has no target). A target counts as found in the bin of the GT
      instance its estimate was matched to.
    """

    summary: dict[str, Any]
    errors: pd.DataFrame
    per_object: pd.DataFrame
    recalls: dict[str, np.ndarray] = field(default_factory=dict)
    per_visibility: pd.DataFrame = field(default_factory=pd.DataFrame)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready content of ``scores.json``."""
        return {
            "summary": self.summary,
            "recalls": {k: np.asarray(v).tolist() for k, v in self.recalls.items()},
            "per_object": _records(self.per_object),
            "per_visibility": _records(self.per_visibility),
        }


def _records(df: pd.DataFrame) -> list[dict[str, Any]]:
    """Rows of a table as JSON-ready dicts (NaN as None)."""
    return [
        {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()}
        for r in df.to_dict(orient="records")
    ]


# ---------------------------------------------------------------------------- inputs


def _targets_list(dataset: BopDataset, targets: Sequence[Target] | Path | str | None) -> list[Target]:
    if targets is None or isinstance(targets, (str, Path)):
        return dataset.targets(targets)
    return list(targets)


class NotARotationError(BopFormatError):
    """Estimates of a results file whose R is not a rotation (:func:`check_rotations`)."""


def rotation_deviations(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each of the (N, 3, 3) matrices ``R`` is from a rotation: max|R^T R - I|
    (N,) and |det R - 1| (N,), both dimensionless (0 for an exact rotation; 1 and 1 for
    an all-zero R; a reflection has det -1, so 2)."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    ortho = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    det = np.abs(np.linalg.det(R) - 1.0) if len(R) else np.zeros(0)
    return ortho, det


def check_rotations(results: pd.DataFrame, source: str | Path = "results",
                    tol: float = ROTATION_TOLERANCE) -> None:
    """Refuse estimates whose R is not a rotation; the one check every scoring path runs.

    results: as ``read_results_csv`` returns (R: (3, 3) arrays, or 9 values, each finite).
    source: what the message names first (the results file).
    Raises :class:`NotARotationError` (a ``BopFormatError``) with one line naming
    ``source``, how many rows are bad, and the first bad row (its 1-based position among
    the estimates, scene_id, im_id, obj_id) with its two deviations, when
    max|R^T R - I| > ``tol`` or |det R - 1| > ``tol`` for any row.
    """
    if len(results) == 0:
        return
    R = np.stack([np.asarray(v, dtype=np.float64).reshape(3, 3) for v in results["R"]])
    ortho, det = rotation_deviations(R)
    # NaN deviations (a non-finite R that slipped through) count as bad, hence "not <=".
    bad = np.flatnonzero(~((ortho <= tol) & (det <= tol)))
    if not len(bad):
        return
    i = int(bad[0])
    row = results.iloc[i]
    raise NotARotationError(
        f"{source}: {len(bad)} of {len(results)} estimates have an R that is not a rotation "
        f"(max|R^T R - I| or |det R - 1| above {tol:g}); first: estimate {i + 1} "
        f"(scene_id {int(row['scene_id'])}, im_id {int(row['im_id'])}, obj_id {int(row['obj_id'])}) "
        f"with max|R^T R - I| = {ortho[i]:.3g}, |det R - 1| = {det[i]:.3g}")


def _check_results(results: pd.DataFrame, source: str | Path = "results") -> pd.DataFrame:
    """``results`` with its types checked and normalised (time -1 when absent); raises
    ValueError naming ``source``, the row and the field, or :class:`NotARotationError`."""
    missing = [c for c in ("scene_id", "im_id", "obj_id", "score", "R", "t") if c not in results.columns]
    if missing:
        raise ValueError(f"{source}: missing column(s) {missing}; expected scene_id, im_id, obj_id, score, R, t, time")
    df = results.reset_index(drop=True).copy()
    if "time" not in df.columns:
        df["time"] = -1.0
    for c in ("scene_id", "im_id", "obj_id"):
        df[c] = df[c].astype(np.int64)
    df["score"] = df["score"].astype(np.float64)
    df["time"] = df["time"].astype(np.float64)
    for name, n in (("R", 9), ("t", 3)):
        bad = _first_bad_row(df[name], n)
        if bad is not None:
            v = df[name].iloc[bad]
            raise ValueError(f"{source}: row {bad}, field '{name}': expected {n} finite values, got {v!r}")
    if not np.all(np.isfinite(df["score"])):
        raise ValueError(f"{source}: row {int(np.flatnonzero(~np.isfinite(df['score']))[0])}, field 'score': not finite")
    check_rotations(df, source)
    return df


def _first_bad_row(values: pd.Series, n: int) -> int | None:
    """Position of the first row of a column of arrays that is not ``n`` finite values;
    None when all are. One stacked check when the rows have one shape (the usual case),
    row by row otherwise."""
    if not len(values):  # a results file without estimates has nothing wrong in it
        return None
    try:
        a = np.stack([np.asarray(v, dtype=np.float64) for v in values])
    except ValueError:  # rows of different shapes
        a = None
    if a is not None and a.reshape(len(values), -1).shape[1] == n:
        ok = np.isfinite(a.reshape(len(values), n)).all(axis=1)
        return None if ok.all() else int(np.flatnonzero(~ok)[0])
    for i, v in enumerate(values):
        a = np.asarray(v, dtype=np.float64)
        if a.size != n or not np.all(np.isfinite(a)):
            return i
    return None


def time_per_image(df: pd.DataFrame) -> tuple[float, list[str]]:
    """The BOP mean time per image (s) and notes on what in the times is not as BOP wants.

    As the BOP toolkit (``scripts/eval_bop19_pose.py``) defines it: the mean over images
    of each image's time, and -1 (unknown) as soon as any estimate's time is negative
    (-1 means "not measured"). Notes (one line each, for ``summary["notes"]``):

    - images with both a negative (unknown) and a positive time: BOP requires one time
      for all estimates of an image; the mean is then -1, as the toolkit gives (it stops
      at the first negative time);
    - images whose lines differ by more than 1 ms: the toolkit raises; here the first
      line's time is used (the toolkit's value when it passes).
    """
    if len(df) == 0:
        return -1.0, []
    notes: list[str] = []
    g = df.groupby(["scene_id", "im_id"], sort=True)["time"]
    lo, hi = g.min(), g.max()
    mixed = lo[(lo < 0) & (hi > 0)]
    if len(mixed):
        s, i = mixed.index[0]
        notes.append(f"results: {len(mixed)} image(s) have both unknown (-1) and measured times for their estimates "
                     f"(first: scene {s} image {i}); BOP needs one time for all estimates of an image, and any "
                     "unknown time makes the mean time per image unknown (-1), as in the BOP toolkit")
    if (df["time"] < 0).any():
        return -1.0, notes
    spread = hi - lo
    bad = spread[spread > 0.001]
    if len(bad):
        shown = ", ".join(f"scene {s} image {i}" for s, i in bad.index[:5])
        more = f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""
        notes.append(f"results: the time differs between estimates of the same image for {shown}{more}; "
                     "BOP needs one time per image (using the first line's time)")
    return float(g.first().mean()), notes


def mean_time_per_image(df: pd.DataFrame) -> float:
    """The BOP mean time per image (s; -1 if any time is unknown), as
    :func:`time_per_image` gives it, its notes issued as warnings."""
    mean, notes = time_per_image(df)
    for note in notes:
        warnings.warn(note, stacklevel=2)
    return mean


def unscored_summary(results_csv: Path, targets: Sequence[Target], why: str) -> dict[str, Any]:
    """What ``scores.json`` says of a results file that cannot be scored here because the
    ground truth is missing (``why``): counts, the BOP time per image, and the file to
    submit to the BOP evaluation server."""
    df = read_results_csv(results_csv)
    # Not scored here, but this is the file to submit: refuse it as scoring would.
    check_rotations(df, results_csv)
    mean_time, time_notes = time_per_image(df)
    return {
        "status": "no_ground_truth",
        "AR": None, "AR_VSD": None, "AR_MSSD": None, "AR_MSPD": None,
        # a target listed twice counts once, its last line's inst_count winning, as the
        # scorer (and BOP's toolkit) count targets
        "n_targets": int(sum({(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in targets}.values())),
        "n_estimates": int(len(df)),
        "mean_time_per_image": mean_time,
        "results_file": str(results_csv),
        "notes": [f"not scored: {why}; submit {results_csv} to the BOP evaluation server (bop.felk.cvut.cz)",
                  *time_notes],
    }


def _select_estimates(df: pd.DataFrame, inst_counts: dict[tuple[int, int, int], int]) -> tuple[pd.DataFrame, int]:
    """Estimates kept for scoring, with est_id; and the number outside the targets."""
    keys = list(zip(df["scene_id"].tolist(), df["im_id"].tolist(), df["obj_id"].tolist()))
    in_targets = np.array([k in inst_counts for k in keys], dtype=bool)
    n_ignored = int((~in_targets).sum())
    sel = df[in_targets].copy()
    # est_id: position among the image's estimates of the object, in file order.
    sel["est_id"] = sel.groupby(["scene_id", "im_id", "obj_id"], sort=False).cumcount()
    sel = sel.sort_values(["scene_id", "im_id", "obj_id", "score", "est_id"], ascending=[True, True, True, False, True], kind="stable")
    rank = sel.groupby(["scene_id", "im_id", "obj_id"], sort=False).cumcount().to_numpy()
    limit = np.array([inst_counts[k] for k in zip(sel["scene_id"], sel["im_id"], sel["obj_id"])], dtype=np.int64)
    return sel[rank < limit].reset_index(drop=True), n_ignored


# ---------------------------------------------------------------------------- errors


def _image_jobs(dataset: BopDataset, ests: pd.DataFrame) -> list[ImageJob]:
    """One :class:`ImageJob` per image of the selected estimates ``ests`` (with est_id),
    by increasing (scene_id, im_id), the estimates of an image in their order in ``ests``."""
    if len(ests) == 0:
        return []
    scene = ests["scene_id"].to_numpy(np.int64)
    image = ests["im_id"].to_numpy(np.int64)
    # Plain Python values and stacked arrays once, instead of per row of every image.
    est_ids = ests["est_id"].to_numpy(np.int64).tolist()
    obj_ids = ests["obj_id"].to_numpy(np.int64).tolist()
    scores = ests["score"].to_numpy(np.float64).tolist()
    Rs = np.stack([np.asarray(v, dtype=np.float64).reshape(3, 3) for v in ests["R"]])
    ts = np.stack([np.asarray(v, dtype=np.float64).reshape(3) for v in ests["t"]])
    order = np.lexsort((image, scene))  # stable: rows of an image keep their order
    new_image = np.ones(len(order), dtype=bool)
    new_image[1:] = (scene[order][1:] != scene[order][:-1]) | (image[order][1:] != image[order][:-1])
    bounds = np.append(np.flatnonzero(new_image), len(order))
    jobs = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        rows = order[a:b].tolist()
        scene_id, im_id = int(scene[rows[0]]), int(image[rows[0]])
        cams = dataset.scene_camera(scene_id)
        gts_all = dataset.scene_gt(scene_id)
        if im_id not in cams or im_id not in gts_all:
            raise ValueError(
                f"{dataset.scene_dir(scene_id)}: image {im_id} is a target but has no entry in "
                "scene_camera.json / scene_gt.json"
            )
        cam = cams[im_id]
        objs = {obj_ids[i] for i in rows}
        gts = [(g, p.obj_id, p.R, p.t) for g, p in enumerate(gts_all[im_id]) if p.obj_id in objs]
        ests_list = [(est_ids[i], obj_ids[i], scores[i], Rs[i], ts[i]) for i in rows]
        jobs.append(ImageJob(scene_id, im_id, cam.K, int(cam.width), int(cam.height), gts, ests_list))
    return jobs


def _chunks(items: list, n: int) -> list[list]:
    return [items[i : i + n] for i in range(0, len(items), n)]


def _compute_errors(
    dataset: BopDataset, jobs: list[ImageJob], params: ErrorParams, n_workers: int, progress: bool,
    mapper: Any = None,
) -> tuple[list[dict], dict[str, float]]:
    """Error rows of all jobs, and the seconds per part summed over the processes (or
    threads). mapper: a :class:`pipeline.common.parallel.Mapper` on threads or a dask cluster,
    used instead of ``n_workers`` processes when it is not serial."""
    rows: list[dict] = []
    timing: dict[str, float] = {}

    def add(part: dict[str, float]) -> None:
        for k, v in part.items():
            timing[k] = timing.get(k, 0.0) + v

    from pipeline.common.progress import progress_bar

    # The images' errors are most of the time of a large file: count, rate and time left.
    with progress_bar("pose errors (images)", total=len(jobs), enabled=progress and bool(jobs)) as bar:
        if mapper is not None and mapper.kind != "serial" and len(jobs) > 1:
            from functools import partial

            # One calculator per thread (its EGL context is bound to the thread); the
            # rows come back in the jobs' order, as from the pool below.
            work = ErrorWork(mapper.per_thread(partial(ErrorWork.make_calculator, str(dataset.root), dataset.split,
                                                       dataset.split_type, params)))
            for part, part_time in mapper.map(image_errors_task, jobs, work, bar.advance if progress else None):
                rows.extend(part)
                add(part_time)
        elif n_workers <= 1 or len(jobs) <= 1:
            calc = ErrorCalculator(dataset, params)
            try:
                for part in calc.errors_of(jobs):
                    rows.extend(part)
                    bar.advance()
            finally:
                add(calc.timing)
                calc.close()
        else:
            # Small chunks keep the workers busy to the end; a chunk amortises the IPC.
            chunk = max(1, min(8, len(jobs) // (4 * n_workers)))
            ctx = multiprocessing.get_context("spawn")
            with ctx.Pool(
                n_workers,
                initializer=init_worker,
                initargs=(str(dataset.root), dataset.split, dataset.split_type, params),
            ) as pool:
                chunks = _chunks(jobs, chunk)
                for (part, part_time), done in zip(pool.imap(run_jobs, chunks), chunks):
                    rows.extend(part)
                    add(part_time)
                    bar.advance(len(done))
    return rows, timing


def _errors_frame(rows: list[dict], taus: np.ndarray) -> pd.DataFrame:
    cols = ["scene_id", "im_id", "obj_id", "est_id", "gt_id", "score", "mssd", "mspd"]
    vsd_cols = [vsd_column(t) for t in taus]
    if not rows:
        df = pd.DataFrame({c: pd.Series(dtype=np.int64 if c.endswith("id") else np.float64) for c in cols})
        for c in vsd_cols:
            df[c] = pd.Series(dtype=np.float64)
        return df
    df = pd.DataFrame([{c: r[c] for c in cols} for r in rows])
    vsd = np.array([r["vsd"] if r["vsd"] is not None else np.full(len(taus), np.nan) for r in rows], dtype=np.float64)
    for i, c in enumerate(vsd_cols):
        df[c] = vsd[:, i]
    df = df.astype({"scene_id": np.int64, "im_id": np.int64, "obj_id": np.int64, "est_id": np.int64, "gt_id": np.int64})
    return df.sort_values(["scene_id", "im_id", "obj_id", "est_id", "gt_id"], kind="stable").reset_index(drop=True)


# ---------------------------------------------------------------------------- matching and recall


#: Edges of the visible-fraction bins of the per-visibility breakdown: [0, 0.1), [0.1,
#: 0.2), ..., [0.9, 1.0] (the last bin is closed). Built from tenths for exact edges.
VISIB_BIN_EDGES: np.ndarray = np.arange(11) / 10.0


def visib_bin(visib_fract: np.ndarray | float) -> np.ndarray:
    """Index (0..9) of the visible-fraction bin of each value (see ``VISIB_BIN_EDGES``)."""
    idx = np.searchsorted(VISIB_BIN_EDGES, np.asarray(visib_fract, dtype=np.float64), side="right") - 1
    return np.clip(idx, 0, len(VISIB_BIN_EDGES) - 2)


@dataclass(frozen=True)
class ScoreTables:
    """What the matching of :func:`_score` gives.

    recalls: "vsd" (n_tau, n_theta) (only with VSD), "mssd" (10,), "mspd" (10,) recall
      arrays over all valid GT instances (zeros when there is none).
    per_object: obj_id, n_targets, AR_VSD, AR_MSSD, AR_MSPD, AR per object with a valid
      GT instance.
    n_targets: valid GT instances of the target images (the recalls' denominator).
    validity: scene_id, im_id, gt_id, gt_visib_fract, gt_valid of every GT instance of
      the target images (merged into the errors table).
    per_visibility: visib_min, visib_max, n_targets, AR_VSD, AR_MSSD, AR_MSPD, AR per
      visible-fraction bin (:data:`VISIB_BIN_EDGES`).
    """

    recalls: dict[str, np.ndarray]
    per_object: pd.DataFrame
    n_targets: int
    validity: pd.DataFrame
    per_visibility: pd.DataFrame


@dataclass(frozen=True)
class _Settings:
    """The K correctness settings of BOP19 in order: VSD (tau-major, theta-minor; none
    without VSD), MSSD (x diameter), MSPD (px at 640 px width)."""

    with_vsd: bool
    n_tau: int
    n_vsd: int
    n_mssd: int
    K: int
    thresholds: np.ndarray  # (K,)
    tau_index: np.ndarray  # (n_tau * n_theta,): the tau of each VSD setting

    @classmethod
    def of(cls, taus: np.ndarray, with_vsd: bool) -> "_Settings":
        n_tau = len(taus)
        n_vsd = n_tau * len(VSD_THETAS) if with_vsd else 0
        n_mssd = len(MSSD_THRESHOLDS)
        thresholds = np.concatenate([np.tile(VSD_THETAS, n_tau) if with_vsd else np.empty(0), MSSD_THRESHOLDS,
                                     MSPD_THRESHOLDS])
        return cls(with_vsd, n_tau, n_vsd, n_mssd, n_vsd + n_mssd + len(MSPD_THRESHOLDS), thresholds,
                   np.repeat(np.arange(n_tau), len(VSD_THETAS)))

    def split(self, counts: np.ndarray) -> dict[str, np.ndarray]:
        """Per-setting values (K,) as {"vsd": (n_tau, n_theta), "mssd": (10,), "mspd": (10,)}."""
        out = {}
        if self.with_vsd:
            out["vsd"] = counts[: self.n_vsd].reshape(self.n_tau, len(VSD_THETAS))
        out["mssd"] = counts[self.n_vsd : self.n_vsd + self.n_mssd]
        out["mspd"] = counts[self.n_vsd + self.n_mssd :]
        return out

    def ar_row(self, hits: np.ndarray, n: int) -> dict[str, float]:
        """AR_VSD, AR_MSSD, AR_MSPD and AR of ``hits`` (K,) true positives of ``n`` targets
        (NaN when ``n`` is 0; AR_VSD and AR NaN without VSD)."""
        if n == 0:
            return {"AR_VSD": float("nan"), "AR_MSSD": float("nan"), "AR_MSPD": float("nan"), "AR": float("nan")}
        r = self.split(hits.astype(np.float64) / n)
        row = {
            "AR_VSD": float(r["vsd"].mean()) if self.with_vsd else float("nan"),
            "AR_MSSD": float(r["mssd"].mean()),
            "AR_MSPD": float(r["mspd"].mean()),
        }
        row["AR"] = float(np.mean([row["AR_VSD"], row["AR_MSSD"], row["AR_MSPD"]])) if self.with_vsd else float("nan")
        return row


@dataclass
class _SortedErrors:
    """Error rows as arrays sorted by (scene, image, object, matching order, gt_id), the
    matching order being decreasing score, then est_id (file order); ``groups`` maps
    (scene, image, object) to its rows ``[a, b)``. mssd in mm, mspd in px, vsd (rows,
    n_tau) (None without VSD)."""

    est: np.ndarray | None = None
    gt: np.ndarray | None = None
    mssd: np.ndarray | None = None
    mspd: np.ndarray | None = None
    vsd: np.ndarray | None = None
    groups: dict[tuple[int, int, int], tuple[int, int]] = field(default_factory=dict)

    @classmethod
    def of(cls, errors: pd.DataFrame, taus: np.ndarray, with_vsd: bool) -> "_SortedErrors":
        if not len(errors):
            return cls()
        sc, im, ob = (errors[c].to_numpy(np.int64) for c in ("scene_id", "im_id", "obj_id"))
        est, gt, score = errors["est_id"].to_numpy(np.int64), errors["gt_id"].to_numpy(np.int64), errors["score"].to_numpy(np.float64)
        order = np.lexsort((gt, est, -score, ob, im, sc))
        sc, im, ob, est, gt = sc[order], im[order], ob[order], est[order], gt[order]
        new_group = np.ones(len(sc), dtype=bool)
        new_group[1:] = (sc[1:] != sc[:-1]) | (im[1:] != im[:-1]) | (ob[1:] != ob[:-1])
        starts = np.flatnonzero(new_group)
        ends = np.append(starts[1:], len(sc))
        return cls(est, gt, errors["mssd"].to_numpy(np.float64)[order], errors["mspd"].to_numpy(np.float64)[order],
                   errors[[vsd_column(t) for t in taus]].to_numpy(np.float64)[order] if with_vsd else None,
                   {(int(sc[a]), int(im[a]), int(ob[a])): (int(a), int(b)) for a, b in zip(starts, ends)})


@dataclass
class _Tally:
    """True positives (per setting) and valid targets, in all, per object and per
    visible-fraction bin, and every GT instance's validity row."""

    tps: np.ndarray  # (K,)
    bin_tars: np.ndarray  # (n_bins,)
    bin_tps: np.ndarray  # (n_bins, K)
    obj_tars: dict[int, int] = field(default_factory=dict)
    obj_tps: dict[int, np.ndarray] = field(default_factory=dict)
    n_targets: int = 0
    validity: list[tuple[int, int, int, float, bool]] = field(default_factory=list)


def _score(
    dataset: BopDataset,
    targets: list[Target],
    errors: pd.DataFrame,
    taus: np.ndarray,
    with_vsd: bool,
    visib_gt_min: float,
) -> ScoreTables:
    """Match the estimates of every target image to its valid GT instances, per
    correctness setting, and pool the recalls (see :class:`ScoreTables`)."""
    st = _Settings.of(taus, with_vsd)
    infos = eval_models_info(dataset)
    n_bins = len(VISIB_BIN_EDGES) - 1
    by_image: dict[tuple[int, int], dict[int, int]] = {}
    for t in targets:
        by_image.setdefault((t.scene_id, t.im_id), {})[t.obj_id] = t.inst_count
    srt = _SortedErrors.of(errors, taus, with_vsd)
    tally = _Tally(np.zeros(st.K, dtype=np.int64), np.zeros(n_bins, dtype=np.int64),
                   np.zeros((n_bins, st.K), dtype=np.int64))
    for (scene_id, im_id), inst_counts in sorted(by_image.items()):
        _tally_image(tally, dataset, scene_id, im_id, inst_counts, srt, st, infos, visib_gt_min)

    recalls = {k: (v / tally.n_targets if tally.n_targets else np.zeros(v.shape))
               for k, v in st.split(tally.tps.astype(np.float64)).items()}
    ar_cols = ["AR_VSD", "AR_MSSD", "AR_MSPD", "AR"]
    per_object = pd.DataFrame(
        [{"obj_id": o, "n_targets": tally.obj_tars[o], **st.ar_row(tally.obj_tps[o], tally.obj_tars[o])}
         for o in sorted(tally.obj_tars)],
        columns=["obj_id", "n_targets", *ar_cols],
    )
    per_visibility = pd.DataFrame(
        [
            {
                "visib_min": float(VISIB_BIN_EDGES[i]),
                "visib_max": float(VISIB_BIN_EDGES[i + 1]),
                "n_targets": int(tally.bin_tars[i]),
                **st.ar_row(tally.bin_tps[i], int(tally.bin_tars[i])),
            }
            for i in range(n_bins)
        ],
        columns=["visib_min", "visib_max", "n_targets", *ar_cols],
    )
    validity = pd.DataFrame(tally.validity, columns=["scene_id", "im_id", "gt_id", "gt_visib_fract", "gt_valid"])
    return ScoreTables(recalls, per_object, tally.n_targets, validity, per_visibility)


def _tally_image(tally: _Tally, dataset: BopDataset, scene_id: int, im_id: int, inst_counts: dict[int, int],
                 srt: _SortedErrors, st: _Settings, infos: dict, visib_gt_min: float) -> None:
    """Add one target image to ``tally``: its valid GT instances (targets, per object and
    per visible-fraction bin), the validity of each GT instance, and the true positives
    of the greedy matching of each target object's estimates. ``inst_counts``: obj_id ->
    inst_count of the image's targets."""
    gts = dataset.scene_gt(scene_id).get(im_id)
    gt_infos = dataset.scene_gt_info(scene_id).get(im_id)
    if gts is None or gt_infos is None or len(gt_infos) != len(gts):
        raise ValueError(
            f"{dataset.scene_dir(scene_id)}: target image {im_id} lacks consistent entries in "
            "scene_gt.json and scene_gt_info.json"
        )
    gt_obj = np.array([g.obj_id for g in gts], dtype=np.int64)
    fracts = [i.visib_fract for i in gt_infos]
    gt_bin = visib_bin(fracts) if len(fracts) else np.zeros(0, dtype=np.int64)
    valid = valid_gt_mask(gt_obj.tolist(), fracts, inst_counts, visib_gt_min)
    for g in np.flatnonzero(valid):
        o = int(gt_obj[g])
        tally.obj_tars[o] = tally.obj_tars.get(o, 0) + 1
        tally.obj_tps.setdefault(o, np.zeros(st.K, dtype=np.int64))
        tally.bin_tars[gt_bin[g]] += 1
        tally.n_targets += 1
    for g, (f, v) in enumerate(zip(fracts, valid)):
        tally.validity.append((scene_id, im_id, g, float(f), bool(v)))
    width = None
    for obj_id in inst_counts:
        span = srt.groups.get((scene_id, im_id, obj_id))
        if span is None:
            continue
        if width is None:
            width = dataset.scene_camera(scene_id)[im_id].width
        gt_ids = np.flatnonzero(gt_obj == obj_id)
        err = _object_errors(srt, span, gt_obj, gt_ids, st, float(infos[obj_id].diameter), width)
        matched = greedy_match(err, valid[gt_ids], st.thresholds)  # (K, E)
        ks, es = np.nonzero(matched >= 0)
        hits = np.bincount(ks, minlength=st.K)
        tally.tps += hits
        tally.obj_tps.setdefault(obj_id, np.zeros(st.K, dtype=np.int64))
        tally.obj_tps[obj_id] += hits
        np.add.at(tally.bin_tps, (gt_bin[gt_ids[matched[ks, es]]], ks), 1)


def _object_errors(srt: _SortedErrors, span: tuple[int, int], gt_obj: np.ndarray, gt_ids: np.ndarray,
                   st: _Settings, diameter: float, width: int) -> np.ndarray:
    """The (E, G, K) error of each of an object's E estimates (error rows ``span`` of
    ``srt``, in matching order) against each of its G GT instances (``gt_ids``, indices
    into the image's GT list ``gt_obj``) per setting, in the settings' units: VSD, MSSD
    / ``diameter`` (mm), MSPD scaled to a 640 px wide image (``width`` px); inf where a
    pair has no error row."""
    a, b = span
    lut = np.full(len(gt_obj), -1, dtype=np.int64)
    lut[gt_ids] = np.arange(len(gt_ids))
    est_g = srt.est[a:b]
    new_est = np.ones(b - a, dtype=bool)
    new_est[1:] = est_g[1:] != est_g[:-1]
    ei = np.cumsum(new_est) - 1
    gi = lut[srt.gt[a:b]]
    E, G = int(ei[-1]) + 1, len(gt_ids)
    err = np.full((E, G, st.K), np.inf)
    if st.with_vsd:
        err[ei, gi, : st.n_vsd] = srt.vsd[a:b][:, st.tau_index]
    err[ei, gi, st.n_vsd : st.n_vsd + st.n_mssd] = (srt.mssd[a:b] / diameter)[:, None]
    err[ei, gi, st.n_vsd + st.n_mssd :] = ((640.0 / width) * srt.mspd[a:b])[:, None]
    return err


# ---------------------------------------------------------------------------- entry points


def evaluate(
    results: pd.DataFrame,
    dataset: BopDataset,
    *,
    targets: Sequence[Target] | Path | str | None = None,
    vsd_delta: float = 15.0,
    n_workers: int = 1,
    progress: bool = True,
    visib_gt_min: float = -1.0,
    max_sym_disc_step: float = DEFAULT_MAX_SYM_DISC_STEP,
    source: str | Path = "results",
    mapper: Any = None,
    steps: StepTimer | None = None,
) -> Scores:
    """Score pose estimates with the BOP19 metrics.

    results: DataFrame with scene_id, im_id, obj_id, score, R ((3, 3) arrays), t ((3,)
      mm) and optionally time (s per image), as ``read_results_csv`` returns.
    targets: Target list, or a targets file path; default the dataset's
      ``test_targets_bop19.json``.
    vsd_delta: VSD visibility tolerance in mm (BOP: 15, ITODD 5; see ``bop_vsd_delta``).
    n_workers: processes for the error computation (spawned; each renders on its own).
    visib_gt_min: which GT instances are valid targets (see ``matching.valid_gt_mask``;
      the default -1 is the toolkit's BOP19 rule).
    source: what error messages about ``results`` name first (the results file).
    mapper: a :class:`pipeline.common.parallel.Mapper` over threads or a dask cluster that the
      images go to, one task each, instead of ``n_workers`` processes (None or serial:
      ``n_workers`` decides). The errors are the same either way.
    steps: where the steps before and after the images' errors report (a spinner and
      their durations, :class:`pipeline.common.progress.StepTimer`); silent when None. The
      images themselves have a bar with ``progress``.

    Raises ValueError on a malformed row or a ``vsd_delta`` that is not a finite number
    > 0 and :class:`NotARotationError` when an R is not
    a rotation within :data:`ROTATION_TOLERANCE` (:func:`check_rotations`).
    """
    try:
        delta_ok = math.isfinite(float(vsd_delta)) and float(vsd_delta) > 0
    except (TypeError, ValueError):
        delta_ok = False
    if not delta_ok:  # a NaN would make every VSD error NaN, a negative one every pixel "invisible"
        raise ValueError(f"vsd_delta must be a finite number of mm > 0, got {vsd_delta!r}")
    steps = steps or StepTimer(enabled=False)
    t_start = _time.perf_counter()
    with steps(f"check {len(results)} estimates"):
        df = _check_results(results, source)
    target_list = _targets_list(dataset, targets)
    inst_counts = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in target_list}
    unknown = sorted({t.obj_id for t in target_list} - set(eval_models_info(dataset)))
    if unknown:
        raise ValueError(f"{dataset.root}: target object(s) {unknown} have no entry in models_info.json")

    mean_time, time_notes = time_per_image(df)
    for note in time_notes:
        warnings.warn(note, stacklevel=2)
    ests, n_ignored = _select_estimates(df, inst_counts)
    n_in_targets = len(df) - n_ignored
    if n_ignored:
        log.warning("%d of %d estimates are for (scene, image, object) not in the targets and were ignored", n_ignored, len(df))

    target_images = sorted({(t.scene_id, t.im_id) for t in target_list})
    no_depth = [(s, i) for s, i in target_images if not dataset.has_depth(s, i)]
    with_vsd = not no_depth
    notes = []
    if no_depth:
        notes.append(
            f"VSD not computed: {len(no_depth)} of {len(target_images)} target images have no depth image "
            f"(first: scene {no_depth[0][0]} image {no_depth[0][1]}); AR_VSD and AR are None, "
            "AR_MSSD and AR_MSPD are valid"
        )
        warnings.warn(notes[-1], stacklevel=2)

    taus = VSD_TAUS
    params = ErrorParams(
        vsd_delta=float(vsd_delta), vsd_taus=tuple(taus.tolist()), max_sym_disc_step=max_sym_disc_step, compute_vsd=with_vsd
    )
    with steps(f"gather the images of {len(ests)} estimates"):
        jobs = _image_jobs(dataset, ests)
    t_prepare = _time.perf_counter() - t_start
    t_err = _time.perf_counter()
    rows, timing = _compute_errors(dataset, jobs, params, n_workers, progress, mapper)
    t_err = _time.perf_counter() - t_err
    t_match = _time.perf_counter()
    with steps("match estimates and compute the recalls"):
        errors = _errors_frame(rows, taus)

        tables = _score(dataset, target_list, errors, taus, with_vsd, visib_gt_min)
        errors = errors.merge(tables.validity, on=["scene_id", "im_id", "gt_id"], how="left")
        order = ["scene_id", "im_id", "obj_id", "est_id", "gt_id", "score", "gt_visib_fract", "gt_valid", "mssd", "mspd"]
        errors = errors[order + [c for c in errors.columns if c not in order]]
    t_match = _time.perf_counter() - t_match

    recalls = tables.recalls
    ar_mssd = float(recalls["mssd"].mean())
    ar_mspd = float(recalls["mspd"].mean())
    ar_vsd = float(recalls["vsd"].mean()) if with_vsd else None
    summary = {
        "AR": float(np.mean([ar_vsd, ar_mssd, ar_mspd])) if with_vsd else None,
        "AR_VSD": ar_vsd,
        "AR_MSSD": ar_mssd,
        "AR_MSPD": ar_mspd,
        "n_targets": int(tables.n_targets),
        "n_estimates": int(len(df)),
        "n_ignored": n_ignored,
        "n_evaluated": int(len(ests)),
        "n_beyond_inst_count": int(n_in_targets - len(ests)),
        "mean_time_per_image": mean_time,
        "vsd_delta": float(vsd_delta),
        "visib_gt_min": float(visib_gt_min),
        "images_without_depth": len(no_depth),
        "n_target_images": len(target_images),
        "eval_seconds": round(_time.perf_counter() - t_start, 3),
        "error_seconds": round(t_err, 3),
        "timing": _timing_summary(timing, t_prepare, t_match, t_err, _workers_used(n_workers, mapper, len(jobs))),
        "notes": notes + time_notes,
    }
    return Scores(summary, errors, tables.per_object, recalls, tables.per_visibility)


def _workers_used(n_workers: int, mapper: Any, n_jobs: int) -> int:
    """How many processes or threads computed the errors (see :func:`_compute_errors`)."""
    if n_jobs <= 1:
        return 1
    return mapper.workers if mapper is not None and mapper.kind != "serial" else n_workers


def _timing_summary(parts: dict[str, float], prepare: float, match: float, errors_wall: float, n_workers: int) -> dict[str, Any]:
    """Seconds per part of ``evaluate`` (rounded to ms).

    prepare (main process: checking and selecting the estimates, reading the GT
    annotations); load (depth images, models and their symmetries, or the wait for the
    reader thread that loads them ahead), vsd_render (drawing and collecting the renders),
    vsd_compare, mssd, mspd: summed over the worker processes, so with several workers
    their sum exceeds errors_wall (the wall time of the error computation, including
    starting the workers); match (errors table, greedy matching, recalls, breakdowns);
    n_renders: model depth renders; n_workers.
    """
    out: dict[str, Any] = {"prepare": prepare}
    for k in ("load", "vsd_render", "vsd_compare", "mssd", "mspd"):
        out[k] = parts.get(k, 0.0)
    out["errors_wall"] = errors_wall
    out["match"] = match
    out = {k: round(float(v), 3) for k, v in out.items()}
    out["n_renders"] = int(parts.get("n_renders", 0))
    out["n_workers"] = int(n_workers)
    return out


def _atomic_parquet(df: pd.DataFrame, path: Path) -> None:
    """``df`` written to the Parquet file ``path`` atomically, mode ``0o666 & ~umask``."""
    from pipeline.common.published_files import publishable

    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)
        publishable(tmp)


def _resolve_targets(dataset_root: Path, targets_file: Path | str | None) -> Path | None:
    if targets_file is None:
        return None
    p = Path(targets_file)
    if not p.is_absolute() and not p.exists() and (dataset_root / p).exists():
        return dataset_root / p
    return p


def score_results_file(
    results_csv: Path | str,
    dataset_root: Path | str,
    split: str = "test",
    targets_file: Path | str | None = None,
    out_dir: Path | str | None = None,
    n_workers: int = 1,
    *,
    split_type: str | None = None,
    vsd_delta: float | None = None,
    progress: bool = False,
    mapper: Any = None,
    steps: StepTimer | None = None,
) -> Scores:
    """Score a BOP results CSV against a dataset folder; optionally write the outputs.

    targets_file: default ``<dataset_root>/test_targets_bop19.json``; a relative path
    not found from the working directory is looked up in ``dataset_root``.
    vsd_delta: default the BOP value for the dataset (folder) name.
    out_dir: when given, ``errors.parquet`` and ``scores.json`` are written there,
    each atomically, with the mode the umask gives a new file (0644 under umask 022).
    mapper: where the images' errors are computed (see :func:`evaluate`).
    progress: a bar over the images' errors; steps: a spinner and the duration of each
    step before and after them (reading, checking, matching, writing), silent when None.
    ``scores.json`` is standard JSON: a value that is not finite is written as null.

    Raises ``BopFormatError`` naming the file: a malformed line, or
    :class:`NotARotationError` when an estimate's R is not a rotation
    (:data:`ROTATION_TOLERANCE`); nothing is written then.
    """
    from pipeline.common.published_files import write_text_published

    steps = steps or StepTimer(enabled=False)
    dataset_root = Path(dataset_root)
    t0 = _time.perf_counter()
    dataset = BopDataset(dataset_root, split, split_type)
    with steps(f"read {Path(results_csv).name}"):
        results = read_results_csv(results_csv)
    t_read = _time.perf_counter() - t0
    delta = bop_vsd_delta(dataset.name) if vsd_delta is None else float(vsd_delta)
    scores = evaluate(
        results,
        dataset,
        targets=_resolve_targets(dataset_root, targets_file),
        vsd_delta=delta,
        n_workers=n_workers,
        progress=progress,
        source=results_csv,
        mapper=mapper,
        steps=steps,
    )
    scores.summary["results_file"] = str(results_csv)
    scores.summary["dataset"] = str(dataset_root)
    scores.summary["split"] = split
    timing = scores.summary.setdefault("timing", {})
    timing["read"] = round(t_read, 3)
    if out_dir is not None:
        out = Path(out_dir)
        with steps(f"write {out / 'errors.parquet'}, scores.json"):
            t0 = _time.perf_counter()
            _atomic_parquet(scores.errors, out / "errors.parquet")
            # The time to write scores.json itself (milliseconds) cannot be in it.
            timing["write"] = round(_time.perf_counter() - t0, 3)
            # allow_nan=False: NaN and Infinity are not JSON; _json_safe made them null already.
            write_text_published(out / "scores.json",
                                 json.dumps(_json_safe(scores.to_json()), indent=1, allow_nan=False) + "\n")
    return scores


def _json_safe(obj: Any) -> Any:
    """``obj`` with every float that is not finite (NaN, +-inf) replaced by None, as
    :func:`_records` does for the tables: ``scores.json`` must be standard JSON."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def load_scores(out_dir: Path | str) -> tuple[dict[str, Any], pd.DataFrame]:
    """Read back ``scores.json`` (as a dict) and ``errors.parquet`` written by :func:`score_results_file`."""
    out = Path(out_dir)
    return json.loads((out / "scores.json").read_text()), pd.read_parquet(out / "errors.parquet")


__all__ = [
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "ROTATION_TOLERANCE",
    "VISIB_BIN_EDGES",
    "VSD_THETAS",
    "NotARotationError",
    "Scores",
    "bop_vsd_delta",
    "check_rotations",
    "evaluate",
    "load_scores",
    "score_results_file",
    "vsd_column",
]

"""The scene side of the method, written once: from an image's depth and candidate masks
to the chosen, refined poses of a scene.

The stages ``scene_features``, ``register`` and ``refine`` read their inputs, call the
functions here and publish what they return; ``freeze estimate`` runs those same stages
on its frame, wrapped as a one-image BOP dataset. Everything here works on arrays and
plain records (pandas tables, dataclasses) and on callables that load an image or a
mesh when asked, never on artifact folders.

1. :func:`scene_features`: per candidate, mask ∧ valid depth lifted to camera-frame
   points (mm), outliers removed, M sampled (seeded), geometric features of the points
   and visual features of the candidate's square crop sampled at their pixels.
2. :func:`register_candidates`: per object, the model's visual features reduced by PCA
   (:func:`matchable_model`); per candidate, the fused features matched to the model's
   and coarse hypotheses by RANSAC on each modality's matches and on the fused ones
   (:func:`coarse_hypotheses`).
3. :func:`refine_candidates`: ICP of every registered candidate and its evidence (RANSAC
   inlier ratio x ICP fitness); :func:`choose_estimates`: up to ``inst_count`` distinct
   estimates per target; :func:`refine_by_symmetry`: the symmetry-aware refinement of
   those whose shape has symmetries beyond the declared ones.

Units and conventions: BOP's (mm, OpenCV camera, model-to-camera ``R``, ``t``).
"""

from __future__ import annotations

import math
import time
from functools import cached_property
from dataclasses import dataclass, replace
from typing import Any, Callable, Collection, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.common.config import RefineParams, RegisterParams, SceneFeaturesParams
from pipeline.common.parallel import Mapper

VERIFICATION_COLUMNS = ["silhouette", "depth_fit", "coverage", "free_space", "verification"]
"""The verification terms of a refined pose and its score
(:mod:`pipeline.method.refinement.verification`)."""
CANDIDATE_COLUMNS = ["cand_id", "scene_id", "im_id", "obj_id", "hyp", "parent", "source", "prior_score", "n_inliers",
                     "inlier_ratio", "R", "t", "fitness", "inlier_rmse", "evidence", *VERIFICATION_COLUMNS,
                     "fine_icp", "time_s"]
"""Columns of refine's ``candidate_choices.parquet``: each candidate's chosen hypothesis, its pose
after the fine ICP when ``fine_icp`` (before the choice among a target's candidates adds
selected, rank, note); time_s is the candidate's, over its hypotheses and the fine ICP."""
HYPOTHESIS_COLUMNS = ["cand_id", "scene_id", "im_id", "obj_id", "hyp", "parent", "source", "prior_score",
                      "n_inliers", "inlier_ratio", "R", "t", "fitness", "inlier_rmse", "evidence",
                      *VERIFICATION_COLUMNS, "time_s", "chosen"]
"""Columns of refine's ``hypotheses.parquet``: every hypothesis after ICP, with its
verification terms, and whether it is its candidate's pose. Register's hypotheses have
parent -1; a turn (source ``turn``) names the hypothesis it turned."""
POSE_COLUMNS = ["scene_id", "im_id", "obj_id", "cand_id", "hyp", "source", "R", "t", "score", "evidence",
                "verification", "fitness", "inlier_rmse", "n_inliers", "sar_variant", "sar_reason"]
"""Columns of refine's ``poses.parquet``; ``score`` is the value written to the results CSV."""
SAR_COLUMNS = ["scene_id", "im_id", "obj_id", "cand_id", "variant", "R", "t", "similarity", "chosen"]
"""Columns of refine's ``sar.parquet``: one row per symmetric variant tried."""
REGISTER_COLUMNS = ["cand_id", "scene_id", "im_id", "obj_id", "prior_score", "status", "reason", "hyp", "source",
                    "source_rank", "w_geometric", "w_visual", "signal_geometric", "signal_visual", "modalities_agree",
                    "R", "t", "n_inliers", "inlier_ratio", "ransac_fitness", "n_correspondences", "time_s"]
"""Columns of register's ``coarse_hypotheses.parquet``: one row per coarse hypothesis."""
SKIPPED_REGISTER_ROW = {"source_rank": -1, "w_geometric": float("nan"), "w_visual": float("nan"),
                        "signal_geometric": float("nan"), "signal_visual": float("nan"), "modalities_agree": False,
                        "R": None, "t": None, "n_inliers": 0, "inlier_ratio": float("nan"),
                        "ransac_fitness": float("nan"), "n_correspondences": 0, "time_s": 0.0}
"""The values of a skipped candidate's one row of register's table beyond its identity."""

QUICK_ICP_ITERATIONS = 10
"""Iterations of the quick ICP that ranks the turns of a hypothesis (at the coarsest
correspondence distance only)."""

FINE_NEAR_FRAC = 0.05
"""The fine ICP's depth points are the candidate's valid masked depth within this
fraction of the diameter of its scene_features points, which passed the outlier filters
(:func:`pipeline.method.geometry.depth.remove_outliers`): the separate blobs that the
filters' clustering drops lie farther than its 0.1 diameter from every object point.
Running the filters again instead cost 25.1 ms a candidate on semi-real LM-O's first 80
(one thread), this selection 1.7 ms."""

Progress = Callable[[], None]
"""Called once per candidate done (a progress bar's ``advance``)."""


def _noop() -> None:
    pass


def _flat(a: np.ndarray, n: int) -> list[float]:
    return np.asarray(a, float).reshape(n).tolist()


# ------------------------------------------------------------------ scene features


@dataclass(frozen=True)
class CandidateMask:
    """One candidate of an image, as the prior gives it: mask (H, W) bool, bbox
    (x, y, w, h) px, the object's diameter (mm) and the seed of its point sampling."""

    cand_id: int
    obj_id: int
    mask: np.ndarray
    bbox: tuple[float, float, float, float]
    diameter: float
    seed: int


@dataclass
class CandidateFeatures:
    """What :func:`scene_features` found for one candidate: ``n_valid`` object points
    after outlier removal, of which ``k`` were sampled: points (k, 3) float32 mm (camera
    frame), pixels (k, 2) int32 (u, v), geometric (k, G) and visual (k, C) float32.
    ``reason`` says why the candidate was skipped ("" when it was not; the arrays are
    then empty)."""

    cand_id: int
    n_valid: int
    points: np.ndarray
    pixels: np.ndarray
    geometric: np.ndarray
    visual: np.ndarray
    reason: str = ""

    @property
    def ok(self) -> bool:
        return not self.reason


def candidate_points(depth: np.ndarray, K: np.ndarray, mask: np.ndarray, diameter: float) -> tuple[np.ndarray, np.ndarray]:
    """The candidate's object points: the valid depth under ``mask`` (H, W) bool lifted to
    the camera frame, outliers removed (:func:`pipeline.method.geometry.depth.remove_outliers`).
    Returns points (P, 3) float32 mm and their pixels (P, 2) int64 (u, v)."""
    from pipeline.method.geometry.depth import lift_depth, remove_outliers

    pts, pix = lift_depth(depth, K, mask)
    if len(pts):
        keep = remove_outliers(pts, diameter)
        pts, pix = pts[keep], pix[keep]
    return pts, pix


def sample_candidate(n_points: int, n: int, seed: int) -> np.ndarray:
    """Sorted indices of ``min(n, n_points)`` of ``n_points`` points, drawn without
    replacement with ``seed``."""
    rng = np.random.default_rng(seed)
    sel = rng.choice(n_points, size=min(n, n_points), replace=False)
    sel.sort()
    return sel


def scene_features(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, candidates: Sequence[CandidateMask], geo, vis,
                   params: SceneFeaturesParams, progress: Progress = _noop) -> list[CandidateFeatures]:
    """Points and features of the candidates of one image.

    rgb (H, W, 3) uint8, depth (H, W) float32 mm, K (3, 3); geo, vis: the run's
    encoders. A candidate with fewer than ``params.min_points`` object points is skipped
    with the reason. Otherwise M = ``params.n_points`` points are sampled, encoded by
    ``geo`` (normals oriented to the camera), and take the visual features of the
    candidate's square crop (its box with ``params.crop_margin``, resized to the
    encoder's input size) at their pixels. The crops of one image go through the visual
    encoder as one batch.
    """
    from pipeline.method.encoders.lifting import crop_and_resize, sample_features_at_pixels, square_crop_box

    out: list[CandidateFeatures] = []
    crops, crop_boxes, crop_of = [], [], []
    for c in candidates:
        pts, pix = candidate_points(depth, K, c.mask, c.diameter)
        if len(pts) < params.min_points:
            out.append(CandidateFeatures(c.cand_id, len(pts), np.zeros((0, 3), np.float32), np.zeros((0, 2), np.int32),
                                         np.zeros((0, geo.dim), np.float32), np.zeros((0, vis.dim), np.float32),
                                         reason=f"{len(pts)} valid depth points < min_points {params.min_points}"))
            progress()
            continue
        sel = sample_candidate(len(pts), params.n_points, c.seed)
        spts, spix = pts[sel], pix[sel].astype(np.int32)
        geometric = np.asarray(geo.encode(spts, None, c.diameter, viewpoint=np.zeros(3)), np.float32)
        box = square_crop_box(c.bbox, depth.shape, margin=params.crop_margin)
        crops.append(crop_and_resize(rgb, box, vis.input_size))
        crop_boxes.append(box)
        crop_of.append(len(out))
        out.append(CandidateFeatures(c.cand_id, len(pts), spts, spix, geometric,
                                     np.zeros((len(sel), vis.dim), np.float32)))
        progress()
    if crops and vis.dim:
        feats = vis.encode(np.stack(crops))
        for j, i in enumerate(crop_of):
            f = out[i]
            f.visual = sample_features_at_pixels(feats[j], crop_boxes[j], vis.input_size, f.pixels.astype(np.float32))
    return out


def packed_points(arrays: Mapping[str, np.ndarray]) -> Callable[[int], np.ndarray]:
    """cand_id -> that candidate's sampled points (k, 3) mm, from :func:`pack_candidates`'
    arrays (``points``, ``n_points``, ``cand_id``)."""
    row = {int(c): i for i, c in enumerate(arrays["cand_id"])}

    def points(cand_id: int) -> np.ndarray:
        i = row[int(cand_id)]
        return arrays["points"][i, :int(arrays["n_points"][i])]
    return points


def pack_candidates(found: Sequence[CandidateFeatures], n_points: int, geo_dim: int, vis_dim: int) -> dict[str, np.ndarray]:
    """The ``features.zarr`` arrays of a scene: points (C, M, 3) float32 mm, pixels
    (C, M, 2) int32, geometric (C, M, G), visual (C, M, V) float32 (NaN / -1 beyond each
    candidate's ``n_points``), n_points (C,) int32 and cand_id (C,) int64."""
    n = len(found)
    arrays = {
        "points": np.full((n, n_points, 3), np.nan, np.float32),
        "pixels": np.full((n, n_points, 2), -1, np.int32),
        "geometric": np.full((n, n_points, geo_dim), np.nan, np.float32),
        "visual": np.full((n, n_points, vis_dim), np.nan, np.float32),
        "n_points": np.zeros(n, np.int32),
        "cand_id": np.asarray([f.cand_id for f in found], np.int64),
    }
    for i, f in enumerate(found):
        k = len(f.points)
        arrays["points"][i, :k], arrays["pixels"][i, :k] = f.points, f.pixels
        arrays["geometric"][i, :k], arrays["visual"][i, :k] = f.geometric, f.visual
        arrays["n_points"][i] = k
    return arrays


# ------------------------------------------------------------------ registration


@dataclass
class MatchableModel:
    """An object's model side ready for matching: points (N, 3) mm, its geometric (N, G)
    and PCA-reduced visual (N, V) features, each L2-normalised per row (``visual`` is
    None when the run has no visual channels or the object's visual features carry no
    variance), and the PCA basis its visual part was reduced with (None without visual
    channels)."""

    points: np.ndarray
    geometric: np.ndarray
    visual: np.ndarray | None
    basis: Any

    @cached_property
    def fused(self) -> np.ndarray:
        """The paper's fused features (both parts at weight 1), (N, G + V)."""
        from pipeline.method.registration.fusion import fuse

        return fuse(self.geometric, self.visual if self.visual is not None else self._zero_visual())

    def _zero_visual(self) -> np.ndarray | None:
        return None if self.basis is None else np.zeros((len(self.points), self.basis.n_components), np.float32)

    @property
    def modalities(self) -> tuple[str, ...]:
        """The modalities whose features can carry signal for this object."""
        return tuple(m for m, ok in (("geometric", self.geometric.shape[1] > 0), ("visual", self.visual is not None))
                     if ok)


def matchable_model(features: Mapping[str, np.ndarray], pca_dim: int) -> MatchableModel:
    """A model's ``features.zarr`` arrays made matchable: PCA of its visual features to
    ``pca_dim`` (fitted on the model), each part L2-normalised."""
    from pipeline.method.registration.fusion import apply_pca, fit_pca, l2_normalise

    visual = features["visual"]
    basis = fit_pca(visual, n_components=pca_dim) if visual.shape[1] else None
    reduced = l2_normalise(apply_pca(basis, visual)) if basis is not None and basis.informative else None
    return MatchableModel(points=features["points"], geometric=l2_normalise(features["geometric"]), visual=reduced,
                          basis=basis)


@dataclass(frozen=True)
class Hypothesis:
    """One coarse pose of a candidate: where it came from (``source``: ``fused`` (the
    paper's), ``weighted`` (fused with the modality weights), ``geometric`` or ``visual``
    matches; ``source_rank``: its place among that source's distinct
    RANSAC poses, 0 = the winner) and its :class:`pipeline.method.registration.ransac.Registration`."""

    source: str
    source_rank: int
    registration: Any


@dataclass(frozen=True)
class CoarseResult:
    """A candidate's coarse hypotheses, distinct, in the order made, and the fusion
    weights (0-1) of its ``weighted`` hypothesis, with the held-out signals (z-scores)
    they came from (see :func:`coarse_hypotheses`)."""

    hypotheses: list[Hypothesis]
    w_geometric: float = 1.0
    w_visual: float = 1.0
    signal_geometric: float = float("nan")
    signal_visual: float = float("nan")
    agree: bool = True


def coarse_hypotheses(model: MatchableModel, points: np.ndarray, geometric: np.ndarray, visual: np.ndarray,
                      diameter: float, params: RegisterParams, seed: int, device: str | None = None) -> CoarseResult:
    """Distinct coarse model-to-camera poses of a candidate's points (k, 3) mm with their
    geometric (k, G) and visual (k, C) features.

    With both modalities (geometric features, and visual ones with variance on the
    model):

    - ``geometric``, ``visual``: the ``params.hypotheses`` best distinct RANSAC poses of
      each modality's own matches (with ``params.modality_hypotheses``);
    - fusion weights (``params.weighting``, :func:`_modality_weights`): RANSAC on each
      modality's matches of the even-indexed points gives one pose each; the matches of
      the odd-indexed points, held out, are scored against both poses
      (:func:`pipeline.method.registration.fusion.match_signal`, a z-score of agreeing matches
      beyond chance). A modality's *own* signal is that of its matches under its pose;
      its *cross* signal, under the other's. When some cross signal reaches
      ``params.signal_none`` the modalities agree and each weight follows its larger
      signal (:func:`~pipeline.method.registration.fusion.modality_weight`: 0 up to
      ``signal_none``, 1 from ``signal_full``); when neither has signal both are 1 (the
      paper); when both have signal but neither agrees with the other's pose, the one
      with the stronger own signal gets 1 and the other 0. (Held out from RANSAC, random
      matches score about 0; but matches that are wrong and spatially coherent, as a
      smooth colour descriptor's on a real image, agree with their own modality's pose
      too: only the cross signal tells them apart.)
    - ``fused``: RANSAC on the paper's fusion (equal weights): its ``params.hypotheses``
      best distinct poses, or its winner only when the weights are not equal, and then
    - ``weighted``: the RANSAC winner of the weighted fusion (unless a weight is 0: that
      fusion is then the other modality alone, already a hypothesis).

    With one modality: its ``params.hypotheses`` best distinct poses. Poses that repeat
    an earlier one (within 5 degrees and 0.05 diameters) are dropped. With both, every
    hypothesis' n_inliers and inlier_ratio count the same matches, the weighted
    fusion's top-1 matches, so that the evidence compares hypotheses of any source.

    device: where RANSAC's loop and the feature matching run: None for numpy (the faster
    on a CPU), or a torch device (``cuda``; the same samples and pools,
    :mod:`pipeline.method.registration.ransac_torch`).
    """
    from pipeline.method.registration.fusion import apply_pca, fuse, l2_normalise
    from pipeline.method.registration.ransac import RansacParams, distinct_poses, feature_neighbours, ransac_hypotheses

    ransac = RansacParams(inlier_frac=params.inlier_frac, max_iterations=params.max_iterations,
                          confidence=params.confidence, mutual=params.mutual)
    g = l2_normalise(geometric)
    v = l2_normalise(apply_pca(model.basis, visual)) if model.visual is not None else None

    def run(mf: np.ndarray, sf: np.ndarray, k: int, rows: Any = slice(None)) -> list:
        return ransac_hypotheses(model.points, mf, points[rows], sf[rows], diameter, params=ransac, seed=seed, k=k,
                                 nms_deg=params.nms_deg, nms_frac=params.nms_frac, device=device)

    found: list[Hypothesis] = []
    result = CoarseResult(found)
    if model.modalities == ("geometric", "visual"):
        feats = {"geometric": (model.geometric, g), "visual": (model.visual, v)}
        if params.modality_hypotheses:
            for m, (mf, sf) in feats.items():
                found += [Hypothesis(m, j, r) for j, r in enumerate(run(mf, sf, params.hypotheses))]
        if params.weighting:
            result = _modality_weights(model, points, feats, diameter, params, run, found, device)
        # With one weight 0 the weighted fusion is the other modality alone, whose own
        # RANSAC (same seed, same matches) is already a hypothesis.
        weighted = (result.w_geometric, result.w_visual) != (1.0, 1.0) and (
            min(result.w_geometric, result.w_visual) > 0 or not params.modality_hypotheses)
        paper = run(model.fused, fuse(g, v), 1 if weighted else params.hypotheses)
        found += [Hypothesis("fused", j, r) for j, r in enumerate(paper)]
        if weighted:
            wg, wv = result.w_geometric, result.w_visual
            found += [Hypothesis("weighted", 0, run(fuse(model.geometric, model.visual, wv, wg), fuse(g, v, wv, wg),
                                                    1)[0])]
    elif model.modalities:
        (m,) = model.modalities
        mf, sf = (model.geometric, g) if m == "geometric" else (model.visual, v)
        found += [Hypothesis(m, j, r) for j, r in enumerate(run(mf, sf, params.hypotheses))]
    else:  # no modality can carry signal: the paper's fusion, as it is
        vz = np.zeros((len(points), model.basis.n_components), np.float32) if model.basis is not None else None
        found += [Hypothesis("fused", j, r) for j, r in enumerate(run(model.fused, fuse(g, vz), params.hypotheses))]
    keep = distinct_poses([(h.registration.R, h.registration.t) for h in found], len(found), 5.0, 0.05 * diameter)
    found[:] = [found[i] for i in keep]
    if model.modalities == ("geometric", "visual"):
        # Every hypothesis counts its inliers among the same matches, those of the
        # weighted fusion: a visual hypothesis' own visual inliers and a geometric one's
        # geometric inliers are not comparable, and the evidence breaks the ties that
        # depth cannot (a shape's near-symmetries).
        wg, wv = result.w_geometric, result.w_visual
        matches = feature_neighbours(fuse(g, v, wv, wg), fuse(model.geometric, model.visual, wv, wg),
                                     device=device)[:, 0]
        thr = params.inlier_frac * diameter
        for i, h in enumerate(found):
            r = h.registration
            res = model.points[matches] @ r.R.T + r.t - points
            n = int(np.sum(np.sum(res * res, axis=1) < thr * thr))
            found[i] = Hypothesis(h.source, h.source_rank, replace(r, n_inliers=n, inlier_ratio=n / len(points)))
    return result


def _modality_weights(model: MatchableModel, points: np.ndarray, feats: Mapping[str, tuple[np.ndarray, np.ndarray]],
                      diameter: float, params: RegisterParams, run: Callable[..., list],
                      found: list[Hypothesis], device: str | None = None) -> CoarseResult:
    """The fusion weights of :func:`coarse_hypotheses` (see there) and the signals behind them."""
    from pipeline.method.registration.fusion import match_signal, modality_weight
    from pipeline.method.registration.ransac import feature_neighbours

    fit, held = np.arange(len(points)) % 2 == 0, np.arange(len(points)) % 2 == 1
    poses = {m: run(mf, sf, 1, fit)[0] for m, (mf, sf) in feats.items()}
    thr = params.inlier_frac * diameter
    z = {}  # z[m][n]: modality m's held-out matches under modality n's pose
    for m, (mf, sf) in feats.items():
        matches = feature_neighbours(sf[held], mf, device=device)[:, 0]
        z[m] = {n: match_signal(model.points, matches, points[held], r.R, r.t, thr) for n, r in poses.items()}
    own = {m: z[m][m] for m in z}
    other = {"geometric": "visual", "visual": "geometric"}
    cross = {m: z[m][other[m]] for m in z}
    agree = any(c >= params.signal_none for c in cross.values())
    if agree or all(o < params.signal_none for o in own.values()):
        w = {m: modality_weight(max(own[m], cross[m]), params.signal_none, params.signal_full) for m in z}
        if not any(w.values()):
            w = {m: 1.0 for m in z}
    else:  # both have signal but neither's matches agree with the other's pose: trust the stronger
        strong = max(own, key=own.get)
        w = {m: float(m == strong) for m in z}
    return CoarseResult(found, w["geometric"], w["visual"], own["geometric"], own["visual"], agree)


def register_candidates(candidates: pd.DataFrame, arrays: Mapping[str, np.ndarray],
                        model_of: Callable[[int], MatchableModel], diameters: Mapping[int, float],
                        params: RegisterParams, seed_of: Callable[[int], int],
                        progress: Progress = _noop, mapper: Mapper | None = None, device: str | None = None,
                        ) -> tuple[pd.DataFrame, dict[int, float]]:
    """Coarse hypotheses of a scene's candidates (:func:`coarse_hypotheses`, RANSAC and
    the feature matching on ``device``: None for numpy, else a torch device).

    candidates: scene_features' table (cand_id, scene_id, im_id, obj_id, prior_score, status,
    reason, n_points); arrays: its ``features.zarr`` (see :func:`pack_candidates`);
    model_of(obj_id): the object's :class:`MatchableModel`; seed_of(cand_id): the RANSAC
    seed. Returns the table (:data:`REGISTER_COLUMNS`, one row per hypothesis; a skipped
    candidate has one row, hyp 0, with its status and reason; ``time_s``, the
    candidate's time, is on its first row, 0 on the others) and the registration time
    per image (s), the sum of its candidates' times.

    mapper: where the candidates run (:mod:`pipeline.common.parallel`; None: in this thread, one
    after the other). Each candidate is independent (its own seed), and the rows come
    back in the candidates' order, so the table does not depend on the mapper.
    """
    pos = {int(c): i for i, c in enumerate(arrays["cand_id"])}
    rows_of: list[list[dict[str, Any]]] = []
    todo: list[_RegisterItem] = []
    for c in candidates.itertuples(index=False):
        row = {"cand_id": int(c.cand_id), "scene_id": int(c.scene_id), "im_id": int(c.im_id), "obj_id": int(c.obj_id),
               "prior_score": float(c.prior_score), "status": c.status, "reason": c.reason, "hyp": 0, "source": ""}
        # a skipped candidate's row: integer and flag columns keep their dtypes (-1, 0,
        # False), the measured values are NaN, the pose None
        rows_of.append([{**row, **SKIPPED_REGISTER_ROW}])
        if c.status != "ok":
            progress()
            continue
        i, k = pos[int(c.cand_id)], int(c.n_points)
        # The candidate's own slices and seed travel with it; the models are shared.
        todo.append(_RegisterItem(len(rows_of) - 1, row, arrays["points"][i, :k], arrays["geometric"][i, :k],
                                  arrays["visual"][i, :k], seed_of(int(c.cand_id))))
    # Models loaded here, once per object and in this thread, not by each worker.
    shared = _RegisterShared({o: model_of(o) for o in sorted({t.row["obj_id"] for t in todo})},
                             {o: diameters[o] for o in sorted({t.row["obj_id"] for t in todo})}, params, device)
    image_time: dict[int, float] = {}
    for t, (found, dt) in zip(todo, (mapper or Mapper()).map(_register_one, todo, shared, progress)):
        rows_of[t.index] = found
        image_time[t.row["im_id"]] = image_time.get(t.row["im_id"], 0.0) + dt
    return pd.DataFrame([r for rows in rows_of for r in rows], columns=REGISTER_COLUMNS), image_time


@dataclass(frozen=True)
class _RegisterItem:
    """One candidate for :func:`_register_one`: its place in the table, its row's
    identity, its points (k, 3) mm, geometric (k, G) and visual (k, C) features, seed."""

    index: int
    row: dict[str, Any]
    points: np.ndarray
    geometric: np.ndarray
    visual: np.ndarray
    seed: int


@dataclass(frozen=True)
class _RegisterShared:
    """What every candidate of a scene's registration shares: the objects'
    :class:`MatchableModel` and diameters (mm), the stage's parameters, the device of
    RANSAC and the matching (None: numpy)."""

    models: Mapping[int, MatchableModel]
    diameters: Mapping[int, float]
    params: RegisterParams
    device: str | None = None


def _register_one(shared: _RegisterShared, item: _RegisterItem) -> tuple[list[dict[str, Any]], float]:
    """A candidate's rows of register's table (one per hypothesis) and its time (s)."""
    t0 = time.perf_counter()
    row, obj_id = item.row, item.row["obj_id"]
    res = coarse_hypotheses(shared.models[obj_id], item.points, item.geometric, item.visual, shared.diameters[obj_id],
                            shared.params, item.seed, shared.device)
    dt = time.perf_counter() - t0
    rows = []
    for j, h in enumerate(res.hypotheses):
        reg = h.registration
        rows.append({**row, "hyp": j, "source": h.source, "source_rank": h.source_rank,
                     "w_geometric": res.w_geometric, "w_visual": res.w_visual,
                     "signal_geometric": res.signal_geometric, "signal_visual": res.signal_visual,
                     "modalities_agree": res.agree,
                     "R": _flat(reg.R, 9), "t": _flat(reg.t, 3), "n_inliers": int(reg.n_inliers),
                     "inlier_ratio": float(reg.inlier_ratio), "ransac_fitness": float(reg.fitness),
                     "n_correspondences": int(reg.n_correspondences), "time_s": dt if j == 0 else 0.0})
    return rows, dt


def pca_arrays(models: Mapping[int, MatchableModel]) -> dict[str, np.ndarray]:
    """register's ``pca.zarr`` arrays: obj_id (K,), mean (K, C), components (K, V, C),
    explained_variance (K, V), informative (K,) bool, for the objects that had a basis."""
    ids = sorted(o for o, m in models.items() if m.basis is not None)
    bases = [models[o].basis for o in ids]
    return {
        "obj_id": np.asarray(ids, np.int64),
        "mean": np.stack([b.mean for b in bases]) if bases else np.zeros((0, 0), np.float32),
        "components": np.stack([b.components for b in bases]) if bases else np.zeros((0, 0, 0), np.float32),
        "explained_variance": np.stack([b.explained_variance for b in bases]) if bases else np.zeros((0, 0), np.float32),
        "informative": np.asarray([b.informative for b in bases], bool),
    }


# ------------------------------------------------------------------ refinement and choice


@dataclass(frozen=True)
class SceneImages:
    """What refinement needs of a scene, loaded when asked: rgb(im_id) (H, W, 3) uint8,
    depth(im_id) (H, W) float32 mm (0 = no depth), K(im_id) (3, 3), mesh(obj_id)
    (trimesh, mm), candidate(cand_id) -> (bbox (x, y, w, h) px, mask (H, W) bool)."""

    rgb: Callable[[int], np.ndarray]
    depth: Callable[[int], np.ndarray]
    K: Callable[[int], np.ndarray]
    mesh: Callable[[int], Any]
    candidate: Callable[[int], tuple[tuple[float, float, float, float], np.ndarray]]

    def keeping_last(self) -> "SceneImages":
        """The same loaders, with the last image's depth and the last candidate's mask
        kept: refinement asks for them hypothesis after hypothesis, and the verifier and
        the fine ICP share them instead of reading and decoding them twice."""
        return replace(self, depth=_keep_last(self.depth), candidate=_keep_last(self.candidate))


def _keep_last(load: Callable[[int], Any]) -> Callable[[int], Any]:
    last: list = [None, None]

    def cached(key: int) -> Any:
        if last[0] != key or last[1] is None:
            last[:] = [key, load(key)]
        return last[1]
    return cached


class PoseVerifier:
    """Verification (:mod:`pipeline.method.refinement.verification`) of poses in the images of
    one scene, with one renderer (give it :meth:`SceneImages.keeping_last` loaders). Use
    as a context manager (it holds an EGL context). device: where :meth:`many` compares
    a candidate's renders with the depth: None in numpy, one at a time (the faster on a
    CPU), or a torch device, all together."""

    def __init__(self, images: SceneImages, params: RefineParams, device: str | None = None):
        self.images, self.params, self.device = images, params, device
        self._renderer = None

    def __enter__(self) -> "PoseVerifier":
        return self

    def __exit__(self, *exc) -> None:
        if self._renderer is not None:
            self._renderer.close()

    def __call__(self, im_id: int, cand_id: int, obj_id: int, R: np.ndarray, t: np.ndarray, diameter: float,
                 evidence: float):
        """The :class:`~pipeline.method.refinement.verification.Verification` of one pose."""
        (v,) = self.many(im_id, cand_id, obj_id, [(R, t)], diameter, [evidence])
        return v

    def many(self, im_id: int, cand_id: int, obj_id: int, poses: Sequence[tuple[np.ndarray, np.ndarray]],
             diameter: float, evidence: Sequence[float]) -> list:
        """The verifications of several poses (R (3, 3), t (3,) mm) of one candidate,
        with their evidence, in order (compared on :attr:`device`)."""
        from pipeline.method.refinement.verification import verification_window, verify_poses
        from pipeline.method.render import Renderer

        depth = self.images.depth(im_id)
        if self._renderer is None:
            self._renderer = Renderer(depth.shape[1], depth.shape[0], znear=1.0, zfar=100000.0)
        if not self._renderer.has_mesh(obj_id):
            self._renderer.add_mesh(obj_id, self.images.mesh(obj_id))
        bbox, mask = self.images.candidate(cand_id)
        tol = max(self.params.verify_min_tol_mm, self.params.verify_tol_frac * diameter)
        window = verification_window(bbox, depth.shape, self.params.verify_margin)
        return verify_poses(self._renderer, obj_id, poses, self.images.K(im_id), depth, mask, window, tol, evidence,
                            self.device)


def fine_icp_points(depth: np.ndarray, K: np.ndarray, mask: np.ndarray, near: np.ndarray | None,
                    diameter: float) -> np.ndarray:
    """The fine ICP's depth points of a candidate, (P, 3) float32 mm camera frame: the
    valid depth under ``mask`` (H, W) lifted, those within :data:`FINE_NEAR_FRAC`
    ``diameter`` of ``near`` (k, 3) mm, the candidate's scene_features points (None or
    empty: every one)."""
    from pykdtree.kdtree import KDTree

    from pipeline.method.geometry.depth import lift_depth

    pts, _ = lift_depth(depth, K, mask)
    if len(pts) and near is not None and len(near):
        dist, _ = KDTree(np.ascontiguousarray(near, dtype=np.float64)).query(
            pts.astype(np.float64), distance_upper_bound=FINE_NEAR_FRAC * diameter)
        pts = pts[dist < np.inf]
    return pts


class FineIcp:
    """The fine ICP of a candidate's chosen pose: up to ``params.fine_icp_points`` of the
    candidate's depth points (mask and valid depth near its scene_features points,
    :data:`FINE_NEAR_FRAC`; every one, not just those M samples) against
    ``params.fine_icp_model_points`` samples of the model's surface (kept per object),
    with the coarse-to-fine schedule of the hypotheses' ICP.

    Only objects in ``objects`` (those without shape symmetries) are refined: along a
    shape symmetry depth constrains nothing, and the longer ICP drifts where the visual
    features had placed the texture (on ``synthtiny`` the textured cans and cups turned
    15-20 degrees about their axes and AR fell from 0.82 to 0.74); the pose is then left
    to SAR."""

    def __init__(self, images: SceneImages, params: RefineParams, objects: set[int], device: str | None = None):
        self.images, self.params, self.objects = images, params, set(objects)
        self.device = device  # None: the numpy ICP; else the torch ICP on this device
        self._models: dict[int, Any] = {}  # obj_id -> IcpModel of the dense samples

    def __call__(self, im_id: int, cand_id: int, obj_id: int, R: np.ndarray, t: np.ndarray,
                 diameter: float, near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The fine pose (R (3, 3), t (3,) mm), or None when the object is not refined.
        near: the candidate's scene_features points (k, 3) mm, which select its depth
        points (:data:`FINE_NEAR_FRAC`; None: every valid masked depth point)."""
        from pipeline.method.refinement.icp import IcpModel, refine_icp
        from pipeline.method.geometry.sampling import sample_surface

        if obj_id not in self.objects:
            return None
        if obj_id not in self._models:
            self._models[obj_id] = IcpModel(*sample_surface(self.images.mesh(obj_id),
                                                            self.params.fine_icp_model_points, seed=obj_id))
        _, mask = self.images.candidate(cand_id)
        pts = fine_icp_points(self.images.depth(im_id), self.images.K(im_id), mask, near, diameter)
        if len(pts) < 3:
            return None
        pts = pts[sample_candidate(len(pts), self.params.fine_icp_points, seed=cand_id)]
        kw = {"max_corr_dist_frac": self.params.max_corr_frac, "iterations": self.params.iterations,
              "point_to_plane": self.params.point_to_plane}
        if self.device is not None:
            from pipeline.method.refinement.icp_torch import refine_icp_batch

            (res,) = refine_icp_batch(self._models[obj_id], pts, R[None], t[None], diameter, device=self.device,
                                      **kw)
        else:
            res = refine_icp(self._models[obj_id], None, pts, R, t, diameter, **kw)
        return res.R, res.t


def refine_candidates(registered: pd.DataFrame, scene_points: Callable[[int], np.ndarray],
                      model_of: Callable[[int], Mapping[str, np.ndarray]], diameters: Mapping[int, float],
                      params: RefineParams, verify: Callable[..., Any] | None = None,
                      fine: Callable[..., tuple[np.ndarray, np.ndarray] | None] | None = None,
                      progress: Progress = _noop, turns: Mapping[int, np.ndarray] | None = None,
                      mapper: Mapper | None = None, scene_device: str | None = None,
                      verify_many: Callable[..., list] | None = None,
                      ) -> tuple[pd.DataFrame, pd.DataFrame, dict[int, float]]:
    """ICP and verification of every coarse hypothesis (register's rows with status
    ``ok``), and each candidate's best hypothesis.

    scene_points(cand_id): the candidate's sampled points (k, 3) mm; model_of(obj_id):
    the model's ``points`` and ``normals`` (N, 3); verify: a :class:`PoseVerifier` (None:
    no verification, its terms NaN). With ``params.icp`` off the RANSAC pose and fitness
    are kept. Each hypothesis gets its evidence
    (:func:`pipeline.method.refinement.selection.registration_evidence`) and verification;
    a candidate's hypotheses are ranked like a target's candidates (``params.select_by``,
    ties by order) and the first is the candidate's pose.

    turns: obj_id -> (n, 4, 4) model-frame turns (:mod:`pipeline.method.refinement.turns`).
    With a verifier and ``params.turns`` > 0, the candidate's best hypothesis turned by
    each is aligned by a quick ICP, and the ``params.turns`` best of those by its
    fitness are refined and verified like the others: hypotheses with source ``turn``, ``parent`` the
    hypothesis turned, no RANSAC inliers (so evidence 0: a turn must beat its parent on
    the depth and silhouette by more than the parent's feature evidence). The choice is
    then made again over all.

    fine: a :class:`FineIcp` (None: off), which refines the chosen pose again on denser
    points; the fine pose replaces it (``fine_icp`` True) unless its verification score
    is lower.

    mapper: where the candidates' hypotheses, and then the chosen poses' fine ICP, run
    (:mod:`pipeline.common.parallel`; None: in this thread). With several threads, ``verify``
    and ``fine`` must be per-thread (:class:`pipeline.common.parallel.PerThread`: a renderer
    belongs to its thread). The candidates are independent and their rows come back in
    their order, so the tables do not depend on the mapper.

    scene_device: None for the numpy paths, one hypothesis at a time (the faster on a
    CPU), or a torch device (``cuda``) where a candidate's hypotheses, and its turns, are
    aligned together (:func:`pipeline.method.refinement.icp_torch.refine_icp_batch`, in
    float64: the numpy ICP's poses where a start converges, the same choices and AR)
    and then verified together (``verify_many``). The fine ICP has its own
    (:class:`FineIcp`), as has the verifier's comparison (:class:`PoseVerifier`).
    verify_many: ``verify``'s :meth:`PoseVerifier.many` (None: ``verify.many`` where it
    has one, else ``verify`` pose by pose), which the turns use on every path.

    Returns the hypotheses (:data:`HYPOTHESIS_COLUMNS`, ``chosen`` marking each
    candidate's), the candidates (:data:`CANDIDATE_COLUMNS`: the chosen hypothesis'
    pose, ICP fitness and inlier_rmse (mm), evidence, verification terms) and the time
    per image (s), the sum of its candidates' times.
    """
    from pipeline.method.refinement.selection import SELECT_BY_COLUMN

    key = SELECT_BY_COLUMN[params.select_by]
    if key == "verification" and verify is None:
        raise ValueError("refine: select_by 'verification' needs the verifier")
    mapper = mapper or Mapper()
    groups = [g for _, g in registered.groupby("cand_id", sort=False)]
    objects = sorted({int(o) for o in registered.obj_id})
    # Everything a candidate needs, so that a worker process can have it: the scene
    # points of the candidates, the models (loaded here, once per object).
    from pipeline.method.refinement.icp import IcpModel

    models = {o: model_of(o) for o in objects}
    if verify_many is None and verify is not None:
        verify_many = getattr(verify, "many", None)
    work = _RefineWork({int(g.cand_id.iloc[0]): scene_points(int(g.cand_id.iloc[0])) for g in groups},
                       {o: IcpModel(m["points"], m["normals"] if params.point_to_plane else None)
                        for o, m in models.items()} if params.icp else {},
                       {o: diameters[o] for o in objects}, params, key,
                       verify, fine, {o: turns[o] for o in objects if turns and o in turns}, scene_device,
                       verify_many)
    image_time: dict[int, float] = {}
    rows: list[dict[str, Any]] = []
    done = mapper.map(_refine_one, [g.to_dict("records") for g in groups], work, progress)
    for g, (mine, dt) in zip(groups, done):
        rows += mine
        im_id = int(g.im_id.iloc[0])
        image_time[im_id] = image_time.get(im_id, 0.0) + dt
    hyps = pd.DataFrame(rows, columns=HYPOTHESIS_COLUMNS[:-1])
    best = [min(g.index, key=lambda i: hypothesis_rank(g.at[i, key], g.at[i, "evidence"], g.at[i, "hyp"]))
            for _, g in hyps.groupby("cand_id", sort=False)]
    hyps["chosen"] = hyps.index.isin(best)
    cands = hyps[hyps.chosen].sort_values("cand_id").reset_index(drop=True)
    cand_time = hyps.groupby("cand_id").time_s.sum()
    cands = cands.assign(time_s=cands.cand_id.map(cand_time).astype(float), fine_icp=False)
    if fine is not None:
        chosen = [cands.loc[i, ["cand_id", "im_id", "obj_id", "R", "t", "evidence", "verification"]].to_dict()
                  for i in cands.index]
        fined = mapper.map(_fine_one, chosen, work)
        for i, (update, dt) in zip(cands.index, fined):
            for k, v in update.items():
                cands.at[i, k] = v
            cands.at[i, "time_s"] += dt
            im_id = int(cands.at[i, "im_id"])
            image_time[im_id] = image_time.get(im_id, 0.0) + dt
    return hyps, cands[CANDIDATE_COLUMNS], image_time


def hypothesis_rank(value: float, evidence: float, hyp: int) -> tuple:
    """Sort key of a candidate's hypotheses, best first: the ranking value (higher first),
    then the evidence (higher first), each NaN after every number, then ``hyp``. The one
    order of :meth:`_RefineWork.best_of` (whose best the turns start from) and of the
    candidate's final choice."""
    v, e = float(value), float(evidence)
    return (math.isnan(v), 0.0 if math.isnan(v) else -v, math.isnan(e), 0.0 if math.isnan(e) else -e, int(hyp))


def icp_options(params: RefineParams, quick: bool) -> dict[str, Any]:
    """refine's ICP keyword arguments (:func:`pipeline.method.refinement.icp.refine_icp`)
    from its parameters; ``quick``: only the coarsest correspondence distance,
    :data:`QUICK_ICP_ITERATIONS` iterations (the ICP that ranks the turns)."""
    schedule = {"schedule": (1.0,), "iterations": QUICK_ICP_ITERATIONS} if quick else \
        {"iterations": params.iterations}
    return {"max_corr_dist_frac": params.max_corr_frac, "point_to_plane": params.point_to_plane, **schedule}


def kept_turns(quick: Sequence[tuple], R0: np.ndarray, t0: np.ndarray, n_turns: int, diameter: float) -> list[int]:
    """Which turns of the hypothesis ``(R0 (3, 3), t0 (3,) mm)`` refine refines and
    verifies, from their quick ICPs ``quick`` ((R, t, fitness, ...) each, in the order of
    the object's turns): the indices of up to ``n_turns`` of them, the best fitness first
    (NaN last, ties in order), each distinct from the parent and from the earlier kept
    ones by 5 degrees or 0.05 ``diameter`` (turns that slid to one pose are one
    hypothesis, as register keeps its hypotheses distinct)."""
    from pipeline.method.registration.ransac import distinct_poses

    order = np.argsort(-np.nan_to_num([q[2] for q in quick], nan=-1.0), kind="stable")
    keep = distinct_poses([(R0, t0)] + [quick[j][:2] for j in order], n_turns + 1, 5.0, 0.05 * diameter)
    return [int(order[i - 1]) for i in keep if i > 0]


@dataclass(frozen=True)
class _RefineWork:
    """What every candidate of a scene's refinement shares, and the work on one
    candidate (:func:`_refine_one`, :func:`_fine_one`): points (cand_id -> (k, 3) mm),
    models (obj_id -> :class:`pipeline.method.refinement.icp.IcpModel`, its k-d tree built once for
    every ICP on it), diameters (mm), parameters, the
    ranking column, the verifier, the fine ICP, the turns (obj_id -> (n, 4, 4)), the
    torch device of the scene side (None: numpy) and the verifier of several poses."""

    points: Mapping[int, np.ndarray]
    models: Mapping[int, Any]
    diameters: Mapping[int, float]
    params: RefineParams
    key: str
    verify: Callable[..., Any] | None
    fine: Callable[..., tuple[np.ndarray, np.ndarray] | None] | None
    turns: Mapping[int, np.ndarray]
    scene_device: str | None = None
    verify_many: Callable[..., list] | None = None

    def icp_many(self, ident: dict[str, Any], starts: Sequence[tuple[np.ndarray, np.ndarray, float]],
                 quick: bool = False) -> list[tuple]:
        """:meth:`icp` of several starts (R, t, fitness) of one candidate and object:
        one at a time in numpy, or together on ``scene_device``."""
        if self.scene_device is None or not self.params.icp or not starts:
            return [self.icp(ident, R, t, fitness, quick) for R, t, fitness in starts]
        from pipeline.method.refinement.icp_torch import refine_icp_batch

        done = refine_icp_batch(self.models[ident["obj_id"]], self.points[ident["cand_id"]],
                                np.stack([np.reshape(R, (3, 3)) for R, _, _ in starts]),
                                np.stack([np.reshape(t, 3) for _, t, _ in starts]), self.diameters[ident["obj_id"]],
                                device=self.scene_device, **icp_options(self.params, quick))
        return [(res.R, res.t, float(res.fitness), float(res.inlier_rmse)) for res in done]

    def icp(self, ident: dict[str, Any], R: np.ndarray, t: np.ndarray, fitness: float, quick: bool = False) -> tuple:
        """The hypothesis' pose and fit after ICP: (R, t, fitness, inlier_rmse mm);
        ``quick``: only the coarsest correspondence distance, :data:`QUICK_ICP_ITERATIONS`
        iterations."""
        from pipeline.method.refinement.icp import refine_icp

        if not self.params.icp:
            return R, t, fitness, float("nan")
        res = refine_icp(self.models[ident["obj_id"]], None, self.points[ident["cand_id"]], R, t,
                         self.diameters[ident["obj_id"]], **icp_options(self.params, quick))
        return res.R, res.t, float(res.fitness), float(res.inlier_rmse)

    def verified(self, ident: dict[str, Any], pose: tuple, n_inliers: int, inlier_ratio: float) -> dict[str, Any]:
        """One hypothesis after ICP (``pose``, from :meth:`icp`) and verification, as a row
        of hypotheses.parquet; ident: its cand_id, scene_id, im_id, obj_id, hyp, parent,
        source, prior_score."""
        (row,) = self.verified_many([ident], [pose], [n_inliers], [inlier_ratio])
        return row

    def verified_many(self, idents: Sequence[dict[str, Any]], poses: Sequence[tuple], n_inliers: Sequence[int],
                      inlier_ratios: Sequence[float]) -> list[dict[str, Any]]:
        """:meth:`verified` of several hypotheses of one candidate (the same cand_id,
        im_id and obj_id), in order, their renders compared in one call of
        :attr:`verify_many` where there is one (together on the scene device)."""
        from pipeline.method.refinement.selection import registration_evidence

        if not idents:
            return []
        obj_id, im_id, cand_id = idents[0]["obj_id"], idents[0]["im_id"], idents[0]["cand_id"]
        evidence = [registration_evidence(r, pose[2]) for pose, r in zip(poses, inlier_ratios)]
        checks: list = [None] * len(idents)
        if self.verify is not None and self.verify_many is not None:
            checks = self.verify_many(im_id, cand_id, obj_id, [pose[:2] for pose in poses], self.diameters[obj_id],
                                      evidence)
        elif self.verify is not None:
            checks = [self.verify(im_id, cand_id, obj_id, pose[0], pose[1], self.diameters[obj_id], e)
                      for pose, e in zip(poses, evidence)]
        rows = []
        for ident, (R, t, fitness, rmse), n, r, e, v in zip(idents, poses, n_inliers, inlier_ratios, evidence, checks):
            terms = dict.fromkeys(VERIFICATION_COLUMNS, float("nan"))
            if v is not None:
                terms = {k: getattr(v, k) for k in VERIFICATION_COLUMNS[:-1]} | {"verification": v.value}
            rows.append({**ident, "n_inliers": int(n), "inlier_ratio": float(r), "R": _flat(R, 9), "t": _flat(t, 3),
                         "fitness": fitness, "inlier_rmse": rmse, "evidence": e, **terms})
        return rows

    def best_of(self, rows: list[dict[str, Any]]) -> dict[str, Any]:
        """The first of a candidate's rows by :func:`hypothesis_rank` (the order of the
        final choice in :func:`refine_candidates`)."""
        return min(rows, key=lambda r: hypothesis_rank(r[self.key], r["evidence"], r["hyp"]))

    def turned_rows(self, parent: dict[str, Any], first_hyp: int) -> tuple[list[dict[str, Any]], float]:
        """The turns of ``parent``, each aligned by a quick ICP; the ``params.turns`` best
        by that ICP's fitness refined by the full ICP and verified, numbered from
        ``first_hyp``; and the time they took (s). (The full ICP from a turned start runs
        its whole schedule, about 7x the quick one, and a verification's render costs
        more than either: both are kept for the few turns that fit.)"""
        from pipeline.method.refinement.turns import turned

        params = self.params
        T = self.turns.get(parent["obj_id"])
        if T is None or not len(T) or self.verify is None or params.turns <= 0:
            return [], 0.0
        t0 = time.perf_counter()
        ident = {k: parent[k] for k in ("cand_id", "scene_id", "im_id", "obj_id", "prior_score")}
        ident |= {"parent": parent["hyp"], "source": "turn"}
        R0, t0_ = np.reshape(parent["R"], (3, 3)), np.asarray(parent["t"], float)
        quick = self.icp_many(ident, [(*turned(R0, t0_, Ti), float("nan")) for Ti in T], quick=True)
        best = kept_turns(quick, R0, t0_, params.turns, self.diameters[parent["obj_id"]])
        poses = self.icp_many(ident, [(*quick[j][:2], quick[j][2]) for j in best])
        rows = self.verified_many([ident | {"hyp": first_hyp + k} for k in range(len(poses))], poses,
                                  [0] * len(poses), [0.0] * len(poses))
        dt = time.perf_counter() - t0  # the quick ICPs count even when no turn is kept
        for r in rows:
            r["time_s"] = dt / len(rows)
        return rows, dt


def _refine_one(work: _RefineWork, group: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], float]:
    """One candidate's hypotheses (register's rows ``group``) after ICP and verification,
    with the turns of its best; and the candidate's time (s)."""
    mine, total = [], 0.0
    idents = [{"cand_id": int(c["cand_id"]), "scene_id": int(c["scene_id"]), "im_id": int(c["im_id"]),
               "obj_id": int(c["obj_id"]), "hyp": int(c["hyp"]), "parent": -1, "source": str(c["source"]),
               "prior_score": float(c["prior_score"])} for c in group]
    starts = [(np.asarray(c["R"], float).reshape(3, 3), np.asarray(c["t"], float), float(c["ransac_fitness"]))
              for c in group]
    if work.scene_device is not None:
        # The device path: the candidate's hypotheses aligned together, then verified
        # together; the time is shared evenly by them.
        t0 = time.perf_counter()
        poses = work.icp_many(idents[0], starts)
        mine = work.verified_many(idents, poses, [int(c["n_inliers"]) for c in group],
                                  [float(c["inlier_ratio"]) for c in group])
        total = time.perf_counter() - t0
        for row in mine:
            row["time_s"] = total / len(mine)
    else:
        for c, ident, start in zip(group, idents, starts):
            t0 = time.perf_counter()
            mine.append(work.verified(ident, work.icp(ident, *start), int(c["n_inliers"]), float(c["inlier_ratio"])))
            mine[-1]["time_s"] = dt = time.perf_counter() - t0
            total += dt
    turned, dt = work.turned_rows(work.best_of(mine), max(r["hyp"] for r in mine) + 1)
    return mine + turned, total + dt


def _fine_one(work: _RefineWork, c: dict[str, Any]) -> tuple[dict[str, Any], float]:
    """The fine ICP of a candidate's chosen pose ``c`` (cand_id, im_id, obj_id, R, t,
    evidence, verification): the columns to update (none when the fine pose is not
    kept) and its time (s, 0 for an object the fine ICP does not refine)."""
    t0 = time.perf_counter()
    obj_id, im_id, cand_id = int(c["obj_id"]), int(c["im_id"]), int(c["cand_id"])
    diameter = work.diameters[obj_id]
    pose = work.fine(im_id, cand_id, obj_id, np.reshape(c["R"], (3, 3)), np.asarray(c["t"]), diameter,
                     work.points[cand_id])
    if pose is None:  # an object the fine ICP leaves alone: no work counted
        return {}, 0.0
    R, t = pose
    update: dict[str, Any] = {}
    v = work.verify(im_id, cand_id, obj_id, R, t, diameter, float(c["evidence"])) if work.verify else None
    if v is None or v.value >= c["verification"]:
        update = {"R": _flat(R, 9), "t": _flat(t, 3), "fine_icp": True}
        if v is not None:
            update |= {k: getattr(v, k) for k in VERIFICATION_COLUMNS[:-1]} | {"verification": v.value}
    return update, time.perf_counter() - t0


def choose_estimates(refined: pd.DataFrame, targets: Sequence[Any], diameters: Mapping[int, float],
                     params: RefineParams) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Up to ``inst_count`` distinct estimates per target, ranked by ``params.select_by``
    (:func:`pipeline.method.refinement.selection.select_estimates`).

    Returns the candidates with the choice (selected, rank, note) and the kept estimates
    in the order (im_id, obj_id, rank), with ``score`` (the ranking value, written to the
    results CSV so that BOP's matching order agrees with ours) and SAR's columns unset
    (sar_variant -1).
    """
    from pipeline.method.refinement.selection import SELECT_BY_COLUMN, select_estimates

    table = select_estimates(refined, targets, dict(diameters), by=params.select_by,
                             duplicate_frac=params.duplicate_frac)
    chosen = table[table.selected].sort_values(["im_id", "obj_id", "target_rank"])
    poses = chosen.assign(score=chosen[SELECT_BY_COLUMN[params.select_by]].astype(float), sar_variant=-1, sar_reason="")
    return table, poses


def sar_transforms(estimated, declared, diameter: float, params: RefineParams) -> np.ndarray:
    """The model-frame transforms (V, 4, 4) SAR tries for an object, identity first: its
    estimated shape symmetries (continuous ones sampled every ``params.sar_step_deg``),
    without those the declared symmetries (a :class:`pipeline.method.geometry.symmetry.SymmetrySet`
    from models_info) already equate when ``params.sar_skip_declared``."""
    from pipeline.method.geometry.symmetry import distinct_under

    variants = estimated.transforms(params.sar_step_deg) if not estimated.is_trivial else [np.eye(4)]
    if params.sar_skip_declared:
        variants = distinct_under(variants, declared, max_trans_mm=max(1.0, 0.01 * diameter))
    return np.stack(variants)


def refine_by_symmetry(poses: pd.DataFrame, transforms: Mapping[int, np.ndarray], images: SceneImages, vis,
                       params: RefineParams, crop_margin: float, image_mode: str, image_time: dict[int, float],
                       progress: Callable[[int], Progress] | None = None,
                       untextured: Collection[int] = ()) -> list[dict]:
    """Symmetry-aware refinement (:func:`pipeline.method.refinement.sar.symmetry_aware_refinement`)
    of the kept estimates, in place.

    poses: :func:`choose_estimates`' estimates; transforms: per object, its
    :func:`sar_transforms`; vis: the run's visual encoder (None when SAR is off);
    crop_margin: scene_features' (SAR compares the crop the scene features came from);
    image_mode: the dataset's (grey datasets get grey renders). Updates R, t,
    sar_variant (the chosen variant, 0 = the ICP pose) and sar_reason (why SAR did not
    run) of ``poses``, and adds SAR's time to ``image_time``; returns one row per variant
    tried (:data:`SAR_COLUMNS`). progress(n) gives the callback for the n estimates SAR runs on.
    untextured: objects whose model has no texture to compare (SAR skips them: on the
    untextured YCB-V meshes it kept the ICP pose in 56 of 56 estimates, at 1.2 s per image).
    """
    from pipeline.method.refinement.sar import symmetry_aware_refinement
    from pipeline.method.render import Renderer

    if not params.sar:
        poses["sar_reason"] = "sar off"
        return []
    if vis is None or vis.dim == 0:
        poses["sar_reason"] = "no visual encoder"
        return []
    todo = [i for i in poses.index if len(transforms[int(poses.at[i, "obj_id"])]) > 1]
    poses.loc[[i for i in poses.index if i not in set(todo)], "sar_reason"] = (
        "no symmetry" + (" beyond the declared ones" if params.sar_skip_declared else ""))
    bare = [i for i in todo if int(poses.at[i, "obj_id"]) in set(untextured)]
    poses.loc[bare, "sar_reason"] = "untextured model"
    todo = [i for i in todo if i not in set(bare)]
    if not todo:
        return []
    advance = progress(len(todo)) if progress else _noop
    S = vis.input_size
    rows: list[dict] = []
    rgb: dict[int, np.ndarray] = {}
    with Renderer(S, S, znear=1.0, zfar=100000.0) as renderer:
        added: set[int] = set()
        for i in todo:
            t0 = time.perf_counter()
            obj_id, im_id, cand_id = int(poses.at[i, "obj_id"]), int(poses.at[i, "im_id"]), int(poses.at[i, "cand_id"])
            scene_id = int(poses.at[i, "scene_id"])
            if obj_id not in added:
                renderer.add_mesh(obj_id, images.mesh(obj_id))
                added.add(obj_id)
            if im_id not in rgb:
                rgb = {im_id: images.rgb(im_id)}  # estimates come sorted by image: keep one
            bbox, mask = images.candidate(cand_id)
            res = symmetry_aware_refinement(
                renderer, obj_id, vis, rgb[im_id], images.K(im_id), bbox,
                np.asarray(poses.at[i, "R"], float).reshape(3, 3), np.asarray(poses.at[i, "t"], float),
                transforms[obj_id], margin=crop_margin, min_cover=params.sar_min_cover, min_gain=params.sar_min_gain,
                centre=params.sar_centre, scene_mask=mask if params.sar_use_mask else None, image_mode=image_mode,
                coarse_deg=params.sar_coarse_deg)
            k = int(res.index)
            poses.at[i, "R"] = _flat(res.Rs[k], 9)
            poses.at[i, "t"] = _flat(res.ts[k], 3)
            poses.at[i, "sar_variant"] = k
            for v, (Rv, tv, s) in enumerate(zip(res.Rs, res.ts, res.similarities)):
                if np.isnan(s):  # left out by the coarse-to-fine search
                    continue
                rows.append({"scene_id": scene_id, "im_id": im_id, "obj_id": obj_id, "cand_id": cand_id, "variant": v,
                             "R": _flat(Rv, 9), "t": _flat(tv, 3), "similarity": float(s), "chosen": v == k})
            image_time[im_id] = image_time.get(im_id, 0.0) + time.perf_counter() - t0
            advance()
    return rows


def path_name(device: str | None) -> str:
    """How a stage's manifest names the path its numeric work took (``runtime``; not
    keyed): ``numpy``, or ``torch-<device>`` for the torch path on ``device``."""
    return "numpy" if device is None else f"torch-{device}"


def time_table(scene_id: int, image_time: Mapping[int, float]) -> pd.DataFrame:
    """``image_times.parquet``: a stage's time per image of one scene (scene_id, im_id, time_s)."""
    return pd.DataFrame([{"scene_id": scene_id, "im_id": k, "time_s": v} for k, v in sorted(image_time.items())],
                        columns=["scene_id", "im_id", "time_s"])

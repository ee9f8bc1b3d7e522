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
   and a coarse pose by RANSAC (:func:`coarse_pose`).
3. :func:`refine_candidates`: ICP of every registered candidate and its evidence (RANSAC
   inlier ratio x ICP fitness); :func:`choose_estimates`: up to ``inst_count`` distinct
   estimates per target; :func:`refine_by_symmetry`: the symmetry-aware refinement of
   those whose shape has symmetries beyond the declared ones.

Units and conventions: BOP's (mm, OpenCV camera, model-to-camera ``R``, ``t``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.config import RefineParams, RegisterParams, SceneFeaturesParams

CANDIDATE_COLUMNS = ["cand_id", "scene_id", "im_id", "obj_id", "prior_score", "n_inliers", "inlier_ratio", "R", "t",
                     "fitness", "inlier_rmse", "evidence", "time_s"]
"""Columns of refine's ``candidates.parquet`` (before the choice adds selected, rank, note)."""
POSE_COLUMNS = ["scene_id", "im_id", "obj_id", "cand_id", "R", "t", "score", "evidence", "fitness", "inlier_rmse",
                "n_inliers", "sar_variant", "sar_reason"]
"""Columns of refine's ``poses.parquet``; ``score`` is the value written to the results CSV."""
SAR_COLUMNS = ["scene_id", "im_id", "obj_id", "cand_id", "variant", "R", "t", "similarity", "chosen"]
"""Columns of refine's ``sar.parquet``: one row per symmetric variant tried."""
REGISTER_COLUMNS = ["cand_id", "scene_id", "im_id", "obj_id", "prior_score", "status", "reason", "R", "t",
                    "n_inliers", "inlier_ratio", "fitness", "n_correspondences", "time_s"]
"""Columns of register's ``candidates.parquet``."""

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
    the camera frame, outliers removed (:func:`pipeline.geometry.depth.remove_outliers`).
    Returns points (P, 3) float32 mm and their pixels (P, 2) int64 (u, v)."""
    from pipeline.geometry.depth import lift_depth, remove_outliers

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
    from pipeline.encoders.lifting import crop_and_resize, sample_features_at_pixels, square_crop_box

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
    """An object's model side ready for matching: points (N, 3) mm, fused (N, D)
    features, and the PCA basis its visual part was reduced with (None when the run has
    no visual channels)."""

    points: np.ndarray
    fused: np.ndarray
    basis: Any


def matchable_model(features: Mapping[str, np.ndarray], pca_dim: int) -> MatchableModel:
    """Fuse a model's ``features.zarr`` arrays: PCA of its visual features to ``pca_dim``
    (fitted on the model), each part L2-normalised, concatenated."""
    from pipeline.registration.fusion import apply_pca, fit_pca, fuse

    visual = features["visual"]
    basis = fit_pca(visual, n_components=pca_dim) if visual.shape[1] else None
    fused = fuse(features["geometric"], apply_pca(basis, visual) if basis is not None else None)
    return MatchableModel(points=features["points"], fused=fused, basis=basis)


def coarse_pose(model: MatchableModel, points: np.ndarray, geometric: np.ndarray, visual: np.ndarray, diameter: float,
                params: RegisterParams, seed: int):
    """Coarse model-to-camera pose of a candidate's points (k, 3) mm with their geometric
    (k, G) and visual (k, C) features: fused with the model's basis, matched, RANSAC
    (:func:`pipeline.registration.ransac.ransac_align`). Returns its ``Registration``."""
    from pipeline.registration.fusion import apply_pca, fuse
    from pipeline.registration.ransac import RansacParams, ransac_align

    fused = fuse(geometric, apply_pca(model.basis, visual) if model.basis is not None else None)
    ransac = RansacParams(inlier_frac=params.inlier_frac, max_iterations=params.max_iterations,
                          confidence=params.confidence, mutual=params.mutual)
    return ransac_align(model.points, model.fused, points, fused, diameter, params=ransac, seed=seed)


def register_candidates(candidates: pd.DataFrame, arrays: Mapping[str, np.ndarray],
                        model_of: Callable[[int], MatchableModel], diameters: Mapping[int, float],
                        params: RegisterParams, seed_of: Callable[[int], int],
                        progress: Progress = _noop) -> tuple[pd.DataFrame, dict[int, float]]:
    """Coarse poses of a scene's candidates.

    candidates: scene_features' table (cand_id, scene_id, im_id, obj_id, score, status,
    reason, n_points); arrays: its ``features.zarr`` (see :func:`pack_candidates`);
    model_of(obj_id): the object's :class:`MatchableModel`; seed_of(cand_id): the RANSAC
    seed. Returns the table (:data:`REGISTER_COLUMNS`; skipped candidates keep their
    status and reason) and the registration time per image (s).
    """
    pos = {int(c): i for i, c in enumerate(arrays["cand_id"])}
    rows = []
    image_time: dict[int, float] = {}
    for c in candidates.itertuples(index=False):
        row = {"cand_id": int(c.cand_id), "scene_id": int(c.scene_id), "im_id": int(c.im_id), "obj_id": int(c.obj_id),
               "prior_score": float(c.score), "status": c.status, "reason": c.reason}
        if c.status == "ok":
            t0 = time.perf_counter()
            i, k = pos[int(c.cand_id)], int(c.n_points)
            reg = coarse_pose(model_of(int(c.obj_id)), arrays["points"][i, :k], arrays["geometric"][i, :k],
                              arrays["visual"][i, :k], diameters[int(c.obj_id)], params, seed_of(int(c.cand_id)))
            dt = time.perf_counter() - t0
            image_time[int(c.im_id)] = image_time.get(int(c.im_id), 0.0) + dt
            row.update({"R": _flat(reg.R, 9), "t": _flat(reg.t, 3), "n_inliers": int(reg.n_inliers),
                        "inlier_ratio": float(reg.inlier_ratio), "fitness": float(reg.fitness),
                        "n_correspondences": int(reg.n_correspondences), "time_s": dt})
        rows.append(row)
        progress()
    return pd.DataFrame(rows, columns=REGISTER_COLUMNS), image_time


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


def refine_candidates(registered: pd.DataFrame, scene_points: Callable[[int], np.ndarray],
                      model_of: Callable[[int], Mapping[str, np.ndarray]], diameters: Mapping[int, float],
                      params: RefineParams, progress: Progress = _noop) -> tuple[pd.DataFrame, dict[int, float]]:
    """ICP of every registered candidate (register's rows with status ``ok``).

    scene_points(cand_id): the candidate's sampled points (k, 3) mm; model_of(obj_id):
    the model's ``points`` and ``normals`` (N, 3). With ``params.icp`` off the RANSAC
    pose and fitness are kept. Returns the table (:data:`CANDIDATE_COLUMNS`: refined R,
    t, ICP fitness and inlier_rmse (mm), the evidence
    :func:`pipeline.registration.selection.registration_evidence`) and the time per image (s).
    """
    from pipeline.geometry.icp import refine_icp
    from pipeline.registration.selection import registration_evidence

    rows = []
    image_time: dict[int, float] = {}
    for c in registered.itertuples(index=False):
        t0 = time.perf_counter()
        obj_id = int(c.obj_id)
        R, t = np.asarray(c.R, float).reshape(3, 3), np.asarray(c.t, float)
        fitness, rmse = float(c.fitness), float("nan")
        if params.icp:
            m = model_of(obj_id)
            res = refine_icp(m["points"], m["normals"], scene_points(int(c.cand_id)), R, t, diameters[obj_id],
                             max_corr_dist_frac=params.max_corr_frac, iterations=params.iterations,
                             point_to_plane=params.point_to_plane)
            R, t, fitness, rmse = res.R, res.t, float(res.fitness), float(res.inlier_rmse)
        dt = time.perf_counter() - t0
        image_time[int(c.im_id)] = image_time.get(int(c.im_id), 0.0) + dt
        rows.append({"cand_id": int(c.cand_id), "scene_id": int(c.scene_id), "im_id": int(c.im_id), "obj_id": obj_id,
                     "prior_score": float(c.prior_score), "n_inliers": int(c.n_inliers),
                     "inlier_ratio": float(c.inlier_ratio), "R": _flat(R, 9), "t": _flat(t, 3), "fitness": fitness,
                     "inlier_rmse": rmse, "evidence": registration_evidence(c.inlier_ratio, fitness), "time_s": dt})
        progress()
    return pd.DataFrame(rows, columns=CANDIDATE_COLUMNS), image_time


def choose_estimates(refined: pd.DataFrame, targets: Sequence[Any], diameters: Mapping[int, float],
                     params: RefineParams) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Up to ``inst_count`` distinct estimates per target, ranked by ``params.select_by``
    (:func:`pipeline.registration.selection.select_estimates`).

    Returns the candidates with the choice (selected, rank, note) and the kept estimates
    in the order (im_id, obj_id, rank), with ``score`` (the ranking value, written to the
    results CSV so that BOP's matching order agrees with ours) and SAR's columns unset
    (sar_variant -1).
    """
    from pipeline.registration.selection import RANK_COLUMNS, select_estimates

    table = select_estimates(refined, targets, dict(diameters), by=params.select_by,
                             duplicate_frac=params.duplicate_frac)
    chosen = table[table.selected].sort_values(["im_id", "obj_id", "rank"])
    poses = chosen.assign(score=chosen[RANK_COLUMNS[params.select_by]].astype(float), sar_variant=-1, sar_reason="")
    return table, poses


def sar_transforms(estimated, declared, diameter: float, params: RefineParams) -> np.ndarray:
    """The model-frame transforms (V, 4, 4) SAR tries for an object, identity first: its
    estimated shape symmetries (continuous ones sampled every ``params.sar_step_deg``),
    without those the declared symmetries (a :class:`pipeline.geometry.symmetry.SymmetrySet`
    from models_info) already equate when ``params.sar_skip_declared``."""
    from pipeline.geometry.symmetry import distinct_under

    variants = estimated.transforms(params.sar_step_deg) if not estimated.is_trivial else [np.eye(4)]
    if params.sar_skip_declared:
        variants = distinct_under(variants, declared, max_trans_mm=max(1.0, 0.01 * diameter))
    return np.stack(variants)


@dataclass(frozen=True)
class SarImages:
    """What SAR needs of a scene, loaded when asked: rgb(im_id) (H, W, 3) uint8, K(im_id)
    (3, 3), mesh(obj_id) (trimesh, mm), candidate(cand_id) -> (bbox (x, y, w, h) px,
    mask (H, W) bool)."""

    rgb: Callable[[int], np.ndarray]
    K: Callable[[int], np.ndarray]
    mesh: Callable[[int], Any]
    candidate: Callable[[int], tuple[tuple[float, float, float, float], np.ndarray]]


def refine_by_symmetry(poses: pd.DataFrame, transforms: Mapping[int, np.ndarray], images: SarImages, vis,
                       params: RefineParams, crop_margin: float, image_mode: str, image_time: dict[int, float],
                       progress: Callable[[int], Progress] | None = None) -> list[dict]:
    """Symmetry-aware refinement (:func:`pipeline.refinement.sar.symmetry_aware_refinement`)
    of the kept estimates, in place.

    poses: :func:`choose_estimates`' estimates; transforms: per object, its
    :func:`sar_transforms`; vis: the run's visual encoder (None when SAR is off);
    crop_margin: scene_features' (SAR compares the crop the scene features came from);
    image_mode: the dataset's (grey datasets get grey renders). Updates R, t,
    sar_variant (the chosen variant, 0 = the ICP pose) and sar_reason (why SAR did not
    run) of ``poses``, and adds SAR's time to ``image_time``; returns one row per variant
    tried (:data:`SAR_COLUMNS`). progress(n) gives the callback for the n estimates SAR runs on.
    """
    from pipeline.refinement.sar import symmetry_aware_refinement
    from pipeline.render import Renderer

    if not params.sar:
        poses["sar_reason"] = "sar off"
        return []
    if vis is None or vis.dim == 0:
        poses["sar_reason"] = "no visual encoder"
        return []
    todo = [i for i in poses.index if len(transforms[int(poses.at[i, "obj_id"])]) > 1]
    poses.loc[[i for i in poses.index if i not in set(todo)], "sar_reason"] = (
        "no symmetry" + (" beyond the declared ones" if params.sar_skip_declared else ""))
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
                centre=params.sar_centre, scene_mask=mask if params.sar_use_mask else None, image_mode=image_mode)
            k = int(res.index)
            poses.at[i, "R"] = _flat(res.Rs[k], 9)
            poses.at[i, "t"] = _flat(res.ts[k], 3)
            poses.at[i, "sar_variant"] = k
            for v, (Rv, tv, s) in enumerate(zip(res.Rs, res.ts, res.similarities)):
                rows.append({"scene_id": scene_id, "im_id": im_id, "obj_id": obj_id, "cand_id": cand_id, "variant": v,
                             "R": _flat(Rv, 9), "t": _flat(tv, 3), "similarity": float(s), "chosen": v == k})
            image_time[im_id] = image_time.get(im_id, 0.0) + time.perf_counter() - t0
            advance()
    return rows


def time_table(scene_id: int, image_time: Mapping[int, float]) -> pd.DataFrame:
    """``images.parquet``: a stage's time per image of one scene (scene_id, im_id, time_s)."""
    return pd.DataFrame([{"scene_id": scene_id, "im_id": k, "time_s": v} for k, v in sorted(image_time.items())],
                        columns=["scene_id", "im_id", "time_s"])

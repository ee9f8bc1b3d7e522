"""What each stage writes, declared once: every artifact's file name, kind and fields.

An :class:`Artifact` is one file (or folder) of an item folder: a Parquet ``table``
(columns with their dtype), a Zarr group of ``arrays`` (dtype and shape), a ``json``
document, the results ``csv`` or the ``dataset`` folder. The stage declarations
(:mod:`pipeline.workflow.stage_graph`) list them per item kind; the stages write them
through :class:`pipeline.workflow.plan.StageIO` (``w.write(name, data)`` checks the
columns or arrays against the declaration, so a declaration that is not true fails the
stage) and read them by name (``io.table(stage, name)``, ``io.arrays(stage, name)``), and
``docs/artifacts.md`` is generated from them (``scripts/update_docs.py``).

Shapes use: N model points, C candidates of a scene, M sampled points per candidate
(``scene_features.n_points``), G and V the geometric and visual feature dimensions, R
template views, S the template size (px), K objects with a PCA basis. Units: mm, px, s.
A pose is R (9 floats, row-major, model-to-camera) and t (3 floats, mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

ArtifactKind = Literal["table", "arrays", "json", "csv", "dataset"]


@dataclass(frozen=True)
class Field:
    """One column of a table, or one array of a Zarr group.

    dtype: ``int64``, ``int32``, ``float64``, ``float32``, ``bool``, ``uint8``, ``str``
    or ``list`` (of float64; a pose's R and t); shape: an array's, e.g. ``(C, M, 3)``.
    A name ending in ``*`` stands for every column with that prefix."""

    name: str
    dtype: str
    doc: str
    shape: str = ""


@dataclass(frozen=True)
class Artifact:
    """One file of an item folder: its accessor name, file name (``{results_csv}``:
    ``<method>_<dataset>-<split>.csv``, ``{dataset}``: the dataset's name), kind,
    what it holds, and its fields (tables and arrays)."""

    name: str
    file: str
    kind: ArtifactKind
    doc: str
    fields: tuple[Field, ...] = ()

    def field_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)


F = Field
_IDS = (F("cand_id", "int64", "candidate id, unique in the dataset"), F("scene_id", "int64", "BOP scene id"),
        F("im_id", "int64", "BOP image id"), F("obj_id", "int64", "BOP object id"))
_POSE = (F("R", "list", "rotation, 9 floats row-major, model-to-camera"), F("t", "list", "translation, 3 floats, mm"))
_BOX = (F("bbox_x", "float64", "box left, px"), F("bbox_y", "float64", "box top, px"),
        F("bbox_w", "float64", "box width, px"), F("bbox_h", "float64", "box height, px"),
        F("area", "int64", "mask pixels"), F("height", "int64", "image height, px"),
        F("width", "int64", "image width, px"))
_PRIOR_TAIL = (F("det_index", "int64", "position in the prior file (in the merged list when several are merged)"),
               F("prior_time", "float64", "the detector's time for the image, s"),
               F("prior_source", "str", "detector name of the file the detection came from"))
_VERIFICATION = (F("silhouette", "float64", "agreement of the rendered and the prior's silhouette"),
                 F("depth_fit", "float64", "fraction of rendered pixels whose depth agrees with the image's"),
                 F("coverage", "float64", "fraction of the prior's valid depth pixels the render covers"),
                 F("free_space", "float64", "fraction of rendered pixels not in front of observed depth"),
                 F("verification", "float64", "the verification score, the product of the terms"))
_REFINED = (*_IDS, F("hyp", "int64", "hypothesis index within the candidate"),
            F("parent", "int64", "the hypothesis a turn turned (-1: register's own)"),
            F("source", "str", "geometric, visual, fused, weighted or turn"),
            F("prior_score", "float64", "the prior's confidence"),
            F("n_inliers", "int64", "RANSAC inliers"), F("inlier_ratio", "float64", "RANSAC inliers / points"),
            *_POSE, F("fitness", "float64", "ICP fitness (RANSAC's when ICP is off)"),
            F("inlier_rmse", "float64", "ICP inlier RMSE, mm"),
            F("evidence", "float64", "RANSAC inlier ratio x fitness"), *_VERIFICATION)
_TIMES = (F("scene_id", "int64", "BOP scene id"), F("im_id", "int64", "BOP image id"),
          F("time_s", "float64", "the stage's time for the image, s"))

DATASET = Artifact("dataset", "{dataset}", "dataset", "the BOP dataset folder, with its localisation prior under "
                   "detections/")
TEMPLATES = Artifact("templates", "templates.zarr", "arrays", "object-centred template views (one chunk per view)", (
    F("rgb", "uint8", "colour (grey datasets: grey in 3 channels)", "(R, S, S, 3)"),
    F("depth", "float32", "depth, mm (0: background)", "(R, S, S)"),
    F("mask", "bool", "object pixels", "(R, S, S)"),
    F("K", "float64", "camera intrinsics", "(R, 3, 3)"),
    F("R", "float64", "rotation, model-to-camera", "(R, 3, 3)"),
    F("t", "float64", "translation, mm", "(R, 3)")))
SYMMETRIES = Artifact("symmetries", "symmetries.json", "json", "the estimated shape symmetries (BOP models_info form: "
                      "symmetries_discrete, 16 floats row-major with mm translations; symmetries_continuous, axis and "
                      "offset mm), the declared ones, n_discrete, n_continuous, threshold_mm, rejected_best_mm, "
                      "near_symmetries (T, score_mm: the turns refine tries) and seconds")
MODEL_FEATURES = Artifact("features", "features.zarr", "arrays", "features of the model's sampled surface points", (
    F("points", "float32", "surface points, model frame, mm", "(N, 3)"),
    F("normals", "float32", "unit normals", "(N, 3)"),
    F("geometric", "float32", "geometric features (multi-scale, concatenated)", "(N, G)"),
    F("visual", "float32", "template features lifted onto the points, averaged over the views that see them",
      "(N, V)"),
    F("view_count", "int32", "templates that saw the point (0: copied from the nearest seen point)", "(N,)")))
PRIOR_CANDIDATES = Artifact("prior_candidates", "prior_candidates.parquet", "table",
                            "one row per candidate mask kept from the localisation prior(s): the top_k x inst_count "
                            "most confident per target (image, object)", (
                                *_IDS, F("prior_score", "float64", "the prior's confidence"), *_BOX,
                                F("rle_counts", "list", "mask as uncompressed COCO RLE, column-major, background first"),
                                *_PRIOR_TAIL))
CANDIDATE_FEATURES = Artifact("features", "features.zarr", "arrays", "each candidate's lifted points and their "
                              "features (NaN, or -1, beyond its n_points)", (
                                  F("points", "float32", "points, camera frame, mm", "(C, M, 3)"),
                                  F("pixels", "int32", "their pixels (u, v)", "(C, M, 2)"),
                                  F("geometric", "float32", "geometric features", "(C, M, G)"),
                                  F("visual", "float32", "visual features at the pixels", "(C, M, V)"),
                                  F("n_points", "int32", "points sampled", "(C,)"),
                                  F("cand_id", "int64", "candidate ids, the rows' order", "(C,)")))
CANDIDATE_STATUS = Artifact("candidate_status", "candidate_status.parquet", "table",
                            "every candidate of the scene (item), lifted or skipped", (
                                *_IDS, F("prior_score", "float64", "the prior's confidence"), *_BOX, *_PRIOR_TAIL,
                                F("status", "str", "ok or skipped"), F("reason", "str", "why it was skipped"),
                                F("n_valid_points", "int64", "depth points under the mask after outlier removal"),
                                F("n_points", "int32", "points sampled")))
SCENE_FEATURES_TIMES = Artifact("image_times", "image_times.parquet", "table", "scene_features' time per image", (
    *_TIMES[:2], F("n_candidates", "int64", "candidates of the image"), _TIMES[2]))
COARSE_HYPOTHESES = Artifact("coarse_hypotheses", "coarse_hypotheses.parquet", "table",
                             "one row per coarse hypothesis (a skipped candidate: one row with its status and "
                             "reason)", (
                                 *_IDS, F("prior_score", "float64", "the prior's confidence"),
                                 F("status", "str", "ok or skipped"), F("reason", "str", "why it was skipped"),
                                 F("hyp", "int64", "hypothesis index within the candidate"),
                                 F("source", "str", "geometric, visual, fused or weighted matches"),
                                 F("source_rank", "int64", "rank among the hypotheses of its source (-1: a "
                                                           "skipped candidate's row)"),
                                 F("w_geometric", "float64", "the candidate's fusion weight of the geometric part"),
                                 F("w_visual", "float64", "the candidate's fusion weight of the visual part"),
                                 F("signal_geometric", "float64", "held-out signal (z-score) of the geometric part"),
                                 F("signal_visual", "float64", "held-out signal (z-score) of the visual part"),
                                 F("modalities_agree", "bool", "whether the two modalities' poses agree"),
                                 *_POSE, F("n_inliers", "int64", "RANSAC inliers"),
                                 F("inlier_ratio", "float64", "RANSAC inliers / points"),
                                 F("ransac_fitness", "float64", "RANSAC fitness"),
                                 F("n_correspondences", "int64", "feature matches RANSAC drew from"),
                                 F("time_s", "float64", "the candidate's time, s (on its first row, 0 on the others)")))
REGISTER_TIMES = Artifact("image_times", "image_times.parquet", "table", "register's time per image", _TIMES)
PCA = Artifact("pca", "pca.zarr", "arrays", "the per-object PCA bases of the visual features (empty in "
               "geometry-only runs)", (
                   F("obj_id", "int64", "objects", "(K,)"), F("mean", "float32", "feature mean", "(K, V)"),
                   F("components", "float32", "principal axes", "(K, P, V)"),
                   F("explained_variance", "float32", "their variance", "(K, P)"),
                   F("informative", "bool", "False when the visual features carried no variance", "(K,)")))
HYPOTHESES = Artifact("hypotheses", "hypotheses.parquet", "table",
                      "every hypothesis after ICP and verification (register's, and the turns of each candidate's "
                      "best)", (*_REFINED, F("time_s", "float64", "its time, s"),
                                F("chosen", "bool", "its candidate's best")))
CANDIDATE_CHOICES = Artifact("candidate_choices", "candidate_choices.parquet", "table",
                             "each registered candidate's chosen hypothesis, after the fine ICP, and the choice per "
                             "target", (*_REFINED, F("fine_icp", "bool", "whether the fine ICP's pose was kept"),
                                        F("time_s", "float64", "the candidate's time over its hypotheses, s"),
                                        F("selected", "bool", "kept as an estimate of its target"),
                                        F("target_rank", "int64", "0 = best kept of its target, -1 = not kept"),
                                        F("note", "str", "why it was not kept")))
POSES = Artifact("poses", "poses.parquet", "table", "the kept estimates, up to inst_count distinct ones per target, "
                 "ranked by refine.select_by", (
                     F("scene_id", "int64", "BOP scene id"), F("im_id", "int64", "BOP image id"),
                     F("obj_id", "int64", "BOP object id"), F("cand_id", "int64", "candidate id"),
                     F("hyp", "int64", "hypothesis index"), F("source", "str", "its hypothesis' source"), *_POSE,
                     F("score", "float64", "the ranking value (select_by), the results CSV's score"),
                     F("evidence", "float64", "RANSAC inlier ratio x fitness"),
                     F("verification", "float64", "the verification score"),
                     F("fitness", "float64", "ICP fitness (RANSAC's when ICP is off)"),
                     F("inlier_rmse", "float64", "ICP inlier RMSE, mm"), F("n_inliers", "int64", "RANSAC inliers"),
                     F("sar_variant", "int64", "SAR's chosen symmetric variant (0: the ICP pose, -1: no SAR)"),
                     F("sar_reason", "str", "why SAR did not run")))
SAR = Artifact("sar", "sar.parquet", "table", "per estimate SAR ran on, one row per symmetric variant compared", (
    F("scene_id", "int64", "BOP scene id"), F("im_id", "int64", "BOP image id"), F("obj_id", "int64", "BOP object id"),
    F("cand_id", "int64", "candidate id"), F("variant", "int64", "variant index (0: the ICP pose)"), *_POSE,
    F("similarity", "float64", "feature similarity of its render to the image"),
    F("chosen", "bool", "the variant kept")))
REFINE_TIMES = Artifact("image_times", "image_times.parquet", "table", "refine's time per image", _TIMES)
RESULTS_CSV = Artifact("results", "{results_csv}", "csv", "the BOP results CSV (scene_id, im_id, obj_id, score, R, "
                       "t, time): time per image is the prior's plus scene_features', register's and refine's")
ERRORS = Artifact("errors", "errors.parquet", "table", "one row per (evaluated estimate, ground-truth instance of its "
                  "object)", (
                      F("scene_id", "int64", "BOP scene id"), F("im_id", "int64", "BOP image id"),
                      F("obj_id", "int64", "BOP object id"), F("est_id", "int64", "the estimate's row in the CSV"),
                      F("gt_id", "int64", "ground-truth instance"), F("score", "float64", "the estimate's score"),
                      F("gt_visib_fract", "float64", "visible fraction of the instance"),
                      F("gt_valid", "bool", "whether the instance is evaluated (visible enough)"),
                      F("mssd", "float64", "MSSD, mm"), F("mspd", "float64", "MSPD, px"),
                      F("vsd_tau_*", "float64", "VSD at each misalignment tolerance tau (NaN without depth)")))
SCORES = Artifact("scores", "scores.json", "json", "``{\"summary\": ...}``: AR, AR_VSD, AR_MSSD, AR_MSPD, the "
                  "recalls, the counts (the manifest's summary)")


class ArtifactMismatch(ValueError):
    """Data written under an artifact's name does not match its declaration."""


def _columns_match(art: Artifact, columns: list[str]) -> bool:
    """Whether ``columns`` are the declared ones, in order (``prefix*``: any run of
    columns with that prefix, at least one)."""
    i = 0
    for f in art.fields:
        if f.name.endswith("*"):
            start = i
            while i < len(columns) and columns[i].startswith(f.name[:-1]):
                i += 1
            if i == start:
                return False
        elif i < len(columns) and columns[i] == f.name:
            i += 1
        else:
            return False
    return i == len(columns)


def _dtype_ok(declared: str, series) -> bool:
    import numpy as np
    import pandas as pd

    if declared in ("str", "list"):
        if series.dtype != object and not (declared == "str" and pd.api.types.is_string_dtype(series.dtype)):
            return False
        first = next((v for v in series if v is not None), None)
        if first is None:
            return True
        return isinstance(first, str) if declared == "str" else isinstance(first, (list, tuple, np.ndarray))
    return series.dtype == np.dtype(declared)


def check_table(art: Artifact, table, where: str) -> None:
    """Raise :class:`ArtifactMismatch` (naming ``where``, the file and the column) unless
    ``table`` (a DataFrame) has the declared columns, in order, of the declared dtypes (an
    empty table: the columns alone)."""
    columns = [str(c) for c in table.columns]
    if not _columns_match(art, columns):
        raise ArtifactMismatch(f"{where}: {art.file} has columns {columns}, its declaration "
                               f"(pipeline/workflow/artifact_schema.py) says {list(art.field_names())}")
    if not len(table):
        return
    by_name = {f.name: f for f in art.fields}
    for c in columns:
        f = by_name.get(c) or next(f for f in art.fields if f.name.endswith("*") and c.startswith(f.name[:-1]))
        if not _dtype_ok(f.dtype, table[c]):
            raise ArtifactMismatch(f"{where}: {art.file} column '{c}' is {table[c].dtype}, declared {f.dtype}")


def check_arrays(art: Artifact, arrays, where: str) -> None:
    """Raise :class:`ArtifactMismatch` unless ``arrays`` (name -> ndarray) are the declared
    ones, of the declared dtypes and numbers of dimensions."""
    import numpy as np

    if set(arrays) != set(art.field_names()):
        raise ArtifactMismatch(f"{where}: {art.file} has arrays {sorted(arrays)}, its declaration "
                               f"(pipeline/workflow/artifact_schema.py) says {sorted(art.field_names())}")
    for f in art.fields:
        a = np.asarray(arrays[f.name])
        ndim = len([d for d in f.shape.strip("()").split(",") if d.strip()])
        if a.dtype != np.dtype(f.dtype) or a.ndim != ndim:
            raise ArtifactMismatch(f"{where}: {art.file} array '{f.name}' is {a.dtype} with {a.ndim} dimensions, "
                                   f"declared {f.dtype} {f.shape}")

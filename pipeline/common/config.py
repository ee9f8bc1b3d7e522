"""Manifests and their schema.

Three kinds of YAML manifest live in ``manifests/``:

- ``runs/<name>.yaml``: what ``bop_all`` runs: the method name, the datasets, which
  encoder manifests to use, and the parameters of every stage.
- ``datasets/<name>.yaml``: one dataset (a synthetic preset, a semi-real or real one
  built from a sample under ``../shared``, or a BOP dataset on disk).
- ``encoders/<name>.yaml``: one encoder configuration (registry name + parameters); it
  may ``extends:`` a shared part in ``encoders/base/`` (which is not an encoder itself).

All are validated by the pydantic models below; a bad value fails with the file and
the field. Snakemake's ``--config`` may override a few top-level run keys with plain
strings (``datasets=a,b``, ``geometric_encoder=...`` or its short form ``geometric=...``,
``visual_encoder=...`` or ``visual=...``, ``weights_dir=...``, ``bop_root=...``,
``method=...``, ``prior=sam6d-fastsam[,cnos-fastsam]`` or its long form ``priors=...``,
``images_per_job=N``, ``dask_scheduler=tcp://host:8786``, ``device=auto|cpu|cuda``,
``allow_download=true``, ``run=manifests/runs/other.yaml``); ``bop_root`` defaults to ``$BOP_ROOT``. An encoder may be ``none``
(geometry-only or vision-only runs), not both.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Any, Callable, Literal, Mapping

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

PROJECT_ROOT = Path(__file__).resolve().parents[2]  # pipeline/common/config.py -> the clone
MANIFEST_DIR = PROJECT_ROOT / "manifests"


def shared_root() -> Path:
    """The folder of the real samples semi-real datasets are built from: ``$FREEZE_SHARED``,
    else ``shared/`` beside the project (``../shared``)."""
    return Path(os.environ.get("FREEZE_SHARED", PROJECT_ROOT.parent / "shared")).resolve()
DEFAULT_RUN = MANIFEST_DIR / "runs" / "default.yaml"

_NAME = re.compile(r"^[a-z0-9][a-z0-9-]*$")
_DATASET_NAME = re.compile(r"^[a-z0-9]+$")


class ManifestError(ValueError):
    """A manifest file is missing or invalid; the message names the file and field."""


class _Strict(BaseModel):
    # allow_inf_nan=False: `.inf` or `nan` for any number of any manifest (or of
    # --config) is refused with the field's name; accepted, it reached json.dumps of the
    # cache key as a ValueError traceback, or a stage as silent nonsense.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# ------------------------------------------------------------------ stage parameters


class RenderTemplatesParams(_Strict):
    n_views: int = Field(42, ge=1, description="template viewpoints on a Fibonacci sphere")
    image_size: int = Field(224, ge=32, description="square template side in px")
    fill: float = Field(0.85, gt=0, le=1, description="fraction of the side the object diameter spans")
    distance_factor: float = Field(3.0, gt=1, description="camera distance in object diameters")


class ModelFeaturesParams(_Strict):
    n_points: int = Field(5000, ge=100, description="N surface points sampled on the model")
    seed: int = 0
    batch_size: int = Field(16, ge=1, description="template crops per visual-encoder batch")


class SegmentPriorParams(_Strict):
    top_k: int = Field(3, ge=1, description="candidates kept per instance of a target (top_k * inst_count per "
                                            "(image, object)), most confident first")
    min_score: float = Field(0.0, ge=0.0, description="drop detections scoring below this")
    min_area: int = Field(64, ge=1, description="drop masks with fewer pixels")
    merge_iou: float = Field(0.5, gt=0, le=1, description="several prior files: a detection whose mask overlaps a "
                                                          "more confident one of another file by this IoU is the "
                                                          "same instance and is dropped")
    category_ids: Literal["obj_id", "index0", "index1"] = Field(
        "obj_id", description="what a detection's category_id means: the BOP obj_id (BOP's convention), or a 0-/1-based "
                              "position in the dataset's sorted object ids (some detector exports)")


class SceneFeaturesParams(_Strict):
    n_points: int = Field(1000, ge=10, description="M points sampled per candidate")
    min_points: int = Field(50, ge=3, description="candidates with fewer valid depth pixels are skipped")
    crop_margin: float = Field(0.1, ge=0.0, description="margin around the bbox, fraction of its side")
    seed: int = 0


class RegisterParams(_Strict):
    pca_dim: int = Field(64, ge=1, description="V: visual feature dims after per-object PCA")
    inlier_frac: float = Field(0.05, gt=0, description="RANSAC inlier distance, fraction of the diameter")
    max_iterations: int = Field(50000, ge=100)
    confidence: float = Field(0.999, gt=0, lt=1)
    mutual: bool = False
    seed: int = 0
    hypotheses: int = Field(3, ge=1, description="distinct coarse poses kept from each RANSAC (non-maximum "
                                                 "suppression in pose space); the paper's fusion keeps 1 when a "
                                                 "weighted hypothesis is added")
    modality_hypotheses: bool = Field(True, description="add the best poses of each modality's own matches to a "
                                                        "candidate's hypotheses")
    weighting: bool = Field(True, description="add a hypothesis from the fusion with each modality weighted by how "
                                              "far its matches agree with the referee pose beyond chance")
    signal_none: float = Field(3.0, description="agreement of a modality's matches beyond chance (z-score) up to "
                                                "which its fusion weight is 0")
    signal_full: float = Field(6.0, description="agreement beyond chance (z-score) from which a modality's fusion "
                                                "weight is 1 (linear in between)")
    nms_deg: float = Field(30.0, gt=0, description="hypotheses closer than this rotation (deg) and nms_frac "
                                                   "translation are one")
    nms_frac: float = Field(0.2, gt=0, description="translation of the pose-space suppression, fraction of the "
                                                   "diameter")

    @model_validator(mode="after")
    def _signal_order(self) -> "RegisterParams":
        if self.signal_full <= self.signal_none:
            raise ValueError(f"signal_full ({self.signal_full}) must exceed signal_none ({self.signal_none})")
        return self


RENAMED_VALUES: dict[tuple[str, str], dict[str, str]] = {("refine", "select_by"): {"score": "evidence"}}
"""(stage, parameter) -> {former value: its name now}: values renamed after caches
existed. A manifest may still give the former value; the keys hash it under the former
spelling (:data:`pipeline.workflow.stage_graph.LEGACY_KEY_SPELLING`), so the rename keeps
every key."""


class RefineParams(_Strict):
    icp: bool = Field(True, description="refine every registered candidate by ICP (False: keep the RANSAC pose)")
    max_corr_frac: float = Field(0.1, gt=0, description="largest ICP correspondence distance, fraction of the diameter")
    iterations: int = Field(30, ge=1, description="ICP iterations per threshold of the coarse-to-fine schedule")
    point_to_plane: bool = True
    select_by: Literal["verification", "evidence", "inliers", "prior", "fitness"] = Field(
        "verification", description="how a candidate's hypotheses and a target's candidates are ranked: the "
                                    "verification score (rendered depth and silhouette against the observation, "
                                    "plus the evidence), the registration evidence (RANSAC inlier ratio x ICP "
                                    "fitness), RANSAC inliers (the paper), the prior's confidence, or the ICP "
                                    "fitness alone ('score' is accepted for 'evidence', its former name)")
    turns: int = Field(3, ge=0, description="each candidate's best hypothesis is also tried turned by the object's "
                                            "near-symmetries and by quarter and half turns about the model's axes; "
                                            "each turn is aligned by a quick ICP, and this many of them, the best "
                                            "by its fitness, are refined and verified like the other hypotheses "
                                            "(0: off; needs select_by verification)")
    fine_icp_points: int = Field(2000, ge=0, description="each candidate's chosen pose is refined again by ICP on up "
                                                         "to this many of its depth points (0: off)")
    fine_icp_model_points: int = Field(20000, ge=100, description="model surface samples of the fine ICP")
    verify_tol_frac: float = Field(0.05, gt=0, description="verification: rendered and observed depths agree within "
                                                           "this fraction of the diameter")
    verify_min_tol_mm: float = Field(5.0, ge=0, description="verification: the depth tolerance is at least this "
                                                            "(sensor noise), mm")
    verify_margin: float = Field(0.25, ge=0, description="verification window: the candidate's box grown by this "
                                                         "fraction of its size on every side")
    duplicate_frac: float = Field(0.25, gt=0, description="candidates of a target whose translations are closer "
                                                          "than this fraction of the diameter are one instance")
    sar: bool = Field(True, description="symmetry-aware refinement of objects with geometric symmetries")
    sar_step_deg: float = Field(30.0, gt=0, le=180, description="sampling step of continuous symmetries for SAR")
    sar_coarse_deg: float = Field(60.0, ge=0, le=180, description="SAR searches coarse to fine: first the variants "
                                                                  "at least this far apart (deg), then those nearer "
                                                                  "than that to the two best (0: every variant)")
    sar_min_gain: float = Field(0.005, ge=0, description="SAR leaves the ICP pose unless a variant's similarity "
                                                         "beats it by more than this")
    sar_skip_declared: bool = Field(True, description="SAR does not try variants that the dataset's models_info "
                                                      "declares equivalent (BOP's metrics cannot tell them apart)")
    sar_use_mask: bool = Field(True, description="SAR compares only where the candidate's mask is (occluders "
                                                 "in front of the object stay out of the comparison)")
    sar_centre: bool = Field(True, description="subtract each feature map's mean over the object before the "
                                               "cosine (cancels the scene light's colour cast; the paper does not)")
    sar_min_cover: float = Field(0.5, gt=0, le=1, description="feature cells used by SAR: those the render covers "
                                                              "by at least this fraction")

    @field_validator("select_by", mode="before")
    @classmethod
    def _former_name(cls, v: Any) -> Any:
        return RENAMED_VALUES[("refine", "select_by")].get(v, v)


class SymmetriesParams(_Strict):
    """Parameters of the per-object symmetry estimation (pipeline/method/geometry/symmetry.py)."""

    n_points: int = Field(20000, ge=1000, description="surface samples of the model the estimation uses")
    threshold: float = Field(0.005, gt=0, description="acceptance: symmetric mean point-to-plane distance as a "
                                                       "fraction of the diameter (0.005: a turn that moves the "
                                                       "surface by less than a depth sensor resolves is a "
                                                       "symmetry, which SAR then decides by texture; 0.003 "
                                                       "missed the TYO-L basket's half turn, 0.0048 d)")
    seed: int = 0


class ScoreParams(_Strict):
    n_workers: int = Field(1, ge=1, description="worker processes for rendering VSD depth")


# A field named "register" (the stage) shadows ABCMeta.register on the class, which
# nothing here uses; instances return the field value.
warnings.filterwarnings("ignore", message='Field name "register"', category=UserWarning)


class StageParams(_Strict):
    render_templates: RenderTemplatesParams = RenderTemplatesParams()
    symmetries: SymmetriesParams = SymmetriesParams()
    model_features: ModelFeaturesParams = ModelFeaturesParams()
    segment_prior: SegmentPriorParams = SegmentPriorParams()
    scene_features: SceneFeaturesParams = SceneFeaturesParams()
    register: RegisterParams = RegisterParams()
    refine: RefineParams = RefineParams()
    score: ScoreParams = ScoreParams()


# ---------------------------------------------------------------------- manifests


class EncoderManifest(_Strict):
    """One encoder configuration: registry ``encoder`` name and its parameters."""

    encoder: str
    kind: Literal["geometric", "visual"]
    params: dict[str, Any] = {}
    description: str = ""
    paper: bool = Field(False, description="one of the encoders of the paper's configuration (GeDi + DINOv2)")
    stand_in: bool = Field(False, description="a weight-free encoder standing in for the paper's (printed at the "
                                              "start of a run and in its report)")
    download: list["WeightDownload"] = Field(
        default_factory=list, description="where `freeze weights fetch` gets the weight files this encoder loads; "
                                          "never part of a cache key")


class WeightDownload(_Strict):
    """One weight file an encoder loads, and where it is published (``freeze weights fetch``)."""

    url: str = Field(description="http(s) address of the file (or of an archive holding it)")
    file: str = Field(description="where it goes, relative to the weights folder (the path the loader looks up)")
    member: str | None = Field(None, description="the url is a zip archive: the member to extract as `file`")
    sha256: str | None = Field(None, description="expected SHA-256 of `file` (null: not pinned; the digest of the "
                                                 "first download is recorded beside the file and checked after)")
    source: Literal["official", "hf"] = Field(
        "official", description="official: the project's own release; hf: the Hugging Face copy (--source hf)")
    size: int | None = Field(None, ge=0, description="approximate size in bytes, for `freeze weights list`")
    exact_size: int | None = Field(None, ge=0, description="exact size in bytes of what `url` serves (the archive, "
                                                           "for a zip): a download of another size is refused (null: "
                                                           "not known; Content-Length and the format check apply)")

    @field_validator("url")
    @classmethod
    def _http_only(cls, value: str) -> str:
        # file:// would copy any local file into the weights folder as if downloaded (pipeline.formats.weights.fetch)
        from urllib.parse import urlsplit

        parts = urlsplit(value)
        if parts.scheme.lower() not in ("http", "https") or not parts.netloc:
            raise ValueError("must be an http(s) URL with a host (file:// and other schemes are not fetched)")
        return value


class PriorFaultRates(_Strict):
    """The rates of a real dataset's faulty prior, every one stated in its manifest
    (:class:`pipeline.evaluation.synth.detector_faults.DetectorFaults` says what each does)."""

    miss: float = Field(..., ge=0, le=1, description="probability that an instance gets no detection")
    erode: float = Field(..., ge=0, le=1, description="probability that a kept mask is eroded")
    dilate: float = Field(..., ge=0, le=1, description="probability that a kept mask is dilated")
    max_morph_px: int = Field(..., ge=1, description="erosion/dilation radius: 1 to this many px")
    occlusion_cut: float = Field(..., ge=0, le=1, description="probability that a kept mask is cut by a straight "
                                                              "occluding edge")
    cut_fraction: tuple[float, float] = Field(..., description="range of the fraction of the mask such a cut removes")
    wrong_label: float = Field(..., ge=0, le=1, description="probability that an instance is labelled as another "
                                                            "object present in the image")
    stray_per_image: float = Field(..., ge=0, description="mean number (Poisson) of detections per image of "
                                                          "objects absent from it")
    score_quality_weight: float = Field(..., ge=0, le=1, description="weight of the mask's quality (IoU) in its "
                                                                     "score; the rest is uniform noise")
    min_pixels: int = Field(60, ge=1, description="masks smaller than this are kept as they are")

    @model_validator(mode="after")
    def _consistent(self) -> "PriorFaultRates":
        lo, hi = self.cut_fraction
        if not 0.0 < lo <= hi < 1.0:
            raise ValueError(f"cut_fraction is {list(self.cut_fraction)}: 0 < low <= high < 1")
        if self.erode + self.dilate > 1.0:
            raise ValueError(f"erode + dilate is {self.erode + self.dilate}: at most 1")
        return self


class DatasetManifest(_Strict):
    """One dataset: a synthetic preset made by ``freeze synth``, a semi-real dataset built
    from a real sample (``source``, under :func:`shared_root`), a real dataset sample
    there (kind ``real``: a bop_root-style folder, copied with its shipped prior and a
    faulty prior derived from it), or a BOP dataset on disk. Synthetic, semi-real and
    real-sample datasets are built by the ``synth`` stage."""

    name: str
    kind: Literal["synthetic", "bop", "semireal", "real"]
    split: str = "test"
    split_type: str | None = None
    targets_file: str = "test_targets_bop19.json"
    vsd_delta: float = Field(15.0, gt=0, description="VSD misalignment tolerance in mm")
    # synthetic datasets
    preset: str | None = None
    seed: int = 0
    # semi-real datasets (pipeline/evaluation/synth/semireal.py)
    source: str | None = Field(None, description="the real BOP-format sample, relative to the shared folder")
    depth: Literal["rendered", "real"] = Field(
        "rendered", description="semi-real: depth rendered from the ground-truth poses through the sensor model, "
                                "or the sample's real depth")
    gt_prior: Literal["faulty", "exact"] = Field(
        "faulty", description="semi-real: prior from the ground-truth visible masks with the synthetic prior's faults, "
                              "or exact")
    # real-sample datasets (pipeline/evaluation/synth/real_sample.py); `folder` names the
    # dataset folder inside `source`
    source_prior: str | None = Field(None, description="real: the sample's exact prior, relative to source")
    prior_faults: PriorFaultRates | None = Field(None, description="real: the rates of the derived faulty prior")
    depth_scale: float | None = Field(None, gt=0, description="mm per depth unit that every scene_camera entry must "
                                                             "declare (checked; None: not checked)")
    # where the localisation prior lives; relative to the dataset root (synthetic) or
    # to bop_root (real datasets); may hold glob characters (must match one file) and
    # a "{detector}" placeholder filled from `detector` or the run's `priors`
    prior: str
    detector: str | None = Field(None, description="default detector name put in the prior's {detector} placeholder")
    # real datasets: folder name under bop_root, and what differs between them
    folder: str | None = None
    obj_ids: list[int] | None = Field(None, description="the dataset's object ids (BOP dataset_params)")
    models: str = Field("models", description="model folder used for onboarding (T-LESS: models_cad); scores "
                                              "always use models_eval, as BOP does")
    camera_file: str | None = Field(None, description="camera file when it is not camera[_<split_type>].json "
                                                      "(YCB-V: camera_uw.json)")
    image_dir: Literal["rgb", "gray"] = Field("rgb", description="image folder of the split; 'gray' datasets get "
                                                                 "grey templates and grey SAR renders")
    image_ext: str = Field(".png", description="extension of the images")
    depth_ext: str = Field(".png", description="extension of the depth images")
    image_size: tuple[int, int] | None = Field(None, description="test image (width, height) in px")
    public_gt: bool = Field(True, description="false when the test ground truth is private (ITODD, HB): the "
                                              "results CSV is made for the BOP server and no AR is computed here")

    @property
    def image_mode(self) -> str:
        """"gray" or "rgb": how templates and SAR renders are coloured to look like the images."""
        return "gray" if self.image_dir == "gray" else "rgb"

    def prior_patterns(self, priors: list[str] | None = None) -> list[str]:
        """The prior file patterns of this dataset for a run's ``priors`` (None: the
        dataset's default). An entry with a '/' or ending in '.json' is a path pattern
        itself, in which ``{dataset}`` stands for the dataset's name; any other is a
        detector name put in the ``{detector}`` placeholder."""
        out = []
        for entry in priors or [self.detector or ""]:
            if "/" in entry or entry.endswith(".json"):
                out.append(entry.replace("{dataset}", self.name))
            elif "{detector}" in self.prior:
                if not entry:
                    raise ManifestError(f"dataset '{self.name}': field 'prior' has a {{detector}} placeholder "
                                        "but no field 'detector' and the run names no priors")
                out.append(self.prior.replace("{detector}", entry))
            elif entry and entry != self.detector:
                raise ManifestError(f"dataset '{self.name}': prior '{entry}' asked for, but its field 'prior' "
                                    f"({self.prior}) has no {{detector}} placeholder; give a path instead")
            else:
                out.append(self.prior)
        return out

    @field_validator("name")
    @classmethod
    def _name_ok(cls, v: str) -> str:
        if not _DATASET_NAME.match(v):
            raise ValueError("dataset names are lowercase letters and digits only (BOP file names split on '_' and '-')")
        return v


NO_ENCODER = "none"


def _is_none(name: str, kind: str) -> bool:
    return name in (NO_ENCODER, f"{NO_ENCODER}-{kind}")


def encoder_manifest_name(name: str, kind: str) -> str:
    """The encoder manifest a run's ``name`` refers to: ``none`` is short for
    ``none-geometric`` / ``none-visual``."""
    return f"{NO_ENCODER}-{kind}" if name == NO_ENCODER else name


class RunManifest(_Strict):
    """What ``bop_all`` runs."""

    method: str = "freeze"
    datasets: list[str]
    geometric_encoder: str = "fpfh"
    visual_encoder: str = "colortex"
    bop_root: str | None = None
    priors: list[str] | None = Field(
        None, description="localisation priors to use instead of each dataset's default: detector names (filled "
                          "into the dataset's prior pattern, e.g. sam6d-fastsam) or path patterns relative to "
                          "bop_root; several are merged (see segment_prior.merge_iou)")
    weights_dir: str | None = Field(
        None, description="folder of encoder weights (default $FREEZE_WEIGHTS or <project>/weights); "
                          "not part of any cache key: the encoders key on weight checksums")
    images_per_job: int = Field(
        0, ge=0, description="scene-side jobs (scene_features, register, refine) cover at most this many of a "
                             "scene's target images each, so that a scene of many images spreads over many jobs "
                             "(0: one job per scene); the results do not depend on it, nor does any cache key")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="where torch runs (DINOv2, GeDi, SAR's encoder passes): auto picks cuda when present; "
                            "the precision follows the device (bf16 where the hardware has it); keys change only "
                            "where outputs do (the precision is keyed, the device recorded)")
    allow_download: bool = Field(
        False, description="let a missing DINOv2 load from the Hugging Face hub through transformers, cached in "
                           "the weights folder (default: offline; `freeze weights fetch` is the explicit way)")
    dask_scheduler: str | None = Field(
        None, description="address of a running dask.distributed scheduler (tcp://host:8786) that register, "
                          "refine and score send their per-candidate and per-image work to (default "
                          "$DASK_SCHEDULER_ADDRESS, else the job's own process); the results do not depend on it, "
                          "nor does any cache key")
    stages: StageParams = StageParams()

    @model_validator(mode="after")
    def _one_encoder_at_least(self) -> "RunManifest":
        if _is_none(self.geometric_encoder, "geometric") and _is_none(self.visual_encoder, "visual"):
            raise ValueError("geometric_encoder and visual_encoder are both 'none': nothing left to match")
        return self

    @field_validator("method")
    @classmethod
    def _method_ok(cls, v: str) -> str:
        if not _NAME.match(v):
            raise ValueError("method names are lowercase letters, digits and '-' (no '_': BOP result names split on it)")
        return v


def _read_yaml(path: Path) -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise ManifestError(f"{path}: manifest not found")
    try:
        with open(path) as f:
            data = yaml.safe_load(f)
    except yaml.YAMLError as e:
        raise ManifestError(f"{path}: not valid YAML: {_yaml_reason(e)}") from None
    if not isinstance(data, dict):
        raise ManifestError(f"{path}: expected a mapping at the top level")
    return data


def _shown(value: Any, limit: int = 60) -> str:
    """``repr(value)`` on one line, cut to about ``limit`` characters (for messages)."""
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _yaml_reason(e: yaml.YAMLError) -> str:
    """PyYAML's error on one line: what is wrong and where (line, column; 1-based)."""
    mark = getattr(e, "problem_mark", None)
    problem = getattr(e, "problem", None)
    if problem is None:
        return " ".join(str(e).split())
    context = getattr(e, "context", None)
    where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
    return f"{context + ': ' if context else ''}{problem}{where}"


def _validate(model: type[BaseModel], data: Mapping[str, Any], source: str,
              origins: Mapping[tuple[str, ...], str] | None = None):
    """``model`` validated from ``data``, else ``ManifestError`` on one line: per bad
    field, where it came from (``source``, the manifest file, or the ``origins`` entry of
    the field or of a mapping above it: the ``--config key=value`` that set it), the
    field, what is expected and the value given."""
    try:
        return model.model_validate(dict(data))
    except ValidationError as e:
        parts = []
        for err in e.errors():
            loc = tuple(str(p) for p in err["loc"])
            where = next((origins[loc[:n]] for n in range(len(loc), 0, -1) if origins and loc[:n] in origins), source)
            value = err.get("input")
            got = f", got {_shown(value)}" if loc and isinstance(value, (str, int, float, bool, type(None))) else ""
            field = ".".join(loc) or "(top level)"
            parts.append(f"{where}: field '{field}': {err['msg']}{got}")
        raise ManifestError("; ".join(parts)) from None


def encoder_manifest_names(manifest_dir: Path = MANIFEST_DIR) -> list[str]:
    """The names of the encoder manifests, ``<manifest_dir>/encoders/<name>.yaml``, sorted.
    The shared parts they extend (``encoders/base/*.yaml``) are not encoders and not listed."""
    return sorted(p.stem for p in (Path(manifest_dir) / "encoders").glob("*.yaml"))


def load_encoder_manifest(name: str, manifest_dir: Path = MANIFEST_DIR) -> EncoderManifest:
    """The encoder manifest ``<manifest_dir>/encoders/<name>.yaml``, with ``extends:
    OTHER.yaml`` (relative to the file, e.g. ``base/dinov2.yaml``) resolved as for run
    manifests: the other manifest, with this file's keys merged over it."""
    path = Path(manifest_dir) / "encoders" / f"{name}.yaml"
    if not path.exists():
        known = encoder_manifest_names(manifest_dir)
        raise ManifestError(f"{path}: no encoder manifest named '{name}' (known: {', '.join(known)})")
    return _validate(EncoderManifest, _read_encoder_yaml(path), str(path))


def is_manifest_path(entry: str) -> bool:
    """Whether a run's dataset entry is a manifest file (``.../name.yaml``) rather than a
    name in ``manifests/datasets/``."""
    return str(entry).endswith((".yaml", ".yml"))


def load_dataset_manifest(name: str, manifest_dir: Path = MANIFEST_DIR) -> DatasetManifest:
    """The dataset manifest ``manifests/datasets/<name>.yaml``, or the file ``name`` when
    it is a path ending in ``.yaml`` (e.g. the one ``freeze estimate`` writes)."""
    if is_manifest_path(name):
        path = Path(name)
        if not path.exists():
            raise ManifestError(f"{path}: dataset manifest not found")
    else:
        path = Path(manifest_dir) / "datasets" / f"{name}.yaml"
        if not path.exists():
            known = sorted(p.stem for p in (Path(manifest_dir) / "datasets").glob("*.yaml"))
            raise ManifestError(f"{path}: no dataset manifest named '{name}' (known: {', '.join(known)})")
    ds = _validate(DatasetManifest, _read_yaml(path), str(path))
    if not is_manifest_path(name) and ds.name != name:
        raise ManifestError(f"{path}: field 'name' is '{ds.name}' but the file is named '{name}'")
    if ds.kind == "synthetic" and not ds.preset:
        raise ManifestError(f"{path}: field 'preset' is required for synthetic datasets")
    if ds.kind in ("semireal", "real") and not ds.source:
        raise ManifestError(f"{path}: field 'source' is required for {ds.kind} datasets")
    if ds.kind == "real":
        for name_ in ("folder", "source_prior", "prior_faults"):
            if getattr(ds, name_) is None:
                raise ManifestError(f"{path}: field '{name_}' is required for real datasets")
    return ds


# Flat keys that `snakemake --config key=value` may set.
_OVERRIDES = ("datasets", "geometric_encoder", "visual_encoder", "bop_root", "weights_dir", "method", "priors",
              "images_per_job", "dask_scheduler", "device", "allow_download")
# Short forms accepted on the command line.
_ALIASES = {"geometric": "geometric_encoder", "visual": "visual_encoder", "prior": "priors"}


def _deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


def _read_run_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A run manifest's mapping, with ``extends: OTHER.yaml`` (relative to the file)
    resolved: the other manifest, with this file's keys merged over it (nested
    mappings such as ``stages.refine`` merge key by key).

    Any unreadable file (a folder, not UTF-8 text, YAML nested too deeply for the parser)
    raises ``ManifestError`` naming it; so does a ``bop_root`` that is not a path
    string, which ``load_run`` turns into an absolute path before validation.
    """
    data = _read_extending_yaml(path, seen, _read_run_yaml)
    root = data.get("bop_root")
    if root is not None and not (isinstance(root, str) and "\0" not in root):
        raise ManifestError(f"{path}: field 'bop_root': expected a folder path, got {root!r:.80}")
    return data


def _read_encoder_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """An encoder manifest's mapping, with ``extends: OTHER.yaml`` resolved as for run
    manifests (:func:`_read_extending_yaml`): ``manifests/encoders/dinov2-*.yaml``
    extend ``base/dinov2.yaml``."""
    return _read_extending_yaml(path, seen, _read_encoder_yaml)


def _read_extending_yaml(path: Path, seen: tuple[Path, ...],
                         read_base: Callable[[Path, tuple[Path, ...]], dict[str, Any]]) -> dict[str, Any]:
    """The mapping of the manifest ``path``, with ``extends: OTHER.yaml`` (relative to
    the file) resolved: ``read_base(OTHER, seen)`` (the same reader, so that chains
    resolve), with this file's keys merged over it by :func:`_deep_merge` (nested
    mappings merge key by key; lists and scalars are replaced). ``seen``: the files
    extending this one, to refuse a cycle.

    Any unreadable file (a folder, not UTF-8 text, YAML nested too deeply for the parser)
    raises ``ManifestError`` naming it.
    """
    try:
        data = _read_yaml(path)
    except UnicodeDecodeError as e:
        raise ManifestError(f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x})") from None
    except RecursionError:  # PyYAML's composer recurses once per nesting level
        raise ManifestError(f"{path}: not valid YAML: nested too deeply") from None
    except ManifestError:
        raise
    except ValueError as e:  # PyYAML's int(): more digits than sys.get_int_max_str_digits()
        reason = ("an integer has more digits than Python reads (4300)" if "integer string conversion" in str(e)
                  else " ".join(str(e).split())[:100])
        raise ManifestError(f"{path}: not valid YAML: {reason}") from None
    except IsADirectoryError:
        raise ManifestError(f"{path}: is a directory, not a manifest file") from None
    except OSError as e:
        raise ManifestError(f"{path}: cannot read the manifest: {e.strerror or e}") from None
    parent = data.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str) or not parent.strip() or "\0" in parent:
            raise ManifestError(f"{path}: field 'extends': expected a manifest file name, got {parent!r:.80}")
        base_path = (path.parent / parent).resolve()
        if base_path in seen or base_path == path.resolve():
            raise ManifestError(f"{path}: field 'extends' makes a cycle through {base_path}")
        if base_path.is_dir():
            raise ManifestError(f"{path}: field 'extends': {base_path} is a directory, not a manifest file")
        data = _deep_merge(read_base(base_path, seen + (path.resolve(),)), data)
    return data


def known_config_keys() -> list[str]:
    """The keys ``--config`` accepts (Snakemake's and ``freeze``'s): ``run``, the run
    manifest's top-level keys and their short forms."""
    return sorted({"run", *_OVERRIDES, *_ALIASES, *RunManifest.model_fields})


def _refuse_unknown_keys(config: Mapping[str, Any]) -> None:
    """Raise :class:`ManifestError` naming every key of ``config`` that nothing reads,
    with the known keys and the closest one: a typo (``visaul=none``) must not run the
    default configuration quietly."""
    import difflib

    known = known_config_keys()
    unknown = [k for k in config if k not in known]
    if not unknown:
        return
    stage_param = next((k for k in unknown if "." in str(k) and str(k).split(".")[0] in (*StageParams.model_fields,
                                                                                         "stages")), None)
    if stage_param is not None:  # a stage parameter where only flat keys go (what freeze estimate's -c takes)
        raise ManifestError(f"config: '{stage_param}' is a stage parameter: only `freeze estimate -c` takes those; a "
                            "run, plan or stage reads them from a run manifest: run=FILE, whose 'extends:' names "
                            "manifests/runs/default.yaml (relative to FILE), with the parameter under 'stages:'")
    hints = []
    for k in unknown:
        close = difflib.get_close_matches(str(k), known, n=1, cutoff=0.6)
        hints.append(f"'{k}'" + (f" (did you mean '{close[0]}'?)" if close else ""))
    raise ManifestError(f"config: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(hints)}; known keys: "
                        f"{', '.join(known)} (one stage parameter: freeze ... -c register.max_iterations=20000, or a "
                        "run manifest with run=FILE)")


def load_run(config: Mapping[str, Any] | None = None, path: Path | None = None) -> RunManifest:
    """Resolve the run manifest.

    ``config`` is Snakemake's config dict (or CLI overrides): it may name another
    manifest with ``run`` and override the flat keys in ``_OVERRIDES``; any other key
    of the run manifest is taken from ``config`` as-is (so a ``configfile`` works too).
    ``bop_root`` falls back to the environment variable ``BOP_ROOT`` and is made
    absolute (stage jobs may run elsewhere).
    """
    config = dict(config or {})
    _refuse_unknown_keys(config)
    run_path = Path(config.pop("run", None) or path or DEFAULT_RUN)
    if not run_path.is_absolute() and not run_path.exists():
        run_path = PROJECT_ROOT / run_path
    data = _read_run_yaml(run_path)
    # a bad value given with --config is named as given there, not as the manifest's
    origins = {(_ALIASES.get(k, k),): f"--config {k}={_shown(v)[1:-1] if isinstance(v, str) else _shown(v)}"
               for k, v in config.items()}
    for alias, key in _ALIASES.items():
        if alias in config:
            if config.get(key) not in (None, config[alias]):
                raise ManifestError(f"config: both '{alias}' and '{key}' given, with different values")
            config[key] = config.pop(alias)
    for key, value in config.items():
        if key in _OVERRIDES and value is not None:
            if key in ("datasets", "priors") and isinstance(value, str):
                value = [v for v in value.split(",") if v]
            if key == "datasets":
                # manifest files: absolute, since stage jobs may run elsewhere
                value = [str(Path(v).expanduser().resolve()) if is_manifest_path(v) else v for v in value]
            if key == "weights_dir":
                # stage jobs may run elsewhere: fix a relative folder to where it was given
                value = str(Path(value).expanduser().resolve())
            data[key] = value
        elif key in data and key not in _OVERRIDES:
            data[key] = value
    if not data.get("bop_root") and os.environ.get("BOP_ROOT"):
        data["bop_root"] = os.environ["BOP_ROOT"]  # the one setting, from the environment
    if data.get("bop_root"):
        data["bop_root"] = str(Path(data["bop_root"]).expanduser().resolve())
    return _validate(RunManifest, data, str(run_path), origins)


def load_run_with_overrides(overrides: Mapping[str, Any] | None = None) -> RunManifest:
    """The run manifest with command-line overrides.

    Flat keys go to :func:`load_run` as on the Snakemake command line
    (``visual=dinov2-vits14``, ``run=manifests/runs/refine-icp.yaml``, ...). Dotted keys
    set one stage parameter: ``register.max_iterations=20000`` or
    ``stages.register.max_iterations=20000`` (string values parsed as YAML scalars).
    """
    flat, dotted = {}, {}
    for k, v in (overrides or {}).items():
        (dotted if "." in k else flat)[k] = v
    run = load_run(flat)
    if not dotted:
        return run
    data = run.model_dump()
    origins: dict[tuple[str, ...], str] = {}
    for k, v in dotted.items():
        path = k.split(".")
        if path[0] != "stages":
            path = ["stages"] + path
        node = data
        for p in path[:-1]:
            if not isinstance(node, dict) or p not in node:
                raise ManifestError(f"--config {k}: unknown key '{p}' (stages: {', '.join(data['stages'])})")
            node = node[p]
        if path[-1] not in node:
            raise ManifestError(f"--config {k}: unknown parameter '{path[-1]}' (known: {', '.join(node)})")
        node[path[-1]] = _override_value(k, v)
        origins[tuple(path)] = f"--config {k}={v}"
    return _validate(RunManifest, data, "--config", origins)


def _override_value(key: str, value: Any) -> Any:
    """The value of a ``--config key=value`` stage parameter: a string is read as one
    YAML value (``20000``, ``true``, ``[1, 2]``), with PyYAML's safe loader, so that
    ``!!python/...`` tags construct nothing. Malformed YAML or a tag is ``ManifestError``
    naming the key and the value; the field's own type is checked by the schema after."""
    if not isinstance(value, str):
        return value
    try:
        return yaml.safe_load(value)
    except yaml.constructor.ConstructorError as e:
        tag = f" ({e.problem.split('tag ')[-1]})" if e.problem and "tag " in e.problem else ""
        raise ManifestError(f"--config {key}={_shown(value)[1:-1]}: YAML tags{tag} are not accepted; give a plain "
                            f"{_PLAIN}") from None
    except yaml.YAMLError as e:
        reason = " ".join(str(getattr(e, "problem", None) or e).split())
        raise ManifestError(f"--config {key}={_shown(value)[1:-1]}: not a YAML value ({reason}); give a plain "
                            f"{_PLAIN}") from None
    except (ValueError, RecursionError):  # an int beyond Python's digit limit; nesting deeper than the parser
        raise ManifestError(f"--config {key}={_shown(value)[1:-1]}: not a value this parser reads; give a plain "
                            f"{_PLAIN}") from None


_PLAIN = "number, true/false, a string or a list such as [1, 2]"
"""What a --config value may be (no "[word": rich would take it for markup where printed)."""

"""The run plan: every stage's key, signature and artifact paths, known before running.

Snakemake calls :func:`plan_run` at DAG time to compute its output paths; the stage
entry points call it again to find their inputs and outputs, and check that they agree
with the path Snakemake asked for. Nothing here touches the artifacts themselves.

Item names: ``obj_000001`` (model side), ``scene_000001`` (scene side), ``all``
(dataset-wide artifacts), ``dataset`` (the synthetic dataset itself).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from pipeline import config as cfg
from pipeline.store import MANIFEST_NAME, file_sha1, make_key, make_signature

STAGES = (
    "synth",
    "render_templates",
    "symmetries",
    "model_features",
    "segment_prior",
    "scene_features",
    "register",
    "refine",
    "score",
)


def cache_root() -> Path:
    """Root of the artifact store: ``$FREEZE_CACHE`` or ``<project>/cache``."""
    return Path(os.environ.get("FREEZE_CACHE", cfg.PROJECT_ROOT / "cache")).resolve()


def obj_item(obj_id: int) -> str:
    return f"obj_{obj_id:06d}"


def scene_item(scene_id: int) -> str:
    return f"scene_{scene_id:06d}"


def parse_item(item: str) -> tuple[str, int | None]:
    """``obj_000005`` -> ("obj", 5); ``all`` -> ("all", None)."""
    if "_" in item:
        kind, num = item.split("_", 1)
        return kind, int(num)
    return item, None


def resolve_prior(base: Path, pattern: str) -> Path:
    """The prior file ``base / pattern``; ``pattern`` may hold glob characters (the BOP
    default detection files carry a suffix after ``<method>_<dataset>-test``), and must
    then match exactly one file. Raises ``ManifestError`` naming the pattern otherwise."""
    path = Path(base) / pattern
    if not any(c in pattern for c in "*?["):
        return path.resolve()
    matches = sorted(Path(base).glob(pattern))
    if len(matches) != 1:
        found = ", ".join(str(m) for m in matches) if matches else "no file"
        raise cfg.ManifestError(f"{path}: the prior pattern (field 'prior') must match exactly one file, found {found}")
    return matches[0].resolve()


def item_id(item: str, kind: str, stage: str) -> int:
    """The id in ``item`` (``obj_000005`` -> 5), checking it is of ``kind`` for ``stage``."""
    got, num = parse_item(item)
    if got != kind or num is None:
        raise ValueError(f"{stage} items are {kind}_XXXXXX, not '{item}'")
    return num


@dataclass(frozen=True)
class StagePlan:
    """Key and location of one stage's artifacts for one dataset."""

    dataset: str
    stage: str
    key: str
    signature: str
    params: dict[str, Any]
    upstream: dict[str, str]
    code_version: int
    dir: Path

    def item_dir(self, item: str) -> Path:
        return self.dir / item

    def manifest(self, item: str) -> Path:
        return self.dir / item / MANIFEST_NAME

    def publish_kwargs(self, item: str) -> dict[str, Any]:
        """Keyword arguments for :func:`pipeline.store.publish`."""
        return dict(
            stage=self.stage, item=item, key=self.key, signature=self.signature,
            params=self.params, upstream=self.upstream, code_version=self.code_version,
            dataset=self.dataset,
        )


@dataclass
class DatasetPlan:
    """All stage plans of one dataset under one run manifest."""

    run: cfg.RunManifest
    dataset: cfg.DatasetManifest
    root: Path
    obj_ids: list[int]
    scene_ids: list[int]
    stages: dict[str, StagePlan] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.dataset.name

    def __getitem__(self, stage: str) -> StagePlan:
        return self.stages[stage]

    @property
    def prior_paths(self) -> list[Path]:
        """The localisation prior files (several are merged by segment_prior)."""
        base = self.root if self.dataset.kind == "synthetic" else Path(self.run.bop_root or ".")
        return [resolve_prior(base, pattern) for pattern in self.dataset.prior_patterns(self.run.priors)]

    @property
    def prior_path(self) -> Path:
        """The prior file of a run with one prior (see ``prior_paths``)."""
        paths = self.prior_paths
        if len(paths) != 1:
            raise ValueError(f"dataset '{self.name}' merges {len(paths)} prior files; use prior_paths")
        return paths[0]

    @property
    def results_csv_name(self) -> str:
        return f"{self.run.method}_{self.name}-{self.dataset.split}.csv"

    def bop(self):
        """The dataset reader (:class:`pipeline.bop.BopDataset`)."""
        return open_bop(self.root, self.dataset)

    def model_info(self, bop, obj_id: int):
        """``bop.models_info()[obj_id]``, failing with the file and the known ids."""
        infos = bop.models_info()
        if obj_id not in infos:
            raise ValueError(f"{bop.models_info_path()}: dataset '{self.name}' has no object {obj_id} "
                           f"(objects: {', '.join(map(str, sorted(infos)))})")
        return infos[obj_id]


def _encoder_manifest(name: str, kind: str) -> cfg.EncoderManifest:
    name = cfg.encoder_manifest_name(name, kind)
    man = cfg.load_encoder_manifest(name)
    if man.kind != kind:
        raise cfg.ManifestError(f"manifests/encoders/{name}.yaml: field 'kind' is '{man.kind}', but it is used as the {kind} encoder")
    return man


def _encoder_entry(name: str, kind: str, weights_dir: str | None = None) -> dict[str, Any]:
    """Cache-relevant description of an encoder manifest: registry name, version, params."""
    from pipeline.encoders.registry import EncoderSpec, build_encoder

    man = _encoder_manifest(name, kind)
    enc = build_encoder(EncoderSpec(name=man.encoder, params=dict(man.params)), weights_dir=weights_dir)
    return {
        "manifest": cfg.encoder_manifest_name(name, kind),
        "encoder": man.encoder,
        "version": enc.version,
        "params": enc.cache_params(),
        "signature": enc.signature(),
    }


def _synthetic_layout(ds: cfg.DatasetManifest) -> tuple[list[int], list[int]]:
    from pipeline.synth import preset_layout

    return preset_layout(ds.preset, ds.seed)


def open_bop(root: Path, ds: cfg.DatasetManifest):
    """The reader (:class:`pipeline.bop.BopDataset`) of dataset ``ds`` at ``root``, with
    its manifest's split, split type, model folder and camera file."""
    from pipeline.bop import BopDataset

    return BopDataset(root, split=ds.split, split_type=ds.split_type, models_dir=ds.models, camera_file=ds.camera_file)


def detector_name(prior_file: Path) -> str:
    """The detector of a prior file: the part of its name before the first '_' (BOP's
    ``<method>_<dataset>-<split>...json``)."""
    return Path(prior_file).stem.split("_")[0]


def prior_label(paths: list[Path]) -> str:
    """Readable name of the prior files for a signature: their detector names, reduced to
    the characters signatures allow, joined by '+'."""
    return "+".join(re.sub(r"[^A-Za-z0-9.-]", "", detector_name(p)) or "prior" for p in paths)


def missing_ground_truth(bop, scene_ids) -> list[Path]:
    """The ``scene_gt.json`` files of ``scene_ids`` that the dataset (a
    :class:`pipeline.bop.BopDataset`) lacks: private test ground truth (ITODD, HB)."""
    return [bop.scene_dir(s) / "scene_gt.json" for s in scene_ids if not (bop.scene_dir(s) / "scene_gt.json").is_file()]


# Parameters added after caches existed enter a key only when they change the output,
# so that runs made before them keep their artifacts.

def _grey(ds: cfg.DatasetManifest) -> dict[str, str]:
    """``{"image_mode": "gray"}`` for grey datasets, nothing for colour ones."""
    return {"image_mode": "gray"} if ds.image_mode == "gray" else {}


def _prior_params(patterns: list[str], p: cfg.SegmentPriorParams) -> dict[str, Any]:
    """segment_prior's keyed parameters: the prior pattern(s), the selection, and the
    merge threshold and category-id mode only where they act."""
    out = {"prior": patterns[0] if len(patterns) == 1 else patterns,
           **p.model_dump(exclude={"merge_iou", "category_ids"})}
    if len(patterns) > 1:
        out["merge_iou"] = p.merge_iou
    if p.category_ids != "obj_id":
        out["category_ids"] = p.category_ids
    return out


def _bop_layout(root: Path, ds: cfg.DatasetManifest) -> tuple[list[int], list[int], str, bool]:
    """(target objects, target scenes, dataset fingerprint, whether every target scene has
    ground truth) of a BOP dataset on disk."""
    bop = open_bop(root, ds)
    targets = bop.targets(root / ds.targets_file)
    obj_ids = sorted({t.obj_id for t in targets})
    scene_ids = sorted({t.scene_id for t in targets})
    return obj_ids, scene_ids, bop.fingerprint(), not missing_ground_truth(bop, scene_ids)


class RunPlan:
    """Plans of every dataset of a run, built lazily per dataset."""

    def __init__(self, run: cfg.RunManifest, cache: Path | None = None):
        self.run = run
        self.cache = Path(cache) if cache else cache_root()
        self._plans: dict[str, DatasetPlan] = {}

    @cached_property
    def encoders(self) -> dict[str, dict[str, Any]]:
        return {
            "geometric": _encoder_entry(self.run.geometric_encoder, "geometric", self.run.weights_dir),
            "visual": _encoder_entry(self.run.visual_encoder, "visual", self.run.weights_dir),
        }

    def available(self, name: str) -> tuple[bool, str]:
        """Whether a dataset can run here, and why not."""
        ds = cfg.load_dataset_manifest(name)
        if ds.kind == "synthetic":
            return True, ""
        if not self.run.bop_root:
            return False, f"{name}: skipped, no bop_root set (--config bop_root=/path/to/bop, or $BOP_ROOT)"
        root = Path(self.run.bop_root) / (ds.folder or ds.name)
        if not (root / ds.targets_file).exists():
            return False, f"{name}: skipped, {root / ds.targets_file} not found"
        return True, ""

    def notes(self, name: str) -> list[str]:
        """Things a user should know before running dataset ``name`` with this run."""
        ds = cfg.load_dataset_manifest(name)
        out = []
        vis = self.encoders["visual"]
        if ds.image_mode == "gray" and vis["encoder"] == "colortex" and not vis["params"].get("intensity_weight"):
            out.append(f"{name}: grey images, on which the colour channels of visual encoder '{vis['manifest']}' are "
                       "all zero (geometry alone matches); --config visual=colortex-intensity adds intensity texture")
        if not ds.public_gt:
            out.append(f"{name}: the test ground truth is private, so no AR is computed here: submit "
                       f"results/{self.run.method}_{name}-{ds.split}.csv to the BOP evaluation server")
        return out

    def __getitem__(self, name: str) -> DatasetPlan:
        if name not in self._plans:
            self._plans[name] = self._plan_dataset(name)
        return self._plans[name]

    def _stage(self, ds: str, stage: str, readable: str, params: dict, upstream: dict[str, str]) -> StagePlan:
        from stages import code_version

        version = code_version(stage)
        key = make_key(stage, version, params, upstream)
        sig = make_signature(readable, key)
        return StagePlan(ds, stage, key, sig, params, upstream, version, self.cache / ds / stage / sig)

    def _plan_dataset(self, name: str) -> DatasetPlan:
        ds = cfg.load_dataset_manifest(name)
        run = self.run
        sp = run.stages
        stages: dict[str, StagePlan] = {}
        score_extra: dict[str, Any] = {}
        if ds.kind == "synthetic":
            synth = self._stage(name, "synth", f"{ds.preset}-seed{ds.seed}", {"preset": ds.preset, "seed": ds.seed}, {})
            stages["synth"] = synth
            root = synth.item_dir("dataset") / name
            obj_ids, scene_ids = _synthetic_layout(ds)
            dataset_key = synth.key
            prior_key = synth.key
        else:
            if not run.bop_root:
                raise cfg.ManifestError(f"dataset '{name}' is a BOP dataset on disk: set bop_root (--config bop_root=/path)")
            root = Path(run.bop_root).resolve() / (ds.folder or ds.name)
            obj_ids, scene_ids, dataset_key, has_gt = _bop_layout(root, ds)
            if not has_gt:  # score cannot compute AR; ground truth added later must rescore
                score_extra = {"ground_truth": False}
            prior_files = [resolve_prior(Path(run.bop_root), p) for p in ds.prior_patterns(run.priors)]
            for prior_file in prior_files:
                if not prior_file.exists():
                    raise cfg.ManifestError(f"{prior_file}: localisation prior of dataset '{name}' not found (field 'prior')")
            prior_key = "+".join(file_sha1(f) for f in prior_files)
        ds_params = {"dataset": name, "split": ds.split, "split_type": ds.split_type}
        enc = self.encoders
        geo, vis = enc["geometric"], enc["visual"]
        enc_params = {"geometric": {k: geo[k] for k in ("encoder", "version", "params")},
                      "visual": {k: vis[k] for k in ("encoder", "version", "params")}}
        enc_name = f"{geo['signature']}+{vis['signature']}"

        rt = sp.render_templates
        stages["render_templates"] = self._stage(
            name, "render_templates", f"r{rt.n_views}-s{rt.image_size}",
            {**ds_params, **rt.model_dump(), **_grey(ds)}, {"dataset": dataset_key})
        sym = sp.symmetries
        stages["symmetries"] = self._stage(
            name, "symmetries", f"so3-n{sym.n_points}",
            {**ds_params, **sym.model_dump()}, {"dataset": dataset_key})
        stages["model_features"] = self._stage(
            name, "model_features", enc_name,
            {**sp.model_features.model_dump(), "encoders": enc_params},
            {"render_templates": stages["render_templates"].key})
        stages["segment_prior"] = self._stage(
            name, "segment_prior", f"{prior_label([Path(p) for p in ds.prior_patterns(run.priors)])}-top{sp.segment_prior.top_k}",
            {**ds_params, **_prior_params(ds.prior_patterns(run.priors), sp.segment_prior),
             "targets_file": ds.targets_file},
            {"dataset": dataset_key, "prior": prior_key})
        stages["scene_features"] = self._stage(
            name, "scene_features", enc_name,
            {**sp.scene_features.model_dump(), "encoders": enc_params},
            {"segment_prior": stages["segment_prior"].key, "dataset": dataset_key})
        stages["register"] = self._stage(
            name, "register", f"{enc_name}-ransac", sp.register.model_dump(),
            {"model_features": stages["model_features"].key, "scene_features": stages["scene_features"].key})
        rf = sp.refine
        refine_name = "+".join(["icp" if rf.icp else "coarse"] + (["sar"] if rf.sar else [])) + f"-by{rf.select_by}"
        stages["refine"] = self._stage(
            name, "refine", refine_name, {"method": run.method, **rf.model_dump(), **_grey(ds)},
            {"register": stages["register"].key, "symmetries": stages["symmetries"].key})
        stages["score"] = self._stage(
            name, "score", "bop19", {"vsd_delta": ds.vsd_delta, "targets_file": ds.targets_file, **sp.score.model_dump(),
                                     **score_extra},
            {"refine": stages["refine"].key, "dataset": dataset_key})
        return DatasetPlan(run=run, dataset=ds, root=root, obj_ids=obj_ids, scene_ids=scene_ids, stages=stages)

    def to_json(self) -> str:
        """The resolved run manifest as JSON (passed to stage jobs)."""
        return json.dumps(self.run.model_dump(), sort_keys=True)


def plan_from_json(run_json: str | None = None, overrides: dict[str, Any] | None = None) -> RunPlan:
    """Rebuild the plan in a stage job from the JSON Snakemake passed (or from manifests)."""
    if run_json:
        run = cfg.RunManifest.model_validate(json.loads(run_json))
    else:
        run = cfg.load_run(overrides or {})
    return RunPlan(run)


def build_encoders(run: cfg.RunManifest):
    """Instantiate the run's (geometric, visual) encoders from their manifests."""
    from pipeline.encoders.registry import EncoderSpec, build_encoder

    out = []
    for name, kind in ((run.geometric_encoder, "geometric"), (run.visual_encoder, "visual")):
        man = _encoder_manifest(name, kind)
        out.append(build_encoder(EncoderSpec(name=man.encoder, params=dict(man.params)), weights_dir=run.weights_dir))
    return tuple(out)

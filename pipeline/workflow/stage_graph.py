"""The stage graph, declared once.

Each stage has one :class:`StageSpec`: its name, code version, the kinds of item it is
run for (one job each), what it reads and what it writes, per item kind. Everything
else is derived from these declarations:

- the cache key's upstream part (:attr:`StageSpec.keyed_by`, in :mod:`pipeline.workflow.plan`);
- the inputs of the Snakemake rules (``stage_inputs`` in the ``Snakefile``, through
  :meth:`pipeline.workflow.plan.DatasetPlan.input_manifests`);
- what a running stage may open (:class:`pipeline.workflow.plan.StageIO` refuses an undeclared
  upstream; ``tests/test_stage_graph.py`` runs every stage under an audit hook and
  fails on any file it opens outside its declared reads);
- the files a stage may publish (checked by ``StageIO.publish``);
- each stage's readable signature label and keyed parameters (:attr:`StageSpec.label`,
  :attr:`StageSpec.params`, computed from a :class:`PlanContext` by
  :meth:`pipeline.workflow.plan.RunPlan._plan_dataset`, which loops over the declarations);
- the Snakemake rules (:func:`stage_rules`: the ``Snakefile`` defines one rule per stage
  and item kind in a loop);
- the model- and scene-side stage lists of ``freeze estimate`` (:func:`stages_of_side`)
  and the stages whose per-image times the results CSV sums (:func:`stages_writing`);
- the stage table of ``docs/architecture.md`` (:mod:`pipeline.workflow.stage_docs`,
  rewritten by ``scripts/update_docs.py``, checked by ``tests/test_stage_docs.py``).

Adding a stage touches its module (``stages/<name>.py``), its declaration here (and its
parameters' model in :mod:`pipeline.common.config`, if it has any), and its tests.

Reads name upstream stages or the external inputs: ``dataset`` (the BOP dataset's own
files: models, images, camera, ground truth, targets), ``prior`` (the localisation prior
files) and ``source`` (the real sample a semi-real dataset is built from; a synthetic
dataset has none, and an external input a dataset does not have is left out of keys).

Items: ``dataset`` (the synthetic dataset itself), ``obj_XXXXXX`` (model side, one
per object), ``scene_XXXXXX`` (scene side, one per scene) and ``all`` (dataset-wide).
A stage run for an item reads these items of an upstream stage:

==============  ==================  ===============================
upstream item   reader item         items read
==============  ==================  ===============================
dataset/all     any                 that one item
obj             obj                 the same object
obj             scene, all          every object of the dataset
scene           scene               the same scene
scene           all                 every scene of the dataset
==============  ==================  ===============================

A stage with several item kinds is read by its last one (``score`` reads ``refine``'s
``all``, the results CSV); only the stage itself reads its first kind (``refine``'s
``all`` gathers its scenes).

Keys. ``keyed_by`` lists the upstream keys hashed into a stage's key. It defaults to
everything read, but may leave out an upstream that another keyed upstream already
covers (``refine`` reads ``scene_features``, which ``register``'s key covers):
:func:`check_graph` verifies that the keyed upstreams cover every read, so no input can
change without changing the key. The ``keyed_by`` sets are those the stages have had
since their artifacts were first cached, so that existing caches stay valid.

Bump a stage's ``code_version`` whenever a change alters its output: it is part of
the key, so the stage and everything downstream are rebuilt.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Literal, Mapping, NamedTuple

from pipeline.common import config as cfg
from pipeline.workflow import artifact_schema as A

if TYPE_CHECKING:
    from pipeline.common.config import DatasetManifest, RunManifest

ItemKind = Literal["dataset", "obj", "scene", "all"]
Side = Literal["model", "scene", "evaluation", "dataset"]
EXTERNAL = ("dataset", "prior", "source")
"""Inputs that are not stages: the dataset's files, the localisation prior's, and the real
sample a semi-real dataset is built from."""


class UndeclaredRead(RuntimeError):
    """A stage asked for an input its declaration does not list."""


LEGACY_KEY_SPELLING = {where: {new: old for old, new in names.items()} for where, names in cfg.RENAMED_VALUES.items()}
"""Parameter values renamed after caches existed, hashed (and shown in signatures) under
their old spelling so that the rename keeps every key: ``select_by: evidence`` was
``select_by: score`` (the run manifest accepts the old spelling too:
:data:`pipeline.common.config.RENAMED_VALUES`, the one statement of the renames)."""


def legacy_spelling(stage: str, params: dict[str, Any]) -> dict[str, Any]:
    """``params`` with renamed values put back in the spelling keys were made with
    (:data:`LEGACY_KEY_SPELLING`)."""
    out = dict(params)
    for (s, field_name), table in LEGACY_KEY_SPELLING.items():
        if s == stage and field_name in out:
            out[field_name] = table.get(out[field_name], out[field_name])
    return out


@dataclass(frozen=True)
class PlanContext:
    """What the stages' labels and keyed parameters are computed from: one dataset under
    one run (built by :meth:`pipeline.workflow.plan.RunPlan._plan_dataset`).

    ``encoder_entries`` returns :attr:`pipeline.workflow.plan.RunPlan.encoders` (called
    only by the stages that need the encoders, so that the synth stage is planned
    before they are built)."""

    run: "RunManifest"
    dataset: "DatasetManifest"
    encoder_entries: Callable[[], Mapping[str, Mapping[str, Any]]]
    ground_truth: bool = True
    """Whether every target scene has ground truth (a BOP dataset on disk may lack it)."""

    def stage_params(self, stage: str) -> dict[str, Any]:
        """The run manifest's parameters of ``stage``, in the spelling keys were made with."""
        return legacy_spelling(stage, getattr(self.run.stages, stage).model_dump())

    def has_stage_params(self, stage: str) -> bool:
        return stage in type(self.run.stages).model_fields

    @property
    def dataset_params(self) -> dict[str, Any]:
        """The dataset's name, split and split type (keyed by the stages that read it by name)."""
        ds = self.dataset
        return {"dataset": ds.name, "split": ds.split, "split_type": ds.split_type}

    @property
    def encoder_params(self) -> dict[str, dict[str, Any]]:
        """The keyed part of each encoder: registry name, version and output-relevant parameters."""
        enc = self.encoder_entries()
        return {kind: {k: enc[kind][k] for k in ("encoder", "version", "params")} for kind in ("geometric", "visual")}

    @property
    def encoder_label(self) -> str:
        """``<geometric signature>+<visual signature>``, e.g. ``fpfh-ms+colortex``."""
        enc = self.encoder_entries()
        return f"{enc['geometric']['signature']}+{enc['visual']['signature']}"

    @property
    def prior_patterns(self) -> list[str]:
        """The dataset's localisation prior file pattern(s) under the run's ``priors``."""
        return self.dataset.prior_patterns(self.run.priors)


@dataclass(frozen=True)
class StageSpec:
    """Declaration of one stage (see the module docstring).

    reads / writes: per item kind, the upstream stages (or ``dataset``, ``prior``)
    read, and the file names written into the item folder (``{results_csv}`` stands
    for ``<method>_<dataset>-<split>.csv``, ``{dataset}`` for the dataset's name).
    side: ``model`` for the per-object onboarding stages, whose ``dataset`` key may be
    the models' own fingerprint (:attr:`pipeline.workflow.plan.DatasetPlan.models_key`);
    ``scene`` for the stages that estimate poses in the images (``freeze estimate`` runs
    the model and scene sides, :func:`stages_of_side`), ``evaluation`` for scoring and
    ``dataset`` for building the dataset.
    algorithm: where the stage's method lives, one import away from the stage module
    (for its first item kind). more_algorithms: per item kind, further library functions
    its jobs call: for the first kind those called after ``algorithm``, for a later kind
    that kind's own, its main one first; a ``(role, function)`` pair is one called for a
    part of the work (``("times per image", ...)``). The docs' stage table shows them
    (:meth:`algorithms_for` gives the functions alone).
    notes: per item kind, a few words on what its job does, for the docs' stage table.
    label, params: the readable part of the stage's signature and its keyed parameters,
    each a function of the :class:`PlanContext` (default: the stage's name, and its
    parameters in the run manifest, if it has any). Parameters added after caches
    existed enter them only when they change the output, so that runs made before keep
    their artifacts.
    seed_version: the code version the stage's random draws are keyed by (default: its
    code version; :attr:`pipeline.workflow.plan.StagePlan.seed_key`). A bump that does not
    change what the stage computes (issue 29 renamed files) keeps it, so the draws, and
    the results, stay the same.
    threads, mem_mb, runtime_min: what one job needs, the Snakemake rule's ``threads``
    and ``resources: mem_mb, runtime`` (a cluster profile may raise them per rule). The
    memory is about twice the peak measured with the default encoders on the benchmarks
    (the manifests' ``peak_rss_mb``), more where the foundation encoders run. The wall
    time (minutes, what a SLURM job asks for) leaves room for a real BOP scene of a few
    hundred images in one job, or GeDi on CPU; ``images_per_job`` makes the scene-side
    jobs shorter.
    """

    name: str
    code_version: int
    items: tuple[ItemKind, ...]
    reads: Mapping[str, tuple[str, ...]]
    writes: Mapping[str, tuple[A.Artifact, ...]]
    keyed_by: tuple[str, ...]
    algorithm: str
    side: Side = "scene"
    synthetic_only: bool = False
    summary: str = ""
    module: str = field(default="")
    threads: int = 1
    mem_mb: int = 1500
    runtime_min: int = 60
    label: Callable[[PlanContext], str] | None = None
    params: Callable[[PlanContext], dict[str, Any]] | None = None
    more_algorithms: Mapping[str, tuple[str | tuple[str, str], ...]] = field(default_factory=dict)
    notes: Mapping[str, str] = field(default_factory=dict)
    seed_version: int = 0

    def __post_init__(self) -> None:
        if not self.module:
            object.__setattr__(self, "module", f"stages.{self.name}")
        if not self.seed_version:
            object.__setattr__(self, "seed_version", self.code_version)

    def reads_for(self, kind: str) -> tuple[str, ...]:
        """What the stage reads when run for an item of ``kind``."""
        if kind not in self.items:
            raise ValueError(f"stage {self.name} has no '{kind}' items (its items: {', '.join(self.items)})")
        return self.reads.get(kind, ())

    def writes_for(self, kind: str) -> tuple[str, ...]:
        """The file names the stage writes into an item folder of ``kind``."""
        return tuple(a.file for a in self.writes.get(kind, ()))

    def artifacts_for(self, kind: str) -> tuple[A.Artifact, ...]:
        """The artifacts (:class:`pipeline.workflow.artifact_schema.Artifact`) the stage
        writes into an item folder of ``kind``."""
        return tuple(self.writes.get(kind, ()))

    def artifact(self, name: str, kind: str | None = None) -> A.Artifact:
        """The artifact ``name`` written for items of ``kind`` (default: the first kind
        writing one of that name)."""
        for k in ([kind] if kind is not None else self.items):
            for a in self.writes.get(k, ()):
                if a.name == name:
                    return a
        known = sorted({a.name for k in self.items for a in self.writes.get(k, ())})
        raise KeyError(f"stage {self.name} writes no artifact '{name}' (it writes: {', '.join(known)})")

    @property
    def all_reads(self) -> set[str]:
        return {r for rs in self.reads.values() for r in rs}

    @property
    def item_kind(self) -> ItemKind:
        """The item kind of the stage's main jobs (the first declared)."""
        return self.items[0]

    def algorithms_for(self, kind: str) -> tuple[str, ...]:
        """The library functions the stage's job for an item of ``kind`` calls, its
        algorithm first (dotted names)."""
        more = tuple(a if isinstance(a, str) else a[1] for a in self.more_algorithms.get(kind, ()))
        return (self.algorithm, *more) if kind == self.items[0] else more

    def plan_label(self, ctx: PlanContext) -> str:
        """The readable part of the stage's signature for ``ctx``."""
        return self.label(ctx) if self.label is not None else self.name

    def plan_params(self, ctx: PlanContext) -> dict[str, Any]:
        """The stage's keyed parameters for ``ctx``."""
        if self.params is not None:
            return self.params(ctx)
        return ctx.stage_params(self.name) if ctx.has_stage_params(self.name) else {}


# ------------------------------------------------------ labels and keyed parameters
# One function per stage and signature part, named in its declaration below. A value
# that changes here changes the stage's key, so its artifacts and everything after them
# are rebuilt: tests/test_plan.py pins the main job's keys.

def _grey(c: PlanContext) -> dict[str, str]:
    """``{"image_mode": "gray"}`` for grey datasets, nothing for colour ones."""
    return {"image_mode": "gray"} if c.dataset.image_mode == "gray" else {}


def _look_at(c: PlanContext) -> dict[str, str]:
    """render_templates looks at each model's bounding-box centre. The synthetic objects
    are centred on it by construction (tests/test_synth.py checks it), so their
    templates are those made before this rule, under the same key; on a BOP dataset a
    model off its origin gets other templates, hence the parameter in its key."""
    return {"look_at": "bbox_centre"} if c.dataset.kind in ("bop", "real") else {}


def prior_label(paths: list[Path]) -> str:
    """Readable name of the prior files for a signature: their detector names, reduced to
    the characters signatures allow, joined by '+'."""
    import re

    from pipeline.formats.bop.detections import detector_name

    return "+".join(re.sub(r"[^A-Za-z0-9.-]", "", detector_name(p)) or "prior" for p in paths)


def _synth_label(c: PlanContext) -> str:
    ds = c.dataset
    if ds.kind == "semireal":
        return f"semireal-{ds.depth}-{ds.gt_prior}-seed{ds.seed}"
    if ds.kind == "real":
        return f"real-seed{ds.seed}"
    return f"{ds.preset}-seed{ds.seed}"


def _synth_params(c: PlanContext) -> dict[str, Any]:
    ds = c.dataset
    if ds.kind == "semireal":
        return {"builder": "semireal", "source": ds.source, "depth": ds.depth, "gt_prior": ds.gt_prior, "seed": ds.seed}
    if ds.kind == "real":
        return {"builder": "real", "source": ds.source, "folder": ds.folder, "source_prior": ds.source_prior,
                "split": ds.split, "targets_file": ds.targets_file, "camera_file": ds.camera_file,
                "depth_scale": ds.depth_scale, "prior_faults": ds.prior_faults.model_dump(), "seed": ds.seed}
    return {"preset": ds.preset, "seed": ds.seed}


def _render_templates_label(c: PlanContext) -> str:
    p = c.stage_params("render_templates")
    return f"r{p['n_views']}-s{p['image_size']}"


def _render_templates_params(c: PlanContext) -> dict[str, Any]:
    return {**c.dataset_params, **c.stage_params("render_templates"), **_grey(c), **_look_at(c)}


def _symmetries_label(c: PlanContext) -> str:
    return f"so3-n{c.stage_params('symmetries')['n_points']}"


def _symmetries_params(c: PlanContext) -> dict[str, Any]:
    return {**c.dataset_params, **c.stage_params("symmetries")}


def _encoders_label(c: PlanContext) -> str:
    return c.encoder_label


def _model_features_params(c: PlanContext) -> dict[str, Any]:
    return {**c.stage_params("model_features"), "encoders": c.encoder_params}


def _segment_prior_label(c: PlanContext) -> str:
    return f"{prior_label([Path(p) for p in c.prior_patterns])}-top{c.stage_params('segment_prior')['top_k']}"


def _segment_prior_params(c: PlanContext) -> dict[str, Any]:
    """The prior pattern(s), the selection, and the merge threshold and category-id mode
    only where they act."""
    patterns = c.prior_patterns
    p = c.stage_params("segment_prior")
    out = {"prior": patterns[0] if len(patterns) == 1 else patterns,
           **{k: v for k, v in p.items() if k not in ("merge_iou", "category_ids")}}
    if len(patterns) > 1:
        out["merge_iou"] = p["merge_iou"]
    if p["category_ids"] != "obj_id":
        out["category_ids"] = p["category_ids"]
    return {**c.dataset_params, **out, "targets_file": c.dataset.targets_file}


def _scene_features_params(c: PlanContext) -> dict[str, Any]:
    return {**c.stage_params("scene_features"), "encoders": c.encoder_params}


def _register_label(c: PlanContext) -> str:
    return f"{c.encoder_label}-ransac"


def _refine_label(c: PlanContext) -> str:
    rf = c.stage_params("refine")
    return "+".join(["icp" if rf["icp"] else "coarse"] + (["sar"] if rf["sar"] else [])) + f"-by{rf['select_by']}"


def _refine_params(c: PlanContext) -> dict[str, Any]:
    return {"method": c.run.method, **c.stage_params("refine"), **_grey(c)}


def _score_params(c: PlanContext) -> dict[str, Any]:
    # without ground truth score computes no AR; ground truth added later must rescore
    return {"vsd_delta": c.dataset.vsd_delta, "targets_file": c.dataset.targets_file, **c.stage_params("score"),
            **({} if c.ground_truth else {"ground_truth": False})}


_SPECS = (
    StageSpec(
        "synth", 1, ("dataset",), reads={"dataset": ("source",)}, writes={"dataset": (A.DATASET,)},
        keyed_by=("source",), algorithm="pipeline.evaluation.synth.build_dataset", side="dataset", synthetic_only=True,
        summary="the synthetic or semi-real BOP dataset and its prior (those datasets only)",
        threads=1, mem_mb=2000, runtime_min=30, label=_synth_label, params=_synth_params),
    StageSpec(
        "render_templates", 1, ("obj",), reads={"obj": ("dataset",)}, writes={"obj": (A.TEMPLATES,)},
        keyed_by=("dataset",), algorithm="pipeline.method.render.templates.render_object_templates", side="model",
        summary="R object-centred template views of one object",
        threads=1, mem_mb=1500, runtime_min=60, label=_render_templates_label, params=_render_templates_params),
    StageSpec(
        "symmetries", 2, ("obj",), reads={"obj": ("dataset",)}, writes={"obj": (A.SYMMETRIES,)},
        keyed_by=("dataset",), algorithm="pipeline.method.model_side.symmetry_record", side="model",
        summary="the shape symmetries of one object",
        threads=1, mem_mb=1000, runtime_min=30, label=_symmetries_label, params=_symmetries_params),
    StageSpec(
        "model_features", 1, ("obj",), reads={"obj": ("render_templates", "dataset")},
        writes={"obj": (A.MODEL_FEATURES,)}, keyed_by=("render_templates",),
        algorithm="pipeline.method.model_side.model_features", side="model",
        summary="geometric and lifted visual features of one object's sampled points",
        # One thread: a second speeds one job by only 1.4x (7.6 -> 5.5 s an object with
        # fpfh + colortex), so two jobs side by side finish the objects sooner (the main
        # job 172 -> 129 s on 2 cores, issue 31). The scene side keeps two: its time per
        # image is what the results report.
        threads=1, mem_mb=4000, runtime_min=120, label=_encoders_label, params=_model_features_params),
    StageSpec(
        "segment_prior", 4, ("all",), reads={"all": ("dataset", "prior")}, writes={"all": (A.PRIOR_CANDIDATES,)},
        keyed_by=("dataset", "prior"), algorithm="pipeline.method.segmentation.candidates_from_priors",
        summary="candidate masks of every target from the localisation prior(s)",
        threads=1, mem_mb=1000, runtime_min=30, label=_segment_prior_label, params=_segment_prior_params,
        seed_version=3),
    StageSpec(
        "scene_features", 2, ("scene",), reads={"scene": ("segment_prior", "dataset")},
        writes={"scene": (A.CANDIDATE_FEATURES, A.CANDIDATE_STATUS, A.SCENE_FEATURES_TIMES)},
        keyed_by=("segment_prior", "dataset"), algorithm="pipeline.method.estimator.Estimator.scene_features",
        summary="lifted points and features of every candidate of one scene",
        threads=2, mem_mb=4000, runtime_min=240, label=_encoders_label, params=_scene_features_params,
        seed_version=1),
    StageSpec(
        "register", 6, ("scene",), reads={"scene": ("scene_features", "model_features", "dataset")},
        writes={"scene": (A.COARSE_HYPOTHESES, A.REGISTER_TIMES, A.PCA)},
        keyed_by=("model_features", "scene_features"), algorithm="pipeline.method.estimator.Estimator.register",
        summary="coarse pose hypotheses of every candidate of one scene (RANSAC on weighted fused features and on "
                "each modality's own)",
        threads=1, mem_mb=1500, runtime_min=240, label=_register_label, seed_version=5),
    StageSpec(
        "refine", 11, ("scene", "all"),
        reads={"scene": ("register", "symmetries", "scene_features", "model_features", "segment_prior", "dataset"),
               "all": ("refine", "scene_features", "register", "segment_prior")},
        writes={"scene": (A.CANDIDATE_CHOICES, A.HYPOTHESES, A.POSES, A.SAR, A.REFINE_TIMES),
                "all": (A.RESULTS_CSV,)},
        keyed_by=("register", "symmetries"), algorithm="pipeline.method.estimator.Estimator.refine",
        more_algorithms={"scene": ("pipeline.method.estimator.Estimator.refine_by_symmetry",),
                         "all": ("pipeline.formats.bop.results.write_results_csv",
                                 ("times per image", "pipeline.formats.bop.results.image_times"))},
        notes={"all": "gathers every scene's estimates"},
        summary="ICP and verification of every hypothesis, the estimates chosen per target, SAR; item 'all': the BOP "
                "results CSV",
        threads=1, mem_mb=2000, runtime_min=240, label=_refine_label, params=_refine_params, seed_version=8),
    StageSpec(
        "score", 2, ("all",), reads={"all": ("refine", "dataset")}, writes={"all": (A.ERRORS, A.SCORES)},
        keyed_by=("refine", "dataset"), algorithm="pipeline.evaluation.metrics.score_results_file",
        side="evaluation", summary="BOP19 VSD, MSSD, MSPD and AR of the results CSV",
        threads=1, mem_mb=2000, runtime_min=120, label=lambda c: "bop19", params=_score_params),
)

STAGES: dict[str, StageSpec] = {s.name: s for s in _SPECS}
"""Every stage, in an order where each comes after the stages it reads."""


def spec(stage: str) -> StageSpec:
    if stage not in STAGES:
        raise KeyError(f"unknown stage '{stage}' (known: {', '.join(STAGES)})")
    return STAGES[stage]


def code_version(stage: str) -> int:
    return spec(stage).code_version


def run_stage(plan: Any, stage: str, item: str, progress: bool = True) -> None:
    """Run ``stage`` for ``item`` of the dataset plan ``plan`` (what ``freeze stage``,
    every Snakemake job and ``freeze estimate`` call): the ``run(plan, item)`` of the
    module its declaration names (:attr:`StageSpec.module`, ``stages/<name>.py``),
    imported by that name when it runs. The library knows a stage only by its
    declaration: no module under ``pipeline/`` imports the ``stages`` package
    (``tests/test_layers.py``)."""
    import importlib

    importlib.import_module(spec(stage).module).run(plan, item, progress=progress)


def stages_of_side(side: Side) -> tuple[str, ...]:
    """The stages of one side, in declaration order: ``model`` (render_templates,
    symmetries, model_features), ``scene`` (segment_prior, scene_features, register,
    refine), ``evaluation`` (score), ``dataset`` (synth)."""
    return tuple(name for name, s in STAGES.items() if s.side == side)


def stages_writing(artifact: str, kind: str) -> tuple[str, ...]:
    """The stages whose items of ``kind`` hold the artifact named ``artifact``, in
    declaration order: ``stages_writing("image_times", "scene")`` are those that record
    their time per image (scene_features, register, refine), which the results CSV sums."""
    return tuple(name for name, s in STAGES.items()
                 if kind in s.items and artifact in (a.name for a in s.artifacts_for(kind)))


class StageRule(NamedTuple):
    """One Snakemake rule: the jobs of ``stage`` for its items of ``kind``."""

    name: str
    stage: str
    kind: str


def rule_name(stage: str | StageSpec, kind: str) -> str:
    """The Snakemake rule running ``stage`` for items of ``kind``: the stage's name for
    its first item kind, ``<stage>_collect`` for a later ``all`` (``refine_collect``),
    ``<stage>_<kind>`` otherwise."""
    s = spec(stage) if isinstance(stage, str) else stage
    if kind not in s.items:
        raise ValueError(f"stage {s.name} has no '{kind}' items (its items: {', '.join(s.items)})")
    if kind == s.items[0]:
        return s.name
    return f"{s.name}_collect" if kind == "all" else f"{s.name}_{kind}"


def stage_rules(specs: Mapping[str, StageSpec] | None = None) -> tuple[StageRule, ...]:
    """Every stage rule of the ``Snakefile``, one per stage and item kind, in declaration
    order (the cluster profiles may name them in ``set-resources``)."""
    specs = STAGES if specs is None else specs
    return tuple(StageRule(rule_name(s, kind), name, kind) for name, s in specs.items() for kind in s.items)


def item_kind(item: str) -> str:
    """``obj_000005`` -> ``obj``, ``scene_000001`` -> ``scene``, ``all``, ``dataset``."""
    return item.split("_", 1)[0]


def upstream_items(upstream: str, reader_item: str, obj_ids: Iterable[int], scene_items: Iterable[str],
                   reader_stage: str | None = None) -> list[str]:
    """The items of stage ``upstream`` that the job of ``reader_stage`` for ``reader_item``
    reads (module docstring table); ``scene_items`` are the dataset's scene items (a
    scene, or a chunk of its images: ``scene_000002`` or ``scene_000002-001``)."""
    items = spec(upstream).items
    kind = items[0] if upstream == reader_stage else items[-1]
    reader = item_kind(reader_item)
    if kind in ("dataset", "all"):
        return [kind]
    if kind == reader:
        return [reader_item]
    if kind == "obj":
        return [f"obj_{o:06d}" for o in obj_ids]
    if kind == "scene" and reader == "all":
        return list(scene_items)
    raise ValueError(f"a {reader} item cannot read the {kind} items of stage {upstream}")


def _closure(name: str, specs: Mapping[str, StageSpec]) -> set[str]:
    """Everything the key of ``name`` covers: its keyed upstreams and, recursively, theirs."""
    out: set[str] = set()
    for u in specs[name].keyed_by:
        out.add(u)
        if u not in EXTERNAL:
            out |= _closure(u, specs)
    return out


def check_graph(specs: Mapping[str, StageSpec] = STAGES) -> None:
    """Raise ValueError unless the declarations are consistent: every read names a known
    stage declared earlier (or the stage itself for a later item kind) or an external
    input; keyed upstreams are read; and the keyed upstreams cover every read."""
    seen: set[str] = set()
    for name, s in specs.items():
        for kind in s.reads:
            if kind not in s.items:
                raise ValueError(f"stage {name}: reads declared for item kind '{kind}', which it does not have")
        for r in s.all_reads:
            if r in EXTERNAL or r in seen:
                continue
            if r == name and len(s.items) > 1:
                continue
            raise ValueError(f"stage {name}: reads '{r}', which is neither an earlier stage nor {' or '.join(EXTERNAL)}")
        missing = set(s.keyed_by) - s.all_reads
        if missing:
            raise ValueError(f"stage {name}: keyed by {sorted(missing)}, which it does not read")
        covered = _closure(name, specs) | {name}
        uncovered = s.all_reads - covered
        if uncovered:
            raise ValueError(f"stage {name}: reads {sorted(uncovered)}, which no keyed upstream covers")
        seen.add(name)


check_graph()

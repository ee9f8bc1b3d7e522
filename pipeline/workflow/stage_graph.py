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
- the files a stage may publish (checked by ``StageIO.publish``).

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
from typing import Iterable, Literal, Mapping

ItemKind = Literal["dataset", "obj", "scene", "all"]
EXTERNAL = ("dataset", "prior", "source")
"""Inputs that are not stages: the dataset's files, the localisation prior's, and the real
sample a semi-real dataset is built from."""


class UndeclaredRead(RuntimeError):
    """A stage asked for an input its declaration does not list."""


@dataclass(frozen=True)
class StageSpec:
    """Declaration of one stage (see the module docstring).

    reads / writes: per item kind, the upstream stages (or ``dataset``, ``prior``)
    read, and the file names written into the item folder (``{results_csv}`` stands
    for ``<method>_<dataset>-<split>.csv``, ``{dataset}`` for the dataset's name).
    side: ``model`` for the per-object onboarding stages, whose ``dataset`` key may be
    the models' own fingerprint (:attr:`pipeline.workflow.plan.DatasetPlan.models_key`).
    algorithm: where the stage's method lives, one import away from the stage module.
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
    writes: Mapping[str, tuple[str, ...]]
    keyed_by: tuple[str, ...]
    algorithm: str
    side: Literal["model", "scene", "dataset"] = "scene"
    synthetic_only: bool = False
    summary: str = ""
    module: str = field(default="")
    threads: int = 1
    mem_mb: int = 1500
    runtime_min: int = 60

    def __post_init__(self) -> None:
        if not self.module:
            object.__setattr__(self, "module", f"stages.{self.name}")

    def reads_for(self, kind: str) -> tuple[str, ...]:
        """What the stage reads when run for an item of ``kind``."""
        if kind not in self.items:
            raise ValueError(f"stage {self.name} has no '{kind}' items (its items: {', '.join(self.items)})")
        return self.reads.get(kind, ())

    def writes_for(self, kind: str) -> tuple[str, ...]:
        return self.writes.get(kind, ())

    @property
    def all_reads(self) -> set[str]:
        return {r for rs in self.reads.values() for r in rs}

    @property
    def item_kind(self) -> ItemKind:
        """The item kind of the stage's main jobs (the first declared)."""
        return self.items[0]


_SPECS = (
    StageSpec(
        "synth", 1, ("dataset",), reads={"dataset": ("source",)}, writes={"dataset": ("{dataset}",)},
        keyed_by=("source",), algorithm="pipeline.evaluation.synth.build_dataset", side="dataset", synthetic_only=True,
        summary="the synthetic or semi-real BOP dataset and its prior (those datasets only)",
        threads=1, mem_mb=2000, runtime_min=30),
    StageSpec(
        "render_templates", 1, ("obj",), reads={"obj": ("dataset",)}, writes={"obj": ("templates.zarr",)},
        keyed_by=("dataset",), algorithm="pipeline.method.render.templates.render_object_templates", side="model",
        summary="R object-centred template views of one object",
        threads=1, mem_mb=1500, runtime_min=60),
    StageSpec(
        "symmetries", 2, ("obj",), reads={"obj": ("dataset",)}, writes={"obj": ("symmetries.json",)},
        keyed_by=("dataset",), algorithm="pipeline.method.model_side.symmetry_record", side="model",
        summary="the shape symmetries of one object",
        threads=1, mem_mb=1000, runtime_min=30),
    StageSpec(
        "model_features", 1, ("obj",), reads={"obj": ("render_templates", "dataset")},
        writes={"obj": ("features.zarr",)}, keyed_by=("render_templates",),
        algorithm="pipeline.method.model_side.model_features", side="model",
        summary="geometric and lifted visual features of one object's sampled points",
        threads=2, mem_mb=4000, runtime_min=120),
    StageSpec(
        "segment_prior", 3, ("all",), reads={"all": ("dataset", "prior")}, writes={"all": ("candidates.parquet",)},
        keyed_by=("dataset", "prior"), algorithm="pipeline.method.segmentation.candidates_from_priors",
        summary="candidate masks of every target from the localisation prior(s)",
        threads=1, mem_mb=1000, runtime_min=30),
    StageSpec(
        "scene_features", 1, ("scene",), reads={"scene": ("segment_prior", "dataset")},
        writes={"scene": ("features.zarr", "candidates.parquet", "images.parquet")},
        keyed_by=("segment_prior", "dataset"), algorithm="pipeline.method.scene_side.scene_features",
        summary="lifted points and features of every candidate of one scene",
        threads=2, mem_mb=4000, runtime_min=240),
    StageSpec(
        "register", 5, ("scene",), reads={"scene": ("scene_features", "model_features", "dataset")},
        writes={"scene": ("candidates.parquet", "images.parquet", "pca.zarr")},
        keyed_by=("model_features", "scene_features"), algorithm="pipeline.method.scene_side.register_candidates",
        summary="coarse pose hypotheses of every candidate of one scene (RANSAC on weighted fused features and on "
                "each modality's own)",
        threads=1, mem_mb=1500, runtime_min=240),
    StageSpec(
        "refine", 8, ("scene", "all"),
        reads={"scene": ("register", "symmetries", "scene_features", "model_features", "segment_prior", "dataset"),
               "all": ("refine", "scene_features", "register", "segment_prior")},
        writes={"scene": ("candidates.parquet", "hypotheses.parquet", "poses.parquet", "sar.parquet",
                          "images.parquet"),
                "all": ("{results_csv}",)},
        keyed_by=("register", "symmetries"), algorithm="pipeline.method.scene_side.refine_candidates",
        summary="ICP and verification of every hypothesis, the estimates chosen per target, SAR; item 'all': the BOP "
                "results CSV",
        threads=1, mem_mb=2000, runtime_min=240),
    StageSpec(
        "score", 2, ("all",), reads={"all": ("refine", "dataset")}, writes={"all": ("errors.parquet", "scores.json")},
        keyed_by=("refine", "dataset"), algorithm="pipeline.evaluation.metrics.score_results_file",
        summary="BOP19 VSD, MSSD, MSPD and AR of the results CSV",
        threads=1, mem_mb=2000, runtime_min=120),
)

STAGES: dict[str, StageSpec] = {s.name: s for s in _SPECS}
"""Every stage, in an order where each comes after the stages it reads."""


def spec(stage: str) -> StageSpec:
    if stage not in STAGES:
        raise KeyError(f"unknown stage '{stage}' (known: {', '.join(STAGES)})")
    return STAGES[stage]


def code_version(stage: str) -> int:
    return spec(stage).code_version


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

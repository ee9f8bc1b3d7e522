"""The run plan: every stage's key, signature and artifact paths, known before running.

The ``Snakefile`` builds a :class:`RunPlan` at DAG time to compute its output paths; the
stage jobs build it again (:func:`plan_from_json`, from the run manifest Snakemake passes
them) to find their inputs and outputs, and check that their signature is the one
Snakemake asked for. Each stage's signature label and keyed parameters come from its
declaration (:class:`pipeline.workflow.stage_graph.StageSpec`). Nothing here touches the
artifacts themselves.

Item names: ``obj_000001`` (model side), ``scene_000001`` (scene side), ``all``
(dataset-wide artifacts), ``dataset`` (the synthetic dataset itself).
"""

from __future__ import annotations

import dataclasses
import json
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterator

from pipeline.common import config as cfg
from pipeline.workflow import stage_graph
from pipeline.workflow.stage_graph import EXTERNAL, PlanContext, UndeclaredRead, item_kind, upstream_items
from pipeline.common.store import MANIFEST_NAME, ensure_sound, file_sha1, make_key, make_signature

STAGES = tuple(stage_graph.STAGES)
"""Stage names in graph order (declared in :mod:`pipeline.workflow.stage_graph`)."""


BUILT_KINDS = ("synthetic", "semireal", "real")
"""Dataset kinds the synth stage builds (the others are BOP datasets on disk)."""


def cache_root() -> Path:
    """Root of the artifact store: ``$FREEZE_CACHE`` or ``<project>/cache``."""
    return Path(os.environ.get("FREEZE_CACHE", cfg.PROJECT_ROOT / "cache")).resolve()


def obj_item(obj_id: int) -> str:
    return f"obj_{obj_id:06d}"


def scene_item(scene_id: int, chunk: int | None = None) -> str:
    """``scene_000002``, or the chunk ``scene_000002-001`` of its images (see
    :meth:`DatasetPlan.scene_items`)."""
    return f"scene_{scene_id:06d}" if chunk is None else f"scene_{scene_id:06d}-{chunk:03d}"


def parse_item(item: str) -> tuple[str, int | None]:
    """``obj_000005`` -> ("obj", 5); ``scene_000002-001`` -> ("scene", 2); ``all`` ->
    ("all", None)."""
    if "_" in item:
        kind, num = item.split("_", 1)
        return kind, int(num.split("-", 1)[0])
    return item, None


def image_chunks(images: list[int], per_job: int) -> list[list[int]]:
    """A scene's image ids (sorted) cut into consecutive chunks of ``per_job`` (0: one
    chunk)."""
    images = sorted(images)
    if per_job <= 0 or len(images) <= per_job:
        return [images]
    return [images[i:i + per_job] for i in range(0, len(images), per_job)]


def resolve_prior(base: Path, pattern: str) -> Path:
    """The prior file ``base / pattern``; ``pattern`` may hold glob characters (the BOP
    default detection files carry a suffix after ``<method>_<dataset>-test``), and must
    then match exactly one file. Raises ``ManifestError`` naming the pattern otherwise.
    A relative pattern must stay inside ``base`` (``../../etc/passwd`` is refused); a
    file elsewhere is given by its absolute path."""
    path = Path(base) / pattern
    if not any(c in pattern for c in "*?["):
        found = path.resolve()
    else:
        matches = sorted(Path(base).glob(pattern)) if not Path(pattern).is_absolute() else \
            sorted(Path(path.anchor).glob(str(path.relative_to(path.anchor))))
        if len(matches) != 1:
            listed = ", ".join(str(m) for m in matches) if matches else "no file"
            raise cfg.ManifestError(f"{path}: the prior pattern (field 'prior') must match exactly one file, "
                                    f"found {listed}")
        found = matches[0].resolve()
    if not Path(pattern).is_absolute() and not found.is_relative_to(Path(base).resolve()):
        raise cfg.ManifestError(f"prior '{pattern}' resolves to {found}, outside bop_root {Path(base).resolve()}; "
                                "give the absolute path of a prior file kept elsewhere")
    return found


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
    seed_key: str = ""
    """What the stage's random draws come from (:meth:`StageIO.seed`): its key with the
    declaration's ``seed_version`` for the code version, and the upstreams' seed keys. A
    change that bumps the code version without changing what the stage computes (a file
    renamed) keeps every draw, hence every result."""

    def __post_init__(self) -> None:
        if not self.seed_key:
            self.seed_key = self.key

    def item_dir(self, item: str) -> Path:
        return self.dir / item

    def manifest(self, item: str) -> Path:
        return self.dir / item / MANIFEST_NAME

    @property
    def spec(self) -> stage_graph.StageSpec:
        return stage_graph.spec(self.stage)

    def path(self, item: str, name: str) -> Path:
        """The file of the artifact ``name`` (declared in :mod:`pipeline.workflow.artifact_schema`)
        in ``item``'s folder."""
        art = self.spec.artifact(name, item_kind(item))
        if "{" in art.file:
            raise ValueError(f"stage {self.stage}: artifact '{name}' is named per dataset ({art.file}); "
                             "use DatasetPlan.results_csv_name")
        return self.item_dir(item) / art.file

    def table(self, item: str, name: str):
        """The table artifact ``name`` of ``item`` (a DataFrame)."""
        from pipeline.common.store import read_table

        return read_table(self.path(item, name))

    def arrays(self, item: str, name: str, names: list[str] | None = None) -> dict[str, Any]:
        """The arrays artifact ``name`` of ``item`` (name -> ndarray; ``names``: only those)."""
        from pipeline.common.store import load_arrays

        return load_arrays(self.path(item, name), names)

    def publish_kwargs(self, item: str) -> dict[str, Any]:
        """Keyword arguments for :func:`pipeline.common.store.publish`."""
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
    scene_images: dict[int, list[int]]
    """Each target scene's target image ids."""
    stages: dict[str, StagePlan] = field(default_factory=dict)
    dataset_key: str = ""
    models_key: str = ""
    prior_key: str = ""

    @property
    def scene_ids(self) -> list[int]:
        return sorted(self.scene_images)

    @property
    def scene_items(self) -> list[str]:
        """The items of the scene-side stages: one per scene (``scene_000002``), or, with
        the run's ``images_per_job``, one per chunk of that many of a scene's images
        (``scene_000002-000``, ``-001``, ...) when the scene has more. Results do not
        depend on the chunking: every computation is per candidate or per image, and
        the seeds are drawn per scene and candidate."""
        out = []
        for scene_id in self.scene_ids:
            chunks = image_chunks(self.scene_images[scene_id], self.run.images_per_job)
            out += [scene_item(scene_id)] if len(chunks) == 1 else [scene_item(scene_id, k) for k in range(len(chunks))]
        return out

    def items_of_scene(self, scene_id: int) -> list[str]:
        """The scene items (:attr:`scene_items`) covering scene ``scene_id``."""
        return [i for i in self.scene_items if parse_item(i)[1] == scene_id]

    def item_images(self, item: str) -> set[int]:
        """The image ids a scene item covers."""
        kind, scene_id = parse_item(item)
        if kind != "scene" or scene_id not in self.scene_images:
            raise ValueError(f"dataset '{self.name}' has no scene item '{item}'")
        chunks = image_chunks(self.scene_images[scene_id], self.run.images_per_job)
        if "-" not in item:
            if len(chunks) != 1:
                raise ValueError(f"dataset '{self.name}': scene {scene_id} is cut into {len(chunks)} chunks of "
                                 f"{self.run.images_per_job} images (images_per_job); its items are "
                                 f"{', '.join(self.items_of_scene(scene_id))}, not '{item}'")
            return set(chunks[0])
        k = int(item.rsplit("-", 1)[1])
        if len(chunks) == 1 or k >= len(chunks):
            raise ValueError(f"dataset '{self.name}' has no scene item '{item}' (with images_per_job "
                             f"{self.run.images_per_job}: {', '.join(self.items_of_scene(scene_id))})")
        return set(chunks[k])

    @property
    def name(self) -> str:
        return self.dataset.name

    def __getitem__(self, stage: str) -> StagePlan:
        return self.stages[stage]

    def io(self, stage: str, item: str) -> "StageIO":
        """What the job of ``stage`` for ``item`` may read, and where it publishes."""
        return StageIO(self, stage, item)

    def input_manifests(self, stage: str, item: str) -> list[Path]:
        """The manifests of everything the job of ``stage`` for ``item`` reads (the
        Snakemake rule's inputs), from the stage's declaration. The dataset of a
        synthetic run is the synth artifact; a BOP dataset on disk and the prior files
        have no manifest (their content is in the keys)."""
        out: list[Path] = []
        for r in self[stage].spec.reads_for(item_kind(item)):
            if r == "dataset":
                if "synth" in self.stages:
                    out.append(self["synth"].manifest("dataset"))
            elif r not in EXTERNAL:
                out.extend(self[r].manifest(i) for i in upstream_items(r, item, self.obj_ids, self.scene_items, stage))
        return out

    @property
    def prior_paths(self) -> list[Path]:
        """The localisation prior files (several are merged by segment_prior)."""
        base = self.root if self.dataset.kind in BUILT_KINDS else Path(self.run.bop_root or ".")
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

    def file_name(self, declared: str) -> str:
        """A declared file name of this dataset: ``{results_csv}`` and ``{dataset}``
        replaced (:attr:`pipeline.workflow.stage_graph.StageSpec.writes`)."""
        return declared.replace("{results_csv}", self.results_csv_name).replace("{dataset}", self.name)

    def bop(self):
        """The dataset reader (:class:`pipeline.formats.bop.BopDataset`)."""
        return open_bop(self.root, self.dataset)

    def model_info(self, bop, obj_id: int):
        """``bop.models_info()[obj_id]``, failing with the file and the known ids."""
        infos = bop.models_info()
        if obj_id not in infos:
            raise ValueError(f"{bop.models_info_path()}: dataset '{self.name}' has no object {obj_id} "
                           f"(objects: {', '.join(map(str, sorted(infos)))})")
        return infos[obj_id]


class StageIO:
    """What the job of one stage for one item may read, and where it publishes.

    Stages open their inputs only through this object, which refuses what the stage's
    declaration (:mod:`pipeline.workflow.stage_graph`) does not list, and publish through
    :meth:`publish`, which refuses files the declaration does not list.
    """

    def __init__(self, plan: DatasetPlan, stage: str, item: str):
        self.plan = plan
        self.stage = stage
        self.item = item
        self.kind = item_kind(item)
        self.spec = plan[stage].spec
        if self.kind not in self.spec.items:
            raise ValueError(f"{stage} items are {' or '.join(self.spec.items)} items, not '{item}'")

    @property
    def out(self) -> StagePlan:
        """This stage's plan (key, signature, folders)."""
        return self.plan[self.stage]

    @property
    def params(self):
        """This stage's parameters in the run manifest."""
        return getattr(self.plan.run.stages, self.stage)

    def item_id(self) -> int:
        """The object or scene id of this job's item."""
        return item_id(self.item, self.kind, self.stage)

    def images(self) -> set[int]:
        """The image ids of this job's scene item (all the scene's target images, or a
        chunk of them: :meth:`DatasetPlan.scene_items`)."""
        return self.plan.item_images(self.item)

    def candidate_seed(self, cand_id: int, seed: int = 0) -> int:
        """The seed of one candidate: from this stage's key, the scene and the candidate,
        not the item, so that a candidate draws the same numbers however the scene's
        images are chunked."""
        return self.seed(f"{scene_item(self.item_id())}/{cand_id}", seed)

    def _check(self, what: str) -> None:
        if what not in self.spec.reads_for(self.kind):
            raise UndeclaredRead(f"stage {self.stage} ({self.kind} items) reads '{what}', which its declaration in "
                                 f"pipeline/workflow/stage_graph.py does not list (it reads: {', '.join(self.spec.reads_for(self.kind))})")

    def input_dir(self, stage: str, item: str | None = None) -> Path:
        """The folder of ``stage``'s artifact for ``item`` (default: the one item this job reads of it)."""
        self._check(stage)
        allowed = upstream_items(stage, self.item, self.plan.obj_ids, self.plan.scene_items, self.stage)
        if item is None:
            if len(allowed) != 1:
                raise ValueError(f"stage {self.stage}: name which item of {stage} to read (it reads {len(allowed)})")
            item = allowed[0]
        elif item not in allowed:
            raise UndeclaredRead(f"stage {self.stage} for {self.item} reads {stage} items {allowed[:3]}..., not {item}")
        folder = self.plan[stage].item_dir(item)
        ensure_sound(folder)  # a damaged input fails here, naming its file, not deep inside a reader
        return folder

    def path(self, stage: str, name: str, item: str | None = None) -> Path:
        """The file of ``stage``'s artifact ``name`` for ``item`` (as :meth:`input_dir`)."""
        folder = self.input_dir(stage, item)
        return self.plan[stage].path(folder.name, name)

    def table(self, stage: str, name: str, item: str | None = None):
        """``stage``'s table artifact ``name`` for ``item`` (a DataFrame)."""
        from pipeline.common.store import read_table

        return read_table(self.path(stage, name, item))

    def arrays(self, stage: str, name: str, item: str | None = None, names: list[str] | None = None) -> dict[str, Any]:
        """``stage``'s arrays artifact ``name`` for ``item`` (name -> ndarray)."""
        from pipeline.common.store import load_arrays

        return load_arrays(self.path(stage, name, item), names)

    def bop(self):
        """The dataset reader (:class:`pipeline.formats.bop.BopDataset`); the stage must read ``dataset``.
        A generated dataset (the synth stage's artifact) is verified first."""
        self._check("dataset")
        if "synth" in self.plan.stages and self.stage != "synth":
            ensure_sound(self.plan["synth"].item_dir("dataset"))
        return self.plan.bop()

    @property
    def prior_paths(self) -> list[Path]:
        self._check("prior")
        return self.plan.prior_paths

    @property
    def source_dir(self) -> Path:
        """The real sample a semi-real dataset is built from; the stage must read ``source``."""
        self._check("source")
        return cfg.shared_root() / self.plan.dataset.source

    def seed(self, name: str, seed: int = 0) -> int:
        """A seed derived from this stage's seed key (:attr:`StagePlan.seed_key`) and ``name``
        (see :func:`pipeline.common.store.item_seed`)."""
        from pipeline.common.store import item_seed

        return item_seed(self.out.seed_key, name, seed)

    def allowed_files(self) -> set[str]:
        return {self.plan.file_name(w) for w in self.spec.writes_for(self.kind)}

    @contextmanager
    def publish(self) -> Iterator[Any]:
        """:func:`pipeline.common.store.publish` of this item; fails, publishing nothing, when the
        stage wrote a file its declaration does not list."""
        from pipeline.common.store import publish

        with publish(self.out.item_dir(self.item), **self.out.publish_kwargs(self.item)) as w:
            yield StageWriter(w, self)
            extra = sorted(p.name for p in w.dir.iterdir() if p.name != MANIFEST_NAME)
            extra = [n for n in extra if n not in self.allowed_files()]
            if extra:
                raise RuntimeError(f"stage {self.stage} wrote {extra}, which its declaration in "
                                   "pipeline/workflow/stage_graph.py does not list")


class StageWriter:
    """What a stage writes into (:meth:`StageIO.publish`): the store's
    :class:`pipeline.common.store.ArtifactWriter` (``dir``, ``manifest``, ``summary``) and
    :meth:`write`, which writes a declared artifact by name after checking it against
    its declaration (:mod:`pipeline.workflow.artifact_schema`)."""

    def __init__(self, writer: Any, io: StageIO):
        self._w, self._io = writer, io

    def __getattr__(self, name: str) -> Any:
        return getattr(self._w, name)

    def path(self, name: str) -> Path:
        """Where the artifact ``name`` of this item goes (for a kind :meth:`write` does not write)."""
        art = self._io.spec.artifact(name, self._io.kind)
        return self._w.dir / self._io.plan.file_name(art.file)

    def write(self, name: str, data: Any, **options: Any) -> Path:
        """Write ``data`` as the artifact ``name``: a table (DataFrame; Parquet with the
        stage key in its metadata, ``options``: more metadata) or arrays (name -> ndarray; Zarr, ``options``: chunks,
        attrs, to which the key is added), after checking its columns or arrays.
        Returns the path written."""
        from pipeline.common.store import save_arrays, write_table
        from pipeline.workflow.artifact_schema import check_arrays, check_table

        art = self._io.spec.artifact(name, self._io.kind)
        where = f"stage {self._io.stage} ({self._io.item})"
        path = self.path(name)
        if art.kind == "table":
            check_table(art, data, where)
            write_table(data, path, metadata={"key": self._io.out.key, **(options.get("metadata") or {})})
        elif art.kind == "arrays":
            check_arrays(art, data, where)
            save_arrays(path, data, chunks=options.get("chunks"),
                        attrs={"key": self._io.out.key, **(options.get("attrs") or {})})
        else:
            raise ValueError(f"{where}: artifact '{name}' is a {art.kind}; write it at w.path('{name}')")
        return path


def _encoder_manifest(name: str, kind: str) -> cfg.EncoderManifest:
    name = cfg.encoder_manifest_name(name, kind)
    man = cfg.load_encoder_manifest(name)
    if man.kind != kind:
        raise cfg.ManifestError(f"manifests/encoders/{name}.yaml: field 'kind' is '{man.kind}', but it is used as the {kind} encoder")
    return man


def _run_device(run: cfg.RunManifest) -> str | None:
    """The run's device for the encoders: None for ``auto`` (each encoder manifest's own
    ``device``, whose ``auto`` picks CUDA when torch sees it), else ``cpu``/``cuda``.
    ``cuda`` without a visible CUDA device is a :class:`~pipeline.common.config.ManifestError`
    (one line); torch is imported only to check that."""
    device = run.device
    if device == "auto":
        return None
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise cfg.ManifestError("--config device=cuda: no CUDA device is visible here (torch.cuda.is_available() "
                                    "is false); run on a machine with one, or use device=auto or device=cpu")
    return device


def _build(name: str, kind: str, run: cfg.RunManifest):
    """(manifest, encoder) of the encoder manifest ``name``, built with the run's weights
    folder, device and download permission."""
    from pipeline.method.encoders.registry import EncoderSpec, build_encoder

    man = _encoder_manifest(name, kind)
    return man, build_encoder(EncoderSpec(name=man.encoder, params=dict(man.params)), weights_dir=run.weights_dir,
                              device=_run_device(run), allow_download=run.allow_download)


def encoder_runtime(enc: Any) -> dict[str, Any]:
    """Where an encoder runs and in what precision, as the stages record it in their
    manifests (``"runtime"``; never in a key): ``{"encoder", "device", "precision"}``.
    The numpy/open3d encoders run on the CPU and have no precision setting (null)."""
    return {"encoder": enc.name, "device": str(getattr(enc, "device", "cpu")),
            "precision": getattr(enc, "precision", None)}


def scene_device(run: cfg.RunManifest) -> str | None:
    """Where the scene side's numeric work runs for ``run`` (register's RANSAC loop and
    feature matching, refine's ICPs of hypotheses, turns and fine poses and the
    verification's comparisons): ``cuda`` where
    the run's device is (``cuda``, or ``auto`` with CUDA visible), the torch paths; else
    None, the numpy paths, which are the faster on a CPU (20 ICP starts of 1000 scene
    points against 5000 model points: 0.06 s against 6 s for torch's brute-force
    neighbours; RANSAC: ``benchmarks/results/scene_paths.md``)."""
    device = _run_device(run)
    if device is None:
        from importlib.metadata import version

        if version("torch").endswith("+cpu"):
            return None  # the CPU wheel sees no GPU: no need to import torch (1 s) to know
        import torch

        device = "cuda" if torch.cuda.is_available() else "cpu"
    return "cuda" if device == "cuda" else None


def warm_imports(*modules: str) -> None:
    """Import ``modules`` now, before a stage starts its clock per image: loading a library
    once per job (torch 1.1 s, pyrender and trimesh 0.5 s on this CPU) is not time spent
    on an image (BOP's time per image leaves out loading, as the peers' benchmark leaves
    out its imports), and a one-image dataset (TYO-L's) would otherwise count all of it."""
    import importlib

    for m in modules:
        importlib.import_module(m)


def _encoder_entry(name: str, kind: str, run: cfg.RunManifest) -> dict[str, Any]:
    """Cache-relevant description of an encoder manifest: registry name, version, params
    (and, not keyed, ``runtime``: the device and precision it runs with here)."""
    man, enc = _build(name, kind, run)
    return {
        "manifest": cfg.encoder_manifest_name(name, kind),
        "encoder": man.encoder,
        "version": enc.version,
        "params": enc.cache_params(),
        "signature": enc.signature(),
        "runtime": encoder_runtime(enc),
    }


def _synthetic_layout(ds: cfg.DatasetManifest) -> tuple[list[int], dict[int, list[int]]]:
    """(objects, {scene: image ids}) that the synth stage will generate."""
    from pipeline.evaluation.synth import preset_layout
    from pipeline.evaluation.synth.presets import PRESETS

    obj_ids, scene_ids = preset_layout(ds.preset, ds.seed)
    return obj_ids, {s: list(range(PRESETS[ds.preset].images_per_scene)) for s in scene_ids}


def _target_layout(targets) -> tuple[list[int], dict[int, list[int]]]:
    """(target objects, {target scene: its target image ids}) of BOP targets."""
    images: dict[int, set[int]] = {}
    for t in targets:
        images.setdefault(t.scene_id, set()).add(t.im_id)
    return sorted({t.obj_id for t in targets}), {s: sorted(images[s]) for s in sorted(images)}


def _semireal_layout(source: Path) -> tuple[list[int], dict[int, list[int]]]:
    """(target objects, {target scene: image ids}) of the real sample a semi-real dataset
    is built from."""
    from pipeline.formats.bop import BopDataset

    return _target_layout(BopDataset(source).targets())


def _real_layout(source: Path, ds: cfg.DatasetManifest) -> tuple[list[int], dict[int, list[int]]]:
    """(target objects, {target scene: image ids}) of a real sample (kind ``real``): the
    targets file of its dataset folder."""
    root = source / ds.folder
    return _target_layout(open_bop(root, ds).targets(root / ds.targets_file))


def source_files(source: Path, ds: cfg.DatasetManifest) -> list[Path]:
    """The files a semi-real or real dataset's sample must have for its plan: the targets
    file of its dataset folder and its exact prior (a real one), its targets file (a
    semi-real one). A sample that is there without them is an error, not a skip."""
    if ds.kind == "real":
        return [source / ds.folder / ds.targets_file, source / ds.source_prior]
    return [source / "test_targets_bop19.json"]


def _tree_sha1(folder: Path) -> str:
    """SHA-1 over the relative paths and bytes of every file under ``folder`` (a real
    sample of a few tens of MB: hashed whole, about 0.1 s)."""
    import hashlib

    h = hashlib.sha1()
    for p in sorted(q for q in Path(folder).rglob("*") if q.is_file()):
        h.update(p.relative_to(folder).as_posix().encode() + b"\0")
        h.update(file_sha1(p).encode())
    return h.hexdigest()


def open_bop(root: Path, ds: cfg.DatasetManifest):
    """The reader (:class:`pipeline.formats.bop.BopDataset`) of dataset ``ds`` at ``root``, with
    its manifest's split, split type, model folder and camera file."""
    from pipeline.formats.bop import BopDataset

    return BopDataset(root, split=ds.split, split_type=ds.split_type, models_dir=ds.models, camera_file=ds.camera_file)


def missing_ground_truth(bop, scene_ids) -> list[Path]:
    """The ``scene_gt.json`` files of ``scene_ids`` that the dataset (a
    :class:`pipeline.formats.bop.BopDataset`) lacks: private test ground truth (ITODD, HB)."""
    return [bop.scene_dir(s) / "scene_gt.json" for s in scene_ids if not (bop.scene_dir(s) / "scene_gt.json").is_file()]


def _bop_layout(root: Path, ds: cfg.DatasetManifest, cache: Path) -> tuple[list[int], list[int], str, str, bool]:
    """(target objects, target scenes, dataset key, models key, whether every target
    scene has ground truth) of a BOP dataset on disk.

    The keys cover the bytes of what the stages read (:class:`pipeline.common.file_hashes.
    FileHashes`, remembered in ``<cache>/.file-hashes.sqlite`` so that only changed
    files are read again): the models key the model folder and ``models_info.json``
    (all the model side reads, so the model side is reused for new images); the dataset
    key those, ``models_eval/``, the camera file, the targets file and every file of
    the target scenes (images, masks, scene JSON)."""
    from pipeline.common.file_hashes import DB_NAME, FileHashes, files_under

    bop = open_bop(root, ds)
    targets_path = root / ds.targets_file
    obj_ids, scene_images = _target_layout(bop.targets(targets_path))
    scene_ids = sorted(scene_images)
    hashes = FileHashes(cache / DB_NAME)
    models = files_under(bop.model_folder()) + [str(p) for p in [bop.models_info_path()] if p.is_file()]
    scene_files = [p for s in scene_ids for p in files_under(bop.scene_dir(s))]
    extra = [str(p) for p in (bop.camera_path(), targets_path) if p.is_file()] + files_under(root / "models_eval")
    keys = hashes.fingerprints(os.path.abspath(root), {"models": models, "dataset": models + extra + scene_files})
    models_key, dataset_key = keys["models"], keys["dataset"]
    return obj_ids, scene_images, dataset_key, models_key, not missing_ground_truth(bop, scene_ids)


class RunPlan:
    """Plans of every dataset of a run, built lazily per dataset."""

    def __init__(self, run: cfg.RunManifest, cache: Path | None = None):
        self.run = run
        self.cache = Path(cache) if cache else cache_root()
        self._plans: dict[str, DatasetPlan] = {}

    @cached_property
    def encoders(self) -> dict[str, dict[str, Any]]:
        return {
            "geometric": _encoder_entry(self.run.geometric_encoder, "geometric", self.run),
            "visual": _encoder_entry(self.run.visual_encoder, "visual", self.run),
        }

    @cached_property
    def _path_manifests(self) -> dict[str, cfg.DatasetManifest]:
        """The run's datasets given as manifest paths, by name."""
        out = {}
        for entry in self.run.datasets:
            if cfg.is_manifest_path(entry):
                man = cfg.load_dataset_manifest(entry)
                out[man.name] = man
        return out

    @property
    def dataset_names(self) -> list[str]:
        """The run's dataset names (entries given as manifest paths are named by their manifest)."""
        return [self.manifest(e).name for e in self.run.datasets]

    def manifest(self, name: str) -> cfg.DatasetManifest:
        """The manifest of dataset ``name``: a manifest path of the run, or
        ``manifests/datasets/<name>.yaml``."""
        if cfg.is_manifest_path(name):
            return cfg.load_dataset_manifest(name)
        if name in self._path_manifests:
            return self._path_manifests[name]
        return cfg.load_dataset_manifest(name)

    def available(self, name: str) -> tuple[bool, str]:
        """Whether a dataset can run here, and why not."""
        ds = self.manifest(name)
        if ds.kind == "synthetic":
            return True, ""
        if ds.kind in ("semireal", "real"):
            source = cfg.shared_root() / ds.source
            if not source.is_dir():
                return False, (f"{ds.name}: skipped, its real sample {source} is not here ({ds.kind} datasets are built "
                               "from ../shared/realdata; $FREEZE_SHARED points elsewhere)")
            missing = [p for p in source_files(source, ds) if not p.is_file()]
            if missing:  # the sample is here but incomplete: that is an error, not a skip
                raise cfg.ManifestError(f"{missing[0]}: not found in the real sample of dataset '{ds.name}' "
                                        f"(manifests/datasets/{ds.name}.yaml)")
            return True, ""
        if not self.run.bop_root:
            return False, f"{ds.name}: skipped, no bop_root set (--config bop_root=/path/to/bop, or $BOP_ROOT)"
        root = Path(self.run.bop_root) / (ds.folder or ds.name)
        if not (root / ds.targets_file).exists():
            return False, f"{ds.name}: skipped, {root / ds.targets_file} not found"
        return True, ""

    def notes(self, name: str) -> list[str]:
        """Things a user should know before running dataset ``name`` with this run."""
        ds = self.manifest(name)
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
        if cfg.is_manifest_path(name):
            name = self.manifest(name).name
        if name not in self._plans:
            self._plans[name] = self._plan_dataset(name)
        return self._plans[name]

    def _stage(self, ds: str, stage: str, readable: str, params: dict, keys: dict[str, str],
               seed_keys: dict[str, str] | None = None) -> StagePlan:
        """The plan of ``stage``: its key hashes its code version, ``params`` and the keys of
        the upstreams its declaration is keyed by (looked up in ``keys``: stage keys so far,
        ``dataset``, ``models`` and ``prior``). Its seed key hashes the same with the
        declaration's ``seed_version`` and the upstreams' seed keys (``seed_keys``; the
        external inputs' are their keys)."""
        spec = stage_graph.spec(stage)
        upstream, seed_upstream = {}, {}
        seed_keys = {**keys, **(seed_keys or {})}
        for u in spec.keyed_by:
            # a model-side stage's "dataset" is the models' own fingerprint (see DatasetPlan.models_key)
            name = "models" if (u == "dataset" and spec.side == "model") else u
            if keys.get(name) is None and u in EXTERNAL:
                continue  # an input this dataset does not have (a synthetic dataset has no source)
            upstream[u], seed_upstream[u] = keys.get(name), seed_keys.get(name)
        key = make_key(stage, spec.code_version, params, upstream)
        seed_key = make_key(stage, spec.seed_version, params, seed_upstream)
        sig = make_signature(readable, key)
        return StagePlan(ds, stage, key, sig, params, upstream, spec.code_version, self.cache / ds / stage / sig,
                         seed_key)

    def _plan_dataset(self, name: str) -> DatasetPlan:
        """Every stage's plan, in declaration order, its label and parameters from its
        declaration (:class:`pipeline.workflow.stage_graph.StageSpec`); the dataset's
        layout and keys from the synth stage (a synthetic or semi-real dataset) or from
        the files on disk (a BOP dataset)."""
        ds = self.manifest(name)
        run = self.run
        ctx = PlanContext(run=run, dataset=ds, encoder_entries=lambda: self.encoders)
        stages: dict[str, StagePlan] = {}
        if ds.kind in BUILT_KINDS:
            spec = stage_graph.spec("synth")
            if ds.kind == "synthetic":
                source_key = {}
                obj_ids, scene_images = _synthetic_layout(ds)
            else:
                source = cfg.shared_root() / ds.source
                source_key = {"source": _tree_sha1(source)}
                obj_ids, scene_images = (_real_layout(source, ds) if ds.kind == "real" else _semireal_layout(source))
            synth = self._stage(name, "synth", spec.plan_label(ctx), spec.plan_params(ctx), source_key)
            stages["synth"] = synth
            root = synth.item_dir("dataset") / name
            dataset_key = models_key = prior_key = synth.key
            patterns = ds.prior_patterns(run.priors)
            if patterns != ds.prior_patterns(None):
                # a built dataset's prior is part of its synth artifact; another of its
                # priors (realycbv's faulty one) keys the stages that read it apart
                prior_key = make_key("prior", 1, {"patterns": patterns}, {"dataset": synth.key})
        else:
            if not run.bop_root:
                raise cfg.ManifestError(f"dataset '{name}' is a BOP dataset on disk: set bop_root (--config bop_root=/path)")
            root = Path(run.bop_root).resolve() / (ds.folder or ds.name)
            obj_ids, scene_images, dataset_key, models_key, has_gt = _bop_layout(root, ds, self.cache)
            ctx = dataclasses.replace(ctx, ground_truth=has_gt)
            prior_files = [resolve_prior(Path(run.bop_root), p) for p in ds.prior_patterns(run.priors)]
            for prior_file in prior_files:
                if not prior_file.exists():
                    raise cfg.ManifestError(f"{prior_file}: localisation prior of dataset '{name}' not found (field 'prior')")
            prior_key = "+".join(file_sha1(f) for f in prior_files)
        keys = {"dataset": dataset_key, "models": models_key, "prior": prior_key}
        seed_keys: dict[str, str] = {}
        for stage, spec in stage_graph.STAGES.items():
            if stage in stages or spec.synthetic_only:
                continue
            stages[stage] = self._stage(name, stage, spec.plan_label(ctx), spec.plan_params(ctx), keys, seed_keys)
            keys[stage], seed_keys[stage] = stages[stage].key, stages[stage].seed_key
        return DatasetPlan(run=run, dataset=ds, root=root, obj_ids=obj_ids, scene_images=scene_images, stages=stages,
                           dataset_key=dataset_key, models_key=models_key, prior_key=prior_key)

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
    """Instantiate the run's (geometric, visual) encoders from their manifests, with the
    run's weights folder, device (``--config device=cpu|cuda`` replaces the manifests'
    ``device``) and ``allow_download``."""
    return tuple(_build(name, kind, run)[1]
                 for name, kind in ((run.geometric_encoder, "geometric"), (run.visual_encoder, "visual")))

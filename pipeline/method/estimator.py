"""The method on RGB-D images, in memory: one :class:`Estimator` that the stages and the
Python API share.

An :class:`Estimator` holds the prepared objects (what the model side gives the scene
side: :class:`PreparedObject`), the run's stage parameters and its two encoders. Its
three steps are the scene side of the pipeline, one stage each, on the images of one
scene:

- :meth:`Estimator.scene_features`: the candidates' points and features in one image
  (stage ``scene_features``);
- :meth:`Estimator.register`: the coarse hypotheses of every candidate (stage ``register``);
- :meth:`Estimator.refine`: ICP and verification of every hypothesis, the choice per
  target and the symmetry-aware refinement (stage ``refine``).

The stages read their inputs from the cache, call one step and publish what it returns;
:meth:`Estimator.estimate` chains the three on one frame without writing anything::

    run = load_run()                                          # pipeline.common.config
    encoders = build_encoders(run)                            # pipeline.workflow.plan
    obj = prepare_object(1, trimesh.load("obj_000001.ply"), run.stages, encoders)
    result = Estimator({1: obj}, run.stages, encoders).estimate(Observation(rgb, depth, K), [Detection(1, mask)])
    result.poses                                              # R, t (mm) per kept estimate

A prepared object's fields are values or zero-argument loaders, read when a step first
needs them: each stage gives only what it declared it reads (the model features to
register and refine, the symmetries to refine, the diameter to all).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Collection, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.common.config import StageParams
from pipeline.common.parallel import Mapper, ThreadMethod
from pipeline.method.scene_side import (POSE_COLUMNS, SAR_COLUMNS, CandidateFeatures, CandidateMask, FineIcp,
                                        MatchableModel, PoseVerifier, Progress, SceneImages, _noop, choose_estimates,
                                        matchable_model, pack_candidates, packed_points, pca_arrays, refine_by_symmetry,
                                        refine_candidates, register_candidates, sar_transforms, scene_features)

_UNSET = object()


class PreparedObject:
    """One object as the scene side needs it. Each field is given as its value or as a
    zero-argument loader, called once when first read.

    obj_id; diameter (mm); mesh (trimesh, mm); features (model_features' arrays: points
    (N, 3) float32 mm, normals (N, 3), geometric (N, G), visual (N, C) float32);
    symmetries (the estimated :class:`pipeline.method.geometry.symmetry.SymmetrySet`);
    near_symmetries ((4, 4) float64 model-frame transforms, best first); declared (the
    dataset's :class:`~pipeline.method.geometry.symmetry.SymmetrySet`, empty when it
    declares none).
    """

    FIELDS = ("mesh", "features", "symmetries", "near_symmetries", "declared")

    def __init__(self, obj_id: int, diameter: float, **fields: Any):
        unknown = set(fields) - set(self.FIELDS)
        if unknown:
            raise TypeError(f"PreparedObject: unknown field(s) {sorted(unknown)} (known: {', '.join(self.FIELDS)})")
        self.obj_id, self.diameter = int(obj_id), float(diameter)
        self._given = dict(fields)
        self._values: dict[str, Any] = {}

    def _get(self, name: str) -> Any:
        if name not in self._values:
            if name not in self._given:
                raise KeyError(f"object {self.obj_id}: its {name} was not given to the estimator")
            given = self._given[name]
            self._values[name] = given() if callable(given) else given
        return self._values[name]

    mesh = property(lambda self: self._get("mesh"))
    features = property(lambda self: self._get("features"))
    symmetries = property(lambda self: self._get("symmetries"))
    near_symmetries = property(lambda self: self._get("near_symmetries"))
    declared = property(lambda self: self._get("declared"))


def prepare_object(obj_id: int, mesh, stages: StageParams, encoders: tuple[Any, Any], *, diameter: float | None = None,
                   declared=None, image_mode: str = "rgb", seed: int | None = None) -> PreparedObject:
    """The model side of one object, in memory: its templates, model features and
    symmetry record, as the stages render_templates, model_features and symmetries
    compute them (the stages draw their seeds from their cache keys; here every draw
    uses ``seed``, default the stages' ``seed`` parameters).

    mesh: trimesh in mm; stages: the run's stage parameters; encoders: the run's
    (geometric, visual) encoders; diameter: mm (default: the largest distance between
    two of the mesh's vertices); declared: the dataset's SymmetrySet (default none).
    """
    from pipeline.formats.bop.extent import point_cloud_diameter
    from pipeline.method.geometry.symmetry import SymmetrySet
    from pipeline.method.model_side import model_features, symmetry_record
    from pipeline.method.render.templates import render_object_templates

    geo, vis = encoders
    d = float(diameter) if diameter is not None else float(point_cloud_diameter(np.asarray(mesh.vertices)))
    declared = declared if declared is not None else SymmetrySet()
    mf, sy = stages.model_features, stages.symmetries
    templates = render_object_templates(mesh, d, stages.render_templates, image_mode=image_mode)
    features = model_features(mesh, templates, geo, vis, d, n_points=mf.n_points,
                              seed=mf.seed if seed is None else seed, batch_size=mf.batch_size)
    found, record = symmetry_record(mesh, d, n_points=sy.n_points, sample_seed=sy.seed if seed is None else seed,
                                    threshold=sy.threshold, seed=sy.seed, declared=declared, obj_id=obj_id)
    near = [np.asarray(n["T"], float).reshape(4, 4) for n in record["near_symmetries"]]
    return PreparedObject(obj_id, d, mesh=mesh, features=features, symmetries=found, near_symmetries=near,
                          declared=declared)


@dataclass(frozen=True)
class Observation:
    """One RGB-D image: rgb (H, W, 3) uint8, depth (H, W) float32 mm (0 = no depth),
    K (3, 3) camera intrinsics (OpenCV convention)."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray


@dataclass(frozen=True)
class Detection:
    """One candidate of an object in an :class:`Observation`: mask (H, W) bool, bbox
    (x, y, w, h) px (default: the mask's box), the prior's score, and how many instances
    of the object the image holds (the estimates kept for it)."""

    obj_id: int
    mask: np.ndarray
    bbox: tuple[float, float, float, float] | None = None
    score: float = 1.0
    inst_count: int = 1


@dataclass
class Registered:
    """:meth:`Estimator.register`'s result: the table (one row per hypothesis, see
    :data:`pipeline.method.scene_side.REGISTER_COLUMNS`), the registration time per image
    (s) and the PCA bases used (:func:`pipeline.method.scene_side.pca_arrays`)."""

    table: pd.DataFrame
    image_time: dict[int, float]
    pca: dict[str, np.ndarray]


@dataclass
class Refined:
    """:meth:`Estimator.refine`'s result: every hypothesis after ICP, the candidates with
    their choice, the kept estimates (:data:`pipeline.method.scene_side.POSE_COLUMNS`),
    SAR's variants (:data:`~pipeline.method.scene_side.SAR_COLUMNS`), the time per image
    (s), and the visual encoder SAR ran (None when it did not)."""

    hypotheses: pd.DataFrame
    candidates: pd.DataFrame
    poses: pd.DataFrame
    sar: pd.DataFrame
    image_time: dict[int, float]
    sar_encoder: Any = None


@dataclass
class Estimate:
    """:meth:`Estimator.estimate`'s result on one frame: the candidates' features, the
    coarse hypotheses, and the refinement (``poses``: the kept estimates, R as 9
    row-major floats, t mm, model-to-camera)."""

    features: list[CandidateFeatures]
    registered: Registered
    refined: Refined
    poses: pd.DataFrame = field(init=False)

    def __post_init__(self) -> None:
        self.poses = self.refined.poses


class Estimator:
    """The scene side of the method for a set of prepared objects.

    objects: obj_id -> :class:`PreparedObject`; stages: the run's stage parameters
    (scene_features, register and refine are read); encoders: the run's (geometric,
    visual) encoders, or a zero-argument loader of them (called when a step first needs
    them; None: registration alone, which matches features already computed); image_mode: ``rgb`` or ``gray`` (grey datasets get grey SAR renders).
    scene_device: where register's RANSAC and feature matching and refine's ICP and
    verification comparisons run: None for numpy (the faster on a CPU), or a torch
    device such as ``cuda`` (see
    :func:`pipeline.method.scene_side.register_candidates` and
    :func:`~pipeline.method.scene_side.refine_candidates`).
    """

    def __init__(self, objects: Mapping[int, PreparedObject], stages: StageParams,
                 encoders: tuple[Any, Any] | Callable[[], tuple[Any, Any]] | None = None, *, image_mode: str = "rgb",
                 scene_device: str | None = None):
        self.objects, self.stages, self.image_mode = objects, stages, image_mode
        self.scene_device = scene_device
        self._encoders = encoders
        self._matchable: dict[int, MatchableModel] = {}

    @property
    def encoders(self) -> tuple[Any, Any]:
        """The (geometric, visual) encoders, loaded on first use."""
        if self._encoders is None:
            raise ValueError("this step needs the encoders, and the estimator was given none")
        if callable(self._encoders):
            self._encoders = tuple(self._encoders())
        return self._encoders

    def diameters(self, obj_ids: Sequence[int] | None = None) -> dict[int, float]:
        """obj_id -> diameter (mm), of ``obj_ids`` (default: every object)."""
        return {int(o): self.objects[int(o)].diameter for o in (self.objects if obj_ids is None else obj_ids)}

    # -------------------------------------------------------------- the three steps

    def scene_features(self, obs: Observation, candidates: Sequence[CandidateMask],
                       progress: Progress = _noop) -> list[CandidateFeatures]:
        """Points and features of the candidates of one image
        (:func:`pipeline.method.scene_side.scene_features`)."""
        geo, vis = self.encoders
        return scene_features(obs.rgb, obs.depth, obs.K, candidates, geo, vis, self.stages.scene_features, progress)

    def register(self, candidates: pd.DataFrame, arrays: Mapping[str, np.ndarray], seed_of: Callable[[int], int],
                 progress: Progress = _noop, mapper: Mapper | None = None) -> Registered:
        """Coarse hypotheses of a scene's candidates
        (:func:`pipeline.method.scene_side.register_candidates`): candidates is
        scene_features' table, arrays its packed features; seed_of(cand_id) the RANSAC seed."""
        p = self.stages.register
        table, image_time = register_candidates(candidates, arrays, self._matchable_model, self.diameters(), p,
                                                seed_of, progress, mapper, self.scene_device)
        return Registered(table, image_time, pca_arrays(self._matchable))

    def refine(self, registered: pd.DataFrame, scene_points: Callable[[int], np.ndarray], images: SceneImages,
               targets: Sequence[Any], progress: Progress = _noop, mapper: Mapper | None = None) -> Refined:
        """ICP and verification of every registered hypothesis (register's rows with
        status ``ok``), and the choice of up to ``inst_count`` estimates per target
        (``targets``: scene_id, im_id, obj_id, inst_count); SAR is the next step
        (:meth:`refine_by_symmetry`), which completes the result.

        scene_points(cand_id): the candidate's sampled points (k, 3) mm; images: the
        scene's loaders (:class:`pipeline.method.scene_side.SceneImages`); mapper: where
        the candidates run (None: this thread). See
        :func:`pipeline.method.scene_side.refine_candidates` and
        :func:`~pipeline.method.scene_side.choose_estimates`.
        """
        from pipeline.method.refinement.turns import model_turns

        p = self.stages.refine
        objects = sorted(set(registered.obj_id.astype(int)))
        models = {o: self.objects[o].features for o in objects}  # read here once, before any thread starts
        found = {o: self.objects[o].symmetries for o in objects}
        diameters = self.diameters()
        turns = {o: model_turns(self.objects[o].near_symmetries, models[o]["points"], found[o], diameters[o])
                 for o in objects} if p.turns else {}
        fine_objects = {o for o in objects if found[o].is_trivial} if p.icp and p.fine_icp_points else None
        own = mapper is None
        mapper = mapper or Mapper()
        try:
            # A verifier and a fine ICP per thread: a renderer belongs to the thread that
            # made it, and the loaders that keep the last image are not shared between threads.
            tools = mapper.per_thread(partial(_ThreadTools, images, p, fine_objects, self.scene_device))
            hypotheses, refined, image_time = refine_candidates(
                registered, scene_points, models.__getitem__, diameters, p, ThreadMethod(tools, "verify"),
                ThreadMethod(tools, "fine") if fine_objects is not None else None, progress, turns, mapper,
                self.scene_device, ThreadMethod(tools, "verify_many"))
        finally:
            if own:
                mapper.close()
        table, poses = choose_estimates(refined, targets, diameters, p)
        return Refined(hypotheses, table, poses, pd.DataFrame(columns=SAR_COLUMNS), image_time)

    def refine_by_symmetry(self, refined: Refined, images: SceneImages,
                           progress: Callable[[int], Progress] | None = None,
                           untextured: Collection[int] | None = None) -> Refined:
        """Symmetry-aware refinement of :meth:`refine`'s kept estimates
        (:func:`pipeline.method.scene_side.refine_by_symmetry`): their poses and SAR's
        columns updated, SAR's variants and time added. progress(n) gives the callback
        for the n estimates SAR runs on. untextured: the objects whose visual features
        carry no signal, which SAR skips (None: found from their model features by
        register's PCA test; the refine stage reads register's ``pca.zarr`` instead)."""
        p, poses = self.stages.refine, refined.poses
        rows: list[dict] = []
        vis = None
        if len(poses):
            transforms = {o: sar_transforms(self.objects[o].symmetries, self.objects[o].declared,
                                            self.objects[o].diameter, p)
                          for o in sorted(set(poses.obj_id.astype(int)))}
            vis = self.encoders[1] if p.sar else None
            # SAR tells symmetric poses apart by the model's texture: a model whose visual
            # features carry no signal (register's PCA test) has none to tell them by
            if untextured is None:
                untextured = {o for o in transforms if vis is not None and self._matchable_model(o).visual is None}
            rows = refine_by_symmetry(poses, transforms, images.keeping_last(), vis, p,
                                      self.stages.scene_features.crop_margin, self.image_mode, refined.image_time,
                                      progress, untextured=untextured)
        return Refined(refined.hypotheses, refined.candidates, poses[POSE_COLUMNS].reset_index(drop=True),
                       pd.DataFrame(rows, columns=SAR_COLUMNS), refined.image_time, vis)

    # -------------------------------------------------------------- one frame

    def estimate(self, obs: Observation, detections: Sequence[Detection], *, scene_id: int = 0, im_id: int = 0,
                 seed: int = 0) -> Estimate:
        """The three steps on one frame, in memory: the detections' features, their
        hypotheses and the kept estimates (up to each object's ``inst_count``).

        Detection i is candidate i; its point sampling and RANSAC draw from seeds made
        of ``seed`` and i (the stages draw theirs from their cache keys instead).
        """
        from pipeline.formats.bop.dataset import Target
        from pipeline.method.geometry.crops import mask_to_bbox

        masks = []
        for i, d in enumerate(detections):
            if d.obj_id not in self.objects:
                raise KeyError(f"detection {i}: object {d.obj_id} is not among the estimator's objects "
                               f"({sorted(self.objects)})")
            if d.mask.shape != obs.depth.shape:
                raise ValueError(f"detection {i}: mask size {d.mask.shape} differs from the depth image {obs.depth.shape}")
            bbox = tuple(float(v) for v in (d.bbox if d.bbox is not None else mask_to_bbox(d.mask)))
            masks.append(CandidateMask(i, int(d.obj_id), np.asarray(d.mask, bool), bbox,
                                       self.objects[int(d.obj_id)].diameter, _seed(seed, "scene_features", i)))
        found = self.scene_features(obs, masks)
        geo, vis = self.encoders
        arrays = pack_candidates(found, self.stages.scene_features.n_points, geo.dim, vis.dim)
        table = pd.DataFrame({"cand_id": [m.cand_id for m in masks], "scene_id": scene_id, "im_id": im_id,
                              "obj_id": [m.obj_id for m in masks], "prior_score": [float(d.score) for d in detections],
                              "status": ["ok" if f.ok else "skipped" for f in found],
                              "reason": [f.reason for f in found], "n_points": [len(f.points) for f in found]})
        registered = self.register(table, arrays, lambda c: _seed(seed, "register", int(c)))
        images = SceneImages(rgb=lambda _: obs.rgb, depth=lambda _: obs.depth, K=lambda _: obs.K,
                             mesh=lambda o: self.objects[int(o)].mesh,
                             candidate=lambda c: (masks[int(c)].bbox, masks[int(c)].mask))
        counts: dict[int, int] = {}
        for d in detections:
            counts[int(d.obj_id)] = max(counts.get(int(d.obj_id), 0), int(d.inst_count))
        targets = [Target(scene_id, im_id, o, n) for o, n in sorted(counts.items())]
        ok = registered.table[registered.table.status == "ok"]
        refined = self.refine(ok, packed_points(arrays), images, targets)
        return Estimate(found, registered, self.refine_by_symmetry(refined, images))

    def _matchable_model(self, obj_id: int) -> MatchableModel:
        if obj_id not in self._matchable:
            self._matchable[obj_id] = matchable_model(self.objects[obj_id].features, self.stages.register.pca_dim)
        return self._matchable[obj_id]


def _seed(seed: int, step: str, cand_id: int) -> int:
    """A candidate's seed for one step of :meth:`Estimator.estimate`."""
    return int(np.random.SeedSequence([int(seed), sum(map(ord, step)), int(cand_id)]).generate_state(1)[0])


class _ThreadTools:
    """One thread's verifier and fine ICP, sharing that thread's loaders (which keep the
    last image and mask). ``fine_objects``: the objects the fine ICP refines (None: off);
    ``device``: where the fine ICP and the verifier's comparisons run (None: numpy)."""

    def __init__(self, loaders: SceneImages, params: Any, fine_objects: set[int] | None, device: str | None = None):
        images = loaders.keeping_last()
        self.verify = PoseVerifier(images, params, device)
        self.fine = FineIcp(images, params, fine_objects, device) if fine_objects is not None else None

    def verify_many(self, *args: Any) -> list:
        """:meth:`PoseVerifier.many` of this thread's verifier."""
        return self.verify.many(*args)

    def close(self) -> None:
        self.verify.__exit__(None, None, None)


__all__ = ["Detection", "Estimate", "Estimator", "Observation", "PreparedObject", "Refined", "Registered",
           "prepare_object"]

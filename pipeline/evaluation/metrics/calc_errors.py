"""Per-image computation of MSSD, MSPD and VSD for every (estimate, GT instance) pair.

An :class:`ImageJob` is plain data (poses, ids, intrinsics), so jobs can be sent to
worker processes; each process holds one :class:`ErrorCalculator` that loads the
``models_eval`` meshes it needs and its own renderer (EGL contexts must not cross a
``fork``, so workers are started with ``spawn``). The images can also be mapped over
threads or a dask cluster (:class:`ErrorWork`, :func:`image_errors_task`), each thread
with its own calculator.
"""

from __future__ import annotations

import time as _time
import warnings
from collections import defaultdict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from pipeline.formats.bop import BopDataset, ModelInfo, load_json, read_ply
from pipeline.formats.bop.dataset import parse_models_info

from .pose_errors import hull_indices, mspd, mssd, probe_indices
from .bop_symmetries import DEFAULT_MAX_SYM_DISC_STEP, model_symmetries
from .depth_render import DepthAtlasRenderer, DepthRequest
from .vsd import VSD_TAUS, Crop, distance_crop, ray_lengths, sphere_projections_overlap, vsd_distance_crops


@dataclass(frozen=True)
class ErrorParams:
    """Settings of the error computation (plain values, picklable)."""

    vsd_delta: float = 15.0
    vsd_taus: tuple[float, ...] = tuple(VSD_TAUS.tolist())
    max_sym_disc_step: float = DEFAULT_MAX_SYM_DISC_STEP
    compute_vsd: bool = True
    #: Where, in OpenCV pixel coordinates relative to the pixel centre, the VSD renders
    #: sample each pixel. The BOP toolkit's renderers (vispy, cpp) rasterise with
    #: OpenGL's pixel centres at OpenCV coordinates (x + 0.5, y + 0.5); sampling there
    #: too reproduces its silhouettes and hence its VSD values.
    render_offset: float = 0.5
    #: Render the model depths of an image in one batch (``depth_render``); False: one
    #: pyrender render each (``Renderer.render_depth_crop``, the scorer before issue 15),
    #: kept to compare the two.
    batch_render: bool = True


@dataclass
class ImageJob:
    """Everything about one image except its depth and the models.

    K: (3, 3) float64. gts: (gt_id, obj_id, R (3, 3), t (3,) mm) for the GT instances
    of the objects being scored. ests: (est_id, obj_id, score, R, t) of the estimates
    kept for scoring (est_id = index among the image's estimates of that object in the
    results file, as in the BOP toolkit).
    """

    scene_id: int
    im_id: int
    K: np.ndarray
    width: int
    height: int
    gts: list[tuple[int, int, np.ndarray, np.ndarray]] = field(default_factory=list)
    ests: list[tuple[int, int, float, np.ndarray, np.ndarray]] = field(default_factory=list)


@dataclass
class _Model:
    pts: np.ndarray  # (V, 3) float64 mm, models_eval vertices
    faces: np.ndarray  # (F, 3) int64
    sym_R: np.ndarray  # (S, 3, 3)
    sym_t: np.ndarray  # (S, 3) mm
    diameter: float
    hull: np.ndarray  # indices of the convex hull vertices (MSSD is exact on them)
    hull_probes: np.ndarray  # indices into pts[hull] for the MSSD lower bounds
    probes: np.ndarray  # indices into pts (hull vertices) for the MSPD lower bounds


class ErrorCalculator:
    """Computes the pose errors of :class:`ImageJob` s against one dataset."""

    def __init__(self, dataset: BopDataset, params: ErrorParams):
        self.dataset = dataset
        self.params = params
        self._models: dict[int, _Model] = {}
        self._infos: dict[int, ModelInfo] | None = None
        self._renderers: dict[tuple[int, int], Any] = {}
        self._atlas: DepthAtlasRenderer | None = None
        self._ray_cache: dict[tuple[bytes, int, int], np.ndarray] = {}
        self._taus = np.asarray(params.vsd_taus, dtype=np.float64)
        # Reads started ahead by errors_of's reader thread, taken by the main thread.
        self._model_reads: dict[int, Future] = {}
        self._depth_reads: dict[tuple[int, int], Future] = {}
        #: Seconds per part (load: depth images and models, or the wait for them when
        #: :meth:`errors_of` reads ahead; vsd_render; vsd_compare; mssd; mspd) and
        #: ``n_renders``, accumulated over :meth:`image_errors` calls.
        self.timing: dict[str, float] = defaultdict(float)

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()
        if self._atlas is not None:
            self._atlas.close()
            self._atlas = None

    def model(self, obj_id: int) -> _Model:
        if obj_id not in self._models:
            read = self._model_reads.pop(obj_id, None)
            self._models[obj_id] = self._read_model(obj_id) if read is None else read.result()
        return self._models[obj_id]

    def _model_infos(self) -> dict[int, ModelInfo]:
        if self._infos is None:
            self._infos = eval_models_info(self.dataset)
        return self._infos

    def _read_model(self, obj_id: int) -> _Model:
        """The ``models_eval`` mesh of ``obj_id`` with its symmetries and convex hull."""
        infos = self._model_infos()
        if obj_id not in infos:
            raise KeyError(f"{self.dataset.root}: models_info.json has no entry for obj_id {obj_id}")
        ply = read_ply(eval_model_path(self.dataset, obj_id))
        sym_R, sym_t = model_symmetries(infos[obj_id], self.params.max_sym_disc_step)
        pts = ply.vertices.astype(np.float64)
        hull = hull_indices(pts)
        hull_probes = probe_indices(pts[hull])
        return _Model(pts, ply.faces, sym_R, sym_t, float(infos[obj_id].diameter), hull, hull_probes, hull[hull_probes])

    def _depth(self, scene_id: int, im_id: int) -> np.ndarray:
        read = self._depth_reads.pop((scene_id, im_id), None)
        return self.dataset.load_depth(scene_id, im_id) if read is None else read.result()

    def errors_of(self, jobs: Sequence[ImageJob], ahead: int = 2) -> Iterator[list[dict]]:
        """The rows of each job, in order, as :meth:`image_errors` gives them, while one
        reader thread loads the models and decodes the depth images of the next ``ahead``
        jobs. PNG decoding (OpenCV) and the convex hulls (Qhull) release the GIL, so they
        run beside this thread's work; on the bench file (84 images) the wait for them
        fell from 0.6 s to 0.3 s (most of what is left: importing scipy.spatial for the
        first hull). A read that fails raises where the job needs it, as without reading
        ahead."""
        jobs = list(jobs)
        if len(jobs) <= 1:
            for job in jobs:
                yield self.image_errors(job)
            return
        self._model_infos()  # parsed once here, not raced by the reader
        pool = ThreadPoolExecutor(1, thread_name_prefix="score-reader")

        def start(job: ImageJob) -> None:
            gt_objs = {g[1] for g in job.gts}
            needed = sorted({e[1] for e in job.ests} & gt_objs)
            for obj_id in needed:
                if obj_id not in self._models and obj_id not in self._model_reads:
                    self._model_reads[obj_id] = pool.submit(self._read_model, obj_id)
            key = (job.scene_id, job.im_id)
            if self.params.compute_vsd and needed and key not in self._depth_reads:
                self._depth_reads[key] = pool.submit(self.dataset.load_depth, *key)

        try:
            for job in jobs[:ahead]:
                start(job)
            for i, job in enumerate(jobs):
                if i + ahead < len(jobs):
                    start(jobs[i + ahead])
                yield self.image_errors(job)
        finally:
            for read in [*self._model_reads.values(), *self._depth_reads.values()]:
                read.cancel()
            pool.shutdown(wait=True)
            self._model_reads.clear()
            self._depth_reads.clear()

    def _renderer(self, width: int, height: int, obj_id: int):
        key = (width, height)
        if key not in self._renderers:
            from pipeline.method.render.renderer import Renderer

            self._renderers[key] = Renderer(width, height)
        ren = self._renderers[key]
        if not ren.has_mesh(obj_id):
            import trimesh

            m = self.model(obj_id)
            ren.add_mesh(obj_id, trimesh.Trimesh(vertices=m.pts, faces=m.faces, process=False), smooth=False)
        return ren

    def image_errors(self, job: ImageJob) -> list[dict]:
        """One dict per (estimate, GT of the same object) of the image.

        Keys: scene_id, im_id, obj_id, est_id, gt_id, score, mssd (mm; inf when the
        centres are more than a diameter apart, as in the toolkit), mspd (px) and
        ``vsd`` ((T,) float64 per tau, or None when VSD is not computed).

        Every model depth that a VSD needs is rendered, once per estimate and once per GT
        instance, only in the image region where the model projects, all of them in one
        batch (:meth:`_submit_depths`); while the rasteriser draws them, MSSD and MSPD
        are computed and the depth image read; then VSD of each pair. Time spent per
        part accumulates in :attr:`timing`.
        """
        rows, vsd_pairs, pose_pairs = self._rows(job)
        renders = self._start_vsd_renders(job, vsd_pairs) if vsd_pairs else None
        self._pose_errors(job, rows, pose_pairs)
        if renders is not None:
            self._vsd_errors(job, rows, vsd_pairs, *renders)
        return rows

    def _rows(self, job: ImageJob) -> tuple[list[dict], list[tuple[int, int, int]], list[tuple[int, int, int]]]:
        """The rows of the image (MSSD and MSPD still None), the pairs whose VSD needs
        renders as (row index, estimate index in ``job.ests``, gt_id), and every pair as
        (row index, estimate index, index in ``job.gts``).

        VSD is 1 for every tau without rendering when the two poses' bounding spheres
        cannot overlap in the image (the toolkit's shortcut), None without VSD.
        """
        tm = self.timing
        clock = _time.perf_counter
        rows: list[dict] = []
        vsd_pairs: list[tuple[int, int, int]] = []
        pose_pairs: list[tuple[int, int, int]] = []
        for e, (est_id, obj_id, score, R_e, t_e) in enumerate(job.ests):
            gts = [(g, gt) for g, gt in enumerate(job.gts) if gt[1] == obj_id]
            if not gts:
                continue
            t0 = clock()
            m = self.model(obj_id)
            tm["load"] += clock() - t0
            for g, (gt_id, _, R_g, t_g) in gts:
                e_vsd = None
                if self.params.compute_vsd:
                    if sphere_projections_overlap(0.5 * m.diameter, t_e, t_g):
                        vsd_pairs.append((len(rows), e, gt_id))
                    else:
                        e_vsd = np.ones(len(self._taus))
                pose_pairs.append((len(rows), e, g))
                rows.append(
                    {
                        "scene_id": job.scene_id,
                        "im_id": job.im_id,
                        "obj_id": obj_id,
                        "est_id": est_id,
                        "gt_id": gt_id,
                        "score": score,
                        "mssd": None,
                        "mspd": None,
                        "vsd": e_vsd,
                    }
                )
        return rows, vsd_pairs, pose_pairs

    def _pose_errors(self, job: ImageJob, rows: list[dict], pairs: list[tuple[int, int, int]]) -> None:
        """Fill ``rows[i]["mssd"]`` and ``["mspd"]`` for the (row index, estimate index,
        index in ``job.gts``) ``pairs``."""
        tm = self.timing
        clock = _time.perf_counter
        K = np.asarray(job.K, dtype=np.float64)
        for i, e, g in pairs:
            _, obj_id, _, R_e, t_e = job.ests[e]
            _, _, R_g, t_g = job.gts[g]
            m = self.model(obj_id)
            t0 = clock()
            if np.linalg.norm(t_e - t_g) < m.diameter:
                # Exact on the hull vertices (see pose_errors.hull_indices).
                rows[i]["mssd"] = mssd(R_e, t_e, R_g, t_g, m.pts[m.hull], m.sym_R, m.sym_t, m.hull_probes)
            else:
                rows[i]["mssd"] = float("inf")
            t1 = clock()
            rows[i]["mspd"] = mspd(R_e, t_e, R_g, t_g, K, m.pts, m.sym_R, m.sym_t, m.probes, mid=m.hull)
            tm["mssd"] += t1 - t0
            tm["mspd"] += clock() - t1

    def _start_vsd_renders(self, job: ImageJob, pairs: list[tuple[int, int, int]]
                           ) -> tuple[list[tuple[str, int]], Callable[[], list[Crop | None]]]:
        """Start the renders the VSD ``pairs`` need, each once: ("est", index in
        job.ests) or ("gt", gt_id); returns those keys and what collects their crops."""
        gt_pose = {g[0]: g for g in job.gts}
        poses: dict[tuple[str, int], tuple[int, np.ndarray, np.ndarray]] = {}
        for _, e, gt_id in pairs:
            _, obj_id, _, R_e, t_e = job.ests[e]
            poses.setdefault(("est", e), (obj_id, R_e, t_e))
            _, _, R_g, t_g = gt_pose[gt_id]
            poses.setdefault(("gt", gt_id), (obj_id, R_g, t_g))
        t0 = _time.perf_counter()
        collect = self._submit_depths(job, list(poses.values()))
        self.timing["vsd_render"] += _time.perf_counter() - t0
        return list(poses), collect

    def _vsd_errors(self, job: ImageJob, rows: list[dict], pairs: list[tuple[int, int, int]],
                    keys: list[tuple[str, int]], collect: Callable[[], list[Crop | None]]) -> None:
        """Fill ``rows[i]["vsd"]`` for the (row index, estimate index, gt_id) ``pairs``,
        from the renders ``collect`` returns (one per key of ``keys``)."""
        p = self.params
        tm = self.timing
        clock = _time.perf_counter
        t0 = clock()
        depth_test = self._depth(job.scene_id, job.im_id)
        tm["load"] += clock() - t0
        if depth_test.shape != (job.height, job.width):
            raise ValueError(
                f"{self.dataset.depth_path(job.scene_id, job.im_id)}: depth is "
                f"{depth_test.shape[1]}x{depth_test.shape[0]}, camera says {job.width}x{job.height}"
            )
        t0 = clock()
        # Distances from the camera centre, once per image and once per render (VSD
        # compares distances, not depths).
        rays = self._rays(job)
        dist_test = depth_test.astype(np.float64) * rays
        t1 = clock()
        crops = collect()
        t2 = clock()
        dists = {k: None if c is None else distance_crop(c, rays) for k, c in zip(keys, crops)}
        for i, e, gt_id in pairs:
            m = self.model(job.ests[e][1])
            rows[i]["vsd"] = vsd_distance_crops(
                dist_test, dists[("est", e)], dists[("gt", gt_id)], p.vsd_delta, m.diameter, self._taus
            )
        tm["vsd_render"] += t2 - t1
        tm["vsd_compare"] += (t1 - t0) + (clock() - t2)

    def _rays(self, job: ImageJob) -> np.ndarray:
        """:func:`ray_lengths` (H, W) of the job's camera, cached per intrinsics."""
        key = (np.asarray(job.K, dtype=np.float64).tobytes(), job.width, job.height)
        if key not in self._ray_cache:
            if len(self._ray_cache) > 8:
                self._ray_cache.clear()
            self._ray_cache[key] = ray_lengths(job.K, job.width, job.height)
        return self._ray_cache[key]

    def _submit_depths(self, job: ImageJob, poses: list[tuple[int, np.ndarray, np.ndarray]]
                       ) -> Callable[[], list[Crop | None]]:
        """Start rendering the model depth of each (obj_id, R, t) of ``poses``; the
        returned function gives them, each a :class:`Crop` of the image where the model
        projects, or None when the model is outside the image."""
        K_render = np.asarray(job.K, dtype=np.float64).copy()
        K_render[0, 2] -= self.params.render_offset
        K_render[1, 2] -= self.params.render_offset
        if not self.params.batch_render:
            crops = [self._render(job, obj_id, R, t, K_render) for obj_id, R, t in poses]
            return lambda: crops
        ren = self._atlas_renderer(sorted({obj_id for obj_id, _, _ in poses}))
        boxes = [ren.box(obj_id, R, t, K_render, job.width, job.height) for obj_id, R, t in poses]
        requests = [DepthRequest(obj_id, R, t, K_render, box) for (obj_id, R, t), box in zip(poses, boxes) if box is not None]
        pending = ren.submit(requests)
        self.timing["n_renders"] += len(requests)

        def collect() -> list[Crop | None]:
            depths = iter(ren.collect(pending))
            return [None if box is None else Crop(next(depths), box[0], box[1]) for box in boxes]

        return collect

    def _atlas_renderer(self, obj_ids: list[int]) -> DepthAtlasRenderer:
        """The batched depth renderer, with the ``models_eval`` meshes of ``obj_ids``."""
        if self._atlas is None:
            self._atlas = DepthAtlasRenderer()
        for obj_id in obj_ids:
            if not self._atlas.has_mesh(obj_id):
                m = self.model(obj_id)
                self._atlas.add_mesh(obj_id, m.pts, m.faces, m.hull)
        return self._atlas

    def _render(self, job: ImageJob, obj_id: int, R: np.ndarray, t: np.ndarray, K_render: np.ndarray) -> Crop | None:
        """Depth of the model in the part of the image where it projects (one pyrender
        render: the path before the batched renderer); None if outside."""
        ren = self._renderer(job.width, job.height, obj_id)
        box = ren.object_box(obj_id, R, t, K_render)
        if box is None:
            return None
        self.timing["n_renders"] += 1
        x0, y0, w, h = box
        return Crop(ren.render_depth_crop(obj_id, R, t, K_render, box), x0, y0)


def eval_models_info(dataset: BopDataset) -> dict[int, ModelInfo]:
    """models_info of ``models_eval/`` (what the toolkit reads), else the dataset's default one."""
    path = dataset.root / "models_eval" / "models_info.json"
    if path.is_file():
        return parse_models_info(path, load_json(path))
    return dataset.models_info()


def eval_model_path(dataset: BopDataset, obj_id: int) -> Path:
    """The ``models_eval`` mesh of an object; the ``models/`` one, with a warning, if absent."""
    path = dataset.model_path(obj_id, eval=True)
    if path.is_file():
        return path
    fallback = dataset.model_path(obj_id, eval=False)
    if not fallback.is_file():
        raise FileNotFoundError(f"{path}: model of obj_id {obj_id} not found (nor {fallback})")
    warnings.warn(
        f"{path} not found: scoring obj_id {obj_id} on {fallback} (BOP scores use the models_eval meshes)",
        stacklevel=3,
    )
    return fallback


# ---------------------------------------------------------------------------- worker processes

_WORKER: ErrorCalculator | None = None


def init_worker(root: str, split: str, split_type: str | None, params: ErrorParams) -> None:
    """Pool initializer: one dataset reader and calculator per worker process."""
    global _WORKER
    _WORKER = ErrorCalculator(BopDataset(Path(root), split, split_type), params)


@dataclass(frozen=True)
class ErrorWork:
    """What every image shares when the images are mapped over threads or a dask
    cluster (:mod:`pipeline.common.parallel`): one :class:`ErrorCalculator` per thread, made
    on first use from the dataset (root, split, split type) and the parameters. A
    calculator renders on its own EGL context, which belongs to its thread."""

    calculators: Any  # PerThread[ErrorCalculator]

    @staticmethod
    def make_calculator(root: str, split: str, split_type: str | None, params: ErrorParams) -> ErrorCalculator:
        return ErrorCalculator(BopDataset(Path(root), split, split_type), params)


def image_errors_task(work: ErrorWork, job: ImageJob) -> tuple[list[dict], dict[str, float]]:
    """Mapped task: the error rows of one image, and the time this thread spent on it per
    part (the calculator's timing accumulates over the images of its thread)."""
    calc = work.calculators.get()
    before = dict(calc.timing)
    rows = calc.image_errors(job)
    return rows, {k: v - before.get(k, 0.0) for k, v in calc.timing.items()}


def run_jobs(jobs: list[ImageJob]) -> tuple[list[dict], dict[str, float]]:
    """Pool task: the error rows of a chunk of images, and the time spent per part."""
    assert _WORKER is not None, "init_worker was not called in this process"
    before = dict(_WORKER.timing)
    rows = []
    for part in _WORKER.errors_of(jobs):
        rows.extend(part)
    return rows, {k: v - before.get(k, 0.0) for k, v in _WORKER.timing.items()}

"""Classical, training-free peers measured beside the project (run by hand): point-pair
features (OpenCV's ``cv2.ppf_match_3d``) and FPFH + RANSAC + ICP (Open3D), on the same
masked depth the project gets, scored by the project's own scorer.

    .venv/bin/python benchmarks/peers.py --datasets semilmo,tyol,synthhard [--prior NAME] \\
        [--peers ppf,fpfh] [--images N] [--out benchmarks/results/peers] [--set fpfh.voxel=0.03]

For each dataset the project's ``synth`` (when the dataset has one) and ``segment_prior``
artifacts are made if missing (``run_stage``); the candidates are segment_prior's
``prior_candidates.parquet`` (one per kept prior detection, with its mask and score), and
each candidate's points are lifted from the masked depth by the project's own function
(:func:`pipeline.method.scene_side.candidate_points`: valid depth under the mask, camera
frame, mm, outliers removed), skipped under ``scene_features.min_points`` like the project
skips them. So each peer sees the points the project sees before its own sampling and
features. Normals, where a peer needs them, come from the project's
:func:`pipeline.method.geometry.normals.estimate_normals` (radius 0.05 diameter, as the
project's FPFH encoder, facing the camera); the model points are sampled on the model mesh
(:func:`pipeline.method.geometry.sampling.sample_surface`, mm, face normals). Each
candidate gets one pose with a score; BOP keeps the top ``inst_count`` per target by score,
so the score is the same quantity for every candidate of an object. The results CSV
``<out>/<peer>_<dataset>[-<prior>]-<split>.csv`` has, on each row of an image, the peer's
wall time for that image (lifting, normals, matching, ICP, scoring of all its candidates),
plus the prior's own time for the image as the project's CSV adds it (BOP's time per
image includes the detector's), but not the one-off model training, reported per object
as ``onboarding_s``, as BOP separates training. ``<out>/<same stem>.json`` holds the
scores: AR, AR_VSD, AR_MSSD, AR_MSPD, AR per object, s/image.

The peers
---------
* ``ppf``: ``cv2.ppf_match_3d_PPF3DDetector(rel_sampling, rel_distance)``, ``trainModel``
  on the model's points + normals (Nx6 float32), ``match(scene, 1/scene_sample_step,
  rel_scene_distance)`` on the candidate's points + normals, the ``n_icp`` most voted
  poses refined by ``ppf_match_3d_ICP(...).registerModelToScene``. It runs in its own
  virtual environment, ``benchmarks/.peers-venv`` (opencv-contrib-python-headless
  4.14.0.94 and numpy; created here on first use: opencv-contrib cannot share the
  project's env, both install ``cv2``), through ``benchmarks/peer_ppf_worker.py``, one
  process per dataset, exchanging .npz files. Score (``select``): ``votes`` (OpenCV's
  own ranking: the most voted pose after ICP, its vote count) or ``fitness`` (the pose,
  of the ``n_icp``, whose model points have the largest fraction within ``fitness_dist``
  diameters of the candidate's points; that fraction).
* ``fpfh``: the model and the candidate voxel-downsampled at ``voxel`` diameters, FPFH
  (radius ``feature_radius`` diameters, at most 100 neighbours) on both,
  ``registration_ransac_based_on_feature_matching`` (point-to-point, 3 points, distance
  ``ransac_dist`` voxels, mutual filter, edge-length 0.9 and distance checkers,
  ``RANSACConvergenceCriteria(max_iteration, confidence)``), then point-to-plane
  ``registration_icp`` at each of ``icp_dists`` diameters (model sampled at
  ``icp_voxel``, the candidate at ``icp_voxel`` with normals). Score: the last ICP's
  fitness (fraction of the model's points within its distance of the candidate's points).

Reproducibility: Open3D is seeded (``o3d.utility.random.seed(0)``) before every candidate,
so a candidate's pose does not depend on which others ran, and runs on one thread
(``OMP_NUM_THREADS=1``, set here before Open3D loads: its RANSAC draws from one shared
generator across threads, so several threads give other poses from run to run); OpenCV's
worker runs on one thread with ``cv2.setRNGSeed(0)``. Times are therefore one-core
times on a 2-core machine.

Parameters (the defaults below, :data:`DEFAULTS`), from a sweep on a few images
------------------------------------------------------------------------------
Measured 2026-12 on this 2-core machine (shared with another job, so times are +-20%),
``--images`` the first images of the dataset in (scene, image) order, AR over their targets:

semilmo, first 4 images (30 targets, 32 candidates); s/image on one thread, onboarding
(all 8 objects) apart:

| peer | settings (the rest as DEFAULTS) | AR | VSD | MSSD | MSPD | s/image |
|---|---|---|---|---|---|---|
| fpfh | voxel 0.04, feature_radius 0.2, 100k iterations, confidence 0.999 | 0.496 | 0.525 | 0.477 | 0.487 | 3.4 |
| fpfh | the same, no mutual filter | 0.496 | 0.525 | 0.477 | 0.487 | 5.3 |
| fpfh | **voxel 0.025, feature_radius 0.125, 100k, 0.999 (default)** | 0.611 | 0.616 | 0.600 | 0.617 | 5.8 |
| fpfh | voxel 0.025, feature_radius 0.125, 1M, 0.9999 | 0.671 | 0.669 | 0.660 | 0.683 | 23.7 |
| ppf | rel_sampling 0.08, rel_scene_distance 0.05, select votes | 0.520 | 0.489 | 0.497 | 0.573 | 17.9 |
| ppf | the same, select fitness | 0.572 | 0.529 | 0.580 | 0.607 | 21.9 |
| ppf | **rel_scene_distance 0.08, select fitness (default)** | 0.586 | 0.543 | 0.583 | 0.633 | 11.9 (*) |

The 10x longer RANSAC buys 0.06 AR at 4x the time, which ~200 images cannot afford; the
default is the strong setting of a few seconds. The mutual filter changes nothing here
(with so few points per candidate it mostly falls back to all matches). PPF's training
(``trainModel``) grows much faster than the square of the sampled model points in
OpenCV 4.14 (one object of 118 mm: 0.3 s at rel_sampling 0.1, 3.8 s at 0.08, 17 s at
0.07, 63 s at 0.06, minutes at 0.05), so rel_sampling 0.08 is the finest affordable
(onboarding about 5 s per object). Choosing among the 5 ICP-refined poses by fitness
instead of votes adds 0.05 AR; the scene sampled at 0.08 instead of 0.05 diameters
cuts the matching time. (*) measured with three other jobs on the two cores: the same
setting took 3.1 s/image over all of semilmo when the machine was quieter.

The table with the defaults, beside the project's default and geometry-only runs, one
set after the other on an idle machine: ``--table`` writes ``benchmarks/results/peers.md``
(the sweep above shared the machine with other jobs, so its times are up to 2x slower).

    .venv/bin/python benchmarks/peers.py --table realycbv,realycbv:faulty,semilmo,tyol,synthhard \\
        --cache /tmp/peers_cache --label NAME

The outside try quoted in issue 30 (voxel 0.025 d, 4M RANSAC iterations, point-to-plane
ICP) reached AR 0.822 at 32 s per image on five real YCB-V images with ground-truth masks.
"""

from __future__ import annotations

import os
import sys

if "open3d" not in sys.modules:  # one thread, for reproducible RANSAC (see the docstring)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shlex  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Iterable  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PEERS = ("ppf", "fpfh")
PEERS_VENV = ROOT / "benchmarks" / ".peers-venv"
PPF_WORKER = ROOT / "benchmarks" / "peer_ppf_worker.py"
PPF_REQUIREMENTS = ("opencv-contrib-python-headless==4.14.0.94", "numpy==2.4.6")

DEFAULTS: dict[str, dict[str, Any]] = {
    "ppf": {"model_points": 20000, "rel_sampling": 0.08, "rel_distance": 0.05, "num_angles": 30,
            "scene_sample_step": 5, "rel_scene_distance": 0.08, "n_icp": 5, "icp_model_points": 2000, "icp_iterations": 100,
            "icp_tolerance": 0.005, "icp_rejection": 2.5, "icp_levels": 4, "select": "fitness",
            "fitness_dist": 0.02, "normal_radius": 0.05},
    "fpfh": {"model_points": 20000, "voxel": 0.025, "feature_radius": 0.125, "normal_radius": 0.05,
             "ransac_dist": 1.5, "max_iteration": 100000, "confidence": 0.999, "mutual": True,
             "icp_voxel": 0.015, "icp_dists": [0.05, 0.02], "icp_iterations": 30},
}
"""Each peer's parameters (lengths are fractions of the object's diameter, ``ransac_dist``
in voxels); ``run_peer``'s ``params`` override them key by key."""


@dataclass
class Candidate:
    """One prior candidate with its lifted points (P, 3) float32 mm, camera frame."""

    cand_id: int
    scene_id: int
    im_id: int
    obj_id: int
    prior_score: float
    points: np.ndarray
    diameter: float


@dataclass
class ImageCandidates:
    """The candidates of one image, the time spent loading the depth and lifting them (s)
    and the prior's own time for the image (s; 0 when unknown): BOP's time per image
    includes the detector's, and the project's CSV adds it, so the peers' CSVs do too."""

    scene_id: int
    im_id: int
    candidates: list[Candidate]
    n_skipped: int
    lift_s: float
    prior_s: float = 0.0


@dataclass
class PeerResult:
    """What :func:`run_peer` returns: the estimates (one row per candidate that got a pose:
    scene_id, im_id, obj_id, cand_id, score, R (3, 3), t (3,) mm, time s), each image's
    wall time (s, lifting included), each object's onboarding time (s), and counts."""

    peer: str
    dataset: str
    prior: str | None
    split: str
    params: dict[str, Any]
    estimates: pd.DataFrame
    image_times: dict[tuple[int, int], float]
    onboarding_s: dict[int, float]
    n_candidates: int
    n_skipped: int
    n_failed: int
    threads: str = field(default_factory=lambda: os.environ.get("OMP_NUM_THREADS", ""))

    @property
    def images(self) -> list[tuple[int, int]]:
        return sorted(self.image_times)

    @property
    def s_per_image(self) -> float:
        """Mean over images of the peer's wall time per image (s), training excluded."""
        return float(np.mean(list(self.image_times.values()))) if self.image_times else float("nan")

    def csv_name(self) -> str:
        return f"{self.peer}_{self.dataset}{'-' + self.prior if self.prior else ''}-{self.split}.csv"

    def write_csv(self, path: Path | str) -> Path:
        """The BOP results CSV (time: the image's wall time on each of its rows)."""
        from pipeline.formats.bop.results import write_results_csv

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        rows = self.estimates.assign(time=[self.image_times[(int(s), int(i))]
                                           for s, i in zip(self.estimates.scene_id, self.estimates.im_id)])
        write_results_csv(path, rows[["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]])
        return path


class DatasetUnavailable(RuntimeError):
    """A dataset that cannot run here (one line saying why)."""


# ------------------------------------------------------------------ the project's side


def dataset_plan(name: str, prior: str | None = None, cache: Path | None = None):
    """The project's plan of dataset ``name`` (default run manifest, ``prior`` instead of the
    dataset's default), or :class:`DatasetUnavailable`."""
    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan

    config: dict[str, Any] = {"datasets": name}
    if prior:
        config["priors"] = [prior]
    try:
        rp = RunPlan(cfg.load_run(config), cache=cache)
        ok, why = rp.available(name)
        if not ok:
            raise DatasetUnavailable(why)
        return rp[name]
    except (cfg.ManifestError, FileNotFoundError, OSError, ValueError) as e:
        raise DatasetUnavailable(f"{name}: {e}") from None


def ensure_artifacts(plan, progress: bool = True) -> None:
    """Make the dataset (``synth``, where the dataset has that stage) and ``segment_prior``
    artifacts of ``plan`` when they are not in the cache."""
    from pipeline.workflow.stage_graph import run_stage

    if "synth" in plan.stages and not plan["synth"].manifest("dataset").exists():
        run_stage(plan, "synth", "dataset", progress=progress)
    if not plan["segment_prior"].manifest("all").exists():
        run_stage(plan, "segment_prior", "all", progress=progress)


def image_list(plan, images: int | Iterable[tuple[int, int]] | None) -> list[tuple[int, int]]:
    """The (scene_id, im_id) of the plan's target images: all (None), the first ``images``
    (an int, in (scene, image) order) or those given."""
    every = [(s, i) for s in plan.scene_ids for i in sorted(plan.scene_images[s])]
    if images is None:
        return every
    if isinstance(images, int):
        return every[:images]
    wanted = {(int(s), int(i)) for s, i in images}
    return [x for x in every if x in wanted]


def lifted_candidates(plan, images: list[tuple[int, int]], progress: bool = False) -> list[ImageCandidates]:
    """Each image's prior candidates with the points the project lifts for them
    (:func:`pipeline.method.scene_side.candidate_points`), skipping those with fewer than
    ``scene_features.min_points`` points as the project does."""
    from pipeline.common.progress import progress_bar
    from pipeline.formats.bop.detections import prior_row_mask
    from pipeline.method.scene_side import candidate_points

    bop = plan.bop()
    infos = bop.models_info()
    min_points = plan.run.stages.scene_features.min_points
    table = plan["segment_prior"].table("all", "prior_candidates").sort_values("cand_id")
    groups = {k: g for k, g in table.groupby(["scene_id", "im_id"], sort=True)}
    cams: dict[int, Any] = {}
    out = []
    with progress_bar(f"lift {plan.name}", total=len(images), enabled=progress) as bar:
        for scene_id, im_id in images:
            rows = groups.get((scene_id, im_id))
            if rows is None:
                bar.advance()
                continue
            t0 = time.perf_counter()
            if scene_id not in cams:
                cams[scene_id] = bop.scene_camera(scene_id)
            K = cams[scene_id][im_id].K
            depth = bop.load_depth(scene_id, im_id)
            cands, skipped = [], 0
            for r in rows.itertuples(index=False):
                mask = prior_row_mask(r)
                if mask.shape != depth.shape:
                    raise ValueError(f"{plan.name}: candidate {r.cand_id} (scene {scene_id}, image {im_id}): mask "
                                     f"size {mask.shape} differs from the depth image {depth.shape}")
                diameter = float(infos[int(r.obj_id)].diameter)
                pts, _ = candidate_points(depth, K, mask, diameter)
                if len(pts) < min_points:
                    skipped += 1
                    continue
                cands.append(Candidate(int(r.cand_id), scene_id, im_id, int(r.obj_id), float(r.prior_score),
                                       np.asarray(pts, np.float32), diameter))
            prior_s = float(max(0.0, rows["prior_time"].max())) if "prior_time" in rows else 0.0
            out.append(ImageCandidates(scene_id, im_id, cands, skipped, time.perf_counter() - t0, prior_s))
            bar.advance()
    return out


def model_samples(plan, obj_id: int, n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Points (n, 3) float32 mm and unit face normals sampled on the object's model mesh
    (seed 0), and its diameter (mm)."""
    from pipeline.method.geometry.sampling import sample_surface

    bop = plan.bop()
    pts, normals = sample_surface(bop.load_model(obj_id), int(n), seed=0)
    return pts, normals, float(plan.model_info(bop, obj_id).diameter)


def scene_normals(points: np.ndarray, diameter: float, radius: float) -> np.ndarray:
    """The project's normals of camera-frame points, facing the camera."""
    from pipeline.method.geometry.normals import estimate_normals

    return estimate_normals(points, radius * diameter, viewpoint=np.zeros(3))


def _quiet_open3d() -> None:
    """Open3D's warnings off (the mutual filter's fall-back is announced per candidate)."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


def _pcd(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    return pcd


def _pose_row(c: Candidate, T: np.ndarray, score: float) -> dict[str, Any]:
    R = np.asarray(T[:3, :3], np.float64)
    u, _, vt = np.linalg.svd(R)  # the nearest rotation (float32 poses drift off by ~1e-7)
    R = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return {"scene_id": c.scene_id, "im_id": c.im_id, "obj_id": c.obj_id, "cand_id": c.cand_id,
            "score": float(score), "R": R, "t": np.asarray(T[:3, 3], np.float64)}


# ------------------------------------------------------------------ FPFH + RANSAC + ICP


@dataclass
class _FpfhModel:
    down: Any
    feature: Any
    fine: Any
    diameter: float


def _fpfh(pcd, radius: float):
    import open3d as o3d

    return o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=100))


def _fpfh_model(plan, obj_id: int, p: dict[str, Any]) -> _FpfhModel:
    pts, normals, d = model_samples(plan, obj_id, p["model_points"])
    dense = _pcd(pts, normals)
    down = dense.voxel_down_sample(p["voxel"] * d)
    down.normalize_normals()
    fine = dense.voxel_down_sample(p["icp_voxel"] * d)
    fine.normalize_normals()
    return _FpfhModel(down, _fpfh(down, p["feature_radius"] * d), fine, d)


def _fpfh_candidate(model: _FpfhModel, c: Candidate, p: dict[str, Any]) -> tuple[np.ndarray, float] | None:
    import open3d as o3d

    reg = o3d.pipelines.registration
    d = model.diameter
    v = p["voxel"] * d
    o3d.utility.random.seed(0)
    scene = _pcd(c.points).voxel_down_sample(v)
    if len(scene.points) < 5:
        return None
    scene.normals = o3d.utility.Vector3dVector(scene_normals(np.asarray(scene.points), d, p["normal_radius"]))
    feature = _fpfh(scene, p["feature_radius"] * d)
    dist = p["ransac_dist"] * v
    ransac = reg.registration_ransac_based_on_feature_matching(
        model.down, scene, model.feature, feature, bool(p["mutual"]), dist,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(int(p["max_iteration"]), float(p["confidence"])))
    T = np.asarray(ransac.transformation)
    fitness = float(ransac.fitness)
    fine = _pcd(c.points).voxel_down_sample(p["icp_voxel"] * d)
    fine.normals = o3d.utility.Vector3dVector(scene_normals(np.asarray(fine.points), d, p["normal_radius"]))
    for frac in p["icp_dists"]:
        icp = reg.registration_icp(model.fine, fine, frac * d, T, reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=int(p["icp_iterations"])))
        if icp.fitness > 0:
            T, fitness = np.asarray(icp.transformation), float(icp.fitness)
        else:
            fitness = 0.0
    return T, fitness


def _run_fpfh(plan, images: list[ImageCandidates], p: dict[str, Any], progress: bool):
    from pipeline.common.progress import progress_bar

    _quiet_open3d()
    objs = sorted({c.obj_id for im in images for c in im.candidates})
    models, onboarding = {}, {}
    with progress_bar(f"fpfh onboarding {plan.name}", total=len(objs), enabled=progress) as bar:
        for obj in objs:
            t0 = time.perf_counter()
            models[obj] = _fpfh_model(plan, obj, p)
            onboarding[obj] = time.perf_counter() - t0
            bar.advance()
    rows, times, failed = [], {}, 0
    total = sum(len(im.candidates) for im in images)
    with progress_bar(f"fpfh {plan.name}", total=total, enabled=progress) as bar:
        for im in images:
            t0 = time.perf_counter()
            for c in im.candidates:
                found = _fpfh_candidate(models[c.obj_id], c, p)
                if found is None:
                    failed += 1
                else:
                    rows.append(_pose_row(c, *found))
                bar.advance()
            times[(im.scene_id, im.im_id)] = im.prior_s + im.lift_s + time.perf_counter() - t0
    return rows, times, onboarding, failed


# ------------------------------------------------------------------ point-pair features


def ensure_ppf_env(venv: Path = PEERS_VENV) -> Path:
    """The python of the PPF peer's virtual environment, created (``python -m venv`` and
    ``pip install`` of :data:`PPF_REQUIREMENTS`) when missing or pinned differently."""
    python = venv / "bin" / "python"
    stamp = venv / "peers-requirements.txt"
    wanted = "\n".join(PPF_REQUIREMENTS) + "\n"
    if python.exists() and stamp.exists() and stamp.read_text() == wanted:
        return python
    print(f"peers: creating {venv} ({', '.join(PPF_REQUIREMENTS)})", file=sys.stderr, flush=True)
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "-q", *PPF_REQUIREMENTS], check=True)
    subprocess.run([str(python), "-c", "import cv2; cv2.ppf_match_3d_PPF3DDetector"], check=True)
    stamp.write_text(wanted)
    return python


def _fitness(model_pts: np.ndarray, scene, T: np.ndarray, dist: float) -> float:
    """Fraction of the model points, posed by ``T``, within ``dist`` mm of the scene's."""
    import open3d as o3d

    return float(o3d.pipelines.registration.evaluate_registration(_pcd(model_pts), scene, dist, T).fitness)


def _run_ppf(plan, images: list[ImageCandidates], p: dict[str, Any], progress: bool):
    from pipeline.common.progress import progress_bar

    python = ensure_ppf_env()
    cands = [c for im in images for c in im.candidates]
    objs = sorted({c.obj_id for c in cands})
    prep_s: dict[tuple[int, int], float] = {}
    arrays: dict[str, np.ndarray] = {}
    models: dict[int, tuple[np.ndarray, float]] = {}
    sample_s: dict[int, float] = {}
    for obj in objs:
        t0 = time.perf_counter()
        pts, normals, d = model_samples(plan, obj, p["model_points"])
        arrays[f"model_{obj}"] = np.hstack([pts, normals]).astype(np.float32)
        arrays[f"icpmodel_{obj}"] = arrays[f"model_{obj}"][:: max(1, len(pts) // p["icp_model_points"])]
        models[obj] = (pts, d)
        sample_s[obj] = time.perf_counter() - t0
    with progress_bar(f"ppf normals {plan.name}", total=len(cands), enabled=progress) as bar:
        for im in images:
            t0 = time.perf_counter()
            for c in im.candidates:
                n = scene_normals(c.points, c.diameter, p["normal_radius"])
                arrays[f"scene_{c.cand_id}"] = np.hstack([c.points, n]).astype(np.float32)
                bar.advance()
            prep_s[(im.scene_id, im.im_id)] = im.lift_s + time.perf_counter() - t0
    worker_params = {k: p[k] for k in ("rel_sampling", "rel_distance", "num_angles", "scene_sample_step",
                                       "rel_scene_distance", "n_icp", "icp_iterations", "icp_tolerance",
                                       "icp_rejection", "icp_levels")}
    arrays["params"] = np.asarray(json.dumps(worker_params))
    arrays["cand_ids"] = np.asarray([c.cand_id for c in cands], np.int64)
    arrays["cand_obj"] = np.asarray([c.obj_id for c in cands], np.int64)
    with tempfile.TemporaryDirectory(prefix="peers-ppf-") as tmp:
        inp, outp = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(inp, **arrays)
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        env.pop("PYTHONPATH", None)
        with progress_bar(f"ppf {plan.name}", total=len(cands), enabled=progress) as bar:
            proc = subprocess.Popen([str(python), str(PPF_WORKER), str(inp), str(outp)], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, env=env)
            for line in proc.stdout:
                if line.startswith("done "):
                    bar.advance()
            err = proc.stderr.read()
            if proc.wait() != 0:
                raise RuntimeError(f"ppf worker failed ({proc.returncode}): {err.strip()[-2000:]}")
        with np.load(outp) as o:
            res = {k: o[k] for k in o.files}
    onboarding = {int(o): float(s) + sample_s[int(o)] for o, s in zip(res["train_obj"], res["train_s"])}
    row_of = {int(c): i for i, c in enumerate(res["cand_ids"])}
    rows, times, failed = [], {}, 0
    for im in images:
        t0 = time.perf_counter()
        worker_s = 0.0
        for c in im.candidates:
            i = row_of[c.cand_id]
            worker_s += float(res["match_s"][i])
            k = int(res["n_poses"][i])
            if k == 0:
                failed += 1
                continue
            poses, votes = res["poses"][i, :k], res["votes"][i, :k]
            if p["select"] == "votes":
                j = 0  # OpenCV's order: most votes first
                score = float(votes[0])
            elif p["select"] == "fitness":
                scene = _pcd(c.points)
                model_pts, d = models[c.obj_id]
                sub = model_pts[:: max(1, len(model_pts) // 5000)]
                fits = [_fitness(sub, scene, poses[j], p["fitness_dist"] * d) for j in range(k)]
                j = int(np.argmax(fits))
                score = fits[j]
            else:
                raise ValueError(f"ppf: select must be votes or fitness, not {p['select']!r}")
            rows.append(_pose_row(c, poses[j], score))
        times[(im.scene_id, im.im_id)] = (im.prior_s + prep_s[(im.scene_id, im.im_id)] + worker_s
                                          + time.perf_counter() - t0)
    return rows, times, onboarding, failed


# ------------------------------------------------------------------ the API


def run_peer(plan, peer: str, params: dict[str, Any] | None = None,
             images: int | Iterable[tuple[int, int]] | None = None, progress: bool = True) -> PeerResult:
    """Run ``peer`` (``ppf`` or ``fpfh``) on the prior candidates of ``plan``'s target images
    (``images``: all, the first N, or a list of (scene_id, im_id)), with :data:`DEFAULTS`
    overridden by ``params``. Makes the plan's dataset and segment_prior artifacts first
    when missing."""
    if peer not in PEERS:
        raise ValueError(f"unknown peer '{peer}' (known: {', '.join(PEERS)})")
    p = {**DEFAULTS[peer], **(params or {})}
    unknown = set(p) - set(DEFAULTS[peer])
    if unknown:
        raise ValueError(f"{peer}: unknown parameters {sorted(unknown)} (known: {sorted(DEFAULTS[peer])})")
    ensure_artifacts(plan, progress=progress)
    chosen = image_list(plan, images)
    lifted = lifted_candidates(plan, chosen, progress=progress)
    rows, times, onboarding, failed = (_run_fpfh if peer == "fpfh" else _run_ppf)(plan, lifted, p, progress)
    priors = plan.run.priors
    return PeerResult(peer=peer, dataset=plan.name, prior="+".join(priors) if priors else None,
                      split=plan.dataset.split, params=p,
                      estimates=pd.DataFrame(rows, columns=["scene_id", "im_id", "obj_id", "cand_id", "score", "R",
                                                            "t"]),
                      image_times=times, onboarding_s=onboarding,
                      n_candidates=sum(len(im.candidates) for im in lifted),
                      n_skipped=sum(im.n_skipped for im in lifted), n_failed=failed)


def score_peer_csv(plan, csv_path: Path | str, images: Iterable[tuple[int, int]] | None = None) -> dict[str, Any]:
    """Scores of a results CSV by the project's scorer (:func:`pipeline.evaluation.metrics.evaluate.score_results_file`)
    against ``plan``'s dataset: AR, AR_VSD, AR_MSSD, AR_MSPD, per_object ({obj_id: AR}),
    n_targets, n_estimates, mean_time_per_image. ``images``: only the targets of those
    (scene_id, im_id) (for a run on some images)."""
    from pipeline.evaluation.metrics.evaluate import score_results_file

    targets = plan.root / plan.dataset.targets_file
    with tempfile.TemporaryDirectory(prefix="peers-targets-") as tmp:
        if images is not None:
            wanted = {(int(s), int(i)) for s, i in images}
            subset = [t for t in json.loads(targets.read_text()) if (int(t["scene_id"]), int(t["im_id"])) in wanted]
            targets = Path(tmp) / "targets.json"
            targets.write_text(json.dumps(subset))
        scores = score_results_file(csv_path, plan.root, split=plan.dataset.split, split_type=plan.dataset.split_type,
                                    targets_file=targets, vsd_delta=plan.dataset.vsd_delta)
    s = scores.summary
    per = {int(r.obj_id): float(r.AR) for r in scores.per_object.itertuples()} if len(scores.per_object) else {}
    return {"AR": s.get("AR"), "AR_VSD": s.get("AR_VSD"), "AR_MSSD": s.get("AR_MSSD"), "AR_MSPD": s.get("AR_MSPD"),
            "per_object": per, "n_targets": s.get("n_targets"), "n_estimates": s.get("n_estimates"),
            "mean_time_per_image": s.get("mean_time_per_image")}


def peer_summary(result: PeerResult, scores: dict[str, Any], csv_path: Path) -> dict[str, Any]:
    """One line of the benchmark: the scores, s/image, onboarding per object, counts, params."""
    return {"peer": result.peer, "dataset": result.dataset, "prior": result.prior, **scores,
            "s_per_image": result.s_per_image, "n_images": len(result.image_times),
            "onboarding_s": {int(k): round(v, 3) for k, v in result.onboarding_s.items()},
            "n_candidates": result.n_candidates, "n_skipped": result.n_skipped, "n_failed": result.n_failed,
            "threads": result.threads, "params": result.params, "csv": str(csv_path)}


def run_and_score(plan, peer: str, params: dict[str, Any] | None, images: int | None, out: Path,
                  progress: bool = True) -> dict[str, Any]:
    """:func:`run_peer`, its CSV written under ``out``, scored; the summary also written as
    ``<csv stem>.json``."""
    result = run_peer(plan, peer, params, images, progress=progress)
    csv = result.write_csv(out / result.csv_name())
    scores = score_peer_csv(plan, csv, result.images if images is not None else None)
    summary = peer_summary(result, scores, csv)
    csv.with_suffix(".json").write_text(json.dumps(summary, indent=1, default=float) + "\n")
    return summary


def _parse_sets(items: list[str]) -> dict[str, dict[str, Any]]:
    """``--set fpfh.voxel=0.03`` -> {"fpfh": {"voxel": 0.03}} (values parsed as JSON when they parse)."""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        key, _, value = item.partition("=")
        peer, _, name = key.partition(".")
        if peer not in PEERS or not name or not value:
            raise SystemExit(f"--set {item}: expected PEER.NAME=VALUE with PEER one of {', '.join(PEERS)}")
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError:
            parsed = value
        out.setdefault(peer, {})[name] = parsed
    return out


# ------------------------------------------------------------------ the table, side by side

PROJECT_METHODS = {"default": {}, "geometry-only": {"visual": "none"}}
"""The project's configurations in the table: its default, and its geometry-only
ablation (no visual encoder), each a ``bop_all --config`` override."""
METHOD_LABELS = {"default": "FreeZe default (fpfh + colortex)", "geometry-only": "FreeZe geometry-only (fpfh)",
                 "ppf": "PPF (OpenCV ppf_match_3d + ICP)", "fpfh": "FPFH + RANSAC + ICP (Open3D)"}


def project_row(name: str, prior: str | None, method: str, cache: Path | None) -> dict[str, Any]:
    """Run the project's ``method`` (:data:`PROJECT_METHODS`) with ``bop_all`` on dataset
    ``name`` (``prior``: another of its priors) and read its scores, as the peers' rows."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from ablations import run_config

    config = {"datasets": name, **({"prior": prior} if prior else {}), **PROJECT_METHODS[method]}
    r = run_config(config, method, cores=2, cache=cache)
    s = r.scores
    return {"method": method, "dataset": name, "prior": prior, "AR": s["AR"], "AR_VSD": s["AR_VSD"],
            "AR_MSSD": s["AR_MSSD"], "AR_MSPD": s["AR_MSPD"], "n_targets": s["n_targets"],
            "n_estimates": s["n_estimates"], "s_per_image": s["mean_time_per_image"],
            "per_object": {int(o["obj_id"]): float(o["AR"]) for o in r.per_object},
            "onboarding_s_per_object": r.onboarding_s_per_object, "wall_s": r.wall_s}


def _parse_set(entry: str) -> tuple[str, str | None]:
    """``realycbv:faulty`` -> ("realycbv", "faulty"); ``semilmo`` -> ("semilmo", None)."""
    name, _, prior = entry.partition(":")
    return name, prior or None


def table_section(label: str, command: str, sets: list[tuple[str, str | None, list[dict[str, Any]]]]) -> str:
    """The markdown section of :func:`run_table`'s results: per set, one row per method
    (AR, its parts, s/image, AR per object), and the goal's verdict."""
    out = [f"## {label}", "", f"`{command}`", ""]
    for name, prior, rows in sets:
        if not rows:
            continue
        objs = sorted({o for r in rows for o in r["per_object"]})
        n = rows[0]["n_targets"]
        out += [f"### {name}, prior {prior or 'default'} ({n} targets)", "",
                "| method | AR | AR_VSD | AR_MSSD | AR_MSPD | s/image | " + " | ".join(f"obj {o}" for o in objs) + " |",
                "|---|---|---|---|---|---|" + "---|" * len(objs)]
        for r in rows:
            per = " | ".join(f"{r['per_object'][o]:.3f}" if o in r["per_object"] else "-" for o in objs)
            out.append(f"| {METHOD_LABELS.get(r['method'], r['method'])} | {r['AR']:.3f} | {r['AR_VSD']:.3f} | "
                       f"{r['AR_MSSD']:.3f} | {r['AR_MSPD']:.3f} | {r['s_per_image']:.2f} | {per} |")
        default = next((r for r in rows if r["method"] == "default"), None)
        peers = [r for r in rows if r["method"] in PEERS]
        if default and peers:
            best = max(peers, key=lambda r: r["AR"])
            lead = default["AR"] - best["AR"]
            ok = lead >= 0.05 and default["s_per_image"] <= best["s_per_image"]
            out += ["", f"Goal (default at least 0.05 AR ahead of the best peer, at no more s/image): best peer "
                        f"{best['method']}, lead {lead:+.3f} AR, {default['s_per_image']:.2f} against "
                        f"{best['s_per_image']:.2f} s/image: {'met' if ok else 'not met'}."]
        out.append("")
    return "\n".join(out) + "\n"


def run_table(entries: list[str], methods: list[str], cache: Path | None, out_dir: Path,
              progress: bool = True) -> list[tuple[str, str | None, list[dict[str, Any]]]]:
    """Every method on every set, one set after the other (so that each set's times are
    measured side by side on the same machine state): the project's runs through
    ``bop_all`` (in ``cache``, a fresh folder for fresh times), then each peer."""
    results = []
    for entry in entries:
        name, prior = _parse_set(entry)
        rows = []
        for method in methods:
            if method in PROJECT_METHODS:
                rows.append(project_row(name, prior, method, cache))
            else:
                summary = run_and_score(dataset_plan(name, prior, cache), method, None, None, out_dir,
                                        progress=progress)
                rows.append({**summary, "method": method})
            print(json.dumps({k: v for k, v in rows[-1].items() if k != "params"}, default=float), flush=True)
        results.append((name, prior, rows))
    return results


def write_section(path: Path, label: str, text: str) -> None:
    """Replace the section ``## <label>`` of ``path`` by ``text`` (or append it)."""
    import re

    head = ("# The classical peers, side by side\n\nMade by `benchmarks/peers.py --table` (see its docstring): "
            "the project's default and geometry-only runs and each peer on the same masked depth, priors and "
            "scorer, one set after the other.\n\n")
    old = path.read_text() if path.exists() else head
    pattern = re.compile(rf"^## {re.escape(label)}\n.*?(?=^## |\Z)", re.S | re.M)
    new = pattern.sub(lambda _: text, old) if pattern.search(old) else old.rstrip("\n") + "\n\n" + text
    path.write_text(new)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default="semilmo,tyol,synthhard")
    ap.add_argument("--prior", default=None, help="a prior instead of each dataset's default (e.g. faulty)")
    ap.add_argument("--peers", default="ppf,fpfh")
    ap.add_argument("--images", type=int, default=None, help="only the first N target images of each dataset")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "peers")
    ap.add_argument("--set", action="append", default=[], metavar="PEER.NAME=VALUE",
                    help="override a parameter, e.g. fpfh.voxel=0.03 (repeatable)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--table", default=None, metavar="SETS",
                    help="the side-by-side table instead: sets as dataset[:prior], comma-separated (e.g. "
                         "realycbv,realycbv:faulty,semilmo,tyol,synthhard), each with --methods")
    ap.add_argument("--methods", default="default,geometry-only,ppf,fpfh", help="with --table")
    ap.add_argument("--cache", type=Path, default=None, help="with --table: the project's cache (a fresh folder "
                                                              "measures every time anew)")
    ap.add_argument("--label", default=None, help="with --table: the section of benchmarks/results/peers.md")
    args = ap.parse_args(argv)
    if args.table:
        methods = [m for m in args.methods.split(",") if m]
        bad = [m for m in methods if m not in PROJECT_METHODS and m not in PEERS]
        if bad:
            raise SystemExit(f"--methods: unknown {', '.join(bad)} (known: {', '.join([*PROJECT_METHODS, *PEERS])})")
        results = run_table([e for e in args.table.split(",") if e], methods, args.cache, args.out,
                            progress=not args.no_progress)
        label = args.label or "table"
        command = "benchmarks/peers.py " + shlex.join(argv if argv is not None else sys.argv[1:])
        md = ROOT / "benchmarks" / "results" / "peers.md"
        write_section(md, label, table_section(label, command, results))
        print(f"wrote {md}")
        return [r for _, _, rows in results for r in rows]
    sets = _parse_sets(args.set)
    peers = [x for x in args.peers.split(",") if x]
    for peer in peers:
        if peer not in PEERS:
            raise SystemExit(f"--peers: unknown peer '{peer}' (known: {', '.join(PEERS)})")
    out_rows = []
    for name in [x for x in args.datasets.split(",") if x]:
        try:
            plan = dataset_plan(name, args.prior)
            ensure_artifacts(plan, progress=not args.no_progress)
        except DatasetUnavailable as e:
            print(f"peers: {e}", file=sys.stderr)
            continue
        except (FileNotFoundError, OSError, ValueError) as e:  # a BopFormatError is a ValueError
            print(f"peers: {name}: {e}", file=sys.stderr)
            continue
        for peer in peers:
            summary = run_and_score(plan, peer, sets.get(peer), args.images, args.out, progress=not args.no_progress)
            print(json.dumps(summary, default=float), flush=True)
            out_rows.append(summary)
    if not out_rows:  # nothing ran is a failure, not an empty result
        raise SystemExit("peers: no dataset could be run (see above)")
    return out_rows


if __name__ == "__main__":
    main()

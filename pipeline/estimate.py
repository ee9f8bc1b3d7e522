"""The whole method on one RGB-D image of one object (``freeze estimate``).

Inputs: the object's model (PLY, mm), an RGB image, a depth PNG, the camera
intrinsics, and a localisation prior for the object: a mask, or only a bounding box.
Output: the model-to-camera pose (R (3, 3), t (3,) mm) with its evidence, an overlay
picture, and the intermediate artifacts in the layout and names the stages use.

Every step calls the library functions the stages call, with the parameters of the run
manifest (``pipeline.config.load_run``), so that one image gives what the pipeline
would give for it:

- model side (cached per model, see :func:`prepare_model`): ``render_templates`` ->
  ``templates.zarr``; ``symmetries`` -> ``symmetries.json``; ``model_features`` ->
  ``features.zarr``;
- scene side: the candidate's depth lifted to points, outliers removed, M sampled,
  geometric and visual features (``scene_features``); PCA + fusion + RANSAC
  (``register``); ICP, evidence = inlier ratio x ICP fitness, and the symmetry-aware
  refinement of a shape with symmetries (``refine``).

The model cache. The model side costs tens of seconds (renders, symmetry search,
features) and depends only on the model and a few parameters, so it is stored under
``<cache root>/_estimate/<key[:8]>/`` (``templates.zarr``, ``symmetries.json``,
``features.zarr``, ``_manifest.json``), published atomically, and reused by later
calls. ``key = sha1(canonical JSON of {the PLY's SHA-1, model scale, the
render_templates, symmetries and model_features parameters of the run, the encoders'
names, versions and cache parameters, the code versions of those stages})``: editing the
model file, scaling it, changing a model-side parameter or an encoder rebuilds it; a
scene-side parameter or another image does not.

Without a mask (bounding box only), the candidate points come from
:func:`box_candidate_points`; its docstring states the rule.

Units and conventions are BOP's: millimetres, OpenCV camera, ``R_m2c``/``t_m2c``;
depth PNGs hold ``depth_mm / depth_scale`` as uint16 (``depth_mm = value *
depth_scale``).
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

CODE_VERSION = 1

MODEL_CACHE_DIR = "_estimate"
"""Folder under the cache root holding the per-model caches of ``freeze estimate``."""

METRE_DIAMETER_LIMIT = 5.0
"""A model whose diameter is below this (in file units) is taken to be in metres."""

MODEL_BUILDS = 0
"""How many times this process built a model cache (tests check it stays put on reuse)."""

OBJ_ID, SCENE_ID, IM_ID, CAND_ID = 1, 0, 0, 0
"""Ids given to the single object, scene, image and candidate in the artifacts' tables."""


class EstimateError(ValueError):
    """Bad input to ``freeze estimate``; the message names the file and the field."""


# ------------------------------------------------------------------------- progress


class Steps:
    """Status line per step with its duration (rich, on stderr); silent when disabled.

    ``with steps("render templates"):`` shows a spinner while the step runs, then
    ``✓ render templates  3.21 s``; the durations are kept in ``timings`` (s).
    """

    def __init__(self, enabled: bool = True, console: Any = None):
        self.enabled = enabled
        self.timings: dict[str, float] = {}
        self._console = console
        if enabled and console is None:
            from rich.console import Console

            self._console = Console(stderr=True)

    def note(self, text: str) -> None:
        if self.enabled:
            self._console.print(f"  [dim]{text}[/]")

    def warn(self, text: str) -> None:
        if self.enabled:
            self._console.print(f"  [yellow]warning:[/] {text}")

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        if not self.enabled:
            yield
            self.timings[name] = time.perf_counter() - t0
            return
        with self._console.status(f"{name} ..."):
            yield
        dt = time.perf_counter() - t0
        self.timings[name] = dt
        self._console.print(f"[green]✓[/] {name:<38} {dt:7.2f} s")


# --------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class Camera:
    """Intrinsics ``K`` (3, 3) float64 (OpenCV) and the depth scale the file gives
    (mm per depth unit; None when it gives none). ``form`` names the JSON form read."""

    K: np.ndarray
    depth_scale: float | None
    form: str


def _number(path: Path, where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise EstimateError(f"{path}: field '{where}' must be a finite number, got {value!r}")
    return float(value)


def load_camera(path: Path | str) -> Camera:
    """Read the intrinsics from a camera JSON file.

    Accepted forms (all numbers in pixels; ``depth_scale`` optional, mm per depth unit):

    - BOP ``scene_camera.json`` entry, also SAM-6D's ``camera.json``:
      ``{"cam_K": [9 floats, row-major], "depth_scale": s}``;
    - a whole BOP ``scene_camera.json`` with a single image: ``{"0": {"cam_K": ...}}``;
    - ``{"K": [[3 floats] x 3]}`` (or 9 floats);
    - BOP ``camera.json``: ``{"fx", "fy", "cx", "cy"}`` (``width``, ``height`` ignored).
    """
    path = Path(path)
    if not path.is_file():
        raise EstimateError(f"{path}: camera file not found")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise EstimateError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(doc, dict):
        raise EstimateError(f"{path}: expected a JSON object with 'cam_K', 'K' or 'fx', 'fy', 'cx', 'cy'")
    prefix = ""
    if not ({"cam_K", "K", "fx"} & set(doc)) and doc and all(isinstance(v, dict) for v in doc.values()):
        # a whole scene_camera.json: {"<im_id>": {...}}
        if len(doc) != 1:
            raise EstimateError(f"{path}: a scene_camera.json with {len(doc)} images; give the entry of one image "
                                "({\"cam_K\": [...], \"depth_scale\": s})")
        prefix, doc = next(iter(doc.items()))
        prefix += "."
    if "cam_K" in doc or "K" in doc:
        name = "cam_K" if "cam_K" in doc else "K"
        raw = doc[name]
        flat = np.asarray(raw, dtype=object).reshape(-1) if isinstance(raw, list) else None
        if flat is None or flat.size != 9 or any(isinstance(v, list) for v in flat):
            raise EstimateError(f"{path}: field '{prefix}{name}' must be 9 numbers (row-major) or a 3x3 list, got {raw!r}")
        K = np.array([_number(path, f"{prefix}{name}", v) for v in flat], dtype=np.float64).reshape(3, 3)
        form = "scene_camera (cam_K)" if name == "cam_K" else "K matrix"
    elif any(k in doc for k in ("fx", "fy", "cx", "cy")):
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in doc]
        if missing:
            raise EstimateError(f"{path}: field '{prefix}{missing[0]}' missing (need fx, fy, cx, cy)")
        fx, fy, cx, cy = (_number(path, f"{prefix}{k}", doc[k]) for k in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        form = "camera.json (fx, fy, cx, cy)"
    else:
        raise EstimateError(f"{path}: no intrinsics: expected field 'cam_K' (BOP/SAM-6D), 'K' or 'fx', 'fy', 'cx', 'cy' "
                            f"(found: {', '.join(map(str, doc)) or 'nothing'})")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise EstimateError(f"{path}: the intrinsics {K.reshape(-1).tolist()} are not a pinhole camera matrix "
                            "(positive fx, fy; last row 0 0 1)")
    scale = None
    if "depth_scale" in doc:
        scale = _number(path, f"{prefix}depth_scale", doc["depth_scale"])
        if scale <= 0:
            raise EstimateError(f"{path}: field '{prefix}depth_scale' must be positive, got {scale}")
    return Camera(K=K, depth_scale=scale, form=form)


def _imread(path: Path, what: str, flags: int) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise EstimateError(f"{path}: {what} file not found")
    im = cv2.imread(str(path), flags)
    if im is None:
        raise EstimateError(f"{path}: cannot decode the {what} image")
    return im


def load_rgb(path: Path | str) -> np.ndarray:
    """(H, W, 3) uint8 RGB; grey is replicated, alpha dropped, 16-bit reduced to 8
    (the BOP reader's conversion, :func:`pipeline.bop.dataset.decoded_to_rgb`)."""
    import cv2

    from pipeline.bop.dataset import decoded_to_rgb

    im = _imread(Path(path), "RGB", cv2.IMREAD_UNCHANGED)
    try:
        return decoded_to_rgb(im, path)
    except ValueError as e:
        raise EstimateError(str(e)) from None


def load_depth(path: Path | str, depth_scale: float) -> np.ndarray:
    """(H, W) float32 depth in mm = raw value * ``depth_scale``, 0 where invalid.

    The file is a single-channel 16-bit PNG (BOP); float images (e.g. TIFF) are read
    as they are and scaled the same way."""
    import cv2

    raw = _imread(Path(path), "depth", cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if raw.ndim != 2:
        raise EstimateError(f"{path}: depth image has {raw.shape[2]} channels; expected a single-channel 16-bit PNG")
    if raw.dtype == np.uint8:
        raise EstimateError(f"{path}: depth image is 8-bit; expected a 16-bit PNG (depth_mm = value * depth_scale)")
    depth = raw.astype(np.float64) * float(depth_scale)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    if not (depth > 0).any():
        raise EstimateError(f"{path}: depth image has no valid (positive) pixel")
    return depth.astype(np.float32)


def load_mask(path: Path | str, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool object mask.

    An image: every non-zero pixel (any channel) is the object (0/255 or 0/1 PNGs,
    colour masks). A ``.json`` file: BOP/CNOS/SAM-6D detections (a list of
    ``{"bbox", "score", "segmentation": RLE, ...}``, e.g. SAM-6D's
    ``detection_ism.json``); the highest-scoring one is used.
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() == ".json":
        from pipeline.bop.detections import load_detections
        from pipeline.bop.errors import BopFormatError

        if not path.is_file():
            raise EstimateError(f"{path}: mask file not found")
        try:
            dets = load_detections(path)
        except BopFormatError as e:
            raise EstimateError(str(e)) from None
        if not dets:
            raise EstimateError(f"{path}: the detection list is empty")
        mask = max(dets, key=lambda d: d.score).mask()
    else:
        im = _imread(path, "mask", cv2.IMREAD_UNCHANGED)
        mask = (im.reshape(im.shape[0], im.shape[1], -1) > 0).any(axis=2)
    if mask.shape != tuple(shape):
        raise EstimateError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} px but the images are {shape[1]}x{shape[0]}")
    if not mask.any():
        raise EstimateError(f"{path}: the mask is empty")
    return mask


def parse_bbox(text: str | Sequence[float]) -> tuple[float, float, float, float]:
    """``"x,y,w,h"`` (pixels, top-left corner, BOP) -> 4 floats; w and h positive."""
    parts = text.replace(" ", "").split(",") if isinstance(text, str) else list(text)
    try:
        vals = tuple(float(v) for v in parts)
    except ValueError:
        vals = ()
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise EstimateError(f"--bbox: expected four numbers x,y,w,h (pixels), got {text!r}")
    if vals[2] <= 0 or vals[3] <= 0:
        raise EstimateError(f"--bbox: width and height must be positive, got {text!r}")
    return vals  # type: ignore[return-value]


def load_run_manifest(overrides: Mapping[str, Any] | None = None):
    """The run manifest with overrides.

    Flat keys go to :func:`pipeline.config.load_run` as on the Snakemake command line
    (``visual=dinov2-vits14``, ``run=manifests/runs/refine-icp.yaml``, ...). Dotted keys
    set one stage parameter: ``register.max_iterations=20000`` or
    ``stages.register.max_iterations=20000`` (values parsed as YAML scalars).
    """
    import yaml

    from pipeline import config as cfg

    flat, dotted = {}, {}
    for k, v in (overrides or {}).items():
        (dotted if "." in k else flat)[k] = v
    run = cfg.load_run(flat)
    if not dotted:
        return run
    data = run.model_dump()
    for k, v in dotted.items():
        path = k.split(".")
        if path[0] != "stages":
            path = ["stages"] + path
        node = data
        for p in path[:-1]:
            if not isinstance(node, dict) or p not in node:
                raise EstimateError(f"--config {k}: unknown key '{p}' (stages: {', '.join(data['stages'])})")
            node = node[p]
        if path[-1] not in node:
            raise EstimateError(f"--config {k}: unknown parameter '{path[-1]}' (known: {', '.join(node)})")
        node[path[-1]] = yaml.safe_load(v) if isinstance(v, str) else v
    try:
        return cfg.RunManifest.model_validate(data)
    except Exception as e:  # pydantic ValidationError: name the field
        raise EstimateError(f"--config: invalid value: {e}") from None


# ---------------------------------------------------------------------- model side


@dataclass
class ModelAssets:
    """The model side of one object, from the cache or just built.

    mesh: the model (mm, after ``model_scale``); diameter (mm); key: model cache key;
    cache_dir: ``<cache>/_estimate/<key[:8]>``; reused: whether it came from the cache;
    features: ``features.zarr`` arrays (points (N, 3) mm, normals, geometric (N, G),
    visual (N, C), view_count (N,)); symmetries: the estimated SymmetrySet.
    """

    path: Path
    mesh: Any
    diameter: float
    key: str
    cache_dir: Path
    reused: bool
    features: dict[str, np.ndarray]
    symmetries: Any
    summary: dict[str, Any] = field(default_factory=dict)


def load_model(path: Path | str, model_scale: float = 1.0):
    """(trimesh mesh in mm, diameter mm) of a PLY, after multiplying by ``model_scale``.

    A model whose diameter is below :data:`METRE_DIAMETER_LIMIT` is rejected as
    probably being in metres (BOP models are in mm)."""
    from pipeline.bop.errors import BopFormatError
    from pipeline.bop.ply import load_mesh
    from pipeline.encoders.lifting import point_cloud_diameter

    path = Path(path)
    if not path.is_file():
        raise EstimateError(f"{path}: model file not found")
    if not (model_scale > 0 and math.isfinite(model_scale)):
        raise EstimateError(f"--model-scale must be a positive number, got {model_scale}")
    try:
        mesh = load_mesh(path)
    except (BopFormatError, ValueError) as e:
        raise EstimateError(f"{path}: cannot read the model: {e}") from None
    if len(mesh.faces) == 0:
        raise EstimateError(f"{path}: the model has no faces (a triangle mesh is needed)")
    if model_scale != 1.0:
        mesh.apply_scale(model_scale)
    diameter = point_cloud_diameter(np.asarray(mesh.vertices))
    if diameter < METRE_DIAMETER_LIMIT:
        raise EstimateError(
            f"{path}: the model's diameter is {diameter:.4g} units{' after --model-scale' if model_scale != 1 else ''}; "
            "models must be in millimetres (BOP) and this one looks like metres: pass --model-scale 1000")
    return mesh, float(diameter)


def _encoder_params(geo, vis, run) -> dict[str, Any]:
    return {"geometric": {"manifest": run.geometric_encoder, "encoder": geo.name, "version": geo.version,
                          "params": geo.cache_params()},
            "visual": {"manifest": run.visual_encoder, "encoder": vis.name, "version": vis.version,
                       "params": vis.cache_params()}}


def model_cache_key(model_sha1: str, model_scale: float, run, geo, vis) -> tuple[str, dict[str, Any]]:
    """(key, params) of a model cache: see the module docstring."""
    from pipeline.store import make_key
    from stages import code_version

    sp = run.stages
    params = {
        "model_scale": float(model_scale),
        "render_templates": sp.render_templates.model_dump(),
        "symmetries": sp.symmetries.model_dump(),
        "model_features": sp.model_features.model_dump(),
        "encoders": _encoder_params(geo, vis, run),
        "stage_code_versions": {s: code_version(s) for s in ("render_templates", "symmetries", "model_features")},
    }
    return make_key("estimate_model", CODE_VERSION, params, {"model": model_sha1}), params


def prepare_model(model_path: Path | str, run, geo, vis, *, model_scale: float = 1.0, cache: Path | None = None,
                  steps: Steps | None = None) -> ModelAssets:
    """Load a model's cached side or build and cache it (templates, symmetries, features).

    run: RunManifest; geo, vis: its encoders (:func:`pipeline.plan.build_encoders`);
    cache: the cache root (default :func:`pipeline.plan.cache_root`).
    """
    from pipeline.geometry.symmetry import SymmetrySet
    from pipeline.plan import cache_root
    from pipeline.store import MANIFEST_NAME, file_sha1, load_arrays, read_manifest

    steps = steps or Steps(False)
    path = Path(model_path)
    with steps("load model"):
        mesh, diameter = load_model(path, model_scale)
        sha1 = file_sha1(path)
    steps.note(f"{path.name}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, diameter {diameter:.1f} mm")
    key, params = model_cache_key(sha1, model_scale, run, geo, vis)
    folder = Path(cache or cache_root()) / MODEL_CACHE_DIR / key[:8]
    reused = False
    if (folder / MANIFEST_NAME).exists() and read_manifest(folder).get("key") == key:
        reused = True
        with steps("model cache (reused)"):
            features = load_arrays(folder / "features.zarr")
            doc = json.loads((folder / "symmetries.json").read_text())
        steps.note(f"model cache {folder}")
    else:
        _build_model_cache(folder, key, params, sha1, path, mesh, diameter, run, geo, vis, steps)
        features = load_arrays(folder / "features.zarr")
        doc = json.loads((folder / "symmetries.json").read_text())
    return ModelAssets(path=path, mesh=mesh, diameter=diameter, key=key, cache_dir=folder, reused=reused,
                       features=features, symmetries=SymmetrySet.from_dict(doc["estimated"]),
                       summary=read_manifest(folder).get("summary", {}))


def _build_model_cache(folder: Path, key: str, params: dict, sha1: str, path: Path, mesh, diameter: float, run, geo, vis,
                       steps: Steps) -> None:
    """render_templates, symmetries and model_features of one model into ``folder``."""
    global MODEL_BUILDS
    from pipeline.geometry.symmetry import SymmetrySet
    from pipeline.model_side import model_features, save_model_features, symmetry_record
    from pipeline.render import Renderer
    from pipeline.render.templates import TemplateViews, render_templates, template_views
    from pipeline.store import item_seed, publish, save_arrays

    MODEL_BUILDS += 1
    sp = run.stages
    rt, sy, mf = sp.render_templates, sp.symmetries, sp.model_features
    item = "model"
    with publish(folder, stage="estimate_model", item=item, key=key, signature=f"{path.stem}-{key[:8]}",
                 params={**params, "model_file": str(path.resolve())}, upstream={"model": sha1},
                 code_version=CODE_VERSION, dataset=MODEL_CACHE_DIR) as w:
        with steps(f"render {rt.n_views} templates"):
            views = template_views(rt.n_views, diameter, rt.image_size, fill=rt.fill, distance_factor=rt.distance_factor)
            # The templates look at the model's bounding-box centre (the origin of BOP
            # models, but not of every model): t_m2c = t - R c puts c on the optical axis.
            v = np.asarray(mesh.vertices)
            c = 0.5 * (v.min(axis=0) + v.max(axis=0))
            views = TemplateViews(R=views.R, t=views.t - views.R @ c, K=views.K, size=views.size)
            with Renderer(rt.image_size, rt.image_size, znear=1.0,
                          zfar=10 * rt.distance_factor * diameter + float(np.linalg.norm(c))) as r:
                r.add_mesh(OBJ_ID, mesh)
                tpl = render_templates(r, OBJ_ID, views)
            save_arrays(w.dir / "templates.zarr", tpl, attrs={"key": key, "obj_id": OBJ_ID, "diameter": diameter})
        with steps("symmetries"):
            sym, doc = symmetry_record(mesh, diameter, n_points=sy.n_points,
                                       sample_seed=item_seed(key, "symmetries", sy.seed), threshold=sy.threshold,
                                       seed=sy.seed, declared=SymmetrySet(), obj_id=OBJ_ID)
            (w.dir / "symmetries.json").write_text(json.dumps(doc, indent=1) + "\n")
        steps.note(f"symmetries: {len(sym.discrete)} discrete, {len(sym.continuous)} continuous")
        with steps(f"model features ({mf.n_points} points)"):
            f = model_features(mesh, tpl, geo, vis, diameter, n_points=mf.n_points,
                               seed=item_seed(key, "model_features", mf.seed), batch_size=mf.batch_size)
            save_model_features(w.dir / "features.zarr", f,
                                {"key": key, "obj_id": OBJ_ID, "diameter": diameter,
                                 "geometric_encoder": geo.signature(), "visual_encoder": vis.signature()})
            n, view_count = len(f["points"]), f["view_count"]
        w.summary.update({"model_file": str(path.resolve()), "model_sha1": sha1, "diameter_mm": diameter,
                          "n_views": rt.n_views, "n_points": int(n), "n_discrete": len(sym.discrete),
                          "n_continuous": len(sym.continuous), "points_unseen": int((view_count == 0).sum()),
                          "seconds": {k: round(v, 3) for k, v in steps.timings.items()}})


# ---------------------------------------------------------------------- scene side


@dataclass
class BoxSelection:
    """What :func:`box_candidate_points` kept: points (P, 3) float32 mm (camera frame),
    their pixels (P, 2) int64 (u, v), and the numbers of each step (for pose.json)."""

    points: np.ndarray
    pixels: np.ndarray
    details: dict[str, Any]


def box_candidate_points(
    depth: np.ndarray,
    K: np.ndarray,
    bbox: Sequence[float],
    diameter: float,
    *,
    centre_frac: float = 0.5,
    radius_frac: float = 1.0,
    plane_frac: float = 0.02,
    plane_min_share: float = 0.15,
    plane_ring_share: float = 0.3,
    ring_frac: float = 0.25,
    cluster_eps_frac: float = 0.05,
    seed: int = 0,
) -> BoxSelection:
    """The object's depth points inside a bounding box, without a mask.

    depth (H, W) float mm; K (3, 3); bbox (x, y, w, h) px; diameter mm. The rule:

    1. *Centre.* Lift the valid depth inside the box; the reference point is the
       per-axis median of the points in the box's central window (``centre_frac`` of
       its width and height): a box prior is centred on its object, so the centre sees
       the object. Keep the points within ``radius_frac`` diameters of it (no point of
       the object is farther from a point of the object).
    2. *Support plane.* Fit the dominant plane (open3d ``segment_plane``, distance
       ``plane_frac`` x diameter, at least 3 mm for sensor noise). It is the table or
       a wall, to be removed, when it holds at least ``plane_min_share`` of the points
       *and* continues outside the box: at least ``plane_ring_share`` of the valid
       pixels of a ring around the box (``ring_frac`` of its longer side wide) lie on
       it. An object's own flat face (a box seen face-on) fills its box too, but ends
       at the box's edge, so it is not removed. Removing it drops the plane's points
       and every point behind it (seen from the camera).
    3. *Cluster.* DBSCAN (``cluster_eps_frac`` x diameter, at least 3 mm) and keep the
       cluster with most points in the central window (ties: the larger), which drops
       parts of neighbouring objects that the box overlaps.

    The scene-side outlier filter of the stages (:func:`pipeline.geometry.depth.remove_outliers`)
    runs afterwards, as for masks.
    """
    import open3d as o3d

    from pipeline.geometry.depth import lift_depth

    H, W = depth.shape
    x, y, w, h = (float(v) for v in bbox)
    x0, y0 = max(0, int(math.floor(x))), max(0, int(math.floor(y)))
    x1, y1 = min(W, int(math.ceil(x + w))), min(H, int(math.ceil(y + h)))
    box = np.zeros((H, W), bool)
    box[y0:y1, x0:x1] = True
    pts, pix = lift_depth(depth, K, box)
    details: dict[str, Any] = {"box_points": int(len(pts))}
    if len(pts) < 10:
        return BoxSelection(pts, pix, details)
    cx, cy = x + w / 2, y + h / 2
    central = (np.abs(pix[:, 0] - cx) <= centre_frac * w / 2) & (np.abs(pix[:, 1] - cy) <= centre_frac * h / 2)
    ref = np.median(pts[central] if central.sum() >= 10 else pts, axis=0)
    keep = np.linalg.norm(pts - ref, axis=1) <= radius_frac * diameter
    details.update({"centre_mm": [round(float(v), 1) for v in ref], "within_radius": int(keep.sum())})

    # 2. dominant plane
    thr = max(3.0, plane_frac * diameter)
    details["plane_removed"] = False
    idx = np.flatnonzero(keep)
    if len(idx) >= 50:
        o3d.utility.random.seed(seed)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx].astype(np.float64)))
        plane, inl = pcd.segment_plane(distance_threshold=thr, ransac_n=3, num_iterations=1000)
        a = np.asarray(plane, float)
        a = a / np.linalg.norm(a[:3])
        if a[3] < 0:  # orient the normal towards the camera (origin on the positive side)
            a = -a
        share = len(inl) / len(idx)
        m = max(1, int(round(ring_frac * max(w, h))))
        ring = np.zeros((H, W), bool)
        ring[max(0, y0 - m):min(H, y1 + m), max(0, x0 - m):min(W, x1 + m)] = True
        ring &= ~box
        ring_pts, _ = lift_depth(depth, K, ring)
        ring_share = float(np.mean(np.abs(ring_pts @ a[:3] + a[3]) <= thr)) if len(ring_pts) else 0.0
        details.update({"plane": [round(float(v), 4) for v in a], "plane_share": round(share, 3), "ring_on_plane": round(ring_share, 3)})
        if share >= plane_min_share and ring_share >= plane_ring_share:
            keep &= (pts @ a[:3] + a[3]) > thr
            details["plane_removed"] = True
    details["after_plane"] = int(keep.sum())

    # 3. the cluster at the centre of the box
    idx = np.flatnonzero(keep)
    if len(idx) >= 10:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx].astype(np.float64)))
        labels = np.asarray(pcd.cluster_dbscan(eps=max(3.0, cluster_eps_frac * diameter), min_points=10))
        if (labels >= 0).any():
            n_lab = labels.max() + 1
            in_centre = np.bincount(labels[(labels >= 0) & central[idx]], minlength=n_lab)
            sizes = np.bincount(labels[labels >= 0], minlength=n_lab)
            best = int(np.lexsort((sizes, in_centre))[-1])
            keep[idx[labels != best]] = False
            details.update({"clusters": int(n_lab), "cluster_points": int(sizes[best])})
    details["kept"] = int(keep.sum())
    return BoxSelection(pts[keep], pix[keep], details)


def _pixels_mask(pixels: np.ndarray, shape: tuple[int, int], grow: int = 2) -> np.ndarray:
    """(H, W) bool mask of the pixels (P, 2) (u, v), closed and grown by ``grow`` px."""
    import cv2

    m = np.zeros(shape, np.uint8)
    m[pixels[:, 1], pixels[:, 0]] = 1
    k = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
    return cv2.dilate(cv2.morphologyEx(m, cv2.MORPH_CLOSE, k), k) > 0


# ------------------------------------------------------------------------- result


@dataclass
class EstimateResult:
    """The estimate: R (3, 3), t (3,) mm model-to-camera, score (inlier ratio x ICP
    fitness), ``record`` (everything written to pose.json), the output files, and
    whether the model side came from the cache."""

    R: np.ndarray
    t: np.ndarray
    score: float
    record: dict[str, Any]
    out_dir: Path | None
    files: dict[str, Path]
    model: ModelAssets
    timings: dict[str, float]

    @property
    def model_cache_reused(self) -> bool:
        return self.model.reused


def _dumps(record: Mapping[str, Any]) -> str:
    """Indented JSON with each innermost list of numbers on one line (matrix rows stay readable)."""
    import re

    text = json.dumps(record, indent=1, allow_nan=False)
    return re.sub(r"\[\s+([-+0-9.eE,\s]+?)\s+\]", lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]",
                  text) + "\n"


def _jsonable(obj: Any) -> Any:
    """Plain JSON values (numpy scalars and arrays converted; NaN and infinities -> None)."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def estimate(
    model: Path | str,
    rgb: Path | str,
    depth: Path | str,
    camera: Path | str,
    *,
    mask: Path | str | None = None,
    bbox: Sequence[float] | str | None = None,
    depth_scale: float | None = None,
    model_scale: float = 1.0,
    out_dir: Path | str | None = None,
    bop_name: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    cache: Path | str | None = None,
    progress: bool = False,
    console: Any = None,
) -> EstimateResult:
    """Estimate the pose of the object ``model`` (PLY, mm) in one RGB-D image.

    mask: object mask (image, or a detections JSON; see :func:`load_mask`), or bbox:
    ``(x, y, w, h)`` px / ``"x,y,w,h"`` (exactly one of them). depth_scale: mm per
    depth unit (default: the camera file's ``depth_scale``, else 1). model_scale:
    multiplies the model's coordinates (1000 for a model in metres). out_dir: where to
    write ``pose.json``, ``overlay.png``, ``points.png`` and the artifacts (nothing
    written when None), and the frame as a one-image BOP dataset
    ``<out_dir>/bop/<bop_name>`` with its prior ``<out_dir>/bop/detections/`` (see
    :func:`pipeline.bop.wrap.wrap_frame`; a previous one of that name is replaced, as
    the other outputs are). bop_name: default :func:`pipeline.bop.wrap.default_name`
    of the model file. overrides: run-manifest overrides (:func:`load_run_manifest`).
    cache: cache root (default ``$FREEZE_CACHE`` or ``<project>/cache``).
    """
    from pipeline.bop import wrap
    from pipeline.plan import build_encoders

    steps = Steps(progress, console)
    if (mask is None) == (bbox is None):
        raise EstimateError("give exactly one localisation prior: --mask MASK.png or --bbox x,y,w,h")
    bop_name = bop_name if bop_name is not None else wrap.default_name(model)
    try:
        wrap.check_name(bop_name)
    except ValueError as e:
        raise EstimateError(f"--bop-name: {e}") from None
    with steps("inputs"):
        run = load_run_manifest(overrides)
        cam = load_camera(camera)
        for name, p in (("model", model), ("RGB", rgb), ("depth", depth)):
            if not Path(p).is_file():
                raise EstimateError(f"{p}: {name} file not found")
        if depth_scale is not None and not (depth_scale > 0 and math.isfinite(depth_scale)):
            raise EstimateError(f"--depth-scale must be a positive number, got {depth_scale}")
        scale = depth_scale if depth_scale is not None else (cam.depth_scale if cam.depth_scale is not None else 1.0)
        scale_src = "--depth-scale" if depth_scale is not None else (f"{camera}" if cam.depth_scale is not None else "default")
        rgb_im = load_rgb(rgb)
        depth_im = load_depth(depth, scale)
        if rgb_im.shape[:2] != depth_im.shape:
            raise EstimateError(f"{depth}: depth is {depth_im.shape[1]}x{depth_im.shape[0]} px but {rgb} is "
                                f"{rgb_im.shape[1]}x{rgb_im.shape[0]}")
        H, W = depth_im.shape
        mask_im = load_mask(mask, (H, W)) if mask is not None else None
        if bbox is not None:
            box = parse_bbox(bbox)
            if box[0] >= W or box[1] >= H or box[0] + box[2] <= 0 or box[1] + box[3] <= 0:
                raise EstimateError(f"--bbox {box}: lies outside the {W}x{H} image")
        else:
            from pipeline.encoders.lifting import mask_to_bbox

            box = tuple(float(v) for v in mask_to_bbox(mask_im))
        geo, vis = build_encoders(run)
    steps.note(f"camera: {cam.form}; depth scale {scale:g} mm/unit ({scale_src}); image {W}x{H}; "
               f"encoders {geo.signature()} + {vis.signature()}")

    assets = prepare_model(model, run, geo, vis, model_scale=model_scale,
                           cache=Path(cache) if cache else None, steps=steps)
    diameter = assets.diameter
    _check_scale(depth_im, cam.K, box, diameter, steps)

    rec = _run_scene(assets, run, geo, vis, rgb_im, depth_im, cam.K, box, mask_im, steps)
    R, t = rec.pop("_R"), rec.pop("_t")
    record: dict[str, Any] = {
        "R": R.tolist(), "t": t.tolist(), "score": rec["score"],
        "cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": t.tolist(),
        **{k: v for k, v in rec.items() if not k.startswith("_") and k != "score"},
        "inputs": {"model": str(Path(model).resolve()), "rgb": str(Path(rgb).resolve()),
                   "depth": str(Path(depth).resolve()), "camera": str(Path(camera).resolve()),
                   "mask": str(Path(mask).resolve()) if mask is not None else None,
                   "prior": "mask" if mask is not None else "bbox", "bbox": [float(v) for v in box],
                   "depth_scale": scale, "depth_scale_from": scale_src, "model_scale": model_scale,
                   "camera_form": cam.form, "K": cam.K.tolist(), "image_size": [W, H]},
        "model": {"diameter_mm": diameter, "cache_dir": str(assets.cache_dir), "cache_key": assets.key,
                  "cache_reused": assets.reused, "n_discrete_symmetries": len(assets.symmetries.discrete),
                  "n_continuous_symmetries": len(assets.symmetries.continuous)},
        "encoders": {"geometric": geo.signature(), "visual": vis.signature()},
        "units": "R: model-to-camera rotation; t: mm (OpenCV camera, BOP convention)",
    }
    files: dict[str, Path] = {}
    if out_dir is not None:
        with steps("write outputs"):
            files = _write_outputs(Path(out_dir), assets, run, geo, vis, rgb_im, depth_im, cam.K, box, R, t, record,
                                   rec["_artifacts"], steps)
        with steps("write BOP dataset"):
            # box prior: the prior's mask is the pixels of the points kept, so the pipeline lifts those same points
            kept = None
            if mask_im is None:
                kept = np.zeros((H, W), bool)
                pix = rec["_artifacts"]["all_pixels"]
                kept[pix[:, 1], pix[:, 0]] = True
            try:
                files["bop"] = wrap.wrap_frame(Path(out_dir) / "bop", bop_name, rgb=rgb_im, depth_mm=depth_im,
                                               K=cam.K, model_path=Path(model), model_scale=model_scale, mask=mask_im,
                                               bbox=box, kept_mask=kept, overwrite=True)
            except ValueError as e:
                raise EstimateError(f"writing the BOP dataset {Path(out_dir) / 'bop' / bop_name}: {e}") from None
            files["bop_prior"] = wrap.detections_path(Path(out_dir) / "bop", bop_name)
    record["timings_s"] = {k: round(v, 3) for k, v in steps.timings.items()}
    record = _jsonable(record)
    if out_dir is not None:
        (Path(out_dir) / "pose.json").write_text(_dumps(record))
    return EstimateResult(R=R, t=t, score=float(rec["score"]), record=record, out_dir=Path(out_dir) if out_dir else None,
                          files=files, model=assets, timings=dict(steps.timings))


def _check_scale(depth: np.ndarray, K: np.ndarray, box: Sequence[float], diameter: float, steps: Steps) -> None:
    """Warn when the box's metric size at its median depth disagrees wildly with the
    model's diameter: a wrong depth scale or model unit."""
    x, y, w, h = box
    H, W = depth.shape
    sub = depth[max(0, int(y)):min(H, int(math.ceil(y + h))), max(0, int(x)):min(W, int(math.ceil(x + w)))]
    z = sub[sub > 0]
    if len(z) == 0:
        raise EstimateError(f"no valid depth inside the box {[round(v, 1) for v in box]}: check the prior and the depth image")
    size_mm = max(w / K[0, 0], h / K[1, 1]) * float(np.median(z))
    if not 0.2 * diameter <= size_mm <= 5 * diameter:
        steps.warn(f"the box spans {size_mm:.0f} mm at its median depth {np.median(z):.0f} mm, but the model's "
                   f"diameter is {diameter:.0f} mm: check --depth-scale and --model-scale")


def _run_scene(assets: ModelAssets, run, geo, vis, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray,
               box: tuple[float, ...], mask: np.ndarray | None, steps: Steps) -> dict[str, Any]:
    """scene_features, register and refine of the one candidate; returns the record."""
    from pipeline.encoders.lifting import crop_and_resize, sample_features_at_pixels, square_crop_box
    from pipeline.geometry.depth import lift_depth, remove_outliers
    from pipeline.geometry.icp import refine_icp
    from pipeline.registration.fusion import apply_pca, fit_pca, fuse
    from pipeline.registration.ransac import RansacParams, register
    from pipeline.registration.selection import estimate_score
    from pipeline.store import item_seed

    sp = run.stages
    sf, rg, rf = sp.scene_features, sp.register, sp.refine
    diameter = assets.diameter
    # A scene key: the seeds of sampling and RANSAC derive from it, so one input gives one answer.
    scene_key = hashlib.sha1(json.dumps({"model": assets.key, "rgb": hashlib.sha1(rgb.tobytes()).hexdigest(),
                                         "depth": hashlib.sha1(depth.tobytes()).hexdigest(),
                                         "K": K.tolist(), "box": list(box),
                                         "mask": hashlib.sha1(np.packbits(mask).tobytes()).hexdigest() if mask is not None else None,
                                         "stages": sp.model_dump()}, sort_keys=True).encode()).hexdigest()
    rec: dict[str, Any] = {}
    with steps("scene points"):
        if mask is not None:
            pts, pix = lift_depth(depth, K, mask)
            rec["prior_details"] = {"mask_pixels": int(mask.sum()), "valid_depth": int(len(pts))}
        else:
            sel = box_candidate_points(depth, K, box, diameter, seed=sf.seed)
            pts, pix = sel.points, sel.pixels
            rec["prior_details"] = sel.details
        if len(pts):
            keep = remove_outliers(pts, diameter)
            pts, pix = pts[keep], pix[keep]
        if len(pts) < sf.min_points:
            raise EstimateError(f"only {len(pts)} valid depth points on the object (< scene_features.min_points "
                                f"{sf.min_points}): check the mask/box, the depth image and --depth-scale")
        rng = np.random.default_rng(item_seed(scene_key, "scene", sf.seed))
        idx = np.sort(rng.choice(len(pts), size=min(sf.n_points, len(pts)), replace=False))
        spts, spix = pts[idx], pix[idx]
        obj_mask = mask if mask is not None else _pixels_mask(pix, depth.shape)
    steps.note(f"{len(pts)} object points kept, {len(spts)} sampled")
    with steps("scene features"):
        sgeo = geo.encode(spts, None, diameter, viewpoint=np.zeros(3))
        crop_box = square_crop_box(box, depth.shape, margin=sf.crop_margin)
        if vis.dim:
            fmap = vis.encode(crop_and_resize(rgb, crop_box, vis.input_size)[None])[0]
            svis = sample_features_at_pixels(fmap, crop_box, vis.input_size, spix.astype(np.float32))
        else:
            svis = np.zeros((len(spts), 0), np.float32)
    with steps("register (RANSAC)"):
        t0 = time.perf_counter()
        m = assets.features
        basis = fit_pca(m["visual"], n_components=rg.pca_dim) if m["visual"].shape[1] else None
        mfused = fuse(m["geometric"], apply_pca(basis, m["visual"]) if basis is not None else None)
        sfused = fuse(sgeo, apply_pca(basis, svis) if basis is not None else None)
        params = RansacParams(inlier_frac=rg.inlier_frac, max_iterations=rg.max_iterations,
                              confidence=rg.confidence, mutual=rg.mutual)
        reg = register(m["points"], mfused, spts, sfused, diameter, params=params,
                       seed=item_seed(scene_key, "register", rg.seed))
        reg_time = time.perf_counter() - t0
    steps.note(f"RANSAC: {reg.n_inliers} inliers of {len(spts)} ({reg.inlier_ratio:.2f}), fitness {reg.fitness:.2f}")
    with steps("refine (ICP)"):
        t0 = time.perf_counter()
        R, t = np.asarray(reg.R, float), np.asarray(reg.t, float)
        fitness, rmse = float(reg.fitness), float("nan")
        if rf.icp:
            res = refine_icp(m["points"], m["normals"], spts, R, t, diameter, max_corr_dist_frac=rf.max_corr_frac,
                             iterations=rf.iterations, point_to_plane=rf.point_to_plane)
            R, t, fitness, rmse = res.R, res.t, float(res.fitness), float(res.inlier_rmse)
        evidence = estimate_score(reg.inlier_ratio, fitness)
        icp_time = time.perf_counter() - t0
    R_icp, t_icp = R.copy(), t.copy()
    sar_rows, sar_variant, sar_reason, sar_scores = [], -1, "", []
    sym = assets.symmetries
    if not rf.sar:
        sar_reason = "sar off"
    elif vis.dim == 0:
        sar_reason = "no visual encoder"
    elif sym.is_trivial:
        sar_reason = "no symmetry"
    else:
        with steps("symmetry-aware refinement"):
            from pipeline.refinement.sar import symmetry_aware_refinement
            from pipeline.render import Renderer

            transforms = np.stack(sym.transforms(rf.sar_step_deg))
            S = vis.input_size
            with Renderer(S, S, znear=1.0, zfar=100000.0) as renderer:
                renderer.add_mesh(OBJ_ID, assets.mesh)
                res = symmetry_aware_refinement(
                    renderer, OBJ_ID, vis, rgb, K, box, R, t, transforms, margin=sf.crop_margin,
                    min_cover=rf.sar_min_cover, min_gain=rf.sar_min_gain, centre=rf.sar_centre,
                    scene_mask=obj_mask if rf.sar_use_mask else None)
            sar_variant = int(res.index)
            R, t = np.asarray(res.R, float), np.asarray(res.t, float)
            sar_scores = [float(s) for s in res.scores]
            for v, (Rv, tv, s) in enumerate(zip(res.Rs, res.ts, res.scores)):
                sar_rows.append({"scene_id": SCENE_ID, "im_id": IM_ID, "obj_id": OBJ_ID, "cand_id": CAND_ID,
                                 "variant": v, "R": np.asarray(Rv, float).reshape(9).tolist(),
                                 "t": np.asarray(tv, float).reshape(3).tolist(), "similarity": float(s),
                                 "chosen": v == sar_variant})
        steps.note(f"SAR: {len(sar_scores)} variants, chose {sar_variant} "
                   f"({'changed' if sar_variant > 0 else 'kept the ICP pose'})")
    rec.update({
        "_R": R, "_t": t, "score": float(evidence),
        "n_inliers": int(reg.n_inliers), "inlier_ratio": float(reg.inlier_ratio),
        "ransac_fitness": float(reg.fitness), "n_correspondences": int(reg.n_correspondences),
        "fitness": fitness, "inlier_rmse_mm": rmse,
        "sar_variant": sar_variant, "sar_reason": sar_reason, "sar_n_variants": len(sar_scores),
        "sar_scores": sar_scores,
        "n_valid_points": int(len(pts)), "n_points": int(len(spts)),
        "coarse": {"R": np.asarray(reg.R).tolist(), "t": np.asarray(reg.t).tolist()},
        "icp": {"R": R_icp.tolist(), "t": t_icp.tolist()},
        "_artifacts": {"points": spts, "pixels": spix, "geometric": sgeo, "visual": svis, "basis": basis,
                       "n_valid": len(pts), "reg": reg, "reg_time": reg_time, "icp_time": icp_time,
                       "fitness": fitness, "rmse": rmse, "evidence": evidence, "R_icp": R_icp, "t_icp": t_icp,
                       "sar_rows": sar_rows, "all_pixels": pix, "obj_mask": obj_mask, "scene_key": scene_key},
    })
    return rec


# ------------------------------------------------------------------------ outputs


def render_overlay(mesh, R: np.ndarray, t: np.ndarray, K: np.ndarray, rgb: np.ndarray,
                   box: Sequence[float] | None = None, caption: str = "", alpha: float = 0.5) -> np.ndarray:
    """(H, W, 3) uint8: ``mesh`` rendered at (R, t mm) blended over ``rgb`` with its
    contour in green, the prior's box in yellow and a caption."""
    import cv2

    from pipeline.render import Renderer
    from pipeline.report.sar_figure import overlay

    H, W = rgb.shape[:2]
    v = np.asarray(mesh.vertices) @ R.T + t
    zfar = float(max(v[:, 2].max(), 1.0)) * 2 + 1000.0
    with Renderer(W, H, znear=1.0, zfar=zfar) as r:
        r.add_mesh("model", mesh)
        color, d = r.render([("model", R, t)], K, rgb=True)
    m = d > 0
    out = overlay(rgb, color, m, alpha=alpha)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 2)
    if box is not None:
        x, y, w, h = (int(round(float(b))) for b in box)
        cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), (255, 220, 0), 1)
    if caption:
        cv2.putText(out, caption, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, caption, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _write_outputs(out: Path, assets: ModelAssets, run, geo, vis, rgb, depth, K, box, R, t, record: dict,
                   art: dict, steps: Steps) -> dict[str, Path]:
    """pose.json (written by the caller), overlay.png, points.png and the artifacts."""
    import cv2
    import pandas as pd

    from pipeline.bop.dataset import save_rgb
    from pipeline.store import publish, save_arrays, write_table
    from stages.refine import CANDIDATE_COLUMNS, POSE_COLUMNS, SAR_COLUMNS

    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {"pose": out / "pose.json"}
    caption = (f"score {record['score']:.3f}  inliers {record['n_inliers']}  ICP fitness {record['fitness']:.2f}"
               + (f"  SAR variant {record['sar_variant']}" if record["sar_variant"] >= 0 else ""))
    files["overlay"] = out / "overlay.png"
    save_rgb(files["overlay"], render_overlay(assets.mesh, R, t, K, rgb, box, caption))
    pts_im = (0.5 * rgb).astype(np.uint8)
    allp = art["all_pixels"]
    pts_im[allp[:, 1], allp[:, 0]] = (0, 200, 0)  # every object point kept
    pts_im[art["pixels"][:, 1], art["pixels"][:, 0]] = (255, 255, 255)  # the M sampled ones
    x, y, w, h = (int(round(float(b))) for b in box)
    cv2.rectangle(pts_im, (x, y), (x + w - 1, y + h - 1), (255, 220, 0), 1)
    files["points"] = out / "points.png"
    save_rgb(files["points"], pts_im)

    H, Wd = depth.shape
    reg = art["reg"]
    common = dict(code_version=CODE_VERSION, dataset="estimate", upstream={"model_cache": assets.key})
    scene_item, obj_item = f"scene_{SCENE_ID:06d}", f"obj_{OBJ_ID:06d}"
    skey = art["scene_key"]

    # model_features: the cached features, copied so the out dir stands alone
    with publish(out / "model_features", stage="model_features", item=obj_item, key=assets.key,
                 signature=f"estimate-{assets.key[:8]}", params={"model_cache": str(assets.cache_dir)},
                 **common) as w:
        shutil.copytree(assets.cache_dir / "features.zarr", w.dir / "features.zarr")
        shutil.copy2(assets.cache_dir / "symmetries.json", w.dir / "symmetries.json")
        w.summary.update({"obj_id": OBJ_ID, "n_points": int(len(assets.features["points"])),
                          "from_cache": str(assets.cache_dir)})
    files["model_features"] = out / "model_features"

    # scene_features: one candidate (C = 1)
    k = len(art["points"])
    M = run.stages.scene_features.n_points
    arrays = {"points": np.full((1, M, 3), np.nan, np.float32), "pixels": np.full((1, M, 2), -1, np.int32),
              "geometric": np.full((1, M, geo.dim), np.nan, np.float32),
              "visual": np.full((1, M, art["visual"].shape[1]), np.nan, np.float32),
              "n_points": np.array([k], np.int32), "cand_id": np.array([CAND_ID], np.int64)}
    arrays["points"][0, :k], arrays["pixels"][0, :k] = art["points"], art["pixels"]
    arrays["geometric"][0, :k], arrays["visual"][0, :k] = art["geometric"], art["visual"]
    cand = pd.DataFrame([{"cand_id": CAND_ID, "scene_id": SCENE_ID, "im_id": IM_ID, "obj_id": OBJ_ID, "score": 1.0,
                          "bbox_x": float(box[0]), "bbox_y": float(box[1]), "bbox_w": float(box[2]),
                          "bbox_h": float(box[3]), "area": int(art["obj_mask"].sum()), "height": H, "width": Wd,
                          "prior": record["inputs"]["prior"], "status": "ok", "reason": "",
                          "n_valid_points": int(art["n_valid"]), "n_points": k}])
    with publish(out / "scene_features", stage="scene_features", item=scene_item, key=skey,
                 signature=f"estimate-{skey[:8]}", params=run.stages.scene_features.model_dump(), **common) as w:
        save_arrays(w.dir / "features.zarr", arrays, chunks={"n_points": (1,), "cand_id": (1,)},
                    attrs={"key": skey, "scene_id": SCENE_ID, "geometric_encoder": geo.signature(),
                           "visual_encoder": vis.signature()})
        write_table(cand, w.dir / "candidates.parquet", metadata={"key": skey})
        write_table(pd.DataFrame([{"scene_id": SCENE_ID, "im_id": IM_ID, "n_candidates": 1,
                                   "time_s": steps.timings.get("scene points", 0) + steps.timings.get("scene features", 0)}]),
                    w.dir / "images.parquet", metadata={"key": skey})
        w.summary.update({"scene_id": SCENE_ID, "n_candidates": 1, "n_ok": 1, "prior": record["inputs"]["prior"],
                          "prior_details": record["prior_details"]})
    files["scene_features"] = out / "scene_features"

    # register: the RANSAC table and the PCA basis
    reg_row = {"cand_id": CAND_ID, "scene_id": SCENE_ID, "im_id": IM_ID, "obj_id": OBJ_ID, "prior_score": 1.0,
               "status": "ok", "reason": "", "R": np.asarray(reg.R, float).reshape(9).tolist(),
               "t": np.asarray(reg.t, float).reshape(3).tolist(), "n_inliers": int(reg.n_inliers),
               "inlier_ratio": float(reg.inlier_ratio), "fitness": float(reg.fitness),
               "n_correspondences": int(reg.n_correspondences), "time_s": art["reg_time"]}
    reg_table = pd.DataFrame([reg_row])
    basis = art["basis"]
    with publish(out / "register", stage="register", item=scene_item, key=skey, signature=f"estimate-{skey[:8]}",
                 params=run.stages.register.model_dump(), **common) as w:
        write_table(reg_table, w.dir / "candidates.parquet", metadata={"key": skey})
        write_table(reg_table.assign(rank=0), w.dir / "poses.parquet", metadata={"key": skey})
        write_table(pd.DataFrame([{"scene_id": SCENE_ID, "im_id": IM_ID, "time_s": art["reg_time"]}]),
                    w.dir / "images.parquet", metadata={"key": skey})
        save_arrays(w.dir / "pca.zarr", {
            "obj_id": np.asarray([OBJ_ID] if basis is not None else [], np.int64),
            "mean": basis.mean[None] if basis is not None else np.zeros((0, 0), np.float32),
            "components": basis.components[None] if basis is not None else np.zeros((0, 0, 0), np.float32),
            "explained_variance": basis.explained_variance[None] if basis is not None else np.zeros((0, 0), np.float32),
            "informative": np.asarray([basis.informative] if basis is not None else [], bool),
        }, attrs={"key": skey, "pca_dim": run.stages.register.pca_dim})
        w.summary.update({"scene_id": SCENE_ID, "n_candidates": 1, "n_registered": 1, "n_poses": 1})
    files["register"] = out / "register"

    # refine: ICP row, the kept pose, SAR variants
    ref_row = {"cand_id": CAND_ID, "scene_id": SCENE_ID, "im_id": IM_ID, "obj_id": OBJ_ID, "prior_score": 1.0,
               "n_inliers": int(reg.n_inliers), "inlier_ratio": float(reg.inlier_ratio),
               "R": art["R_icp"].reshape(9).tolist(), "t": art["t_icp"].reshape(3).tolist(),
               "fitness": art["fitness"], "inlier_rmse": art["rmse"], "evidence": art["evidence"],
               "time_s": art["icp_time"]}
    ref_table = pd.DataFrame([ref_row], columns=CANDIDATE_COLUMNS).assign(selected=True, rank=0, note="")
    pose_row = {"scene_id": SCENE_ID, "im_id": IM_ID, "obj_id": OBJ_ID, "cand_id": CAND_ID,
                "R": np.asarray(R).reshape(9).tolist(), "t": np.asarray(t).reshape(3).tolist(),
                "score": float(record["score"]), "evidence": art["evidence"], "fitness": art["fitness"],
                "inlier_rmse": art["rmse"], "n_inliers": int(reg.n_inliers), "sar_variant": record["sar_variant"],
                "sar_reason": record["sar_reason"]}
    with publish(out / "refine", stage="refine", item=scene_item, key=skey, signature=f"estimate-{skey[:8]}",
                 params=run.stages.refine.model_dump(), **common) as w:
        write_table(ref_table, w.dir / "candidates.parquet", metadata={"key": skey})
        write_table(pd.DataFrame([pose_row], columns=POSE_COLUMNS), w.dir / "poses.parquet", metadata={"key": skey})
        write_table(pd.DataFrame(art["sar_rows"], columns=SAR_COLUMNS), w.dir / "sar.parquet", metadata={"key": skey})
        w.summary.update({"scene_id": SCENE_ID, "n_candidates": 1, "n_poses": 1,
                          "n_sar": int(record["sar_variant"] >= 0), "n_sar_changed": int(record["sar_variant"] > 0)})
    files["refine"] = out / "refine"
    return files

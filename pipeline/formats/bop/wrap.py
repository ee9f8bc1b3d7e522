"""One RGB-D frame of one object as a one-image BOP dataset (written by ``freeze estimate``).

:func:`wrap_frame` writes, under ``<out_root>``::

    <name>/camera.json                          fx fy cx cy width height depth_scale
    <name>/models/obj_<obj_id:06d>.ply          the model in mm (a byte copy when model_scale == 1)
    <name>/models/models_info.json              diameter, min_*, size_* (mm)
    <name>/test_targets_bop19.json              one target, inst_count 1
    <name>/test/<scene_id:06d>/scene_camera.json
    <name>/test/<scene_id:06d>/rgb/<im_id:06d>.png      (lossless; gray/, one channel, for a grey image)
    <name>/test/<scene_id:06d>/depth/<im_id:06d>.png    uint16, depth_mm = value * depth_scale
    <name>/test/<scene_id:06d>/scene_gt.json    only when a ground-truth pose is given
    detections/<detector>_<name>-test.json      one detection, score 1.0 (the localisation prior)

so that :class:`pipeline.formats.bop.BopDataset` reads the frame like any BOP dataset and the
pipeline takes ``<out_root>`` as its ``bop_root`` (prior ``detections/<detector>_<name>-test.json``).
Units are BOP's: mm, OpenCV camera, model-to-camera poses.
"""

from __future__ import annotations

import dataclasses
import math
import re
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np

from .dataset import (
    MIN_DIAMETER_MM,
    CameraInfo,
    GtPose,
    ModelInfo,
    is_grey,
    Target,
    save_depth_png,
    save_rgb,
    write_camera,
    write_image,
    write_models_info,
    write_scene_camera,
    write_scene_gt,
    write_targets,
)
from pipeline.common.store import atomic_dir, atomic_path

from .detections import detection_from_mask, save_detections
from .ply import read_ply, write_ply

NAME_RE = re.compile(r"^[a-z0-9]+$")
"""Dataset names: lowercase letters and digits (BOP file names split on '_' and '-'),
the rule of :class:`pipeline.common.config.DatasetManifest`."""

DETECTOR_RE = re.compile(r"^[a-z0-9]+(-[a-z0-9]+)*$")
"""Detector names: as BOP's ``cnos-fastsam`` (no '_', which separates it from the dataset)."""

DEPTH_SCALE_STEPS = (1.0, 2.0, 2.5, 5.0)
"""Multipliers (times powers of ten) tried when the preferred depth scale overflows uint16."""


def default_name(model_path: Path | str) -> str:
    """BOP dataset name from a model file: its stem lower-cased with every character
    outside [a-z0-9] removed (``obj_000005.ply`` -> ``obj000005``); ``frame`` if nothing is left."""
    return re.sub(r"[^a-z0-9]", "", Path(model_path).stem.lower()) or "frame"


def check_name(name: str) -> str:
    """``name`` if it is a valid BOP dataset name, else ValueError saying the rule."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise ValueError(f"BOP dataset name {name!r}: use lowercase letters and digits only "
                         "(BOP file names split on '_' and '-')")
    return name


def detections_path(out_root: Path | str, name: str, detector: str = "estimate") -> Path:
    """``<out_root>/detections/<detector>_<name>-test.json``."""
    return Path(out_root) / "detections" / f"{detector}_{name}-test.json"


def choose_depth_scale(depth_mm: np.ndarray, preferred: float = 0.1) -> float:
    """Smallest of ``preferred`` x {1, 2, 2.5, 5} x 10^k (k >= 0) at which the largest
    depth (mm) fits in uint16 (``round(max / scale) <= 65535``)."""
    if not (preferred > 0 and math.isfinite(preferred)):
        raise ValueError(f"depth_scale must be a positive number, got {preferred}")
    top = float(np.max(depth_mm, initial=0.0))
    for k in range(12):
        for m in DEPTH_SCALE_STEPS:
            scale = float(f"{preferred * m * 10 ** k:.12g}")  # 2.5, not 2.5000000000000004
            if round(top / scale) <= 65535:
                return scale
    raise ValueError(f"depth up to {top:g} mm does not fit a uint16 depth image")


def box_mask(bbox: Sequence[float], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the pixels of box (x, y, w, h) px, outward-rounded and clipped to the image
    (the region :func:`pipeline.method.geometry.box_points.box_candidate_points` lifts)."""
    H, W = shape
    x, y, w, h = (float(v) for v in bbox)
    m = np.zeros((H, W), bool)
    m[max(0, math.floor(y)):min(H, math.ceil(y + h)), max(0, math.floor(x)):min(W, math.ceil(x + w))] = True
    return m


def model_info_from_vertices(vertices: np.ndarray) -> ModelInfo:
    """models_info entry of (V, 3) vertices in mm: bounding box, and the diameter as the
    largest distance between two vertices, computed exactly over the convex hull's vertices
    (where it is attained; all vertices when the hull is degenerate)."""
    from pipeline.formats.bop.extent import point_cloud_diameter

    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    if len(v) < 2:
        raise ValueError(f"a model needs at least 2 vertices, got {len(v)}")
    lo, hi = v.min(axis=0), v.max(axis=0)
    return ModelInfo(diameter=point_cloud_diameter(v), min_xyz=lo, size_xyz=hi - lo)


def _write_model(src: Path, models_dir: Path, obj_id: int, model_scale: float) -> ModelInfo:
    """models/obj_<obj_id>.ply (byte copy, or scaled to mm) and its texture image; the ModelInfo."""
    if not (model_scale > 0 and math.isfinite(model_scale)):
        raise ValueError(f"model_scale must be a positive number, got {model_scale}")
    ply = read_ply(src)
    dst = models_dir / f"obj_{obj_id:06d}.ply"
    models_dir.mkdir(parents=True, exist_ok=True)
    if ply.texture_file is not None:
        rel = Path(ply.texture_file)
        if rel.is_absolute() or ".." in rel.parts or not (src.parent / rel).is_file():
            raise ValueError(f"{src}: texture file '{ply.texture_file}' must be an existing file beside the model")
        (models_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src.parent / rel, models_dir / rel)
    if model_scale == 1.0:
        shutil.copyfile(src, dst)
        vertices = ply.vertices
    else:
        vertices = (ply.vertices.astype(np.float64) * model_scale).astype(np.float32)
        write_ply(dst, vertices, ply.faces, normals=ply.normals, colors=ply.colors, texture_uv=ply.texture_uv,
                  texture_file=ply.texture_file)
    info = model_info_from_vertices(vertices)
    if info.diameter < MIN_DIAMETER_MM:
        raise ValueError(f"{src}: the model's diameter is {info.diameter:.4g} after model_scale {model_scale:g}; "
                         "BOP models are in mm and this one looks like metres: use model_scale=1000")
    return info


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _same(a: Path, b: Path) -> bool:
    """Whether two files, or two folders' trees, hold the same bytes."""
    if a.is_dir() and b.is_dir():
        return _files(a) == _files(b)
    return a.is_file() and b.is_file() and a.read_bytes() == b.read_bytes()


def wrap_frame(
    out_root: Path | str,
    name: str,
    *,
    rgb: np.ndarray,
    depth_mm: np.ndarray,
    K: np.ndarray,
    model_path: Path | str,
    model_scale: float = 1.0,
    mask: np.ndarray | None = None,
    bbox: Sequence[float] | None = None,
    kept_mask: np.ndarray | None = None,
    obj_id: int = 1,
    scene_id: int = 1,
    im_id: int = 0,
    depth_scale: float = 0.1,
    detector: str = "estimate",
    gt_R: np.ndarray | None = None,
    gt_t: np.ndarray | None = None,
    overwrite: bool = False,
    grey: bool = False,
) -> Path:
    """Write one frame as the BOP dataset ``<out_root>/<name>`` plus its prior (module docstring).

    rgb (H, W, 3) uint8; depth_mm (H, W) float mm, 0 = no depth (NaN and negatives are
    written as 0); K (3, 3) px; model_path: PLY whose coordinates times ``model_scale``
    are mm. The detection: its mask is ``mask`` (H, W) bool if given; else the box
    ``bbox`` (x, y, w, h) px intersected with ``kept_mask`` (H, W) bool, the object
    pixels an estimate kept, when given; else the whole box. Its bbox is ``bbox`` when
    given, else the mask's (BOP toolkit convention). depth_scale: the preferred depth
    unit in mm, made coarser (:func:`choose_depth_scale`) when the farthest depth would
    not fit uint16; the quantisation error is at most half of it. gt_R (3, 3), gt_t (3,)
    mm: a known model-to-camera pose, written to scene_gt.json. The folder and the
    detection file are written under temporary names and renamed into place
    (:func:`pipeline.common.store.atomic_dir`, :func:`pipeline.common.store.atomic_path`); an existing
    dataset or detection file with other contents raises FileExistsError unless
    ``overwrite``. grey: the image is grey (its three channels equal): written to
    ``gray/`` as a one-channel PNG, as ITODD's images are. Returns ``<out_root>/<name>``.
    """
    name = check_name(name)
    if not DETECTOR_RE.match(detector):
        raise ValueError(f"detector name {detector!r}: lowercase letters, digits and '-' only")
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if grey and not is_grey(rgb):
        raise ValueError("grey=True but the image's three channels differ")
    H, W = rgb.shape[:2]
    depth = np.asarray(depth_mm, np.float64)
    if depth.shape != (H, W):
        raise ValueError(f"depth_mm is {depth.shape} but rgb is {(H, W)}")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"K must be a finite (3, 3) matrix, got {K.tolist()}")
    if mask is None and bbox is None:
        raise ValueError("give the object's mask or its bbox (x, y, w, h)")
    if mask is not None:
        det_mask = np.asarray(mask, bool)
    else:
        det_mask = box_mask(bbox, (H, W))
        if kept_mask is not None:
            kept = np.asarray(kept_mask, bool)
            if kept.shape != (H, W):
                raise ValueError(f"kept_mask is {kept.shape} but rgb is {(H, W)}")
            det_mask &= kept
    if det_mask.shape != (H, W) or not det_mask.any():
        raise ValueError(f"the detection mask is empty or not {W}x{H} px (shape {det_mask.shape})")
    if (gt_R is None) != (gt_t is None):
        raise ValueError("give both gt_R and gt_t, or neither")
    scale = choose_depth_scale(depth, depth_scale)

    out_root = Path(out_root)
    dest, det_dest = out_root / name, detections_path(out_root, name, detector)
    try:
        _write_frame(dest, det_dest, rgb, depth, K, scale, model_path, model_scale, det_mask, bbox, obj_id,
                     scene_id, im_id, gt_R, gt_t, overwrite, grey)
    except _Unchanged:  # the same frame is there already: keep it as it is
        pass
    return dest


class _Unchanged(Exception):
    """Raised inside the atomic writes to publish nothing: the files on disk are the same."""


def _write_frame(dest: Path, det_dest: Path, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray,
                 scale: float, model_path, model_scale: float, det_mask: np.ndarray, bbox, obj_id: int,
                 scene_id: int, im_id: int, gt_R, gt_t, overwrite: bool, grey: bool = False) -> None:
    """The writing part of :func:`wrap_frame`."""
    H, W = rgb.shape[:2]
    with atomic_path(det_dest) as det_tmp, atomic_dir(dest) as ds:
        info = _write_model(Path(model_path), ds / "models", obj_id, model_scale)
        write_models_info(ds / "models" / "models_info.json", {obj_id: info})
        write_camera(ds, {"K": K, "width": W, "height": H, "depth_scale": scale})
        write_targets(ds / "test_targets_bop19.json", [Target(scene_id, im_id, obj_id, 1)])
        scene = ds / "test" / f"{scene_id:06d}"
        write_scene_camera(scene / "scene_camera.json", {im_id: CameraInfo(K, scale, W, H)})
        if grey:
            write_image(scene / "gray" / f"{im_id:06d}.png", rgb[..., 0])
        else:
            save_rgb(scene / "rgb" / f"{im_id:06d}.png", rgb)
        save_depth_png(scene / "depth" / f"{im_id:06d}.png", depth, scale)
        if gt_R is not None:
            R = np.asarray(gt_R, np.float64).reshape(3, 3)
            write_scene_gt(scene / "scene_gt.json", {im_id: [GtPose(obj_id, R, np.asarray(gt_t, np.float64).reshape(3))]})
        det = detection_from_mask(scene_id, im_id, obj_id, 1.0, det_mask)
        if bbox is not None:
            det = dataclasses.replace(det, bbox=tuple(float(v) for v in bbox))
        save_detections(det_tmp, [det])
        differs = [p for p, new in ((dest, ds), (det_dest, det_tmp)) if p.exists() and not _same(p, new)]
        if differs and not overwrite:  # raising here publishes nothing and leaves both as they were
            raise FileExistsError(f"{differs[0]}: holds another dataset or prior; choose another name "
                                  "(freeze estimate --bop-name) or pass overwrite=True")
        if not differs and dest.exists() and det_dest.exists():
            raise _Unchanged

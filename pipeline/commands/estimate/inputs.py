"""Inputs of ``freeze estimate``: camera JSON, images, masks, boxes and the model, read
and checked with errors that name the file and the field.

Units and conventions are BOP's: millimetres, OpenCV camera; depth PNGs hold
``depth_mm / depth_scale`` as uint16 (``depth_mm = value * depth_scale``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

METRE_DIAMETER_LIMIT = 5.0
"""A model whose diameter is below this (in file units) is taken to be in metres."""


class EstimateError(ValueError):
    """Bad input to ``freeze estimate``; the message names the file and the field."""


FOCAL_RANGE = (0.005, 1e4)
"""Sane focal lengths, in image sides: fx / width and fy / height between these, a field
of view between about 179 and 0.006 degrees (real lenses: about 0.5 to 5)."""
PRINCIPAL_MARGIN = 1.0
"""How far outside the image, in image sides, the principal point (cx, cy) may lie (a
crop of a larger image has it off-centre, never far off)."""


@dataclass(frozen=True)
class Camera:
    """Intrinsics ``K`` (3, 3) float64 (OpenCV) and the depth scale the file gives
    (mm per depth unit; None when it gives none). ``form`` names the JSON form read;
    ``path`` the file and ``fields`` the name in it of each of ``fx``, ``fy``, ``cx``,
    ``cy`` (e.g. ``cam_K[0]``), for the messages of :func:`check_intrinsics`."""

    K: np.ndarray
    depth_scale: float | None
    form: str
    path: Path | None = None
    fields: dict[str, str] = field(default_factory=dict)


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
        try:
            flat = np.asarray(raw, dtype=object).reshape(-1) if isinstance(raw, list) else None
        except ValueError:  # ragged nested lists
            flat = None
        if flat is None or flat.size != 9 or any(isinstance(v, list) for v in flat):
            raise EstimateError(f"{path}: field '{prefix}{name}' must be 9 numbers (row-major) or a 3x3 list, got {raw!r}")
        nested = isinstance(raw[0], list)
        element = [f"{prefix}{name}[{i // 3}][{i % 3}]" if nested else f"{prefix}{name}[{i}]" for i in range(9)]
        K = np.array([_number(path, element[i], v) for i, v in enumerate(flat)], dtype=np.float64).reshape(3, 3)
        form = "scene_camera (cam_K)" if name == "cam_K" else "K matrix"
    elif any(k in doc for k in ("fx", "fy", "cx", "cy")):
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in doc]
        if missing:
            raise EstimateError(f"{path}: field '{prefix}{missing[0]}' missing (need fx, fy, cx, cy)")
        fx, fy, cx, cy = (_number(path, f"{prefix}{k}", doc[k]) for k in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        form = "camera.json (fx, fy, cx, cy)"
        element = [f"{prefix}{k}" for k in ("fx", "", "cx", "", "fy", "cy", "", "", "")]
    else:
        raise EstimateError(f"{path}: no intrinsics: expected field 'cam_K' (BOP/SAM-6D), 'K' or 'fx', 'fy', 'cx', 'cy' "
                            f"(found: {', '.join(map(str, doc)) or 'nothing'})")
    fields = {"fx": element[0], "fy": element[4], "cx": element[2], "cy": element[5]}
    for k in ("fx", "fy"):
        v = K[(0, 0) if k == "fx" else (1, 1)]
        if v <= 0:
            raise EstimateError(f"{path}: field {_label(fields[k], k)} = {v:.6g}: the focal length must be a positive "
                                "number of pixels")
    # a pinhole camera matrix is upper triangular with last row 0 0 1: [[fx, s, cx], [0, fy, cy], [0, 0, 1]]
    for (r, c), want in (((1, 0), 0.0), ((2, 0), 0.0), ((2, 1), 0.0), ((2, 2), 1.0)):
        if not math.isclose(K[r, c], want, rel_tol=1e-9, abs_tol=1e-8):
            raise EstimateError(f"{path}: field '{element[3 * r + c]}' = {K[r, c]:.6g} must be {want:g}: a pinhole "
                                "camera matrix is [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (row-major)")
    scale = None
    if "depth_scale" in doc:
        scale = _number(path, f"{prefix}depth_scale", doc["depth_scale"])
        if scale <= 0:
            raise EstimateError(f"{path}: field '{prefix}depth_scale' must be positive, got {scale}")
    return Camera(K=K, depth_scale=scale, form=form, path=path, fields=fields)


def _label(name: str, quantity: str) -> str:
    """``'cam_K[0]' (fx)``, or ``'fx'`` when the field is named as the quantity."""
    return f"'{name}'" if name.rsplit(".", 1)[-1] == quantity else f"'{name}' ({quantity})"


def check_intrinsics(cam: Camera, width: int, height: int) -> None:
    """Refuse intrinsics that no camera taking a ``width`` x ``height`` px image has: a
    focal length outside :data:`FOCAL_RANGE` image sides, or a principal point more than
    :data:`PRINCIPAL_MARGIN` image sides outside the image. One line naming the file,
    the field and its value, and what is expected (else the error would surface at the
    end of the run, blamed on the mask or the depth)."""
    K = cam.K
    where = f"{cam.path}: field" if cam.path is not None else "intrinsics:"
    lo, hi = FOCAL_RANGE
    fov = [math.degrees(2 * math.atan(1 / (2 * f))) for f in (hi, lo)]
    for k, v, side in (("fx", K[0, 0], width), ("fy", K[1, 1], height)):
        if not lo * side <= v <= hi * side:
            raise EstimateError(f"{where} {_label(cam.fields.get(k, k), k)} = {v:.6g} px is no focal length for a "
                                f"{width}x{height} image: expected {lo * side:.6g} to {hi * side:.6g} px (a field of "
                                f"view of {fov[0]:.2g} to {fov[1]:.0f} degrees; real lenses give about "
                                f"{0.5 * side:.0f} to {5 * side:.0f})")
    m = PRINCIPAL_MARGIN
    for k, v, side in (("cx", K[0, 2], width), ("cy", K[1, 2], height)):
        if not -m * side <= v <= (1 + m) * side:
            raise EstimateError(f"{where} {_label(cam.fields.get(k, k), k)} = {v:.6g} px puts the principal point far "
                                f"outside the {width}x{height} image: expected {-m * side:.6g} to {(1 + m) * side:.6g} "
                                f"px (near the image centre, {side / 2:g})")


def check_prior_size(prior: np.ndarray, depth: np.ndarray, K: np.ndarray, diameter: float, *, min_area: int,
                     min_points: int, what: str) -> None:
    """Refuse a prior the stages would drop, before any of them runs: a mask ``prior``
    (H, W) bool of fewer than ``min_area`` pixels (segment_prior's ``min_area``), or
    with fewer than ``min_points`` object points (scene_features' ``min_points``: the
    valid depth under it, outliers removed, as the stage counts them; ``depth`` (H, W)
    mm, ``K`` (3, 3), ``diameter`` mm). ``what`` names the prior (``--mask FILE``,
    ``--bbox x,y,w,h``) in the message, which names the parameter to change."""
    from pipeline.method.scene_side import candidate_points

    area = int(np.count_nonzero(prior))
    if area < min_area:
        raise EstimateError(f"{what}: the prior's mask has {area} pixel{'s' * (area != 1)}, below segment_prior.min_area "
                            f"= {min_area}, so no candidate would be left: give the object's whole mask or box, or "
                            f"lower the limit with -c segment_prior.min_area={max(area, 1)}")
    n = len(candidate_points(depth, K, prior, diameter)[0])
    if n < min_points:
        raise EstimateError(f"{what}: the prior holds {n} valid depth point{'s' * (n != 1)} of the object, below "
                            f"scene_features.min_points = {min_points}, so the candidate would be skipped: check the "
                            "prior, the depth image and --depth-scale"
                            + (f", or lower the limit with -c scene_features.min_points={n}" if n >= 3 else ""))


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
    (the BOP reader's conversion, :func:`pipeline.formats.bop.dataset.decoded_to_rgb`)."""
    return load_rgb_and_mode(path)[0]


def load_rgb_and_mode(path: Path | str) -> tuple[np.ndarray, str | None]:
    """(the image as :func:`load_rgb` returns it, why it is grey or None for colour).

    An image is grey when the file has a single channel, or when its
    three colour channels are identical at every pixel (a grey picture saved as RGB;
    JPEG keeps them identical). The frame's dataset manifest then says so (``image_dir:
    gray``), and templates and SAR renders are made grey to look like it."""
    import cv2

    from pipeline.formats.bop.dataset import decoded_to_rgb, is_grey

    im = _imread(Path(path), "RGB", cv2.IMREAD_UNCHANGED)
    try:
        rgb = decoded_to_rgb(im, path)
    except ValueError as e:
        raise EstimateError(str(e)) from None
    if im.ndim == 2 or im.shape[2] == 1:
        return rgb, "a single-channel image"
    if is_grey(rgb):
        return rgb, "its three channels are identical"
    return rgb, None


def load_depth(path: Path | str, depth_scale: float) -> np.ndarray:
    """(H, W) float32 depth in mm = raw value * ``depth_scale``, 0 where invalid.

    The file is a single-channel 16-bit PNG (BOP); float images (e.g. TIFF) are read
    as they are and scaled the same way: the BOP reader's rule,
    :func:`pipeline.formats.bop.dataset.depth_format_problem`."""
    import cv2

    from pipeline.formats.bop.dataset import depth_format_problem

    raw = _imread(Path(path), "depth", cv2.IMREAD_UNCHANGED)
    problem = depth_format_problem(raw)
    if problem:
        raise EstimateError(f"{path}: {problem} (depth_mm = value * depth_scale)")
    raw = raw.reshape(raw.shape[:2])
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
        from pipeline.formats.bop.detections import load_detections
        from pipeline.formats.bop.errors import BopFormatError

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


def load_model(path: Path | str, model_scale: float = 1.0):
    """(trimesh mesh in mm, diameter mm) of a PLY, after multiplying by ``model_scale``.

    A model whose diameter is below :data:`METRE_DIAMETER_LIMIT` is rejected as
    probably being in metres (BOP models are in mm)."""
    from pipeline.formats.bop.errors import BopFormatError
    from pipeline.formats.bop.ply import load_mesh
    from pipeline.formats.bop.extent import point_cloud_diameter

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
        if model_scale == 1.0:
            raise EstimateError(f"{path}: the model's diameter is {diameter:.4g} units, too small for millimetres "
                                f"(models must be in mm, as BOP's are); it looks like metres: pass --model-scale 1000")
        raise EstimateError(f"{path}: the model's diameter is {diameter:.4g} mm after --model-scale {model_scale:g}, "
                            f"too small for an object; models must be in mm: check --model-scale (1000 for metres)")
    return mesh, float(diameter)


def scale_warning(depth: np.ndarray, K: np.ndarray, box: Sequence[float], diameter: float) -> str | None:
    """A warning when the box's metric size at its median depth disagrees wildly with the
    model's diameter: a wrong depth scale or model unit."""
    x, y, w, h = box
    H, W = depth.shape
    sub = depth[max(0, int(y)):min(H, int(math.ceil(y + h))), max(0, int(x)):min(W, int(math.ceil(x + w)))]
    z = sub[sub > 0]
    if len(z) == 0:
        raise EstimateError(f"no valid depth inside the box {[round(v, 1) for v in box]}: check the prior and the depth image")
    size_mm = max(w / K[0, 0], h / K[1, 1]) * float(np.median(z))
    if not 0.2 * diameter <= size_mm <= 5 * diameter:
        return (f"the box spans {size_mm:.0f} mm at its median depth {np.median(z):.0f} mm, but the model's "
                f"diameter is {diameter:.0f} mm: check --depth-scale and --model-scale")
    return None

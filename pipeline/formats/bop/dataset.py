"""Reader and writers for a BOP dataset directory.

Layout (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md)::

    <root>/camera[_<split_type>].json
    <root>/models[_eval]/models_info.json, obj_<obj_id:06d>.ply
    <root>/test_targets_bop19.json
    <root>/<split>[_<split_type>]/<scene_id:06d>/
        scene_camera.json  scene_gt.json  scene_gt_info.json
        rgb|gray/<im_id:06d>.png|jpg|tif  depth/<im_id:06d>.png|tif
        mask/<im_id:06d>_<gt_id:06d>.png  mask_visib/...

Poses are model-to-camera, R (3, 3) float64 and t (3,) float64 in mm; depth images are
raw integers times ``depth_scale`` = mm. JSON files are parsed once per instance.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import cv2
import numpy as np

from .errors import BopFormatError
from .jsonio import brief, load_json, save_bop_json
from .ply import load_mesh

if TYPE_CHECKING:  # trimesh costs ~0.7 s to import; scoring and most commands never build a mesh
    import trimesh

_RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
_DEPTH_EXTS = (".png", ".tif", ".tiff")
DEFAULT_TARGETS = "test_targets_bop19.json"
MIN_DIAMETER_MM = 5.0
"""Models are in mm; a smaller diameter means the model is in metres (checked by
``freeze datasets check`` and when ``freeze estimate`` wraps a frame)."""


# ---------------------------------------------------------------------------- records


@dataclass
class ModelInfo:
    """Entry of models_info.json. Lengths in mm.

    min_xyz, size_xyz: (3,) float64 bounding box corner and extent.
    symmetries_discrete: list of (4, 4) float64 transforms (translation in mm).
    symmetries_continuous: list of {"axis": (3,) float64, "offset": (3,) float64 mm}.
    """

    diameter: float
    min_xyz: np.ndarray
    size_xyz: np.ndarray
    symmetries_discrete: list[np.ndarray] = field(default_factory=list)
    symmetries_continuous: list[dict[str, np.ndarray]] = field(default_factory=list)

    @property
    def is_symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)


@dataclass
class CameraInfo:
    """Per-image camera of scene_camera.json.

    K: (3, 3) float64 OpenCV intrinsics (px). depth_scale: raw depth unit in mm.
    width, height: image size in px. R_w2c (3, 3) / t_w2c (3,) mm: world-to-camera
    pose when the dataset gives it, else None.
    """

    K: np.ndarray
    depth_scale: float
    width: int
    height: int
    R_w2c: np.ndarray | None = None
    t_w2c: np.ndarray | None = None


@dataclass
class GtPose:
    """One annotated instance: R (3, 3) float64, t (3,) float64 mm, model-to-camera."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray


@dataclass
class GtInfo:
    """Visibility statistics of one instance (scene_gt_info.json); boxes are (x, y, w, h) px."""

    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float


@dataclass(frozen=True)
class Target:
    """One evaluation target: ``inst_count`` instances of ``obj_id`` in image (scene_id, im_id)."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


# ---------------------------------------------------------------------------- field parsing


def _get(path: Path, d: Any, key: str, entry: Any = None) -> Any:
    """Field ``key`` of the JSON object ``d`` (entry ``entry`` of the file at ``path``)."""
    if not isinstance(d, dict):
        where = f"entry {entry}: " if entry is not None else ""
        raise BopFormatError(f"{path}: {where}expected an object, got {type(d).__name__}")
    if key not in d:
        where = f"entry {entry}, " if entry is not None else ""
        raise BopFormatError(f"{path}: {where}field '{key}' missing")
    return d[key]


def _floats(path: Path, value: Any, n: int, key: str, entry: Any = None) -> np.ndarray:
    """(n,) float64 of a JSON number or (nested) list of numbers, all finite.

    Strings, bools and ints beyond float64 are refused: numpy would parse "1.5", count
    True as 1, or raise OverflowError.
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested lists
        arr = None
    ok = arr is not None and arr.dtype.kind in "iuf" and arr.size == n
    if ok:
        arr = arr.astype(np.float64).reshape(-1)
        ok = bool(np.all(np.isfinite(arr)))
    if not ok:
        where = f"entry {entry}, " if entry is not None else ""
        raise BopFormatError(f"{path}: {where}field '{key}': expected {n} finite numbers, got {brief(value)}")
    return arr


def _int(path: Path, value: Any, key: str, entry: Any = None) -> int:
    """A JSON integer (an integral float such as 3.0 is accepted)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not value.is_integer()):
        where = f"entry {entry}, " if entry is not None else ""
        raise BopFormatError(f"{path}: {where}field '{key}': expected an integer, got {brief(value)}")
    return int(value)


def _int_key(path: Path, key: str) -> int:
    """The id of a JSON object key: ASCII digits ("7", "000007"); int() would also take
    " 7", "1_0" and other scripts' digits."""
    if not (isinstance(key, str) and key.isascii() and key.isdigit() and len(key) <= 18):
        raise BopFormatError(f"{path}: key {brief(key)} is not an integer id")
    return int(key)


def _id_items(path: Path, content: Any, what: str) -> list[tuple[int, str, Any]]:
    """(id, key, value) of a JSON object keyed by ids (``what``: "im_id", "obj_id").

    Two keys of the same id ("1" and "01") would silently overwrite each other.
    """
    if not isinstance(content, dict):
        raise BopFormatError(f"{path}: expected an object keyed by {what}, got {type(content).__name__}")
    keys: dict[int, str] = {}
    out = []
    for key, value in content.items():
        i = _int_key(path, key)
        if i in keys:
            raise BopFormatError(f"{path}: key {brief(key)} repeats id {i} (key {brief(keys[i])})")
        keys[i] = key
        out.append((i, key, value))
    return out


def _json_list(path: Path, value: Any, what: str, entry: Any = None) -> list:
    """``value`` if it is a JSON list, else BopFormatError naming ``what``."""
    if not isinstance(value, list):
        where = f"entry {entry}, " if entry is not None else ""
        raise BopFormatError(f"{path}: {where}field '{what}': expected a list, got {type(value).__name__}")
    return value


def parse_models_info(path: Path, content: Any) -> dict[int, ModelInfo]:
    """ModelInfo per obj_id from the parsed JSON of a models_info.json file."""
    out: dict[int, ModelInfo] = {}
    for obj_id, _, d in _id_items(path, content, "obj_id"):
        e = f"obj {obj_id}"
        diameter = float(_floats(path, _get(path, d, "diameter", e), 1, "diameter", e)[0])
        mins = np.array([float(_floats(path, _get(path, d, f"min_{a}", e), 1, f"min_{a}", e)[0]) for a in "xyz"])
        sizes = np.array([float(_floats(path, _get(path, d, f"size_{a}", e), 1, f"size_{a}", e)[0]) for a in "xyz"])
        disc = [
            _floats(path, s, 16, f"symmetries_discrete[{i}]", e).reshape(4, 4)
            for i, s in enumerate(_json_list(path, d.get("symmetries_discrete", []), "symmetries_discrete", e))
        ]
        cont = []
        for i, s in enumerate(_json_list(path, d.get("symmetries_continuous", []), "symmetries_continuous", e)):
            k = f"symmetries_continuous[{i}]"
            cont.append(
                {
                    "axis": _floats(path, _get(path, s, "axis", f"{e} {k}"), 3, f"{k}.axis", e),
                    "offset": _floats(path, s.get("offset", [0, 0, 0]), 3, f"{k}.offset", e),
                }
            )
        out[obj_id] = ModelInfo(diameter, mins, sizes, disc, cont)
    return dict(sorted(out.items()))


# ---------------------------------------------------------------------------- reader


def is_grey(rgb: np.ndarray) -> bool:
    """Whether an (H, W, 3) image's three channels are equal at every pixel (a grey
    picture, as :func:`decoded_to_rgb` makes of a one-channel file)."""
    return bool(np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2]))


def decoded_to_rgb(im: np.ndarray, path: Path | str) -> np.ndarray:
    """An image as ``cv2.imread(..., IMREAD_UNCHANGED)`` returns it -> (H, W, 3) uint8 RGB:
    16-bit grey (ITODD-like) keeps its top 8 bits, grey is replicated to 3 channels,
    alpha is dropped. ``path`` only names the file in the error for other dtypes."""
    if im.dtype == np.uint16:
        im = (im >> 8).astype(np.uint8)
    if im.dtype != np.uint8:
        raise BopFormatError(f"{path}: unsupported image dtype {im.dtype}")
    if im.ndim == 2:
        return np.repeat(im[:, :, None], 3, axis=2)
    if im.shape[2] == 4:
        return cv2.cvtColor(im, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(im, cv2.COLOR_BGR2RGB)


def depth_format_problem(raw: np.ndarray) -> str | None:
    """None if ``raw`` (a depth image as ``cv2.imread(..., IMREAD_UNCHANGED)`` returns
    it) is usable depth, else a one-line reason. The one rule for depth images, shared
    by the dataset reader, ``freeze datasets check --deep`` and ``freeze estimate``:
    a single channel of uint16 (BOP's PNG/TIF, value * depth_scale = mm) or of floats
    (float TIFFs, read the same way). 8-bit depth is refused: 256 levels cannot hold a
    scene's depth, so such a file is a visualisation or a wrongly saved export, and
    reading it would give wrong poses without a word."""
    channels = 1 if raw.ndim == 2 else raw.shape[2]
    if channels == 1 and (raw.dtype == np.uint16 or np.issubdtype(raw.dtype, np.floating)):
        return None
    got = f"{channels}-channel {raw.dtype}" if channels != 1 else f"{raw.dtype}"
    return f"depth must be 16-bit single-channel PNG/TIF, got {got}"


MAX_FOV_DEG = 170.0
"""Widest field of view a pinhole ``cam_K`` may give across its image: a focal length of
a few pixels (fx = 1e-300) or zero is not a camera a depth image can be lifted with."""
MIN_FOV_DEG = 0.1
"""Narrowest field of view: a focal length beyond ~570 image widths is no real lens."""


def _focal_range(size_px: int) -> tuple[float, float]:
    """(smallest, largest) plausible focal length in px for an image side of ``size_px``
    px: the fields of view :data:`MAX_FOV_DEG` and :data:`MIN_FOV_DEG` across it."""
    half = 0.5 * float(size_px)
    return (half / np.tan(np.radians(MAX_FOV_DEG / 2)), half / np.tan(np.radians(MIN_FOV_DEG / 2)))


def depth_scale_problem(bop: BopDataset, scene_id: int, expected: float, stated_by: str) -> str | None:
    """None if every image of scene ``scene_id`` declares ``depth_scale`` ``expected``
    (mm per unit, relative tolerance 1e-6) in its scene_camera.json, else a one-line
    reason naming the file, the first image that departs and the field; ``stated_by``
    says who states the value (a manifest's path). The one rule shared by the real-sample
    builder and ``freeze datasets check``; a scene_camera.json that cannot be read raises
    as the reader does."""
    for im_id, cam in sorted(bop.scene_camera(scene_id).items()):
        if not math.isclose(cam.depth_scale, expected, rel_tol=1e-6):
            return (f"{bop.scene_dir(scene_id) / 'scene_camera.json'}: image {im_id}: field 'depth_scale' is "
                    f"{cam.depth_scale}, but {stated_by} states {expected}")
    return None


def intrinsics_problem(K: np.ndarray, width: int, height: int) -> str | None:
    """None if ``K`` ((3, 3) float64, px) is a plausible pinhole camera matrix for a
    ``width`` x ``height`` px image, else a one-line reason (without the file's name).

    The one rule for intrinsics, shared by the dataset reader and ``freeze datasets
    check``. Refused: non-finite entries; focal lengths that are not positive or give a
    field of view wider than :data:`MAX_FOV_DEG` or narrower than :data:`MIN_FOV_DEG`;
    a principal point more than one image side outside the image (cropped images keep
    theirs near the frame; cy = 1e9 is no camera); a matrix that is not upper triangular
    with last row 0 0 1. Skew (K[0, 1]) is allowed, as in OpenCV's model."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return f"expected 9 finite numbers, got {brief(K.reshape(-1).tolist())}"
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    if fx <= 0 or fy <= 0:
        # (no "[fx, ...": rich would take it for markup where a command prints the line)
        return f"focal lengths must be positive, got fx={fx:g}, fy={fy:g} (cam_K is fx 0 cx 0 fy cy 0 0 1, in px)"
    if not (np.allclose(K[2], [0.0, 0.0, 1.0], rtol=0, atol=1e-6) and K[1, 0] == 0):
        return (f"not a pinhole camera matrix: expected fx 0 cx 0 fy cy 0 0 1, got "
                f"{brief(K.reshape(-1).tolist())}")
    for name, f, side, what in (("fx", fx, width, "wide"), ("fy", fy, height, "high")):
        lo, hi = _focal_range(side)
        if not lo <= f <= hi:
            return (f"{name}={f:g} px is no camera for an image {side} px {what} (expected {lo:.3g} to {hi:.3g} px: "
                    f"a field of view between {MIN_FOV_DEG:g} and {MAX_FOV_DEG:g} degrees)")
    for name, c, side in (("cx", cx, width), ("cy", cy, height)):
        if not -side <= c <= 2 * side:
            return (f"principal point {name}={c:g} px lies far outside the {width}x{height} px image "
                    f"(expected {-side} to {2 * side} px)")
    return None


def read_depth_image(path: Path | str) -> np.ndarray:
    """The raw (H, W) depth image at ``path``: uint16 (or float) depth units, not yet
    multiplied by depth_scale. Raises ``BopFormatError`` naming the file when it cannot
    be decoded or breaks :func:`depth_format_problem`."""
    # IMREAD_UNCHANGED, not IMREAD_ANYDEPTH: the latter folds 3 channels to grey silently,
    # hiding a colourised depth export.
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise BopFormatError(f"{path}: cannot decode depth image")
    problem = depth_format_problem(raw)
    if problem:
        raise BopFormatError(f"{path}: {problem}")
    if raw.ndim == 3:  # a single channel kept as (H, W, 1) by some decoders
        raw = raw[:, :, 0]
    return raw


class BopDataset:
    """Read-only view of one split of a BOP dataset.

    root: dataset folder (holding camera.json, models/, <split>/). split: "test",
    "val", "train_pbr"... split_type: e.g. "primesense" for T-LESS, which selects the
    folder ``<split>_<split_type>`` and ``camera_<split_type>.json``. models_dir:
    the model folder used by ``model_path(eval=False)`` ("models", or T-LESS's
    "models_cad"/"models_reconst"). camera_file: the camera file when it is not
    ``camera[_<split_type>].json`` (YCB-V ships ``camera_uw.json`` and ``camera_cmu.json``).

    Datasets that ship only ``models_eval`` (e.g. the HOPE validation sample) fall
    back to it, with a warning, since those meshes carry no colour.
    """

    def __init__(self, root: Path | str, split: str = "test", split_type: str | None = None, models_dir: str = "models",
                 camera_file: str | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise BopFormatError(f"{self.root}: dataset root is not a directory")
        self.split = split
        self.split_type = split_type
        self.models_dir = models_dir
        self.camera_file = camera_file
        self.split_dir = self.root / (f"{split}_{split_type}" if split_type else split)
        self._json_cache: dict[Path, Any] = {}
        self._models_info: dict[int, ModelInfo] | None = None
        self._scene_camera: dict[int, dict[int, CameraInfo]] = {}
        self._camera_problems: dict[int, list[str]] = {}
        self._scene_gt: dict[int, dict[int, list[GtPose]]] = {}
        self._scene_gt_info: dict[int, dict[int, list[GtInfo]]] = {}
        self._warned_eval_fallback = False

    def __repr__(self) -> str:
        return f"BopDataset(root={str(self.root)!r}, split={self.split!r}, split_type={self.split_type!r})"

    @property
    def name(self) -> str:
        """Dataset name as BOP spells it (the root folder name, e.g. "lmo", "icbin")."""
        return self.root.name

    def _json(self, path: Path) -> Any:
        if path not in self._json_cache:
            self._json_cache[path] = load_json(path)
        return self._json_cache[path]

    # -- camera and models

    def camera_path(self) -> Path:
        if self.camera_file:
            return self.root / self.camera_file
        if self.split_type:
            typed = self.root / f"camera_{self.split_type}.json"
            if typed.is_file():
                return typed
        return self.root / "camera.json"

    def camera(self) -> dict:
        """Contents of camera.json plus ``K`` (3, 3) float64 built from fx, fy, cx, cy."""
        path = self.camera_path()
        cam = self._json(path)
        if not isinstance(cam, dict):
            raise BopFormatError(f"{path}: expected an object with fx, fy, cx, cy, got {type(cam).__name__}")
        cam = dict(cam)  # a copy: the parsed JSON is cached
        fx, fy, cx, cy = (float(_floats(path, _get(path, cam, k), 1, k)[0]) for k in ("fx", "fy", "cx", "cy"))
        cam["K"] = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cam

    def _model_dir(self, eval: bool, warn: bool = True) -> Path:
        if eval:
            return self.root / "models_eval"
        d = self.root / self.models_dir
        if not d.is_dir() and (self.root / "models_eval").is_dir():
            if warn and not self._warned_eval_fallback:
                warnings.warn(
                    f"{self.root}: no '{self.models_dir}/' folder, using 'models_eval/' (geometry only, no colour)",
                    stacklevel=3,
                )
                self._warned_eval_fallback = True
            return self.root / "models_eval"
        return d

    def models_info_path(self) -> Path:
        for d in (self._model_dir(False, warn=False), self.root / "models_eval"):
            if (d / "models_info.json").is_file():
                return d / "models_info.json"
        return self._model_dir(False, warn=False) / "models_info.json"

    def models_info(self) -> dict[int, ModelInfo]:
        """ModelInfo per obj_id (from models/models_info.json, else models_eval/)."""
        if self._models_info is None:
            path = self.models_info_path()
            self._models_info = parse_models_info(path, self._json(path))
        return self._models_info

    def obj_ids(self) -> list[int]:
        return list(self.models_info().keys())

    def model_path(self, obj_id: int, eval: bool = False) -> Path:
        """Path of ``obj_<obj_id:06d>.ply`` in models/ (or models_eval/ when ``eval``)."""
        return self._model_dir(eval) / f"obj_{int(obj_id):06d}.ply"

    def load_model(self, obj_id: int, eval: bool = False) -> trimesh.Trimesh:
        """The model as a trimesh in mm, coloured for rendering (see ``ply.load_mesh``)."""
        path = self.model_path(obj_id, eval)
        if not path.is_file():
            raise BopFormatError(f"{path}: model of obj_id {obj_id} not found")
        return load_mesh(path)

    # -- scenes

    def scene_dir(self, scene_id: int) -> Path:
        return self.split_dir / f"{int(scene_id):06d}"

    def scene_ids(self) -> list[int]:
        """Sorted ids of the scene folders (6-digit names) of the split."""
        if not self.split_dir.is_dir():
            raise BopFormatError(f"{self.split_dir}: split folder not found")
        return sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())

    def image_ids(self, scene_id: int) -> list[int]:
        """Sorted image ids of a scene (the keys of its scene_camera.json)."""
        return list(self.scene_camera(scene_id).keys())

    def _image_size(self, scene_id: int, cam: dict) -> tuple[int, int]:
        if "width" in cam and "height" in cam:
            return int(cam["width"]), int(cam["height"])
        # No camera.json (e.g. a single-scene sample): take the size of one image.
        from PIL import Image

        for sub in ("rgb", "gray", "depth"):
            d = self.scene_dir(scene_id) / sub
            if d.is_dir():
                for p in sorted(d.iterdir()):
                    if p.suffix.lower() in _RGB_EXTS:
                        with Image.open(p) as im:
                            return im.size
        raise BopFormatError(
            f"{self.camera_path()}: fields 'width'/'height' missing and no image in {self.scene_dir(scene_id)} to take them from"
        )

    def scene_camera(self, scene_id: int, check: bool = True) -> dict[int, CameraInfo]:
        """CameraInfo per im_id, sorted by im_id.

        With ``check`` (what every stage gets), entries whose ``cam_K`` is no plausible
        camera (:func:`intrinsics_problem`) or whose ``depth_scale`` is not positive make
        it raise ``BopFormatError``: one line naming the file, the first such image and
        the field, with the count of the others. Lifting depth through a zero focal
        length, or scaling it by 0, would drop every candidate for "too few depth
        points" and end in AR 0 without a word about the camera. ``check=False`` reads
        the values as they are (``freeze datasets check`` reports them through
        :meth:`camera_problems`)."""
        self._read_scene_camera(scene_id)
        if check and self._camera_problems[scene_id]:
            raise BopFormatError("; ".join(self._camera_problems[scene_id]))
        return self._scene_camera[scene_id]

    def camera_problems(self, scene_id: int) -> list[str]:
        """One line per refused field of the scene's camera entries (see
        :meth:`scene_camera`): the file, the first image, the field and why, and how many
        more images share the problem. Empty when every entry is usable."""
        self._read_scene_camera(scene_id)
        return list(self._camera_problems[scene_id])

    def _read_scene_camera(self, scene_id: int) -> None:
        """Parse scene_camera.json of ``scene_id`` into the caches (values and problems)."""
        if scene_id not in self._scene_camera:
            path = self.scene_dir(scene_id) / "scene_camera.json"
            content = self._json(path)
            cam_path = self.camera_path()
            cam = self._json(cam_path) if cam_path.is_file() else {}
            if not isinstance(cam, dict):
                raise BopFormatError(f"{cam_path}: expected an object with fx, fy, cx, cy, got {type(cam).__name__}")
            # Validated here so that _image_size gets ints (it falls back to an image's size).
            size = {k: _int(cam_path, cam[k], k) for k in ("width", "height") if k in cam}
            width, height = self._image_size(scene_id, size if len(size) == 2 else {})
            if width <= 0 or height <= 0:
                raise BopFormatError(f"{cam_path}: fields 'width', 'height' must be positive, got {width}x{height} px")
            cam_scale = float(_floats(cam_path, cam["depth_scale"], 1, "depth_scale")[0]) if "depth_scale" in cam else None
            out = {}
            # (file, field) -> [first problem's line, how many entries have one]: a
            # 1e5-entry file of zeros is one line, not 1e5
            problems: dict[tuple[Path, str], list] = {}

            def refuse(file: Path, field: str, im_id: int, why: str) -> None:
                line = f"{file}: scene {scene_id}, image {im_id}, field '{field}': {why}"
                first = problems.setdefault((file, field), [line, 0])
                first[1] += 1

            for im_id, key, d in _id_items(path, content, "im_id"):
                e = brief(key)
                K = _floats(path, _get(path, d, "cam_K", e), 9, "cam_K", e).reshape(3, 3)
                if "depth_scale" in d:
                    scale = float(_floats(path, d["depth_scale"], 1, "depth_scale", e)[0])
                    scale_file = path
                elif cam_scale is not None:
                    scale, scale_file = cam_scale, cam_path
                else:
                    raise BopFormatError(f"{path}: entry {e}, field 'depth_scale' missing (and not in camera.json)")
                why = intrinsics_problem(K, width, height)
                if why:
                    refuse(path, "cam_K", im_id, why)
                if scale <= 0:
                    refuse(scale_file, "depth_scale", im_id, f"must be positive (mm per depth unit), got {scale:g}")
                R_w2c = t_w2c = None
                if "cam_R_w2c" in d and "cam_t_w2c" in d:
                    R_w2c = _floats(path, d["cam_R_w2c"], 9, "cam_R_w2c", e).reshape(3, 3)
                    t_w2c = _floats(path, d["cam_t_w2c"], 3, "cam_t_w2c", e)
                out[im_id] = CameraInfo(K, scale, width, height, R_w2c, t_w2c)
            self._scene_camera[scene_id] = dict(sorted(out.items()))
            self._camera_problems[scene_id] = [
                line + (f" (and {n - 1} more image{'s' if n > 2 else ''} of the scene)" if n > 1 else "")
                for line, n in problems.values()]

    def scene_gt(self, scene_id: int) -> dict[int, list[GtPose]]:
        """Ground-truth instances per im_id (list index = gt_id, as in mask file names)."""
        if scene_id not in self._scene_gt:
            path = self.scene_dir(scene_id) / "scene_gt.json"
            out = {}
            for im_id, key, items in _id_items(path, self._json(path), "im_id"):
                if not isinstance(items, list):
                    raise BopFormatError(f"{path}: entry {brief(key)}: expected a list of instances, got {type(items).__name__}")
                poses = []
                for gt_id, d in enumerate(items):
                    e = f"{brief(key)}[{gt_id}]"
                    poses.append(
                        GtPose(
                            obj_id=_int(path, _get(path, d, "obj_id", e), "obj_id", e),
                            R=_floats(path, _get(path, d, "cam_R_m2c", e), 9, "cam_R_m2c", e).reshape(3, 3),
                            t=_floats(path, _get(path, d, "cam_t_m2c", e), 3, "cam_t_m2c", e),
                        )
                    )
                out[im_id] = poses
            self._scene_gt[scene_id] = dict(sorted(out.items()))
        return self._scene_gt[scene_id]

    def scene_gt_info(self, scene_id: int) -> dict[int, list[GtInfo]]:
        """Visibility statistics per im_id, aligned with ``scene_gt``."""
        if scene_id not in self._scene_gt_info:
            path = self.scene_dir(scene_id) / "scene_gt_info.json"
            out = {}
            for im_id, key, items in _id_items(path, self._json(path), "im_id"):
                if not isinstance(items, list):
                    raise BopFormatError(f"{path}: entry {brief(key)}: expected a list of instances, got {type(items).__name__}")
                infos = []
                for gt_id, d in enumerate(items):
                    e = f"{brief(key)}[{gt_id}]"
                    boxes = {}
                    for k in ("bbox_obj", "bbox_visib"):  # (x, y, w, h) px: integers, not truncated floats
                        value = _get(path, d, k, e)
                        box = _floats(path, value, 4, k, e)
                        if not all(v.is_integer() for v in box.tolist()):
                            raise BopFormatError(f"{path}: entry {e}, field '{k}': expected 4 integers, got {brief(value)}")
                        boxes[k] = tuple(int(v) for v in box.tolist())
                    counts = {
                        k: _int(path, _get(path, d, k, e), k, e)
                        for k in ("px_count_all", "px_count_valid", "px_count_visib")
                    }
                    fract = float(_floats(path, _get(path, d, "visib_fract", e), 1, "visib_fract", e)[0])
                    infos.append(GtInfo(boxes["bbox_obj"], boxes["bbox_visib"], **counts, visib_fract=fract))
                out[im_id] = infos
            self._scene_gt_info[scene_id] = dict(sorted(out.items()))
        return self._scene_gt_info[scene_id]

    def ground_truth_problems(self, targets: Iterable[Target]) -> list[str]:
        """One line per problem of the ground truth the scorer reads for ``targets``:
        ``scene_gt.json`` of every target scene that has one must parse (finite poses:
        a NaN in ``cam_R_m2c`` is refused here, naming the file, the entry and the
        field), ``scene_gt_info.json`` beside it too, and every target image needs an
        entry in both, of the same length. Scenes without ``scene_gt.json`` are not
        problems (private test ground truth: the score stage says so).

        Checked by ``freeze datasets check`` and by the first scene-side stage
        (segment_prior), so that a bad file stops a run at its start rather than in the
        score stage at its end."""
        by_scene: dict[int, set[int]] = {}
        for t in targets:
            by_scene.setdefault(t.scene_id, set()).add(t.im_id)
        out = []
        for scene_id, im_ids in sorted(by_scene.items()):
            gt_path = self.scene_dir(scene_id) / "scene_gt.json"
            if not gt_path.is_file():
                continue
            info_path = self.scene_dir(scene_id) / "scene_gt_info.json"
            try:
                gts = self.scene_gt(scene_id)
                if not info_path.is_file():
                    out.append(f"{info_path}: not found beside scene_gt.json (the scores need each instance's "
                               "visib_fract)")
                    continue
                infos = self.scene_gt_info(scene_id)
            except BopFormatError as e:
                out.append(str(e))
                continue
            missing = sorted(i for i in im_ids if i not in gts)
            if missing:
                out.append(f"{gt_path}: no entry for target image {missing[0]}"
                           + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
            unequal = sorted(i for i in im_ids if i in gts and len(infos.get(i, ())) != len(gts[i]))
            if unequal:
                i = unequal[0]
                out.append(f"{info_path}: image {i} has {len(infos.get(i, ()))} entries, scene_gt.json has "
                           f"{len(gts[i])} (one per instance in both)"
                           + (f" (and {len(unequal) - 1} more images)" if len(unequal) > 1 else ""))
        return out

    # -- images

    def _find_image(self, scene_id: int, im_id: int, subdirs: Iterable[str], exts: Iterable[str]) -> Path | None:
        for sub in subdirs:
            for ext in exts:
                p = self.scene_dir(scene_id) / sub / f"{int(im_id):06d}{ext}"
                if p.is_file():
                    return p
        return None

    def rgb_path(self, scene_id: int, im_id: int) -> Path:
        p = self._find_image(scene_id, im_id, ("rgb", "gray"), _RGB_EXTS)
        if p is None:
            raise BopFormatError(f"{self.scene_dir(scene_id)}: no rgb/ or gray/ image for im_id {im_id}")
        return p

    def load_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB; grey images are replicated to 3 channels, alpha is dropped."""
        path = self.rgb_path(scene_id, im_id)
        im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if im is None:
            raise BopFormatError(f"{path}: cannot decode image")
        return decoded_to_rgb(im, path)

    def depth_path(self, scene_id: int, im_id: int) -> Path | None:
        return self._find_image(scene_id, im_id, ("depth",), _DEPTH_EXTS)

    def has_depth(self, scene_id: int, im_id: int) -> bool:
        return self.depth_path(scene_id, im_id) is not None

    def load_depth(self, scene_id: int, im_id: int) -> np.ndarray:
        """(H, W) float32 depth in mm (raw * depth_scale), 0 where invalid. The file must
        be 16-bit single-channel (or float); see :func:`depth_format_problem`."""
        path = self.depth_path(scene_id, im_id)
        if path is None:
            raise BopFormatError(f"{self.scene_dir(scene_id)}: no depth/ image for im_id {im_id} (dataset without depth?)")
        raw = read_depth_image(path)  # refuses 8-bit and multi-channel depth, naming the file
        cams = self.scene_camera(scene_id)
        if im_id not in cams:
            raise BopFormatError(f"{self.scene_dir(scene_id) / 'scene_camera.json'}: no entry for im_id {im_id}")
        return (raw.astype(np.float64) * cams[im_id].depth_scale).astype(np.float32)

    def mask_path(self, scene_id: int, im_id: int, gt_id: int, visib: bool = True) -> Path:
        sub = "mask_visib" if visib else "mask"
        return self.scene_dir(scene_id) / sub / f"{int(im_id):06d}_{int(gt_id):06d}.png"

    def load_mask(self, scene_id: int, im_id: int, gt_id: int, visib: bool = True) -> np.ndarray:
        """(H, W) bool mask of GT instance ``gt_id`` (visible part when ``visib``)."""
        path = self.mask_path(scene_id, im_id, gt_id, visib)
        im = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if im is None:
            raise BopFormatError(f"{path}: mask not found or not decodable")
        return im > 0

    # -- targets and identity

    def targets_path(self, path: Path | str | None = None) -> Path:
        return Path(path) if path is not None else self.root / DEFAULT_TARGETS

    def targets(self, path: Path | str | None = None) -> list[Target]:
        """Targets of a BOP19-style file (default ``<root>/test_targets_bop19.json``).

        BOP24 files list images only; use ``image_targets`` for them.
        """
        path = self.targets_path(path)
        content = self._json(path)
        if not isinstance(content, list):
            raise BopFormatError(f"{path}: expected a JSON list of targets")
        out = []
        for i, d in enumerate(content):
            if isinstance(d, dict) and "obj_id" not in d and "scene_id" in d and "im_id" in d:
                raise BopFormatError(
                    f"{path}: entry {i}, field 'obj_id' missing: this looks like a BOP24 (image-level) targets file; "
                    "use image_targets() or a test_targets_bop19.json"
                )
            out.append(
                Target(
                    scene_id=_int(path, _get(path, d, "scene_id", i), "scene_id", i),
                    im_id=_int(path, _get(path, d, "im_id", i), "im_id", i),
                    obj_id=_int(path, _get(path, d, "obj_id", i), "obj_id", i),
                    inst_count=_int(path, _get(path, d, "inst_count", i), "inst_count", i),
                )
            )
        return out

    def image_targets(self, path: Path | str | None = None) -> list[tuple[int, int]]:
        """Sorted unique (scene_id, im_id) of a BOP19 or BOP24 targets file."""
        path = self.targets_path(path)
        content = self._json(path)
        if not isinstance(content, list):
            raise BopFormatError(f"{path}: expected a JSON list of targets")
        pairs = {
            (_int(path, _get(path, d, "scene_id", i), "scene_id", i), _int(path, _get(path, d, "im_id", i), "im_id", i))
            for i, d in enumerate(content)
        }
        return sorted(pairs)

    def model_folder(self) -> Path:
        """The folder the models are read from: ``models/`` (or the manifest's models
        folder), else ``models_eval/``; never warns (planning asks for it)."""
        return self._model_dir(False, warn=False)


# ---------------------------------------------------------------------------- writers


def _list(a: np.ndarray | Iterable[float]) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]


def write_camera(root: Path | str, camera: dict, split_type: str | None = None) -> Path:
    """Write ``<root>/camera[_<split_type>].json`` (fx, fy, cx, cy, width, height, depth_scale).

    A ``K`` (3, 3) entry, if given, fills fx, fy, cx, cy and is not written itself.
    """
    cam = {k: v for k, v in camera.items() if k != "K"}
    if "K" in camera:
        K = np.asarray(camera["K"], dtype=np.float64)
        cam.update(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]))
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        if k not in cam:
            raise ValueError(f"write_camera: field '{k}' missing")
    path = Path(root) / (f"camera_{split_type}.json" if split_type else "camera.json")
    save_bop_json(path, cam)
    return path


def models_info_json(info: dict[int, ModelInfo]) -> dict[int, dict]:
    """The models_info.json content for ``info`` (symmetry keys only when non-empty)."""
    out = {}
    for obj_id, m in info.items():
        d: dict[str, Any] = {"diameter": float(m.diameter)}
        for a, lo, size in zip("xyz", np.asarray(m.min_xyz, float), np.asarray(m.size_xyz, float)):
            d[f"min_{a}"] = float(lo)
            d[f"size_{a}"] = float(size)
        if m.symmetries_discrete:
            d["symmetries_discrete"] = [_list(np.asarray(s).reshape(4, 4)) for s in m.symmetries_discrete]
        if m.symmetries_continuous:
            d["symmetries_continuous"] = [
                {"axis": _list(s["axis"]), "offset": _list(s.get("offset", np.zeros(3)))} for s in m.symmetries_continuous
            ]
        out[int(obj_id)] = d
    return out


def write_models_info(path: Path | str, info: dict[int, ModelInfo]) -> None:
    save_bop_json(path, models_info_json(info))


def write_scene_camera(path: Path | str, cameras: dict[int, CameraInfo]) -> None:
    """Write scene_camera.json: cam_K (9 floats row-major), depth_scale, and the w2c pose if set."""
    out = {}
    for im_id, c in cameras.items():
        d: dict[str, Any] = {"cam_K": _list(c.K), "depth_scale": float(c.depth_scale)}
        if c.R_w2c is not None and c.t_w2c is not None:
            d["cam_R_w2c"] = _list(c.R_w2c)
            d["cam_t_w2c"] = _list(c.t_w2c)
        out[int(im_id)] = d
    save_bop_json(path, out)


def write_scene_gt(path: Path | str, gt: dict[int, list[GtPose]]) -> None:
    """Write scene_gt.json: per im_id a list of {cam_R_m2c (9), cam_t_m2c (3, mm), obj_id}."""
    save_bop_json(
        path,
        {
            int(im_id): [{"cam_R_m2c": _list(p.R), "cam_t_m2c": _list(p.t), "obj_id": int(p.obj_id)} for p in poses]
            for im_id, poses in gt.items()
        },
    )


def write_scene_gt_info(path: Path | str, info: dict[int, list[GtInfo]]) -> None:
    """Write scene_gt_info.json (boxes as 4 ints, pixel counts as ints)."""
    save_bop_json(
        path,
        {
            int(im_id): [
                {
                    "bbox_obj": [int(v) for v in g.bbox_obj],
                    "bbox_visib": [int(v) for v in g.bbox_visib],
                    "px_count_all": int(g.px_count_all),
                    "px_count_valid": int(g.px_count_valid),
                    "px_count_visib": int(g.px_count_visib),
                    "visib_fract": float(g.visib_fract),
                }
                for g in items
            ]
            for im_id, items in info.items()
        },
    )


def write_targets(path: Path | str, targets: Iterable[Target]) -> None:
    """Write a BOP19 targets file (list of {im_id, inst_count, obj_id, scene_id})."""
    save_bop_json(
        path,
        [
            {"im_id": int(t.im_id), "inst_count": int(t.inst_count), "obj_id": int(t.obj_id), "scene_id": int(t.scene_id)}
            for t in targets
        ],
    )


def write_image(path: Path, image: np.ndarray) -> None:
    """Write ``image`` as OpenCV stores it (BGR or single channel; the extension picks the
    format), creating the folder; OSError when OpenCV cannot."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # encoded in memory and written by Python, not cv2.imwrite: a full or read-only disk
    # then raises the OS's error (errno, file name) instead of a bare False that reads
    # like an unsupported extension
    try:
        ok, data = cv2.imencode(path.suffix, image)
    except cv2.error:
        ok = False
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode the image (unsupported extension {path.suffix!r}?)")
    with open(path, "wb") as f:
        f.write(data.tobytes())


def save_depth_png(path: Path | str, depth_mm: np.ndarray, depth_scale: float) -> None:
    """Write (H, W) depth in mm as a uint16 PNG of round(depth_mm / depth_scale).

    Values that do not fit in uint16 raise ValueError rather than wrap around.
    """
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"save_depth_png({path}): depth must be (H, W), got {depth.shape}")
    raw = np.round(depth / float(depth_scale))
    if not np.all(np.isfinite(raw)) or raw.min(initial=0) < 0 or raw.max(initial=0) > 65535:
        raise ValueError(
            f"save_depth_png({path}): depth/depth_scale must lie in [0, 65535] "
            f"(max depth {np.nanmax(depth) if depth.size else 0:.1f} mm at scale {depth_scale}); use a larger depth_scale"
        )
    write_image(Path(path), raw.astype(np.uint16))


def save_mask_png(path: Path | str, mask: np.ndarray) -> None:
    """Write a (H, W) bool mask as a uint8 PNG with values 0/255."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"save_mask_png({path}): mask must be (H, W), got {mask.shape}")
    write_image(Path(path), np.where(mask.astype(bool), 255, 0).astype(np.uint8))


def save_rgb(path: Path | str, rgb: np.ndarray) -> None:
    """Write a (H, W, 3) uint8 RGB image (PNG lossless; JPEG if the suffix says so)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"save_rgb({path}): expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    write_image(Path(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))

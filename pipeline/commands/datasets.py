"""Checking BOP datasets on disk before a long run (``freeze datasets check ROOT``).

For every dataset manifest of kind ``bop`` whose folder exists under ``ROOT`` (the
``bop_root``), and every real-sample manifest (kind ``real``) whose ``source`` is
``ROOT`` (``freeze datasets check ../shared/realdata/ycbv-real-train`` checks
``realycbv``), :func:`check_dataset` reads what the stages will read and reports, as
plain findings naming the file and the field:

- the files every stage needs: the camera file, the model folder of the manifest
  (``models``; T-LESS ``models_cad``) with models_info.json and a model file per target
  object, ``models_eval`` (scoring), the targets file, scene_camera.json per scene, an
  image and a depth image per target image;
- what the manifest says of the dataset as BOP distributes it: the object ids, the
  image folder and extension (ITODD ``gray/*.tif``) and the image size;
- units: diameters present, positive and in mm (a diameter below 5 looks like metres);
- every model file (the manifest's model folder and ``models_eval``), opened through
  the pipeline's own reader (:meth:`pipeline.formats.bop.BopDataset.load_model`): unreadable or
  corrupt PLYs, meshes without faces, NaN/inf vertices, and vertices whose extent
  disagrees with models_info's diameter (a model in metres beside a diameter in mm);
- the cameras of every target scene by the reader's rule (the stages refuse the same):
  ``cam_K`` a plausible pinhole matrix (:func:`pipeline.formats.bop.dataset.intrinsics_problem`),
  ``depth_scale`` positive, and the manifest's ``depth_scale`` where it states one;
- targets whose image is missing; targets of objects without a model; targets listed
  twice (a warning; counted once, as the scorer does); scenes without ground truth
  (expected where it is private: ITODD, HB); the ground truth the scorer will read
  (:meth:`pipeline.formats.bop.BopDataset.ground_truth_problems`: finite poses, an entry per
  target image in scene_gt.json and scene_gt_info.json);
- each prior file: found, parseable, category ids that are the dataset's objects (or
  look like 0-/1-based indices: see ``segment_prior.category_ids``), detections for
  objects not in models_info and targets without any detection.

With ``deep``, it also opens a sample of the images, the first, the middle and the
last target image of every scene (:func:`deep_sample`): the RGB image decodes; the
depth image decodes, is 16-bit single-channel (the reader's rule,
:func:`pipeline.formats.bop.dataset.depth_format_problem`), has the size of the RGB image and
of the camera file's ``width``/``height``, and is not zero everywhere (a warning).

It returns a summary (objects, scenes, images, targets, instances per target) and the
findings; errors make the dataset unusable, warnings do not.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

import numpy as np

from pipeline.formats.bop.dataset import MIN_DIAMETER_MM, intrinsics_problem

EXTENT_TOLERANCE = 1.25
"""How far a model's vertices may stray from models_info's diameter before it is
reported: the diameter lies between the bounding box's largest side and its diagonal,
and this factor either way absorbs rounding and the resampled models_eval meshes while
still catching a unit slip (x10, x1000)."""


class Advance(Protocol):
    """What the checks need of a progress bar (:class:`pipeline.common.progress.ProgressBar`)."""

    def advance(self, n: int = 1) -> None: ...


BarFactory = Callable[[str, int], Advance]
"""(description, total) -> a bar to advance once per item."""


def _no_bar(description: str, total: int) -> Advance:
    from pipeline.common.progress import ProgressBar

    return ProgressBar()  # silent


def no_dataset_message(bop_root: Path) -> str:
    """The one-line message of a check that found no dataset under ``bop_root``."""
    hint = ""
    if (Path(bop_root) / "models").is_dir() or any(Path(bop_root).glob("camera*.json")):
        hint = f" ({bop_root} looks like a dataset folder itself: pass its parent)"
    return (f"no BOP dataset found under {bop_root}; expected folders like lmo/, tless/ with models/ and a "
            f"split folder{hint}")


@dataclass
class DatasetReport:
    """What :func:`check_dataset` found for one dataset."""

    name: str
    root: Path
    summary: dict[str, Any] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "root": str(self.root), "ok": self.ok, "summary": self.summary,
                "errors": self.errors, "warnings": self.warnings}


def check_dataset(bop_root: Path, manifest, priors: list[str] | None = None, *, deep: bool = False,
                  bar: BarFactory | None = None) -> DatasetReport:
    """Check the dataset of ``manifest`` (a :class:`pipeline.common.config.DatasetManifest` of
    kind ``bop``) under ``bop_root``; ``priors`` as the run's (None: the dataset's
    default detections). Every model file is opened; ``deep`` also opens the images of
    :func:`deep_sample`. ``bar(description, total)`` makes a progress bar for the model
    and image loops (None: silent)."""
    from pipeline.workflow.plan import missing_ground_truth, open_bop

    bar = bar or _no_bar
    root = Path(bop_root) / (manifest.folder or manifest.name)
    rep = DatasetReport(manifest.name, root)
    try:
        bop = open_bop(root, manifest)
        bop.camera()
        targets = bop.targets(root / manifest.targets_file)
    except (ValueError, OSError) as e:  # BopFormatError is a ValueError
        rep.errors.append(str(e))
        return rep
    targets = _unique_targets(rep, root / manifest.targets_file, targets)
    diameters = _diameters(rep, bop)
    if diameters is None:
        return rep
    _check_models(rep, bop, manifest, diameters, targets, bar)
    images = sorted({(t.scene_id, t.im_id) for t in targets})
    scenes = sorted({s for s, _ in images})
    missing_images, sizes = _check_images(rep, bop, manifest, images)
    if deep:
        _check_sample(rep, bop, deep_sample(images), bar)
    gt_missing = missing_ground_truth(bop, scenes)
    if gt_missing and manifest.public_gt:
        rep.warnings.append(f"{gt_missing[0]}: not found ({len(gt_missing)} of "
                            f"{len(scenes)} target scenes lack ground truth): estimates will be made, but no AR")
    if manifest.public_gt:  # what the score stage reads (and segment_prior refuses at the start of a run)
        rep.errors.extend(bop.ground_truth_problems(targets))
    _check_depth_scale(rep, bop, manifest, scenes)
    n_detections = _check_priors(rep, Path(bop_root), manifest, priors, diameters, targets)
    per_target = Counter(t.inst_count for t in targets)
    rep.summary = {
        "objects": len({t.obj_id for t in targets}), "scenes": len(scenes), "images": len(images),
        "targets": len(targets), "instances": int(sum(t.inst_count for t in targets)),
        "instances_per_target": {str(k): v for k, v in sorted(per_target.items())},
        "images_with_problems": missing_images, "detections": n_detections,
        "image_size": sorted(sizes)[0] if len(sizes) == 1 else sorted(sizes),
        "ground_truth": not gt_missing,
    }
    return rep


def _unique_targets(rep: DatasetReport, path: Path, targets: list) -> list:
    """``targets`` with each (scene, image, object) once, the last line's inst_count
    kept, as the scorer and BOP's toolkit read the file (both key the targets by
    scene, image and object, so a repeated line counts once and the later one wins);
    one warning with the number of repeated lines and the first of them."""
    unique: dict[tuple[int, int, int], Any] = {}
    repeated = []
    for t in targets:
        key = (t.scene_id, t.im_id, t.obj_id)
        if key in unique:
            repeated.append(t)
        unique[key] = t
    if repeated:
        t = repeated[0]
        counts = {u.inst_count for u in targets if (u.scene_id, u.im_id, u.obj_id) == (t.scene_id, t.im_id, t.obj_id)}
        differ = f", with inst_count {' and '.join(map(str, sorted(counts)))}" if len(counts) > 1 else ""
        rep.warnings.append(f"{path}: {len(repeated)} repeated target line{'s' if len(repeated) > 1 else ''} (first: "
                            f"scene {t.scene_id}, image {t.im_id}, object {t.obj_id}{differ}); each target is counted "
                            "once, with its last line's inst_count, as the scorer and BOP's toolkit read it")
    return list(unique.values())


def _diameters(rep: DatasetReport, bop) -> dict[int, float | None] | None:
    """models_info's diameter (mm) per object, None where it is missing or not a
    number; each missing, non-positive or metre-sized diameter is reported. When the
    file does not parse (a missing diameter stops the reader), the diameters are read
    from the raw JSON so that every object is reported, not only the first, and the
    models are still checked. Returns None when not even that is possible."""
    from pipeline.formats.bop.jsonio import load_json

    path = bop.models_info_path()
    try:
        diameters: dict[int, float | None] = {o: float(i.diameter) for o, i in bop.models_info().items()}
        parse_error = None
    except (ValueError, OSError) as e:
        parse_error = str(e)
        try:
            content = load_json(path)
        except (ValueError, OSError):
            content = None
        if not isinstance(content, dict) or not all(str(k).strip().isdigit() for k in content):
            rep.errors.append(parse_error)
            return None
        diameters = {int(k): _number(v.get("diameter") if isinstance(v, dict) else None)
                     for k, v in sorted(content.items(), key=lambda kv: int(kv[0]))}
    problems = []
    for obj_id, d in diameters.items():
        if d is None:
            problems.append(f"{path}: object {obj_id}: field 'diameter' is missing or not a number: "
                            "give the model's diameter in mm")
        elif d <= 0:
            problems.append(f"{path}: object {obj_id}: field 'diameter' is {d:g}: it must be positive (mm)")
        elif d < MIN_DIAMETER_MM:
            problems.append(f"{path}: object {obj_id}: field 'diameter' is {d:g}, below {MIN_DIAMETER_MM:g}: "
                            "models must be in mm (these look like metres)")
    rep.errors.extend(problems)
    # the reader's own message says the same as ours when it stopped at a diameter
    if parse_error and not (problems and "'diameter'" in parse_error):
        rep.errors.append(parse_error)
    return diameters


def _number(value: Any) -> float | None:
    """A JSON number as a finite float, else None (bools are not numbers here)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _check_models(rep: DatasetReport, bop, manifest, diameters: dict[int, float | None], targets: list,
                  bar: BarFactory) -> None:
    """Model folders, the object ids against the manifest's, and every model file."""
    models_dir = bop.root / manifest.models
    if not models_dir.is_dir():
        where = "models_eval/ (geometry only: no colour for the templates)" if (bop.root / "models_eval").is_dir() else None
        if where:
            rep.warnings.append(f"{models_dir}: model folder (field 'models') not found; onboarding falls back to {where}")
        else:
            rep.errors.append(f"{models_dir}: model folder (field 'models') not found, nor models_eval/")
    if not (bop.root / "models_eval").is_dir():
        rep.warnings.append(f"{bop.root / 'models_eval'}: not found; scores will use {manifest.models}/ "
                            "(BOP scores with the models_eval meshes)")
    target_objs = sorted({t.obj_id for t in targets})
    if manifest.obj_ids:
        foreign = sorted(set(target_objs) - set(manifest.obj_ids))
        if foreign:
            rep.warnings.append(f"{bop.root / manifest.targets_file}: target objects {foreign} are not among BOP's "
                                f"{manifest.name} objects (field 'obj_ids')")
    with warnings.catch_warnings():
        # the missing model folder was reported above; the reader's fallback warning would repeat it
        warnings.simplefilter("ignore", UserWarning)
        _check_model_files(rep, bop, manifest, diameters, target_objs)
        _check_meshes(rep, bop, diameters, bar)


def _check_model_files(rep: DatasetReport, bop, manifest, infos: dict[int, Any], target_objs: list[int]) -> None:
    """A models_info entry and a model file for every target object."""
    for obj_id in target_objs:
        if obj_id not in infos:
            rep.errors.append(f"{bop.root / manifest.targets_file}: object {obj_id} is a target but has no entry in "
                              f"{bop.models_info_path()}")
        elif not bop.model_path(obj_id).is_file():
            rep.errors.append(f"{bop.model_path(obj_id)}: model file of target object {obj_id} not found")


def _check_meshes(rep: DatasetReport, bop, diameters: dict[int, float | None], bar: BarFactory) -> None:
    """Open the model file of every models_info object, in the onboarding folder and in
    models_eval/ (scoring), through the pipeline's reader; absent files are reported by
    :func:`_check_model_files` (targets) or do not matter (other objects)."""
    jobs: list[tuple[int, bool, Path]] = []
    seen: set[Path] = set()
    for obj_id in diameters:
        for eval_ in (False, True):
            path = bop.model_path(obj_id, eval=eval_)
            # without the model folder both paths are models_eval's: open it once
            if path.is_file() and path not in seen:
                seen.add(path)
                jobs.append((obj_id, eval_, path))
    progress = bar(f"{bop.name}: models", len(jobs))
    for obj_id, eval_, path in jobs:
        rep.errors.extend(model_problems(bop, obj_id, eval_, path, diameters[obj_id]))
        progress.advance()


def model_problems(bop, obj_id: int, eval_: bool, path: Path, diameter: float | None) -> list[str]:
    """One line per problem of the model file ``path`` of ``obj_id`` (read with
    ``bop.load_model``), given models_info's ``diameter`` in mm (None or below
    MIN_DIAMETER_MM: already reported, the extent is not compared)."""
    try:
        mesh = bop.load_model(obj_id, eval=eval_)
    except Exception as e:  # noqa: BLE001 - whatever a corrupt file makes the reader raise is a finding, not a crash
        return [_one_line(path, e, "cannot read the PLY")]
    vertices = np.asarray(mesh.vertices, dtype=np.float64)  # (V, 3) mm
    if len(vertices) == 0:
        return [f"{path}: PLY has no vertices"]
    problems = []
    if len(mesh.faces) == 0:
        problems.append(f"{path}: PLY has no faces (a point cloud?): templates and scores need a triangle mesh")
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        problems.append(f"{path}: {int((~finite).sum())} of {len(vertices)} vertices are NaN or inf")
    if diameter is None or diameter < MIN_DIAMETER_MM or not finite.any():
        return problems
    extent = vertices[finite].max(axis=0) - vertices[finite].min(axis=0)  # (3,) bounding box sides
    side, diagonal = float(extent.max()), float(np.linalg.norm(extent))
    if diameter > EXTENT_TOLERANCE * diagonal:
        problems.append(_scale_message(path, diameter / max(diagonal, 1e-12), "smaller", diagonal, diameter))
    elif diameter * EXTENT_TOLERANCE < side:
        problems.append(_scale_message(path, side / diameter, "larger", side, diameter))
    return problems


def _scale_message(path: Path, factor: float, direction: str, span: float, diameter: float) -> str:
    """A model ``factor`` times ``direction`` than its diameter, with the unit slip it
    suggests when the factor is close to 10 or 1000."""
    about = f"{factor:.2g}" if factor < 100 else f"{float(f'{factor:.2g}'):.0f}"
    unit = {("smaller", 3): "in metres? (BOP models are in mm", ("smaller", 1): "in cm? (BOP models are in mm",
            ("larger", 3): "is the diameter in metres? (BOP diameters are in mm"}
    power = round(math.log10(factor))
    hint = unit.get((direction, power)) if abs(math.log10(factor) - power) < 0.2 else None
    numbers = f"the vertices span {span:.3g}, the diameter is {diameter:.4g})"
    head = f"{path}: model is about {about}x {direction} than models_info's diameter"
    return f"{head}: {hint}; {numbers}" if hint else f"{head} ({numbers}"


def _one_line(path: Path, e: BaseException, what: str) -> str:
    """An exception as one line starting with ``path`` (the reader's BopFormatError
    messages already do)."""
    text = " ".join(str(e).split()) or type(e).__name__
    if text.startswith(str(path)):
        return text
    return f"{path}: {what} ({type(e).__name__}: {text})"


def deep_sample(images: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The images ``--deep`` opens: the first, the middle and the last target image
    (by im_id) of every scene, from the sorted (scene_id, im_id) pairs ``images``."""
    by_scene: dict[int, list[int]] = {}
    for scene_id, im_id in images:
        by_scene.setdefault(scene_id, []).append(im_id)
    out = []
    for scene_id, ims in sorted(by_scene.items()):
        ims = sorted(set(ims))
        out += [(scene_id, im_id) for im_id in sorted({ims[0], ims[len(ims) // 2], ims[-1]})]
    return out


def _check_sample(rep: DatasetReport, bop, sample: list[tuple[int, int]], bar: BarFactory) -> None:
    """Open the RGB and depth images of ``sample``: decodable, depth 16-bit single-channel
    and of the RGB image's and the camera file's size, depth not zero everywhere. Missing
    files were reported by :func:`_check_images`."""
    from pipeline.formats.bop.dataset import read_depth_image

    cam = bop.camera()
    cam_size = None
    if isinstance(cam.get("width"), (int, float)) and isinstance(cam.get("height"), (int, float)):
        cam_size = (int(cam["width"]), int(cam["height"]))
    cam_says = f"{bop.camera_path().name} says {{}}x{{}} (fields 'width', 'height')"
    progress = bar(f"{bop.name}: images (--deep)", len(sample))
    for scene_id, im_id in sample:
        rgb_size = None
        try:
            rgb_path = bop.rgb_path(scene_id, im_id)
        except ValueError:
            rgb_path = None
        if rgb_path is not None:
            try:
                rgb = bop.load_rgb(scene_id, im_id)  # (H, W, 3)
                rgb_size = (rgb.shape[1], rgb.shape[0])
            except Exception as e:  # noqa: BLE001 - an undecodable image is a finding
                rep.errors.append(_one_line(rgb_path, e, "cannot read the image"))
            if rgb_size and cam_size and rgb_size != cam_size:
                rep.errors.append(f"{rgb_path}: image is {rgb_size[0]}x{rgb_size[1]} px, " + cam_says.format(*cam_size))
        depth_path = bop.depth_path(scene_id, im_id)
        if depth_path is not None:
            try:
                raw = read_depth_image(depth_path)  # (H, W) depth units
            except Exception as e:  # noqa: BLE001 - BopFormatError names the file; anything else is a finding too
                rep.errors.append(_one_line(depth_path, e, "cannot read the depth image"))
            else:
                size = (raw.shape[1], raw.shape[0])
                differs = []
                if rgb_size and size != rgb_size:
                    differs.append(f"the image {rgb_path.name} is {rgb_size[0]}x{rgb_size[1]}")
                if cam_size and size != cam_size:
                    differs.append(cam_says.format(*cam_size))
                if differs:
                    rep.errors.append(f"{depth_path}: depth is {size[0]}x{size[1]} px, " + " and ".join(differs))
                if not (raw > 0).any():  # NaN compares False: a float map of NaNs is empty too
                    rep.warnings.append(f"{depth_path}: depth is zero everywhere: this image will get no estimate")
        progress.advance()


def _check_images(rep: DatasetReport, bop, manifest, images: list[tuple[int, int]]) -> tuple[int, set]:
    """Camera entries, depth scales and the image files of every target image; the
    first image of each scene is opened for its size. Returns (images with problems,
    the (width, height) sizes seen)."""
    from PIL import Image

    missing_images = 0
    sizes: set[tuple[int, int]] = set()
    for scene_id in sorted({s for s, _ in images}):
        try:
            cams = bop.scene_camera(scene_id, check=False)
        except (ValueError, OSError) as e:
            rep.errors.append(str(e))
            continue
        # the reader's own rule (what the stages refuse): every entry, not only the targets'
        rep.errors.extend(bop.camera_problems(scene_id))
        first = True
        for s, im_id in images:
            if s != scene_id:
                continue
            problems = []
            bad_camera = False  # reported above, once per scene and field; counted per image here
            if im_id not in cams:
                problems.append(f"{bop.scene_dir(scene_id) / 'scene_camera.json'}: no entry for image {im_id}")
            else:
                cam = cams[im_id]
                bad_camera = cam.depth_scale <= 0 or intrinsics_problem(cam.K, cam.width, cam.height) is not None
            try:
                path = bop.rgb_path(scene_id, im_id)
            except ValueError as e:
                problems.append(str(e))
                path = None
            if path is not None and first:
                first = False
                if (path.parent.name, path.suffix) != (manifest.image_dir, manifest.image_ext):
                    rep.warnings.append(f"{path}: BOP's {manifest.name} has {manifest.image_dir}/*{manifest.image_ext} "
                                        "images (fields 'image_dir', 'image_ext'); reading this one instead")
                with Image.open(path) as im:
                    sizes.add(im.size)
                    if manifest.image_size and tuple(im.size) != tuple(manifest.image_size):
                        rep.warnings.append(f"{path}: image is {im.size[0]}x{im.size[1]} px, BOP's {manifest.name} "
                                            f"images are {manifest.image_size[0]}x{manifest.image_size[1]} (field 'image_size')")
            if not bop.has_depth(scene_id, im_id):
                problems.append(f"{bop.scene_dir(scene_id)}: no depth/ image for target image {im_id}")
            if problems or bad_camera:
                missing_images += 1
                rep.errors.extend(problems)
    return missing_images, sizes


def _check_depth_scale(rep: DatasetReport, bop, manifest, scenes: list[int]) -> None:
    """Every camera entry of the target scenes declares the manifest's ``depth_scale``,
    when it states one (one error per scene: the first image that departs)."""
    from pipeline.formats.bop.dataset import depth_scale_problem

    if manifest.depth_scale is None:
        return
    for s in scenes:
        try:
            problem = depth_scale_problem(bop, s, manifest.depth_scale, f"manifests/datasets/{manifest.name}.yaml")
        except (ValueError, OSError):
            continue  # an unreadable scene_camera.json: reported by the image checks
        if problem:
            rep.errors.append(problem)


def _check_priors(rep: DatasetReport, bop_root: Path, manifest, priors: list[str] | None, infos: dict,
                  targets: list) -> int | None:
    """Each prior file: found, parseable, category ids that are objects, coverage of the
    targets. Returns the number of detections (None if a file could not be read)."""
    from pipeline.formats.bop.detections import category_id_problem, load_detections
    from pipeline.common.config import ManifestError
    from pipeline.workflow.plan import resolve_prior

    total: int | None = 0
    try:
        patterns = manifest.prior_patterns(priors)
    except ManifestError as e:
        rep.errors.append(str(e))
        return None
    for pattern in patterns:
        try:
            prior = resolve_prior(bop_root, pattern)
        except ManifestError as e:
            rep.errors.append(str(e))
            total = None
            continue
        if not prior.is_file():
            rep.errors.append(f"{prior}: localisation prior not found (field 'prior' of "
                              f"manifests/datasets/{manifest.name}.yaml)")
            total = None
            continue
        try:
            dets = load_detections(prior)
        except (ValueError, OSError) as e:
            rep.errors.append(str(e))
            total = None
            continue
        if total is not None:
            total += len(dets)
        problem = category_id_problem(dets, sorted(infos))
        if problem:
            rep.errors.append(f"{prior}: {problem}")
        unknown = Counter(d.category_id for d in dets if d.category_id not in infos)
        if unknown and not problem:
            rep.warnings.append(f"{prior}: detections of objects not in models_info: "
                                + ", ".join(f"{o} ({n})" for o, n in sorted(unknown.items())))
        target_keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
        covered = {(d.scene_id, d.image_id, d.category_id) for d in dets}
        uncovered = len(target_keys - covered)
        if uncovered:
            rep.warnings.append(f"{prior}: {uncovered} of {len(target_keys)} targets have no detection "
                                "(they will get no estimate)")
    return total


def check_root(bop_root: Path, priors: list[str] | None = None, *, deep: bool = False,
               progress: bool = False) -> tuple[list[DatasetReport], list[str]]:
    """Reports for every BOP dataset manifest whose folder exists under ``bop_root``,
    and the names of those whose folder is absent. A real-sample manifest (kind
    ``real``) whose ``source`` is ``bop_root`` is checked too, with its exact prior
    (``source_prior``) unless ``priors`` names others, and a folder it claims is not
    also checked as the BOP dataset of that name (the YCB-V sample has ``ycbv/`` but not
    YCB-V's test split). ``deep``: see :func:`check_dataset`; ``progress`` shows rich
    progress bars on stderr while models and images are opened."""
    from pipeline.common.config import MANIFEST_DIR, load_dataset_manifest, shared_root

    manifests = [load_dataset_manifest(p.stem) for p in sorted((MANIFEST_DIR / "datasets").glob("*.yaml"))]
    here = Path(bop_root).resolve()
    samples = [m for m in manifests if m.kind == "real" and (shared_root() / m.source).resolve() == here]
    claimed = {m.folder for m in samples}
    reports, absent = [], []
    with _bars(progress) as bar:
        for man in samples:
            reports.append(check_dataset(Path(bop_root), man, priors or [man.source_prior], deep=deep, bar=bar))
        for man in manifests:
            if man.kind != "bop" or (man.folder or man.name) in claimed:
                continue
            if (Path(bop_root) / (man.folder or man.name)).is_dir():
                reports.append(check_dataset(Path(bop_root), man, priors, deep=deep, bar=bar))
            else:
                absent.append(man.name)
    return reports, absent


@contextmanager
def _bars(enabled: bool) -> Iterator[BarFactory]:
    """A factory of progress bars (one rich display on stderr, so that ``--json`` output
    on stdout stays parseable; transient, so that the report is what remains)."""
    if not enabled:
        yield _no_bar
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from pipeline.common.progress import ProgressBar

    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*columns, console=Console(stderr=True), transient=True) as progress:
        yield lambda description, total: ProgressBar(progress, progress.add_task(description, total=total, rate=""))

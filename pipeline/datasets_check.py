"""Checking BOP datasets on disk before a long run (``freeze datasets check ROOT``).

For every dataset manifest of kind ``bop`` whose folder exists under ``ROOT`` (the
``bop_root``), :func:`check_dataset` reads what the stages will read and reports, as
plain findings naming the file and the field:

- the files every stage needs: the camera file, the model folder of the manifest
  (``models``; T-LESS ``models_cad``) with models_info.json and a model file per target
  object, ``models_eval`` (scoring), the targets file, scene_camera.json per scene, an
  image and a depth image per target image;
- what the manifest says of the dataset as BOP distributes it: the object ids, the
  image folder and extension (ITODD ``gray/*.tif``) and the image size;
- units: diameters in mm (a diameter below 5 looks like metres), depth_scale present
  and positive;
- targets whose image is missing; targets of objects without a model; scenes without
  ground truth (expected where it is private: ITODD, HB);
- each prior file: found, parseable, category ids that are the dataset's objects (or
  look like 0-/1-based indices: see ``segment_prior.category_ids``), detections for
  objects not in models_info and targets without any detection.

It returns a summary (objects, scenes, images, targets, instances per target) and the
findings; errors make the dataset unusable, warnings do not.
"""

from __future__ import annotations

import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.bop.dataset import MIN_DIAMETER_MM


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


def check_dataset(bop_root: Path, manifest, priors: list[str] | None = None) -> DatasetReport:
    """Check the dataset of ``manifest`` (a :class:`pipeline.config.DatasetManifest` of
    kind ``bop``) under ``bop_root``; ``priors`` as the run's (None: the dataset's
    default detections)."""
    from pipeline.plan import missing_ground_truth, open_bop

    root = Path(bop_root) / (manifest.folder or manifest.name)
    rep = DatasetReport(manifest.name, root)
    try:
        bop = open_bop(root, manifest)
        bop.camera()
        infos = bop.models_info()
        targets = bop.targets(root / manifest.targets_file)
    except (ValueError, OSError) as e:  # BopFormatError is a ValueError
        rep.errors.append(str(e))
        return rep
    _check_models(rep, bop, manifest, infos, targets)
    images = sorted({(t.scene_id, t.im_id) for t in targets})
    scenes = sorted({s for s, _ in images})
    missing_images, sizes = _check_images(rep, bop, manifest, images)
    gt_missing = missing_ground_truth(bop, scenes)
    if gt_missing and manifest.public_gt:
        rep.warnings.append(f"{gt_missing[0]}: not found ({len(gt_missing)} of "
                            f"{len(scenes)} target scenes lack ground truth): estimates will be made, but no AR")
    n_detections = _check_priors(rep, Path(bop_root), manifest, priors, infos, targets)
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


def _check_models(rep: DatasetReport, bop, manifest, infos: dict, targets: list) -> None:
    """Model folders, units, and the object ids against the manifest's."""
    for obj_id, info in sorted(infos.items()):
        if info.diameter < MIN_DIAMETER_MM:
            rep.errors.append(f"{bop.models_info_path()}: object {obj_id}: field 'diameter' is {info.diameter:g}, "
                              f"below {MIN_DIAMETER_MM:g}: models must be in mm (these look like metres)")
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
        _check_model_files(rep, bop, manifest, infos, target_objs)


def _check_model_files(rep: DatasetReport, bop, manifest, infos: dict, target_objs: list[int]) -> None:
    """A models_info entry and a model file for every target object."""
    for obj_id in target_objs:
        if obj_id not in infos:
            rep.errors.append(f"{bop.root / manifest.targets_file}: object {obj_id} is a target but has no entry in "
                              f"{bop.models_info_path()}")
        elif not bop.model_path(obj_id).is_file():
            rep.errors.append(f"{bop.model_path(obj_id)}: model file of target object {obj_id} not found")


def _check_images(rep: DatasetReport, bop, manifest, images: list[tuple[int, int]]) -> tuple[int, set]:
    """Camera entries, depth scales and the image files of every target image; the
    first image of each scene is opened for its size. Returns (images with problems,
    the (width, height) sizes seen)."""
    from PIL import Image

    missing_images = 0
    sizes: set[tuple[int, int]] = set()
    for scene_id in sorted({s for s, _ in images}):
        try:
            cams = bop.scene_camera(scene_id)
        except (ValueError, OSError) as e:
            rep.errors.append(str(e))
            continue
        first = True
        for s, im_id in images:
            if s != scene_id:
                continue
            problems = []
            if im_id not in cams:
                problems.append(f"{bop.scene_dir(scene_id) / 'scene_camera.json'}: no entry for image {im_id}")
            elif not cams[im_id].depth_scale or cams[im_id].depth_scale <= 0:
                problems.append(f"{bop.scene_dir(scene_id) / 'scene_camera.json'}: image {im_id}: field "
                                f"'depth_scale' must be positive, got {cams[im_id].depth_scale}")
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
            if problems:
                missing_images += 1
                rep.errors.extend(problems)
    return missing_images, sizes


def _check_priors(rep: DatasetReport, bop_root: Path, manifest, priors: list[str] | None, infos: dict,
                  targets: list) -> int | None:
    """Each prior file: found, parseable, category ids that are objects, coverage of the
    targets. Returns the number of detections (None if a file could not be read)."""
    from pipeline.bop.detections import category_id_problem, load_detections
    from pipeline.config import ManifestError
    from pipeline.plan import resolve_prior

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


def check_root(bop_root: Path, priors: list[str] | None = None) -> tuple[list[DatasetReport], list[str]]:
    """Reports for every BOP dataset manifest whose folder exists under ``bop_root``,
    and the names of those whose folder is absent."""
    from pipeline.config import MANIFEST_DIR, load_dataset_manifest

    reports, absent = [], []
    for path in sorted((MANIFEST_DIR / "datasets").glob("*.yaml")):
        man = load_dataset_manifest(path.stem)
        if man.kind != "bop":
            continue
        if (Path(bop_root) / (man.folder or man.name)).is_dir():
            reports.append(check_dataset(Path(bop_root), man, priors))
        else:
            absent.append(man.name)
    return reports, absent

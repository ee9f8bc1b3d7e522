"""Checking BOP datasets on disk before a long run (``freeze datasets check ROOT``).

For every dataset manifest of kind ``bop`` whose folder exists under ``ROOT`` (the
``bop_root``), :func:`check_dataset` reads what the stages will read and reports, as
plain findings naming the file and the field:

- the files every stage needs: camera.json, models/models_info.json and a model file
  per target object, the targets file, scene_camera.json per scene, an RGB (or grey)
  and a depth image per target image;
- units: diameters in mm (a diameter below 5 looks like metres), depth_scale present
  and positive;
- targets whose image is missing; targets of objects without a model;
- the prior: its file found, parseable, and detections for objects that are not
  targets or not in models_info (reported, not fatal: the stages drop them).

It returns a summary (objects, scenes, images, targets, instances per target) and the
findings; errors make the dataset unusable, warnings do not.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MIN_DIAMETER_MM = 5.0


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


def check_dataset(bop_root: Path, manifest) -> DatasetReport:
    """Check the dataset of ``manifest`` (a :class:`pipeline.config.DatasetManifest` of
    kind ``bop``) under ``bop_root``."""
    from pipeline.bop import BopDataset
    from pipeline.bop.detections import load_detections

    root = Path(bop_root) / (manifest.folder or manifest.name)
    rep = DatasetReport(manifest.name, root)
    try:
        bop = BopDataset(root, split=manifest.split, split_type=manifest.split_type)
        bop.camera()
        infos = bop.models_info()
        targets = bop.targets(root / manifest.targets_file)
    except (ValueError, OSError) as e:  # BopFormatError is a ValueError
        rep.errors.append(str(e))
        return rep
    for obj_id, info in sorted(infos.items()):
        if info.diameter < MIN_DIAMETER_MM:
            rep.errors.append(f"{bop.models_info_path()}: object {obj_id}: field 'diameter' is {info.diameter:g}, "
                              f"below {MIN_DIAMETER_MM:g}: models must be in mm (these look like metres)")
    target_objs = sorted({t.obj_id for t in targets})
    for obj_id in target_objs:
        if obj_id not in infos:
            rep.errors.append(f"{root / manifest.targets_file}: object {obj_id} is a target but has no entry in "
                              f"{bop.models_info_path()}")
        elif not bop.model_path(obj_id).is_file():
            rep.errors.append(f"{bop.model_path(obj_id)}: model file of target object {obj_id} not found")
    images = sorted({(t.scene_id, t.im_id) for t in targets})
    scenes = sorted({s for s, _ in images})
    missing_images = 0
    for scene_id in scenes:
        try:
            cams = bop.scene_camera(scene_id)
        except (ValueError, OSError) as e:
            rep.errors.append(str(e))
            continue
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
                bop.rgb_path(scene_id, im_id)
            except ValueError as e:
                problems.append(str(e))
            if not bop.has_depth(scene_id, im_id):
                problems.append(f"{bop.scene_dir(scene_id)}: no depth/ image for target image {im_id}")
            if problems:
                missing_images += 1
                rep.errors.extend(problems)
    from pipeline.config import ManifestError
    from pipeline.plan import resolve_prior

    n_detections = None
    try:
        prior = resolve_prior(Path(bop_root), manifest.prior)
    except ManifestError as e:
        rep.errors.append(str(e))
        prior = None
    if prior is None:
        pass
    elif not prior.is_file():
        rep.errors.append(f"{prior}: localisation prior not found (field 'prior' of manifests/datasets/{manifest.name}.yaml)")
    else:
        try:
            dets = load_detections(prior)
        except (ValueError, OSError) as e:
            rep.errors.append(str(e))
        else:
            n_detections = len(dets)
            unknown = Counter(d.category_id for d in dets if d.category_id not in infos)
            if unknown:
                rep.warnings.append(f"{prior}: detections of objects not in models_info: "
                                    + ", ".join(f"{o} ({n})" for o, n in sorted(unknown.items())))
            target_keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
            covered = {(d.scene_id, d.image_id, d.category_id) for d in dets}
            uncovered = len(target_keys - covered)
            if uncovered:
                rep.warnings.append(f"{prior}: {uncovered} of {len(target_keys)} targets have no detection "
                                    "(they will get no estimate)")
    per_target = Counter(t.inst_count for t in targets)
    rep.summary = {
        "objects": len(target_objs), "scenes": len(scenes), "images": len(images), "targets": len(targets),
        "instances": int(sum(t.inst_count for t in targets)),
        "instances_per_target": {str(k): v for k, v in sorted(per_target.items())},
        "images_with_problems": missing_images, "detections": n_detections,
    }
    return rep


def check_root(bop_root: Path) -> tuple[list[DatasetReport], list[str]]:
    """Reports for every BOP dataset manifest whose folder exists under ``bop_root``,
    and the names of those whose folder is absent."""
    from pipeline.config import MANIFEST_DIR, load_dataset_manifest

    reports, absent = [], []
    for path in sorted((MANIFEST_DIR / "datasets").glob("*.yaml")):
        man = load_dataset_manifest(path.stem)
        if man.kind != "bop":
            continue
        if (Path(bop_root) / (man.folder or man.name)).is_dir():
            reports.append(check_dataset(Path(bop_root), man))
        else:
            absent.append(man.name)
    return reports, absent

"""Real datasets from real samples: a bop_root-style sample (real RGB, real depth,
ground truth, models and an exact prior) made into a dataset the pipeline runs, with
two priors.

``build_real(source, out_dir, ds)`` copies the dataset folder ``source/<ds.folder>``
whole (nothing of it is changed: the images, depth, cameras, ground truth and models
are the camera's and the sample's) and writes under ``detections/``:

- ``gtmask_<name>-<split>.json``: the sample's own exact prior (``ds.source_prior``),
  byte for byte;
- ``faulty_<name>-<split>.json``: a prior derived from it with a detector's faults at
  the rates the manifest states (``ds.prior_faults``;
  :func:`pipeline.evaluation.synth.detector_faults.derive_faulty_prior`), drawn from a
  generator seeded by ``ds.seed``; beside it, ``faulty_<name>-<split>.faults.json``
  counts the faults made and their measured rates.

The sample is checked first: the targets file and the exact prior are read, every
target image's camera declares the manifest's ``depth_scale`` (when it states one), and
the exact prior has a detection for each target. A sample that fails gets one error
naming the file and the field, and nothing is written.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from pipeline.common.store import atomic_dir
from pipeline.formats.bop import BopDataset, load_detections, save_detections
from pipeline.formats.bop.dataset import depth_scale_problem

from .detector_faults import DetectorFaults, derive_faulty_prior

EXACT_DETECTOR = "gtmask"
"""Detector name of the copied exact prior."""
FAULTY_DETECTOR = "faulty"
"""Detector name of the derived faulty prior."""


def prior_name(detector: str, name: str, split: str) -> str:
    """A prior's path relative to the dataset root: ``detections/<detector>_<name>-<split>.json``."""
    return f"detections/{detector}_{name}-{split}.json"


def detector_faults(ds) -> DetectorFaults:
    """The :class:`DetectorFaults` of a real dataset manifest's ``prior_faults``."""
    rates = ds.prior_faults.model_dump()
    rates["cut_fraction"] = tuple(rates["cut_fraction"])
    return DetectorFaults(**rates)


def _check_sample(bop, ds, targets, exact, prior_path: Path) -> None:
    """Raise ValueError naming the file and the field where the sample departs from its manifest."""
    if ds.depth_scale is not None:
        for s in sorted({t.scene_id for t in targets}):
            problem = depth_scale_problem(bop, s, ds.depth_scale, f"manifests/datasets/{ds.name}.yaml")
            if problem:
                raise ValueError(problem)
    covered = {(d.scene_id, d.image_id, d.category_id) for d in exact}
    uncovered = [t for t in targets if (t.scene_id, t.im_id, t.obj_id) not in covered]
    if uncovered:
        t = uncovered[0]
        raise ValueError(f"{prior_path}: no detection of object {t.obj_id} in scene {t.scene_id} image {t.im_id} "
                         f"({len(uncovered)} targets uncovered): the exact prior must cover every target")


def build_real(source: Path | str, out_dir: Path | str, ds, progress: bool = True) -> dict:
    """Write the real dataset of manifest ``ds`` (kind ``real``; module docstring) to
    ``out_dir`` from the sample ``source`` (a bop_root holding ``ds.folder``). Returns a
    summary: images, targets, instances, detections per prior and the faults made
    (counts and measured rates)."""
    source = Path(source)
    src_root = source / ds.folder
    if not src_root.is_dir():
        raise ValueError(f"{src_root}: dataset folder not found (field 'folder' of dataset '{ds.name}')")
    bop = BopDataset(src_root, split=ds.split, split_type=ds.split_type, models_dir=ds.models,
                     camera_file=ds.camera_file)
    targets = bop.targets(src_root / ds.targets_file)
    prior_path = source / ds.source_prior
    exact = load_detections(prior_path)
    _check_sample(bop, ds, targets, exact, prior_path)
    obj_ids = sorted({t.obj_id for t in targets})
    faulty, log = derive_faulty_prior(exact, obj_ids, np.random.default_rng([ds.seed, 30]), detector_faults(ds))
    with atomic_dir(out_dir) as root:
        shutil.copytree(src_root, root, dirs_exist_ok=True)
        exact_out = root / prior_name(EXACT_DETECTOR, ds.name, ds.split)
        exact_out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(prior_path, exact_out)
        save_detections(root / prior_name(FAULTY_DETECTOR, ds.name, ds.split), faulty)
        log_path = root / prior_name(FAULTY_DETECTOR, ds.name, ds.split).replace(".json", ".faults.json")
        log_path.write_text(json.dumps(log.to_json(), indent=1) + "\n")
    return {"images": len({(t.scene_id, t.im_id) for t in targets}), "targets": len(targets),
            "instances": int(sum(t.inst_count for t in targets)),
            "detections": {EXACT_DETECTOR: len(exact), FAULTY_DETECTOR: len(faulty)},
            "faults": log.to_json()}

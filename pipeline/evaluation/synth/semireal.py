"""Semi-real BOP datasets built from real samples: real camera images, with depth rendered
from the ground-truth poses where the sample has none, and a prior derived from the
ground truth.

``build_semireal(source, out_dir, name)`` reads a BOP-format sample (real RGB, ground
truth, models) and writes a dataset the pipeline runs:

- ``depth="rendered"`` (LM-O's RGB sample has no depth): every annotated object is
  rendered at its ground-truth pose, and the nearest surface is the depth, passed
  through the Primesense-like sensor model (:func:`pipeline.evaluation.synth.sensor.simulate_depth`:
  axial noise growing with z², missing and noisy edges, grazing angles, dropout). Pixels
  of no annotated object get no depth, as sensor holes: the real unannotated clutter of
  the image (LM-O's other LINEMOD objects) has no depth.
- ``depth="real"``: the sample's own depth is kept (the TYO-L frame).

Masks come from the renders (:func:`pipeline.evaluation.synth.annotate.annotate_instance`). An
unannotated object in front of an annotated one is in the image but not in the render:
where the sample's ``scene_gt_info.json`` gives each instance's visible box
(``bbox_visib``, measured on the real data), the visible mask and the rendered depth
are cut to it, so occlusion by such an object at a side is respected (an occluder in
the middle of an object is not: the sample has no visible masks).

The prior is the synthetic prior with its faults (``prior="faulty"``,
:func:`pipeline.evaluation.synth.priors.image_detections`) or the exact visible masks with score 1
(``prior="exact"``). The targets are the sample's own. Everything is written under
temporary names and renamed into place (:func:`pipeline.common.store.atomic_dir`).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.formats.bop import (
    BopDataset,
    CameraInfo,
    GtInfo,
    detection_from_mask,
    save_depth_png,
    save_detections,
    save_mask_png,
    write_scene_camera,
    write_scene_gt_info,
)
from pipeline.formats.bop.ply import load_mesh
from pipeline.method.render import Renderer
from pipeline.common.store import atomic_dir

from .annotate import annotate_instance, bbox_from_mask, projected_bbox
from .priors import PriorFaults, VisibleInstance, image_detections
from .sensor import DepthSensor, simulate_depth

DEPTH_SCALE = 0.1
"""mm per unit of the written depth PNGs (rendered depth)."""
DETECTOR = "gtprior"
"""Detector name of the prior file: ``detections/gtprior_<name>-test.json``."""

DepthMode = Literal["rendered", "real"]
PriorMode = Literal["faulty", "exact"]


def prior_file(name: str) -> str:
    """The prior's path relative to the dataset root."""
    return f"detections/{DETECTOR}_{name}-test.json"


def _clip_to_box(mask: np.ndarray, box: tuple[int, int, int, int] | None) -> np.ndarray:
    """``mask`` outside the BOP box (x, y, w, h; w and h are max - min) set to False."""
    if box is None or box[2] < 0:
        return mask
    x, y, w, h = box
    out = np.zeros_like(mask)
    out[max(0, y):y + h + 1, max(0, x):x + w + 1] = mask[max(0, y):y + h + 1, max(0, x):x + w + 1]
    return out


def build_semireal(source: Path | str, out_dir: Path | str, name: str, *, depth: DepthMode = "rendered",
                   prior: PriorMode = "faulty", seed: int = 0, sensor: DepthSensor = DepthSensor(),
                   faults: PriorFaults = PriorFaults(), progress: bool = True) -> dict:
    """Write the semi-real dataset ``out_dir`` (module docstring) from the BOP sample
    ``source``; returns a summary (images, instances, targets, detections, mean visible
    fraction measured here and in the sample)."""
    source = Path(source)
    src = BopDataset(source)
    if not src.scene_ids():
        raise ValueError(f"{source}: no test scene in the sample")
    from pipeline.common.progress import progress_bar

    rng = np.random.default_rng([seed, 7])
    n_images = sum(len(src.image_ids(s)) for s in src.scene_ids())
    summary = {"images": 0, "instances": 0, "detections": 0, "visib_fract_here": [], "visib_fract_sample": []}
    with atomic_dir(out_dir) as root, progress_bar(f"semireal {name}", total=n_images, enabled=progress) as bar:
        for item in ("camera.json", "test_targets_bop19.json", "models", "models_eval"):
            (shutil.copytree if (source / item).is_dir() else shutil.copy2)(source / item, root / item)
        obj_ids = src.obj_ids()
        detections = []
        for scene_id in src.scene_ids():
            sdir, out_sdir = src.scene_dir(scene_id), root / "test" / f"{scene_id:06d}"
            out_sdir.mkdir(parents=True)
            shutil.copytree(sdir / "rgb", out_sdir / "rgb")
            shutil.copy2(sdir / "scene_gt.json", out_sdir / "scene_gt.json")
            cams = src.scene_camera(scene_id)
            gts = src.scene_gt(scene_id)
            sample_infos = src.scene_gt_info(scene_id) if (sdir / "scene_gt_info.json").is_file() else {}
            W, H = next(iter(cams.values())).width, next(iter(cams.values())).height
            infos: dict[int, list[GtInfo]] = {}
            new_cams: dict[int, CameraInfo] = {}
            with Renderer(W, H, znear=100.0, zfar=15000.0) as renderer:
                meshes = {}
                for o in obj_ids:
                    meshes[o] = load_mesh(src.model_path(o))
                    renderer.add_mesh(o, meshes[o])
                for im_id in src.image_ids(scene_id):
                    K = cams[im_id].K
                    renders = [renderer.render_depth(g.obj_id, g.R, g.t, K) for g in gts[im_id]]
                    clean = np.zeros((H, W), np.float32)
                    for d in renders:
                        clean = np.where((d > 0) & ((clean == 0) | (d < clean)), d, clean)
                    boxes = [sample_infos[im_id][k].bbox_visib if im_id in sample_infos else None
                             for k in range(len(renders))]
                    # what the real image shows: each object's visible part, cut to its measured visible box
                    shown = np.zeros((H, W), bool)
                    for d, box in zip(renders, boxes):
                        shown |= _clip_to_box((d > 0) & (np.abs(d - clean) <= 2.0), box)
                    if depth == "rendered":
                        measured = simulate_depth(np.where(shown, clean, 0.0), K, rng, sensor)
                        save_depth_png(out_sdir / "depth" / f"{im_id:06d}.png", measured, DEPTH_SCALE)
                        new_cams[im_id] = CameraInfo(K=K, depth_scale=DEPTH_SCALE, width=W, height=H,
                                                     R_w2c=cams[im_id].R_w2c, t_w2c=cams[im_id].t_w2c)
                    else:
                        measured = src.load_depth(scene_id, im_id)
                        (out_sdir / "depth").mkdir(exist_ok=True)
                        shutil.copy2(src.depth_path(scene_id, im_id), out_sdir / "depth" / src.depth_path(scene_id, im_id).name)
                        new_cams[im_id] = cams[im_id]
                    infos[im_id], visible = [], []
                    for gt_id, (g, d, box) in enumerate(zip(gts[im_id], renders, boxes)):
                        ann = annotate_instance(d, clean, measured, projected_bbox(np.asarray(meshes[g.obj_id].vertices),
                                                                                     g.R, g.t, K))
                        visib = _clip_to_box(ann.mask_visib, box)
                        n_all = max(1, ann.info.px_count_all)
                        info = GtInfo(bbox_obj=ann.info.bbox_obj, bbox_visib=bbox_from_mask(visib),
                                      px_count_all=ann.info.px_count_all,
                                      px_count_valid=int((ann.mask & (measured > 0)).sum()),
                                      px_count_visib=int(visib.sum()), visib_fract=float(visib.sum() / n_all))
                        save_mask_png(out_sdir / "mask" / f"{im_id:06d}_{gt_id:06d}.png", ann.mask)
                        save_mask_png(out_sdir / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png", visib)
                        infos[im_id].append(info)
                        visible.append(VisibleInstance(g.obj_id, visib, info.visib_fract))
                        summary["visib_fract_here"].append(info.visib_fract)
                        if im_id in sample_infos:
                            summary["visib_fract_sample"].append(sample_infos[im_id][gt_id].visib_fract)
                    if prior == "faulty":
                        detections += image_detections(scene_id, im_id, visible, ~shown, obj_ids, rng, faults)
                    else:
                        detections += [detection_from_mask(scene_id, im_id, v.obj_id, 1.0, v.mask_visib)
                                       for v in visible if v.mask_visib.any()]
                    summary["images"] += 1
                    summary["instances"] += len(renders)
                    bar.advance()
            write_scene_camera(out_sdir / "scene_camera.json", new_cams)
            write_scene_gt_info(out_sdir / "scene_gt_info.json", infos)
        det_path = root / prior_file(name)
        det_path.parent.mkdir(parents=True)
        save_detections(det_path, detections)
        summary["detections"] = len(detections)
        summary["targets"] = int(sum(t.inst_count for t in BopDataset(root).targets()))
    for key in ("visib_fract_here", "visib_fract_sample"):
        values = summary.pop(key)
        summary[f"mean_{key}"] = round(float(np.mean(values)), 4) if values else None
    return summary

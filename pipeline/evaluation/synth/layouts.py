"""Small synthetic datasets written exactly in the layout of a BOP core dataset.

``write_layout(manifest, bop_root)`` renders a tiny synthetic scene at the dataset's
image size and writes it under ``<bop_root>/<folder>/`` the way that dataset is
distributed, so that the reader, ``freeze datasets check`` and ``bop_all`` can be
exercised on each layout without the download:

- the camera file (``camera.json``, ``camera_primesense.json`` for T-LESS/HB,
  ``camera_uw.json`` for YCB-V) and the split folder (``test_primesense`` for T-LESS/HB);
- the model folder of the manifest (``models_cad`` for T-LESS) and ``models_eval``;
- the dataset's own object ids (LM-O: 1, 5, 6, ...) and test scene ids (LM-O: 2,
  YCB-V: 48, HB: 3);
- the image folder and extensions: ``gray/*.tif`` 8-bit and ``depth/*.tif`` 16-bit
  for ITODD, ``rgb/*.png`` and ``depth/*.png`` otherwise;
- no ``scene_gt*.json`` nor masks where the test ground truth is private (ITODD, HB);
- the default detections as ``<bop_root>/detections/<detector>_<name>-test<suffix>.json``.

What is not the real dataset's: the objects, the scenes and the intrinsics (the focal
length is scaled with the image width so that the synthetic scene fills the view).
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2

from pipeline.formats.bop.dataset import write_image
from pipeline.formats.bop.detections import load_detections, save_detections
from pipeline.formats.bop.jsonio import load_json, save_bop_json

# First test scene id of each core dataset (bop_toolkit dataset_params).
FIRST_TEST_SCENE = {"lmo": 2, "tless": 1, "tudl": 1, "icbin": 1, "itodd": 1, "hb": 3, "ycbv": 48}
_BASE_CAMERA = (572.4114, 573.57043, 325.2611, 242.04899)  # at 640 px wide


@dataclass(frozen=True)
class LayoutSummary:
    """Where ``write_layout`` put things: the dataset folder, the detections file, the
    synthetic -> dataset object id map and the scene ids written."""

    root: Path
    detections: Path
    obj_map: dict[int, int]
    scene_ids: list[int]


def write_layout(manifest, bop_root: Path | str, *, seed: int = 0, detector: str = "cnos-fastsam",
                 suffix: str = "_fixture", source_dir: Path | str | None = None,
                 progress: bool = False) -> LayoutSummary:
    """Write a tiny synthetic dataset under ``<bop_root>/<manifest.folder>`` in the
    layout of ``manifest`` (a :class:`pipeline.common.config.DatasetManifest` of kind bop that
    gives ``obj_ids`` and ``image_size``). Three objects (or as many as the dataset has),
    one scene, two images.

    source_dir: keep the synthetic dataset it was made from there (in the generator's
    own layout, with its ground truth), e.g. to compare the two; default: discarded."""
    from pipeline.evaluation.synth import PRESETS, SynthPreset, generate

    if not manifest.obj_ids or not manifest.image_size:
        raise ValueError(f"dataset '{manifest.name}': write_layout needs the manifest's obj_ids and image_size")
    bop_root = Path(bop_root)
    width, height = manifest.image_size
    s = width / 640.0
    n = min(3, len(manifest.obj_ids))  # IC-BIN has two objects
    synth_ids = PRESETS["tiny"].obj_ids[:n]
    preset = SynthPreset(f"{manifest.name}-layout", obj_ids=synth_ids, n_scenes=1, images_per_scene=2,
                         objects_per_scene=(n, n), duplicate_prob=1.0, distractors_per_scene=(1, 1),
                         width=width, height=height,
                         camera=(_BASE_CAMERA[0] * s, _BASE_CAMERA[1] * s, width / 2.0 + 5.3, height / 2.0 + 2.1))
    obj_map = dict(zip(sorted(preset.obj_ids), sorted(manifest.obj_ids)))
    scene_id = FIRST_TEST_SCENE.get(manifest.name, 1)
    with tempfile.TemporaryDirectory(prefix=f"layout-{manifest.name}-") as tmp:
        src = Path(source_dir) if source_dir else Path(tmp) / manifest.name
        generate(src, name=manifest.name, preset=preset, seed=seed, progress=progress)
        dst = bop_root / (manifest.folder or manifest.name)
        if dst.exists():
            raise FileExistsError(f"{dst} exists; write_layout writes a fresh dataset folder")
        _write_dataset(src, dst, manifest, obj_map, {1: scene_id})
        det_path = bop_root / "detections" / f"{detector}_{manifest.name}-test{suffix}.json"
        dets = load_detections(src / "detections" / f"cnos-synth_{manifest.name}-test.json")
        for d in dets:
            d.scene_id, d.category_id = scene_id, obj_map[d.category_id]
        save_detections(det_path, dets)
    return LayoutSummary(dst, det_path, obj_map, [scene_id])


def _camera_name(manifest) -> str:
    if manifest.camera_file:
        return manifest.camera_file
    return f"camera_{manifest.split_type}.json" if manifest.split_type else "camera.json"


def _write_dataset(src: Path, dst: Path, manifest, obj_map: dict[int, int], scene_map: dict[int, int]) -> None:
    dst.mkdir(parents=True)
    shutil.copy2(src / "camera.json", dst / _camera_name(manifest))
    for folder_in, folder_out in (("models", manifest.models), ("models_eval", "models_eval")):
        (dst / folder_out).mkdir()
        info = load_json(src / folder_in / "models_info.json")
        save_bop_json(dst / folder_out / "models_info.json", {obj_map[int(k)]: v for k, v in info.items()})
        for old, new in obj_map.items():
            shutil.copy2(src / folder_in / f"obj_{old:06d}.ply", dst / folder_out / f"obj_{new:06d}.ply")
    targets = load_json(src / "test_targets_bop19.json")
    save_bop_json(dst / manifest.targets_file, [
        {**t, "obj_id": obj_map[t["obj_id"]], "scene_id": scene_map[t["scene_id"]]} for t in targets])
    split = f"{manifest.split}_{manifest.split_type}" if manifest.split_type else manifest.split
    for old_scene, new_scene in scene_map.items():
        s_in = src / "test" / f"{old_scene:06d}"
        s_out = dst / split / f"{new_scene:06d}"
        s_out.mkdir(parents=True)
        shutil.copy2(s_in / "scene_camera.json", s_out / "scene_camera.json")
        for path in sorted((s_in / "rgb").glob("*.png")):
            _write_image(path, s_out / manifest.image_dir / f"{path.stem}{manifest.image_ext}", manifest.image_dir)
        for path in sorted((s_in / "depth").glob("*.png")):
            depth = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
            write_image(s_out / "depth" / f"{path.stem}{manifest.depth_ext}", depth)
        if manifest.public_gt:
            gt = load_json(s_in / "scene_gt.json")
            save_bop_json(s_out / "scene_gt.json", {
                int(im): [{**g, "obj_id": obj_map[g["obj_id"]]} for g in items] for im, items in gt.items()})
            shutil.copy2(s_in / "scene_gt_info.json", s_out / "scene_gt_info.json")
            shutil.copytree(s_in / "mask", s_out / "mask")
            shutil.copytree(s_in / "mask_visib", s_out / "mask_visib")


def _write_image(src_png: Path, dst: Path, image_dir: str) -> None:
    bgr = cv2.imread(str(src_png), cv2.IMREAD_COLOR)
    # ITODD's grey camera: one 8-bit channel
    write_image(dst, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if image_dir == "gray" else bgr)

"""Write a complete synthetic BOP dataset plus a CNOS-style prior.

Layout written in ``out_dir`` (BOP conventions: mm, OpenCV camera, model-to-camera)::

    camera.json  test_targets_bop19.json
    models/ models_eval/        obj_XXXXXX.ply + models_info.json
    test/<scene:06d>/           rgb/ depth/ mask/ mask_visib/ scene_camera.json scene_gt.json scene_gt_info.json
    detections/cnos-synth_<name>-test.json

Everything is written into a hidden sibling directory that is renamed to ``out_dir``
at the end, so an interrupted run leaves nothing that looks complete. The output is a
function of (preset, seed): random draws come from generators seeded with
``[seed, scene_id]``, and the objects are fixed designs.
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Hashable

import numpy as np

from pipeline.formats.bop import (
    CameraInfo,
    Detection,
    GtInfo,
    GtPose,
    Target,
    load_mesh,
    save_depth_png,
    save_detections,
    save_mask_png,
    save_rgb,
    write_camera,
    write_models_info,
    write_ply,
    write_scene_camera,
    write_scene_gt,
    write_scene_gt_info,
    write_targets,
)
from pipeline.method.render import Renderer
from pipeline.common.store import atomic_dir

from .annotate import VISIB_TOL_MM, annotate_instance, image_targets, projected_bbox
from .objects import SynthObject, build_object
from .presets import PRESETS, SynthPreset
from .priors import VisibleInstance, image_detections
from .scene import (
    Placement,
    RestingPoses,
    SceneLights,
    layout_objects,
    make_distractor,
    make_room,
    resting_poses,
    sample_lights,
    sample_views,
)
from .camera_gap import camera_rgb, drift_colours, surface_holes
from .sensor import simulate_depth, simulate_rgb
from .textures import TABLE_TEXTURES

TABLE_TOP_TOL_MM = 1.5


def compose_scenes(preset: SynthPreset, rng: np.random.Generator) -> list[list[int]]:
    """Object ids of each scene's instances; every object of the preset appears at least once."""
    must = [int(o) for o in rng.permutation(preset.obj_ids)]
    scenes = []
    lo, hi = preset.objects_per_scene
    for _ in range(preset.n_scenes):
        k = int(rng.integers(lo, hi + 1))
        take, must = must[:k], must[k:]
        others = [o for o in preset.obj_ids if o not in take]
        fill = [int(o) for o in rng.choice(others, k - len(take), replace=False)] if k > len(take) else []
        chosen = take + fill
        if rng.random() < preset.duplicate_prob:
            chosen.append(chosen[int(rng.integers(len(chosen)))])
        scenes.append(chosen)
    return scenes


def _write_models(root: Path, objects: dict[int, SynthObject]) -> None:
    info = {o: obj.model_info() for o, obj in objects.items()}
    for sub in ("models", "models_eval"):
        (root / sub).mkdir(parents=True)
        write_models_info(root / sub / "models_info.json", info)
    for o, obj in objects.items():
        m = obj.model
        write_ply(
            root / "models" / f"obj_{o:06d}.ply",
            np.asarray(m.vertices), np.asarray(m.faces), normals=np.asarray(m.vertex_normals),
            colors=np.asarray(m.visual.vertex_colors)[:, :3],
        )
        e = obj.eval_mesh
        write_ply(root / "models_eval" / f"obj_{o:06d}.ply", np.asarray(e.vertices), np.asarray(e.faces), normals=np.asarray(e.vertex_normals))


def _progress(enabled: bool):
    if not enabled:
        return nullcontext(None)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())


def _table_mask(depth: np.ndarray, K: np.ndarray, R_w2c: np.ndarray, t_w2c: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """(H, W) bool pixels showing the table top (world z = 0) and no object."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    pc = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], axis=-1)
    z_world = ((pc - t_w2c) @ R_w2c)[..., 2]
    return (depth > 0) & (np.abs(z_world) < TABLE_TOP_TOL_MM) & ~objects


def _write_dataset(root: Path, name: str, preset: SynthPreset, seed: int, progress: bool) -> dict:
    W, H = preset.width, preset.height
    n_images = preset.n_scenes * preset.images_per_scene
    with _progress(progress) as bar:
        task = bar.add_task(f"synth {name}: objects", total=len(preset.obj_ids) + n_images) if bar else None

        def step(desc: str) -> None:
            if bar:
                bar.update(task, advance=1, description=f"synth {name}: {desc}")

        objects: dict[int, SynthObject] = {}
        poses: dict[Hashable, RestingPoses] = {}
        for o in preset.obj_ids:
            objects[o] = build_object(o)
            poses[o] = resting_poses(objects[o])
            step(f"object {o}")
        _write_models(root, objects)
        fx, fy, cx, cy = preset.camera
        write_camera(root, {"cx": cx, "cy": cy, "depth_scale": preset.depth_scale, "fx": fx, "fy": fy, "height": H, "width": W})

        # One renderer for the whole run. znear 100 mm gives ten times finer
        # depth-buffer steps than the default, hence fewer depth ties.
        renderer = Renderer(W, H, znear=100.0, zfar=15000.0)
        out = _Outputs()
        try:
            drift = np.random.default_rng([seed, 99])
            for o in preset.obj_ids:
                # Render what users load: the written PLY, not the in-memory mesh (with the
                # hard preset, its colours drifted: the scene is not printed like the model).
                mesh = load_mesh(root / "models" / f"obj_{o:06d}.ply")
                renderer.add_mesh(o, drift_colours(mesh, drift, preset.camera_gap) if preset.camera_gap else mesh)
            for scene_id, ids in enumerate(compose_scenes(preset, np.random.default_rng([seed, 0])), start=1):
                _write_scene(root, scene_id, ids, preset, seed, renderer, poses, out, step)
        finally:
            renderer.close()
        write_targets(root / "test_targets_bop19.json", out.targets)
        det_path = root / "detections" / f"cnos-synth_{name}-test.json"
        det_path.parent.mkdir(parents=True)
        save_detections(det_path, out.detections)
    return {
        "objects": len(objects),
        "scenes": preset.n_scenes,
        "images": n_images,
        "targets": int(sum(t.inst_count for t in out.targets)),
        "instances": out.instances,
        "detections": len(out.detections),
    }


@dataclass
class _Outputs:
    """What the scenes add to the dataset-level files."""

    targets: list[Target] = field(default_factory=list)
    detections: list[Detection] = field(default_factory=list)
    instances: int = 0


@dataclass
class _Scene:
    """A composed scene in world coordinates; keys are renderer mesh keys."""

    objects: list[Placement]
    clutter: list[Placement]
    room_keys: list[Hashable]
    lights: SceneLights
    views: list[tuple[np.ndarray, np.ndarray]]


def _compose_scene(scene_id: int, ids: list[int], preset: SynthPreset, rng: np.random.Generator,
                   renderer: Renderer, poses: dict[Hashable, RestingPoses]) -> _Scene:
    """Lay out objects and distractors, build the room, draw lights and camera views."""
    lo, hi = preset.distractors_per_scene
    clutter_meshes = {("distractor", scene_id, k): make_distractor(rng) for k in range(int(rng.integers(lo, hi, endpoint=True)))}
    all_poses = dict(poses)
    for key, mesh in clutter_meshes.items():
        renderer.add_mesh(key, mesh)
        all_poses[key] = resting_poses(mesh)
    # Objects first, then distractors, which often land next to them and occlude them.
    placed = layout_objects(list(ids) + list(clutter_meshes), all_poses, rng)
    objects = [p for p in placed if p.key not in clutter_meshes]
    clutter = [p for p in placed if p.key in clutter_meshes]
    room = make_room(str(rng.choice(sorted(TABLE_TEXTURES))), rng, centre=rng.uniform(-250, 250, size=2))
    room_keys = []
    for part, mesh in room.meshes.items():
        room_keys.append(("room", scene_id, part))
        renderer.add_mesh(room_keys[-1], mesh)
    lights = sample_lights(rng, target=np.mean([p.t for p in objects], axis=0))
    views = sample_views(objects, preset.images_per_scene, preset.K, (preset.width, preset.height), rng,
                         preset.elevation_deg, preset.distance_mm)
    return _Scene(objects, clutter, room_keys, lights, views)


def _write_scene(
    root: Path,
    scene_id: int,
    ids: list[int],
    preset: SynthPreset,
    seed: int,
    renderer: Renderer,
    poses: dict[Hashable, RestingPoses],
    out: _Outputs,
    step: Callable[[str], None],
) -> None:
    """Render, annotate and write one scene's images; add its targets and detections to ``out``."""
    rng = np.random.default_rng([seed, scene_id])
    K, W, H, ds = preset.K, preset.width, preset.height, preset.depth_scale
    sdir = root / "test" / f"{scene_id:06d}"
    scene = _compose_scene(scene_id, ids, preset, rng, renderer, poses)
    cams: dict[int, CameraInfo] = {}
    gts: dict[int, list[GtPose]] = {}
    infos: dict[int, list[GtInfo]] = {}
    for im_id, (Rc, tc) in enumerate(scene.views):
        in_cam = lambda p: (p.key, Rc @ p.R, Rc @ p.t + tc)  # noqa: E731
        objs_c = [in_cam(p) for p in scene.objects]
        clutter_c = [in_cam(p) for p in scene.clutter]
        items = [(k, Rc, tc) for k in scene.room_keys] + objs_c + clutter_c
        rgb, depth = renderer.render(items, K, rgb=True, lighting=scene.lights.in_camera(Rc, tc))
        if preset.camera_gap is None:
            measured = simulate_depth(depth, K, rng, preset.sensor)
            image = simulate_rgb(rgb, rng)
        else:
            on_objects = np.zeros((H, W), bool)
            for key, R, t in objs_c + clutter_c:
                d = renderer.render_depth(key, R, t, K)
                on_objects |= (d > 0) & (np.abs(d - depth) <= VISIB_TOL_MM)
            image, highlight = camera_rgb(rgb, depth, on_objects, K, rng, preset.camera_gap)
            measured = simulate_depth(depth, K, rng, preset.sensor)
            measured[surface_holes(rgb, highlight, on_objects, rng, preset.camera_gap)] = 0.0
        save_rgb(sdir / "rgb" / f"{im_id:06d}.png", image)
        save_depth_png(sdir / "depth" / f"{im_id:06d}.png", measured, ds)
        gts[im_id], infos[im_id] = [], []
        visible: list[VisibleInstance] = []
        covered = np.zeros((H, W), bool)
        for gt_id, (o, R, t) in enumerate(objs_c):
            # Hull vertices are enough to project the silhouette's box.
            ann = annotate_instance(renderer.render_depth(o, R, t, K), depth, measured, projected_bbox(poses[o].hull, R, t, K))
            save_mask_png(sdir / "mask" / f"{im_id:06d}_{gt_id:06d}.png", ann.mask)
            save_mask_png(sdir / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png", ann.mask_visib)
            gts[im_id].append(GtPose(o, R, t))
            infos[im_id].append(ann.info)
            visible.append(VisibleInstance(o, ann.mask_visib, ann.info.visib_fract))
            covered |= ann.mask
        clutter_visib = []
        for key, R, t in clutter_c:
            d = renderer.render_depth(key, R, t, K)
            clutter_visib.append((d > 0) & (np.abs(d - depth) <= VISIB_TOL_MM))
            covered |= d > 0
        cams[im_id] = CameraInfo(K=K, depth_scale=ds, width=W, height=H, R_w2c=Rc, t_w2c=tc)
        out.targets += image_targets(scene_id, im_id, [o for o, _, _ in objs_c], infos[im_id])
        out.detections += image_detections(scene_id, im_id, visible, _table_mask(depth, K, Rc, tc, covered),
                                           list(preset.obj_ids), rng, preset.faults, clutter_visib)
        out.instances += len(objs_c)
        step(f"scene {scene_id} image {im_id}")
    write_scene_camera(sdir / "scene_camera.json", cams)
    write_scene_gt(sdir / "scene_gt.json", gts)
    write_scene_gt_info(sdir / "scene_gt_info.json", infos)


def generate(
    out_dir: Path | str,
    name: str,
    preset: str | SynthPreset = "mini",
    seed: int = 0,
    progress: bool = True,
    overwrite: bool = False,
) -> dict:
    """Generate a synthetic BOP dataset in ``out_dir`` and its prior; returns a summary.

    preset: a name in ``PRESETS`` or a ``SynthPreset``. An existing non-empty
    ``out_dir`` is replaced only with ``overwrite=True``. Summary keys: objects,
    scenes, images, targets (instances to estimate, BOP19), instances (annotated
    instances over all images), detections, seconds.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise KeyError(f"unknown synth preset {preset!r}; choose one of {sorted(PRESETS)}")
        preset = PRESETS[preset]
    if not name or "_" in name or "/" in name:
        raise ValueError(f"dataset name {name!r} must be non-empty without '_' or '/' (BOP file names split on '_')")
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise FileExistsError(f"{out_dir} exists and is not empty; pass overwrite=True to replace it")
    t0 = time.perf_counter()
    with atomic_dir(out_dir) as tmp:
        summary = _write_dataset(tmp, name, preset, seed, progress)
    summary["seconds"] = round(time.perf_counter() - t0, 2)
    return summary

"""``freeze estimate``: the method on one RGB-D image of one object.

The frame is wrapped as a one-image BOP dataset with its prior and a dataset manifest
(:mod:`pipeline.commands.estimate.frame`), and the pipeline's own stages run on it, in this
process, through the run plan: the model side (``render_templates``, ``symmetries``,
``model_features``) is taken from the cache when an earlier frame of the same model
built it, and the scene side (``segment_prior``, ``scene_features``, ``register``,
``refine``) runs on the frame. ``freeze estimate`` therefore gives what ``snakemake
bop_all`` gives on the wrapped frame (``tests/test_estimate.py`` checks it to 1e-6).

It runs the stages as ``freeze stage`` does (:func:`pipeline.workflow.stage_graph.run_stage`,
by their declarations: the library under ``pipeline/`` never imports ``stages``). Wired
into the ``freeze`` app by ``add_commands(app, show_app)``.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import typer

from pipeline.commands.estimate.inputs import EstimateError
from pipeline.workflow.stage_graph import STAGES, stages_of_side

MODEL_STAGES = stages_of_side("model")
SCENE_STAGES = stages_of_side("scene")
ESTIMATE_CACHE = "_estimate"
"""Folder under the cache root holding the artifacts of ``freeze estimate`` (per frame name)."""
FLAG_KEYS = {"geometric": ("geometric", "geometric_encoder"), "visual": ("visual", "visual_encoder"),
             "device": ("device",)}
"""``freeze estimate``'s flags and the run-manifest overrides (``--config`` keys, short and
long forms) they stand for; the last is the manifest's field."""


def merge_flags(overrides: Mapping[str, Any] | None, **flags: str | None) -> dict[str, Any]:
    """``overrides`` with the values of ``--geometric``, ``--visual`` and ``--device``
    (``flags``, None: not given) set as the run's fields. A flag and a ``--config`` key
    giving two different values is an EstimateError naming both."""
    out = dict(overrides or {})
    for flag, value in flags.items():
        if value is None:
            continue
        keys = FLAG_KEYS[flag]
        for k in keys:
            if k in out and str(out[k]) != str(value):
                raise EstimateError(f"--{flag} {value} conflicts with --config {k}={out[k]}: give one of them")
        out = {k: v for k, v in out.items() if k not in keys}
        out[keys[-1]] = value
    return out


@dataclass
class EstimateResult:
    """The estimate: R (3, 3), t (3,) mm model-to-camera, evidence (RANSAC inlier ratio x
    ICP fitness), ``record`` (everything written to pose.json), the output files, whether
    the model side came from the cache, the steps' durations (s), and the artifact
    folder of every stage that ran or was reused."""

    R: np.ndarray
    t: np.ndarray
    evidence: float
    record: dict[str, Any]
    out_dir: Path | None
    files: dict[str, Path]
    model_cache_reused: bool
    timings: dict[str, float]
    artifacts: dict[str, Path] = field(default_factory=dict)


def frame_run_plan(run, frame, cache: Path | None = None):
    """The :class:`pipeline.workflow.plan.RunPlan` of ``run`` on a wrapped frame alone, its
    artifacts under ``<cache root>/_estimate/``."""
    from pipeline.workflow.plan import RunPlan, cache_root

    frame_run = run.model_copy(update={"datasets": [str(frame.manifest)], "bop_root": str(frame.bop_root.resolve())})
    return RunPlan(frame_run, cache=Path(cache or cache_root()) / ESTIMATE_CACHE)


def _item(stage: str, scene: str) -> str:
    """The frame's item of a scene-side stage: ``all`` for a dataset-wide one (segment_prior)."""
    return "all" if STAGES[stage].item_kind == "all" else scene


def run_stages(plan, stages_items: Sequence[tuple[str, str]], steps) -> dict[str, bool]:
    """Run each (stage, item) whose artifact is not in the cache yet; stage -> reused."""
    from pipeline.common import store
    from pipeline.workflow.stage_graph import run_stage

    reused = {}
    for stage, item in stages_items:
        reused[stage] = plan[stage].manifest(item).exists()
        if reused[stage]:
            steps.note(f"{stage}: reused {plan[stage].item_dir(item)}")
            continue
        with steps(stage):
            store.mark_job_start()
            run_stage(plan, stage, item, progress=False)
    return reused


def estimate(
    model: Path | str,
    rgb: Path | str,
    depth: Path | str,
    camera: Path | str,
    *,
    mask: Path | str | None = None,
    bbox: Sequence[float] | str | None = None,
    depth_scale: float | None = None,
    model_scale: float = 1.0,
    out_dir: Path | str | None = None,
    bop_name: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    geometric: str | None = None,
    visual: str | None = None,
    device: str | None = None,
    cache: Path | str | None = None,
    progress: bool = False,
    console: Any = None,
) -> EstimateResult:
    """Estimate the pose of the object ``model`` (PLY, mm) in one RGB-D image.

    mask: object mask (image, or a detections JSON; see
    :func:`pipeline.commands.estimate.inputs.load_mask`), or bbox: ``(x, y, w, h)`` px /
    ``"x,y,w,h"`` (exactly one of them; with a box, the object's points are found by
    :func:`pipeline.method.geometry.box_points.box_candidate_points` and their pixels become
    the prior's mask). depth_scale: mm per depth unit (default: the camera file's
    ``depth_scale``, else 1). model_scale: multiplies the model's coordinates (1000 for
    a model in metres). out_dir: where to write ``pose.json``, ``overlay.png``,
    ``points.png``, a copy of the stages' artifacts, and the frame as the BOP dataset
    ``<out_dir>/bop/<bop_name>`` with ``<out_dir>/bop/<bop_name>.yaml`` (a temporary
    folder when None; nothing is kept then but the cache). out_dir is written only as
    :mod:`pipeline.commands.estimate.output` allows: new, empty, or marked by an earlier estimate
    (``.freeze-estimate.json``), whose listed files alone are replaced; it is claimed
    before any stage runs and filled from a staging folder once the run is complete,
    so an error leaves it as it was. bop_name: default
    :func:`pipeline.formats.bop.wrap.default_name` of the model file. overrides: run-manifest
    overrides (:func:`pipeline.common.config.load_run_with_overrides`). geometric, visual:
    encoder manifest names, device: ``auto``, ``cpu`` or ``cuda`` (the same as the
    overrides ``geometric=``, ``visual=``, ``device=``; a conflicting override is an
    error). cache: cache root (default ``$FREEZE_CACHE`` or ``<project>/cache``).

    A grey image (one channel, or three identical ones) makes the frame a grey dataset
    (:func:`pipeline.commands.estimate.frame.dataset_manifest`): templates and SAR renders are
    then grey too.
    """
    from pipeline.common.progress import StepTimer
    from pipeline.commands.estimate.output import claim
    from pipeline.formats.bop import wrap

    steps = StepTimer(progress, console)
    overrides = merge_flags(overrides, geometric=geometric, visual=visual, device=device)
    if (mask is None) == (bbox is None):
        raise EstimateError("give exactly one localisation prior: --mask MASK.png or --bbox x,y,w,h")
    bop_name = bop_name if bop_name is not None else wrap.default_name(model)
    try:
        wrap.check_name(bop_name)
    except ValueError as e:
        raise EstimateError(f"--bop-name: {e}") from None
    with steps("inputs"):
        frame_in = _read_inputs(model, rgb, depth, camera, mask, bbox, depth_scale, model_scale, overrides, steps)
    _describe(frame_in, steps)
    kept, prior_details = _prior_of(frame_in, mask, steps)
    # --out: checked and claimed before any stage runs; the run writes to a staging folder
    # in it, moved into place once complete (pipeline.commands.estimate.output)
    folder = claim(out_dir) if out_dir is not None else None
    work = folder.staging if folder is not None else Path(tempfile.mkdtemp(prefix="freeze-estimate-"))
    committed = False
    try:
        res = _estimate_frame(frame_in, kept, prior_details, bop_name, folder, work, cache, steps,
                              paths={"model": model, "rgb": rgb, "depth": depth, "camera": camera, "mask": mask})
        if folder is None:
            return res
        folder.commit()
        committed = True
        res.out_dir = folder.out
        res.files = {k: folder.final(v) for k, v in res.files.items()}
        return res
    finally:
        if folder is None:
            shutil.rmtree(work, ignore_errors=True)
        elif not committed:  # an error, or an interruption: nothing half-written stays in --out
            folder.abort()


@dataclass
class _FrameInputs:
    """What ``freeze estimate`` read and checked: the run, the camera (``cam.K``), the
    depth scale (mm/unit) and where it came from, the images (rgb (H, W, 3) uint8, why
    it is grey or None, depth (H, W) float32 mm), the mask (H, W) bool or None, the box
    (x, y, w, h) px, the model (trimesh, mm; diameter mm) and the run's encoders."""

    run: Any
    cam: Any
    scale: float
    scale_src: str
    rgb: np.ndarray
    grey_why: str | None
    depth: np.ndarray
    mask: np.ndarray | None
    box: tuple[float, float, float, float]
    mesh: Any
    diameter: float
    model_scale: float
    encoders: tuple[Any, Any]

    @property
    def image_mode(self) -> str:
        return "gray" if self.grey_why else "rgb"


def _read_inputs(model, rgb, depth, camera, mask, bbox, depth_scale: float | None, model_scale: float,
                 overrides: Mapping[str, Any], steps) -> _FrameInputs:
    """Read and check the run, camera, images, prior and model (each refusal one
    EstimateError naming the file or option)."""
    from pipeline.common.config import load_run_with_overrides
    from pipeline.common.stand_in import stand_in_notice
    from pipeline.commands.estimate.inputs import (check_intrinsics, load_camera, load_depth, load_mask, load_model,
                                                   load_rgb_and_mode, parse_bbox)
    from pipeline.method.geometry.crops import mask_to_bbox
    from pipeline.workflow.plan import build_encoders

    run = load_run_with_overrides(overrides)
    notice = stand_in_notice(run.geometric_encoder, run.visual_encoder, form="estimate")
    if notice:
        steps.line(notice)
    cam = load_camera(camera)
    for name, p in (("model", model), ("RGB", rgb), ("depth", depth)):
        if not Path(p).is_file():
            raise EstimateError(f"{p}: {name} file not found")
    if depth_scale is not None and not (depth_scale > 0 and math.isfinite(depth_scale)):
        raise EstimateError(f"--depth-scale must be a positive number, got {depth_scale}")
    scale = depth_scale if depth_scale is not None else (cam.depth_scale if cam.depth_scale is not None else 1.0)
    scale_src = "--depth-scale" if depth_scale is not None else (f"{camera}" if cam.depth_scale is not None else "default")
    rgb_im, grey_why = load_rgb_and_mode(rgb)
    depth_im = load_depth(depth, scale)
    if rgb_im.shape[:2] != depth_im.shape:
        raise EstimateError(f"{depth}: depth is {depth_im.shape[1]}x{depth_im.shape[0]} px but {rgb} is "
                            f"{rgb_im.shape[1]}x{rgb_im.shape[0]}")
    H, W = depth_im.shape
    check_intrinsics(cam, W, H)
    mask_im = load_mask(mask, (H, W)) if mask is not None else None
    if bbox is not None:
        box = parse_bbox(bbox)
        if box[0] >= W or box[1] >= H or box[0] + box[2] <= 0 or box[1] + box[3] <= 0:
            raise EstimateError(f"--bbox {box}: lies outside the {W}x{H} image")
    else:
        box = tuple(float(v) for v in mask_to_bbox(mask_im))
    mesh, diameter = load_model(model, model_scale)
    return _FrameInputs(run, cam, scale, scale_src, rgb_im, grey_why, depth_im, mask_im, box, mesh, diameter,
                        model_scale, build_encoders(run))


def _describe(f: _FrameInputs, steps) -> None:
    """The lines saying what was read: camera, scale, image, model, encoders; a grey
    image; a depth scale that looks wrong for the model's size."""
    from pipeline.commands.estimate.inputs import scale_warning

    geo, vis = f.encoders
    H, W = f.depth.shape
    steps.note(f"camera: {f.cam.form}; depth scale {f.scale:g} mm/unit ({f.scale_src}); image {W}x{H}; "
               f"model diameter {f.diameter:.1f} mm; encoders {geo.signature()} + {vis.signature()}")
    if f.grey_why:
        steps.line(f"grey image detected ({f.grey_why}): the frame is a grey dataset (image_dir: gray), so "
                   "templates and SAR renders are grey too")
    warning = scale_warning(f.depth, f.cam.K, f.box, f.diameter)
    if warning:
        steps.warn(warning)


def _prior_of(f: _FrameInputs, mask, steps) -> tuple[np.ndarray | None, dict]:
    """(the box prior's kept pixels (H, W) bool, None with a mask; the prior's details),
    refusing now, before any stage runs, a prior that segment_prior or scene_features
    would drop (the mask as segment_prior will read it: wrap_frame's rule)."""
    from pipeline.commands.estimate.inputs import check_prior_size
    from pipeline.formats.bop import wrap
    from pipeline.method.geometry.box_points import box_candidate_points

    H, W = f.depth.shape
    kept = None
    if f.mask is None:
        with steps("box prior"):
            sel = box_candidate_points(f.depth, f.cam.K, f.box, f.diameter, seed=f.run.stages.scene_features.seed)
        if len(sel.points) == 0:
            raise EstimateError(f"no depth point of the object found in the box {list(f.box)}: check the box and the "
                                "depth image")
        kept = np.zeros((H, W), bool)
        kept[sel.pixels[:, 1], sel.pixels[:, 0]] = True
        details = sel.details
    else:
        details = {"mask_pixels": int(f.mask.sum()), "valid_depth": int((f.mask & (f.depth > 0)).sum())}
    prior_mask = f.mask if f.mask is not None else wrap.box_mask(f.box, (H, W)) & kept
    check_prior_size(prior_mask, f.depth, f.cam.K, f.diameter, min_area=f.run.stages.segment_prior.min_area,
                     min_points=f.run.stages.scene_features.min_points,
                     what=f"--mask {mask}" if mask is not None else f"--bbox {','.join(f'{v:g}' for v in f.box)}")
    return kept, details


def _estimate_frame(f: _FrameInputs, kept, prior_details: dict, bop_name: str, folder, work: Path, cache, steps,
                    paths: Mapping[str, Any]) -> EstimateResult:
    """Write the frame as a one-image BOP dataset in ``work``, run the stages on it (the
    model side from the cache when it is there), and read the estimate back
    (:func:`_finish`); OSErrors while writing become the one line of :func:`_write_failure`."""
    from pipeline.common.stand_in import encoders_sentence
    from pipeline.commands.estimate.frame import write_frame_dataset

    with steps("write the frame as a BOP dataset"):
        try:
            frame = write_frame_dataset(work / "bop", bop_name, rgb=f.rgb, depth_mm=f.depth, K=f.cam.K,
                                        model_path=Path(paths["model"]), model_scale=f.model_scale, mask=f.mask,
                                        bbox=f.box, kept_mask=kept, image_mode=f.image_mode,
                                        final_root=folder.out / "bop" if folder is not None else None)
        except ValueError as e:
            raise EstimateError(f"writing the BOP dataset {bop_name}: {e}") from None
        except OSError as e:
            raise _write_failure(folder, work, e) from None
    run, (geo, vis) = f.run, f.encoders
    rp = frame_run_plan(run, frame, Path(cache) if cache else None)
    plan = rp[frame.root.name]
    for note in rp.notes(frame.root.name):
        steps.warn(note)
    obj, scene = frame.obj_item(), frame.scene_item()
    reused = run_stages(plan, [(s, obj) for s in MODEL_STAGES], steps)
    run_stages(plan, [(s, _item(s, scene)) for s in SCENE_STAGES], steps)
    H, W = f.depth.shape
    mask = paths["mask"]
    inputs = {k: str(Path(paths[k]).resolve()) for k in ("model", "rgb", "depth", "camera")}
    inputs.update({"mask": str(Path(mask).resolve()) if mask is not None else None,
                   "prior": "mask" if mask is not None else "bbox", "bbox": [float(v) for v in f.box],
                   "depth_scale": f.scale, "depth_scale_from": f.scale_src, "model_scale": f.model_scale,
                   "camera_form": f.cam.form, "K": f.cam.K.tolist(), "image_size": [W, H],
                   "image_mode": f.image_mode, "grey_because": f.grey_why})
    try:
        return _finish(plan, frame, work if folder is not None else None, run=run, mesh=f.mesh, diameter=f.diameter,
                       rgb=f.rgb, K=f.cam.K, box=f.box, steps=steps, model_cache_reused=all(reused.values()),
                       prior_details=prior_details, inputs=inputs,
                       encoders={"geometric": run.geometric_encoder, "visual": run.visual_encoder,
                                 "signatures": {"geometric": geo.signature(), "visual": vis.signature()},
                                 "device": run.device},
                       note=encoders_sentence(run.geometric_encoder, run.visual_encoder, form="estimate"))
    except _WriteFailed as w:
        raise _write_failure(folder, work, w.error) from None


def _write_failure(folder, work: Path, e: OSError) -> EstimateError:
    """The one line for an OSError while writing the outputs into ``work`` (the staging
    folder of ``folder``, or a temporary folder when None): the file (at its final
    place) and why."""
    from pipeline.commands.estimate.output import why

    from pipeline.common.store import StorageError

    name = getattr(e, "filename", None)
    if not name and isinstance(e, StorageError):  # its message starts with the path it was writing
        name = (e.strerror or "").split(": cannot write", 1)[0] or None
    target = Path(name) if name else None
    if folder is not None:
        if target is not None and work in target.parents:
            target = folder.final(target)
        return EstimateError(f"--out {folder.out}: cannot write {target or 'the outputs'} ({why(e)}); the folder is left "
                             "as it was before the run")
    return EstimateError(f"{target or work}: cannot write it ({why(e)})")


def _finish(plan, frame, out: Path | None, *, run, mesh, diameter: float, rgb: np.ndarray, K: np.ndarray, box,
            steps, model_cache_reused: bool, prior_details: dict, inputs: dict, encoders: dict,
            note: str) -> EstimateResult:
    """Read the estimate back from the artifacts; write pose.json, the pictures and the
    artifacts' copies to ``out``. ``note``: which encoders ran, in one sentence
    (:func:`pipeline.common.stand_in.encoders_sentence`). OSErrors while writing come out as
    :class:`_WriteFailed` (told from errors reading the artifacts)."""
    from pipeline.commands.estimate.record import candidate_record, dumps, jsonable
    from pipeline.common.store import atomic_write_text

    rec = candidate_record(plan, frame)
    R, t = rec.pop("R"), rec.pop("t")
    scene, obj = frame.scene_item(), frame.obj_item()
    artifacts = {s: plan[s].item_dir(obj) for s in MODEL_STAGES}
    artifacts.update({s: plan[s].item_dir(_item(s, scene)) for s in SCENE_STAGES})
    record: dict[str, Any] = {
        "R": R.tolist(), "t": t.tolist(), "evidence": rec.pop("evidence"),
        "cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": t.tolist(),
        **{k: v for k, v in rec.items() if not k.endswith("_symmetries")},
        "prior_details": prior_details,
        "inputs": inputs,
        "model": {"diameter_mm": diameter, "cache_reused": model_cache_reused,
                  "artifacts": {s: str(artifacts[s]) for s in MODEL_STAGES},
                  "n_discrete_symmetries": rec["n_discrete_symmetries"],
                  "n_continuous_symmetries": rec["n_continuous_symmetries"]},
        "artifacts": {s: str(artifacts[s]) for s in SCENE_STAGES},
        "encoders": encoders,
        "note": note,
        "units": "R: model-to-camera rotation; t: mm (OpenCV camera, BOP convention)",
    }
    files: dict[str, Path] = {}
    try:
        if out is not None:
            _write_outputs(out, files, plan, frame, artifacts, record, mesh=mesh, R=R, t=t, K=K, rgb=rgb, box=box,
                           diameter=diameter, steps=steps)
        record["timings_s"] = {k: round(v, 3) for k, v in steps.timings.items()}
        record = jsonable(record)
        if out is not None:
            files["pose"] = out / "pose.json"
            atomic_write_text(files["pose"], dumps(record))
    except OSError as e:
        raise _WriteFailed(e) from None
    return EstimateResult(R=R, t=t, evidence=float(record["evidence"]), record=record, out_dir=out, files=files,
                          model_cache_reused=model_cache_reused, timings=dict(steps.timings), artifacts=artifacts)


class _WriteFailed(Exception):
    """An OSError while writing the outputs (``error``), told from one while reading the artifacts."""

    def __init__(self, error: OSError):
        super().__init__(str(error))
        self.error = error


def _write_outputs(out: Path, files: dict[str, Path], plan, frame, artifacts: dict[str, Path], record: dict, *,
                   mesh, R: np.ndarray, t: np.ndarray, K: np.ndarray, rgb: np.ndarray, box, diameter: float,
                   steps) -> None:
    """Write overlay.png, points.png and the stages' copies into ``out`` (the staging
    folder), filling ``files`` (name -> path)."""
    from pipeline.formats.bop.dataset import save_rgb
    from pipeline.commands.estimate.frame import IM_ID, SCENE_ID
    from pipeline.views.overlay import points_picture, render_overlay
    from pipeline.method.scene_side import candidate_points

    with steps("write outputs"):
        caption = (f"evidence {record['evidence']:.3f}  inliers {record['n_inliers']}  "
                   f"ICP fitness {record['fitness']:.2f}"
                   + (f"  SAR variant {record['sar_variant']}" if record["sar_variant"] >= 0 else ""))
        files["overlay"] = out / "overlay.png"
        save_rgb(files["overlay"], render_overlay(mesh, R, t, K, rgb, box, caption))
        # the picture of the points: the candidate's object points, as scene_features lifts them
        depth = plan.bop().load_depth(SCENE_ID, IM_ID)
        mask = plan_prior_mask(plan, frame)
        kept_pixels = candidate_points(depth, K, mask, diameter)[1]
        feats = plan["scene_features"].arrays(frame.scene_item(), "features", ["pixels", "n_points"])
        files["points"] = out / "points.png"
        save_rgb(files["points"], points_picture(rgb, kept_pixels, feats["pixels"][0, :int(feats["n_points"][0])], box))
        for stage, folder in artifacts.items():
            copy = out / stage  # out is this run's fresh staging folder: nothing there to replace
            shutil.copytree(folder, copy)
            files[stage] = copy
        files["bop"], files["bop_manifest"], files["bop_prior"] = frame.root, frame.manifest, frame.prior


def plan_prior_mask(plan, frame) -> np.ndarray:
    """(H, W) bool: the mask of the frame's prior, as segment_prior stored it."""
    from pipeline.formats.bop.detections import prior_row_mask

    c = plan["segment_prior"].table("all", "prior_candidates").iloc[0]
    return prior_row_mask(c)


class Device(str, Enum):
    """``freeze estimate --device``: the run manifest's ``device``."""

    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


def add_commands(app: typer.Typer, show_app: typer.Typer) -> None:
    """Add ``freeze estimate`` to ``app`` (``show_app`` is unused)."""

    @app.command("estimate")
    def estimate_cmd(
        model: Path = typer.Option(..., "--model", help="object model, PLY in mm (BOP models are)"),
        rgb: Path = typer.Option(..., "--rgb", help="RGB image (PNG/JPEG)"),
        depth: Path = typer.Option(..., "--depth", help="depth image, uint16 PNG: depth_mm = value * depth_scale"),
        camera: Path = typer.Option(..., "--camera", help="camera JSON: {\"cam_K\": [9], \"depth_scale\": s} "
                                                         "(BOP scene_camera entry, SAM-6D), {\"K\": [[...]]} or "
                                                         "{\"fx\", \"fy\", \"cx\", \"cy\"}"),
        mask: Optional[Path] = typer.Option(None, "--mask", help="object mask image (non-zero = object), or a "
                                                                 "detections JSON (CNOS/SAM-6D; best score used)"),
        bbox: Optional[str] = typer.Option(None, "--bbox", help="object box x,y,w,h in pixels (instead of --mask)"),
        depth_scale: Optional[float] = typer.Option(None, "--depth-scale", help="mm per depth unit (default: the "
                                                                                "camera file's depth_scale, else 1)"),
        model_scale: float = typer.Option(1.0, "--model-scale", help="multiply the model's coordinates (1000 for "
                                                                     "a model in metres)"),
        out: Path = typer.Option(Path("estimate_out"), "--out", help="output folder: a new or empty one, or one an "
                                 "earlier estimate wrote (marked by OUT/.freeze-estimate.json, which lists its files; "
                                 "a rerun replaces only those). A folder holding anything else is refused, naming "
                                 "the file: the estimate never deletes what it did not write"),
        bop_name: Optional[str] = typer.Option(None, "--bop-name", help="name of the one-image BOP dataset written to "
                                               "OUT/bop/NAME, lowercase letters and digits (default: the model "
                                               "file's name reduced to them: obj_000005.ply -> obj000005)"),
        geometric: Optional[str] = typer.Option(None, "--geometric", help="geometric encoder: a manifest of "
                                                "manifests/encoders/ (`freeze encoders` lists them), e.g. gedi, the "
                                                "paper's; the same as --config geometric=NAME (default: the run's, fpfh)"),
        visual: Optional[str] = typer.Option(None, "--visual", help="visual encoder manifest, e.g. dinov2-vitg14, "
                                             "the paper's; the same as --config visual=NAME (default: the run's, "
                                             "colortex)"),
        device: Optional[Device] = typer.Option(None, "--device", case_sensitive=False, help="where torch runs "
                                                "(DINOv2, GeDi): auto picks cuda when there is one (default: the "
                                                "run's, auto)"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value, e.g. "
                                                   "visual=dinov2-vits14 or register.max_iterations=20000"),
        progress: bool = typer.Option(True, help="show each step with its time"),
    ) -> None:
        """Estimate the 6D pose of one object in one RGB-D image.

        The frame is written as a one-image BOP dataset, OUT/bop/NAME (camera, model in
        mm, models_info, targets, rgb, depth), with its prior
        OUT/bop/detections/estimate_NAME-test.json (the --mask, or the pixels of the
        depth points kept inside the --bbox) and its dataset manifest OUT/bop/NAME.yaml,
        and the pipeline's stages run on it. The model side is cached (under
        <cache>/_estimate/NAME/) and reused for every frame of the same model and
        parameters.

        A grey image (one channel, or three identical ones) is detected and the frame
        declared grey, so that the templates and SAR renders are grey too. The default
        encoders are weight-free stand-ins for the paper's: a note at the start says
        which, and how to fetch and choose the paper's (`freeze encoders` marks them).

        Writes OUT/pose.json (R, t in mm, the evidence and the numbers behind it),
        OUT/overlay.png (the model at the estimated pose over the image), OUT/points.png
        (the depth points used) and a copy of every stage's artifact (OUT/render_templates,
        ..., OUT/refine). The same result comes from `snakemake --cores 2 bop_all
        --config bop_root=OUT/bop datasets=OUT/bop/NAME.yaml` (not scored: no ground truth).

        OUT is the estimate's own: it writes OUT/.freeze-estimate.json listing every file
        it wrote (size, SHA-256), and a rerun into OUT replaces only what that lists.
        A non-empty OUT without it, or a file in the way of the outputs that it does not
        list or that changed since, is refused before any stage runs, naming the file;
        other entries beside the outputs are left alone. Everything is written to a
        staging folder inside OUT first and moved into place once complete: a failed
        run (a full or read-only disk, a stage's error) leaves OUT as it was.

        Inputs are checked before any stage runs: the camera (positive, sane focal
        lengths and a principal point near the image), and the prior (its mask at least
        segment_prior.min_area pixels, with at least scene_features.min_points depth
        points); each refusal is one line naming the file or option and the field.
        """
        from rich.console import Console
        from rich.markup import escape

        from pipeline.commands.common import USER_ERRORS, parse_overrides
        from pipeline.commands.estimate.frame import pipeline_command

        console = Console(stderr=True)
        console.print(f"[bold]freeze estimate[/] {escape(model.name)} in {escape(rgb.name)} -> {escape(str(out))}")
        try:
            res = estimate(model, rgb, depth, camera, mask=mask, bbox=bbox, depth_scale=depth_scale,
                           model_scale=model_scale, out_dir=out, bop_name=bop_name, overrides=parse_overrides(config),
                           geometric=geometric, visual=visual, device=device.value if device else None,
                           progress=progress, console=console)
        except (EstimateError, *USER_ERRORS) as e:
            # one line, whatever the terminal's width: the message names the file to fix
            console.print(f"[red]error:[/] {escape(str(e))}", soft_wrap=True)
            raise typer.Exit(1)
        r = res.record
        h = r["hypothesis"]
        console.print(f"chosen: the {h['source']} hypothesis, verification {h['verification']['verification']:.3f} "
                      f"(best of {len(r['hypotheses'])}; fusion weights geometric {h['fusion_weights']['geometric']:g}, "
                      f"visual {h['fusion_weights']['visual']:g}){'; fine ICP' if h['fine_icp'] else ''}")
        console.print(f"evidence {r['evidence']:.3f} (inlier ratio {r['inlier_ratio']:.3f} x ICP fitness "
                      f"{r['fitness']:.3f}); {r['n_inliers']} RANSAC inliers of {r['n_points']} points; SAR "
                      + (f"variant {r['sar_variant']} of {r['sar_n_variants']}" if r["sar_variant"] >= 0
                         else f"not run ({r['sar_reason']})"))
        console.print("R = " + "; ".join(" ".join(f"{v:+.4f}" for v in row) for row in res.R.tolist()))
        console.print("t = " + " ".join(f"{v:.1f}" for v in res.t.tolist()) + " mm")
        console.print(f"model side: {'reused from' if res.model_cache_reused else 'built in'} "
                      f"{res.artifacts['model_features'].parent.parent.parent}")
        for name, path in res.files.items():
            console.print(f"  {name:<16} {path}", soft_wrap=True, markup=False, highlight=False)
        ds = res.files["bop"]
        # quoted (shlex): the command pastes whole into a shell whatever the paths hold
        console.print(f"BOP dataset (1 image, no ground truth): {ds}; load it with pipeline.formats.bop.BopDataset({str(ds)!r}), "
                      f"or run the pipeline on it: {pipeline_command(ds.parent, res.files['bop_manifest'])}",
                      soft_wrap=True, markup=False, highlight=False)

"""``freeze estimate``: the method on one RGB-D image of one object (pipeline/commands/estimate/command.py,
pipeline/commands/estimate/).

A synthetic toy truck (object 8 of the procedural set) standing on a table is rendered
at a known pose; the estimate must recover it from a mask and from a box alone, and must
equal what the pipeline gives on the same frame. The model side runs with fewer
templates and points than the default manifest (the same code, faster), and is built
once: the later calls reuse its cache.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from pipeline.commands import estimate as est  # noqa: E402  (the inputs: load_camera, load_rgb, ...)
from pipeline.commands.estimate import EstimateError  # noqa: E402
from pipeline.commands.estimate.command import EstimateResult, estimate  # noqa: E402
from pipeline.method.geometry.box_points import box_candidate_points  # noqa: E402


# Smaller model side than the default manifest (42 views, 5000 points, 20000 symmetry samples).
FAST = {"render_templates.n_views": "16", "model_features.n_points": "2000", "symmetries.n_points": "5000"}
FAST_ARGS = [a for k, v in FAST.items() for a in ("-c", f"{k}={v}")]

# Measured on this case: rotation errors 0.1-0.3 deg, translation errors < 0.2 mm (mask
# and box); a wrong registration is tens of degrees off.
MAX_ROT_DEG, MAX_TRANS_MM = 2.0, 3.0


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def _cli() -> typer.Typer:
    from pipeline.commands.estimate.command import add_commands

    app, show = typer.Typer(), typer.Typer()
    app.add_typer(show, name="show")
    add_commands(app, show)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps `estimate` a sub-command
        pass

    return app


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict:
    """Model PLY, RGB, depth (uint16, 0.1 mm units), mask, camera JSON and the true pose."""
    import trimesh

    from pipeline.formats.bop.dataset import save_depth_png, save_mask_png, save_rgb
    from pipeline.formats.bop.ply import write_ply
    from pipeline.method.render import Renderer
    from pipeline.method.geometry.transforms import look_at_rotation
    from pipeline.evaluation.synth.objects import build_object

    d = tmp_path_factory.mktemp("estimate_case")
    obj = build_object(8)
    m = obj.model
    write_ply(d / "model.ply", np.asarray(m.vertices), np.asarray(m.faces), normals=np.asarray(m.vertex_normals),
              colors=np.asarray(m.visual.vertex_colors)[:, :3])
    K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
    el, az = np.radians(40), np.radians(30)
    R = look_at_rotation(np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]))
    t = np.array([40.0, 30.0, 650.0])
    # a table under the object: the box-only prior has to remove it
    table = trimesh.creation.box(extents=[1500, 1500, 4])
    table.apply_translation([0, 0, np.asarray(m.vertices)[:, 2].min() - 2.0])
    table.visual.vertex_colors = np.tile([150, 120, 90, 255], (len(table.vertices), 1))
    with Renderer(640, 480, znear=10, zfar=5000) as r:
        r.add_mesh("obj", m)
        r.add_mesh("table", table)
        rgb, depth = r.render([("obj", R, t), ("table", R, t)], K, rgb=True)
        _, dobj = r.render([("obj", R, t)], K, rgb=False)
    mask = (dobj > 0) & (np.abs(dobj - depth) < 0.5)
    save_rgb(d / "rgb.png", rgb)
    save_depth_png(d / "depth.png", depth, 0.1)
    save_mask_png(d / "mask.png", mask)
    (d / "camera.json").write_text(json.dumps({"cam_K": K.reshape(-1).tolist(), "depth_scale": 0.1}))
    v, u = np.nonzero(mask)
    bbox = (int(u.min()), int(v.min()), int(u.max() - u.min() + 1), int(v.max() - v.min() + 1))
    return {"dir": d, "model": d / "model.ply", "rgb": d / "rgb.png", "depth": d / "depth.png", "mask": d / "mask.png",
            "camera": d / "camera.json", "R": R, "t": t, "K": K, "bbox": bbox, "mask_array": mask,
            "depth_mm": depth, "cache": tmp_path_factory.mktemp("estimate_cache"), "diameter": obj.diameter}


def _run(case: dict, **kw) -> EstimateResult:
    return estimate(case["model"], case["rgb"], case["depth"], case["camera"], overrides=FAST, cache=case["cache"], **kw)


@pytest.mark.slow
def test_recovers_a_known_pose_from_a_mask(case, tmp_path):
    res = _run(case, mask=case["mask"], out_dir=tmp_path / "out", bop_name="truck")
    assert _rot_err_deg(res.R, case["R"]) < MAX_ROT_DEG
    assert np.linalg.norm(res.t - case["t"]) < MAX_TRANS_MM
    assert not res.model_cache_reused and "render_templates" in res.timings
    rec = json.loads((tmp_path / "out" / "pose.json").read_text())
    assert np.allclose(rec["R"], res.R) and np.allclose(rec["t"], res.t)
    assert rec["inputs"]["prior"] == "mask" and rec["inputs"]["depth_scale"] == 0.1
    assert rec["n_inliers"] > 0 and 0 < rec["evidence"] <= 1 and rec["fitness"] > 0.7
    assert rec["evidence"] == pytest.approx(rec["inlier_ratio"] * rec["fitness"])
    assert rec["sar_reason"].startswith("no symmetry") and rec["sar_variant"] == -1  # the truck has none
    assert rec["model"]["diameter_mm"] == pytest.approx(case["diameter"], rel=1e-3)
    # the frame as a one-image BOP dataset: its prior is the mask given
    from pipeline.formats.bop import BopDataset, load_detections

    assert res.files["bop"] == tmp_path / "out" / "bop" / "truck"
    (det,) = load_detections(tmp_path / "out" / "bop" / "detections" / "estimate_truck-test.json")
    assert np.array_equal(det.mask(), case["mask_array"]) and det.bbox == tuple(rec["inputs"]["bbox"])
    assert BopDataset(res.files["bop"]).models_info()[1].diameter == pytest.approx(case["diameter"], rel=1e-3)


@pytest.mark.slow
def test_recovers_it_from_a_box_alone_and_reuses_the_model_cache(case, tmp_path):
    first = _run(case, mask=case["mask"])  # built by the previous test, or now
    manifest = first.artifacts["model_features"] / "_manifest.json"
    mtime = manifest.stat().st_mtime_ns
    res = _run(case, bbox=case["bbox"], out_dir=tmp_path / "out")
    assert res.model_cache_reused and res.artifacts["model_features"] == first.artifacts["model_features"]
    assert manifest.stat().st_mtime_ns == mtime
    assert not any(s in res.timings for s in ("render_templates", "symmetries", "model_features"))
    assert "scene_features" in res.timings  # another frame (a box prior): the scene side runs again
    assert (case["cache"] / "_estimate") in res.artifacts["model_features"].parents
    assert _rot_err_deg(res.R, case["R"]) < MAX_ROT_DEG
    assert np.linalg.norm(res.t - case["t"]) < MAX_TRANS_MM
    det = res.record["prior_details"]
    assert det["plane_removed"], det  # the table was recognised and dropped


def test_box_rule_keeps_the_object_and_drops_the_table(case):
    K, depth, mask = case["K"], case["depth_mm"], case["mask_array"]
    sel = box_candidate_points(depth, K, case["bbox"], case["diameter"])
    kept = np.zeros_like(mask)
    kept[sel.pixels[:, 1], sel.pixels[:, 0]] = True
    x, y, w, h = case["bbox"]
    in_box = np.zeros_like(mask)
    in_box[y:y + h, x:x + w] = True
    table_in_box = in_box & (depth > 0) & ~mask
    assert table_in_box.sum() > 0.3 * mask.sum()  # the box holds plenty of table
    assert (kept & mask).sum() > 0.9 * mask.sum()  # the object's points stay (minus its base on the plane)
    assert (kept & ~mask).sum() < 0.01 * mask.sum()  # almost no table point survives
    # a box-shaped object's face filling its own box is not "a plane to remove": it ends at the box's edge
    flat = np.zeros_like(depth)
    flat[200:300, 250:350] = 600.0
    sel = box_candidate_points(flat, K, (250, 200, 100, 100), 150.0)
    assert not sel.details["plane_removed"] and len(sel.points) == 100 * 100


@pytest.mark.slow
def test_cli_writes_pose_overlay_and_stage_artifacts(case, tmp_path, monkeypatch):
    from pipeline.common.store import load_arrays, read_manifest, read_table

    _run(case, mask=case["mask"])  # the model side, built by an earlier test of the module or now
    monkeypatch.setenv("FREEZE_CACHE", str(case["cache"]))
    out = tmp_path / "cli"
    x, y, w, h = case["bbox"]
    result = CliRunner().invoke(_cli(), ["estimate", "--model", str(case["model"]), "--rgb", str(case["rgb"]),
                                         "--depth", str(case["depth"]), "--camera", str(case["camera"]),
                                         "--bbox", f"{x},{y},{w},{h}", "--out", str(out), *FAST_ARGS])
    assert result.exit_code == 0, result.output
    rec = json.loads((out / "pose.json").read_text())
    assert _rot_err_deg(np.array(rec["R"]), case["R"]) < MAX_ROT_DEG
    assert np.linalg.norm(np.array(rec["t"]) - case["t"]) < MAX_TRANS_MM
    assert rec["model"]["cache_reused"]
    assert "register" in result.output and "reused" in result.output
    import cv2

    overlay = cv2.imread(str(out / "overlay.png"))
    assert overlay.shape == (480, 640, 3)
    # the stages' names and layouts
    feats = load_arrays(out / "scene_features" / "features.zarr")
    assert feats["points"].shape[0] == 1 and feats["n_points"][0] == 1000
    assert load_arrays(out / "model_features" / "features.zarr", ["points"])["points"].shape == (2000, 3)
    reg = read_table(out / "register" / "coarse_hypotheses.parquet")
    registered = rec["hypothesis"]["parent"] if rec["hypothesis"]["source"] == "turn" else rec["hypothesis"]["index"]
    assert reg[reg.hyp == registered].n_inliers.iloc[0] == rec["n_inliers"]
    # register's hypotheses, then refine's turns of the best one
    assert len([h for h in rec["hypotheses"] if h["source"] != "turn"]) == len(reg)
    assert 0 < sum(h["source"] == "turn" for h in rec["hypotheses"]) <= 3
    assert sum(h["chosen"] for h in rec["hypotheses"]) == 1
    poses = read_table(out / "refine" / "poses.parquet")
    assert np.allclose(np.reshape(poses.R.iloc[0], (3, 3)), rec["R"])
    for stage in ("render_templates", "symmetries", "model_features", "segment_prior", "scene_features", "register",
                  "refine"):
        assert read_manifest(out / stage)["stage"] == stage
    # the frame as a one-image BOP dataset (default name: the model file's, "model"), read by the BOP reader
    from pipeline.formats.bop import BopDataset, Target, load_detections

    ds = BopDataset(out / "bop" / "model")
    assert ds.targets() == [Target(1, 0, 1, 1)]
    assert np.array_equal(ds.scene_camera(1)[0].K, case["K"])
    assert np.array_equal(ds.load_rgb(1, 0), est.load_rgb(case["rgb"]))
    assert np.abs(ds.load_depth(1, 0) - est.load_depth(case["depth"], 0.1)).max() < 0.051
    assert ds.model_path(1).read_bytes() == case["model"].read_bytes()
    (det,) = load_detections(out / "bop" / "detections" / "estimate_model-test.json")
    assert det.bbox == case["bbox"]
    # the prior's mask: the pixels of the points the box rule kept, the object's and not the table's
    m, obj = det.mask(), case["mask_array"]
    assert (m & obj).sum() > 0.9 * obj.sum() and (m & ~obj).sum() < 0.01 * obj.sum()
    # scene_features lifts those pixels and drops the outliers among them
    assert m.sum() >= rec["n_valid_points"] > 0.95 * m.sum()
    assert "BopDataset(" in result.output and f"bop_root={out / 'bop'}" in result.output.replace("\n", "")
    assert (out / "bop" / "model.yaml").is_file()


@pytest.mark.slow
def test_model_side_keys_follow_the_model_only(case, tmp_path):
    """The wrapped frame's model-side keys hash the model's files and the model-side
    parameters: another image or a scene-side parameter keeps them (the model side is
    reused), another model or model-side parameter changes them. The scene side's keys
    change with the image."""
    from pipeline.common.config import load_run_with_overrides
    from pipeline.commands.estimate.frame import write_frame_dataset
    from pipeline.commands.estimate.command import frame_run_plan

    rgb, depth = est.load_rgb(case["rgb"]), case["depth_mm"]

    def keys(name, overrides=FAST, image=rgb, model=case["model"]):
        frame = write_frame_dataset(tmp_path / name, "truck", rgb=image, depth_mm=depth, K=case["K"], model_path=model,
                                    mask=case["mask_array"])
        plan = frame_run_plan(load_run_with_overrides(overrides), frame, tmp_path / "cache")[frame.root.name]
        return {s: plan[s].key for s in plan.stages}

    base = keys("a")
    model_side = ("render_templates", "symmetries", "model_features")
    brighter = keys("b", image=np.clip(rgb.astype(int) + 10, 0, 255).astype(np.uint8))
    assert all(brighter[s] == base[s] for s in model_side)
    assert all(brighter[s] != base[s] for s in ("segment_prior", "scene_features", "register", "refine"))
    scene_param = keys("c", {**FAST, "register.max_iterations": "100"})
    assert all(scene_param[s] == base[s] for s in model_side) and scene_param["register"] != base["register"]
    assert keys("d", {**FAST, "model_features.n_points": "3000"})["model_features"] != base["model_features"]
    import trimesh

    other = tmp_path / "other.ply"
    m = trimesh.load(case["model"], process=False)
    m.apply_translation([1.0, 0.0, 0.0])
    m.export(other)
    assert all(keys("e", model=other)[s] != base[s] for s in model_side)


@pytest.mark.slow
def test_estimate_equals_the_pipeline_on_the_wrapped_frame(case, tmp_path):
    """`freeze estimate` runs the stages' code: `snakemake bop_all` on the frame it wrote
    (fresh cache, separate processes) finds the same pose to 1e-6."""
    import os
    import subprocess
    import sys

    from pipeline.common.store import read_table

    root = Path(__file__).resolve().parent.parent
    run = tmp_path / "fast.yaml"  # the FAST parameters as a run manifest both can read
    run.write_text(f"extends: {root / 'manifests' / 'runs' / 'default.yaml'}\nstages:\n"
                   "  render_templates: {n_views: 16}\n  model_features: {n_points: 2000}\n"
                   "  symmetries: {n_points: 5000}\n")
    res = estimate(case["model"], case["rgb"], case["depth"], case["camera"], mask=case["mask"],
                   overrides={"run": str(run)}, cache=tmp_path / "estimate_cache", out_dir=tmp_path / "out")
    bop = tmp_path / "out" / "bop"
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env.update(FREEZE_CACHE=str(tmp_path / "pipeline_cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1")
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-s", str(root / "Snakefile"),
                           "--directory", str(tmp_path / "work"), "--cores", "2", "bop_all", "--config",
                           f"run={run}", f"bop_root={bop}", f"datasets={bop / 'model.yaml'}"],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    poses = list((tmp_path / "pipeline_cache" / "model" / "refine").glob("*/scene_000001/poses.parquet"))
    assert len(poses) == 1
    # the same keys, hence the same folders, in both caches
    assert poses[0].parent.relative_to(tmp_path / "pipeline_cache") == \
        res.artifacts["refine"].relative_to(tmp_path / "estimate_cache" / "_estimate")
    pose = read_table(poses[0]).iloc[0]
    assert np.abs(np.reshape(pose.R, (3, 3)) - res.R).max() < 1e-6
    assert np.abs(np.asarray(pose.t) - res.t).max() < 1e-6


@pytest.mark.slow
def test_the_in_memory_estimator_recovers_the_known_pose(case):
    """The Python API (README): the model side prepared in memory, one frame estimated
    in memory, nothing written; the same method as the stages, hence the same bounds."""
    from pipeline.commands.estimate.inputs import load_model, load_rgb_and_mode
    from pipeline.common.config import load_run_with_overrides
    from pipeline.method.estimator import Detection, Estimator, Observation, prepare_object
    from pipeline.workflow.plan import build_encoders

    run = load_run_with_overrides(FAST)
    encoders = build_encoders(run)
    mesh, diameter = load_model(case["model"])
    obj = prepare_object(1, mesh, run.stages, encoders, diameter=diameter)
    assert obj.features["points"].shape == (2000, 3) and obj.symmetries.is_trivial  # the truck has none
    rgb, _ = load_rgb_and_mode(case["rgb"])
    depth = case["depth_mm"].astype(np.float32)
    result = Estimator({1: obj}, run.stages, encoders).estimate(Observation(rgb, depth, case["K"]),
                                                                [Detection(1, case["mask_array"])])
    assert len(result.poses) == 1 and len(result.registered.table) >= 3  # one hypothesis per source at least
    pose = result.poses.iloc[0]
    R, t = np.reshape(pose.R, (3, 3)), np.asarray(pose.t)
    assert _rot_err_deg(R, case["R"]) < MAX_ROT_DEG
    assert np.linalg.norm(t - case["t"]) < MAX_TRANS_MM
    assert pose.sar_reason.startswith("no symmetry")


def test_the_estimator_names_an_unknown_object_and_a_wrong_mask():
    from pipeline.common.config import load_run
    from pipeline.method.estimator import Detection, Estimator, Observation, PreparedObject

    est = Estimator({1: PreparedObject(1, 100.0)}, load_run().stages, encoders=None)
    obs = Observation(np.zeros((4, 5, 3), np.uint8), np.zeros((4, 5), np.float32), np.eye(3))
    with pytest.raises(KeyError, match="object 2 is not among"):
        est.estimate(obs, [Detection(2, np.ones((4, 5), bool))])
    with pytest.raises(ValueError, match="mask size"):
        est.estimate(obs, [Detection(1, np.ones((3, 3), bool))])
    with pytest.raises(KeyError, match="features was not given"):
        _ = est.objects[1].features


def test_masks_from_pngs_and_detection_files(case, tmp_path):
    from pipeline.formats.bop.detections import detection_from_mask, save_detections

    mask = case["mask_array"]
    assert np.array_equal(est.load_mask(case["mask"], mask.shape), mask)
    # SAM-6D/CNOS detections (RLE): the best-scoring one is used
    other = np.zeros_like(mask)
    other[:10, :10] = True
    save_detections(tmp_path / "dets.json", [detection_from_mask(0, 0, 1, 0.4, other),
                                             detection_from_mask(0, 0, 1, 0.9, mask)])
    assert np.array_equal(est.load_mask(tmp_path / "dets.json", mask.shape), mask)
    with pytest.raises(EstimateError, match="mask is 640x480 px but the images are 320x240"):
        est.load_mask(case["mask"], (240, 320))


# ----------------------------------------------------------------------------- errors


def test_camera_forms(tmp_path):
    K = [[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]]
    forms = {
        "bop.json": {"cam_K": sum(K, []), "depth_scale": 0.1},
        "scene.json": {"3": {"cam_K": sum(K, []), "depth_scale": 0.1}},
        "k.json": {"K": K},
        "fx.json": {"fx": 500.0, "fy": 510.0, "cx": 320, "cy": 240, "width": 640, "height": 480},
    }
    for name, doc in forms.items():
        (tmp_path / name).write_text(json.dumps(doc))
        cam = est.load_camera(tmp_path / name)
        assert np.allclose(cam.K, K), name
    assert est.load_camera(tmp_path / "bop.json").depth_scale == 0.1
    assert est.load_camera(tmp_path / "k.json").depth_scale is None


@pytest.mark.parametrize("doc, field", [
    ({"cam_K": [1, 2, 3]}, "cam_K"),
    ({"fx": 500, "fy": 500, "cx": 320}, "cy"),
    ({"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "depth_scale": "mm"}, "depth_scale"),
    ({"intrinsics": [1, 2]}, "cam_K"),
])
def test_bad_camera_json_names_the_file_and_field(tmp_path, doc, field):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(EstimateError) as e:
        est.load_camera(path)
    assert str(path) in str(e.value) and field in str(e.value)


def test_clear_errors_for_missing_files_and_bad_inputs(case, tmp_path, monkeypatch):
    with pytest.raises(EstimateError, match="rgb_missing.png: RGB file not found"):
        estimate(case["model"], tmp_path / "rgb_missing.png", case["depth"], case["camera"], bbox=case["bbox"])
    with pytest.raises(EstimateError, match="camera file not found"):
        estimate(case["model"], case["rgb"], case["depth"], tmp_path / "nope.json", bbox=case["bbox"])
    with pytest.raises(EstimateError, match="exactly one localisation prior"):
        estimate(case["model"], case["rgb"], case["depth"], case["camera"])
    with pytest.raises(EstimateError, match="--bbox"):
        estimate(case["model"], case["rgb"], case["depth"], case["camera"], bbox="1,2,3")
    with pytest.raises(EstimateError, match="--bop-name.*lowercase letters and digits"):
        estimate(case["model"], case["rgb"], case["depth"], case["camera"], bbox=case["bbox"], bop_name="My_Can")
    # a model in metres is refused, with the option that fixes it
    from pipeline.formats.bop.ply import write_ply

    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], np.float32)
    write_ply(tmp_path / "metres.ply", v, np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]))
    with pytest.raises(EstimateError, match="--model-scale 1000"):
        est.load_model(tmp_path / "metres.ply")
    assert est.load_model(tmp_path / "metres.ply", model_scale=1000.0)[1] == pytest.approx(100 * 2 ** 0.5)
    # the CLI prints the message and exits with 1
    monkeypatch.setenv("FREEZE_CACHE", str(tmp_path / "cache"))
    bad = tmp_path / "bad.json"
    bad.write_text('{"cam_K": [1, 2]}')
    result = CliRunner().invoke(_cli(), ["estimate", "--model", str(case["model"]), "--rgb", str(case["rgb"]),
                                         "--depth", str(case["depth"]), "--camera", str(bad), "--bbox", "1,2,3,4"])
    assert result.exit_code == 1
    said = result.output.replace("\n", "")  # the console wraps a long path
    assert "cam_K" in said and "bad.json" in said


# ----------------------------------------------------------------------- real frame


@pytest.mark.slow
def test_real_linemod_frame_gives_a_pose_inside_the_box(tmp_path):
    """SAM-6D's demo frame (LINEMOD, object 5, the watering can), box prior only. No
    ground truth exists: the pose's projected model centre must lie in the box."""
    from shared_data import shared_dir

    realdata = shared_dir("realdata", "sam6d-example",
                          files=["rgb.png", "depth.png", "camera.json", "obj_000005.ply"])
    bbox = (372, 224, 68, 96)  # read off the image: the can with its spout's rose
    res = estimate(realdata / "obj_000005.ply", realdata / "rgb.png", realdata / "depth.png",
                   realdata / "camera.json", bbox=bbox, overrides=FAST, cache=tmp_path / "cache",
                   out_dir=tmp_path / "out")
    K = est.load_camera(realdata / "camera.json").K
    u, v, w = K @ res.t
    x, y, bw, bh = bbox
    assert x <= u / w <= x + bw and y <= v / w <= y + bh, (u / w, v / w)
    assert 800 < res.t[2] < 1200  # the can stands about 1 m from the camera
    assert res.record["model"]["diameter_mm"] == pytest.approx(201.4, abs=0.5)
    assert (tmp_path / "out" / "overlay.png").exists()
    # wrapped by `freeze estimate`, the frame reads back as a BOP dataset
    from pipeline.formats.bop import BopDataset, load_detections

    ds = BopDataset(tmp_path / "out" / "bop" / "obj000005")
    assert ds.load_rgb(1, 0).shape == (480, 640, 3) and np.array_equal(ds.scene_camera(1)[0].K, K)
    (det,) = load_detections(tmp_path / "out" / "bop" / "detections" / "estimate_obj000005-test.json")
    assert det.bbox == bbox and det.mask().sum() > 1000


# ------------------------------------------------ encoders, device, grey images, units


def _cli_args(case: dict, out: Path, *extra: str, rgb: Path | None = None, model: Path | None = None) -> list[str]:
    return ["estimate", "--model", str(model or case["model"]), "--rgb", str(rgb or case["rgb"]),
            "--depth", str(case["depth"]), "--camera", str(case["camera"]), "--mask", str(case["mask"]),
            "--out", str(out), *extra]


def test_grey_images_are_detected(tmp_path):
    import cv2

    from pipeline.formats.bop.dataset import save_rgb

    rng = np.random.default_rng(0)
    colour = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    grey = colour[..., 1]
    save_rgb(tmp_path / "colour.png", colour)
    cv2.imwrite(str(tmp_path / "one.png"), grey)
    cv2.imwrite(str(tmp_path / "one.jpg"), grey)
    cv2.imwrite(str(tmp_path / "three.png"), np.repeat(grey[..., None], 3, axis=2))
    cv2.imwrite(str(tmp_path / "three.jpg"), np.repeat(grey[..., None], 3, axis=2))
    assert est.load_rgb_and_mode(tmp_path / "colour.png")[1] is None
    for name, why in (("one.png", "single-channel"), ("one.jpg", "single-channel"), ("three.png", "identical"),
                      ("three.jpg", "identical")):
        rgb, said = est.load_rgb_and_mode(tmp_path / name)
        assert said is not None and why in said, name
        assert rgb.shape == (24, 32, 3) and np.array_equal(rgb, est.load_rgb(tmp_path / name))
    # the frame's dataset manifest declares a grey frame as grey datasets are declared
    from pipeline.common.config import DatasetManifest
    from pipeline.commands.estimate.frame import dataset_manifest

    assert DatasetManifest(**dataset_manifest("f", 32, 24, "gray")).image_mode == "gray"
    assert DatasetManifest(**dataset_manifest("f", 32, 24)).image_mode == "rgb"


def test_encoder_and_device_flags_are_config_overrides(case, tmp_path, monkeypatch):
    from pipeline.commands.estimate.command import merge_flags

    assert merge_flags({"visual": "colortex", "k": "1"}, visual="colortex", geometric="gedi", device=None) == \
        {"k": "1", "visual_encoder": "colortex", "geometric_encoder": "gedi"}
    assert merge_flags(None, device="cuda") == {"device": "cuda"}
    with pytest.raises(EstimateError, match="--visual dinov2-vitl14 conflicts with --config visual_encoder=rgb"):
        merge_flags({"visual_encoder": "rgb"}, visual="dinov2-vitl14")
    # through the command: one line, exit 1, nothing run
    monkeypatch.setenv("FREEZE_CACHE", str(tmp_path / "cache"))
    result = CliRunner().invoke(_cli(), _cli_args(case, tmp_path / "out", "--visual", "rgb", "-c", "visual=colortex"))
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit)
    [line] = [ln for ln in result.output.splitlines() if "error" in ln]
    assert line == "error: --visual rgb conflicts with --config visual=colortex: give one of them"
    result = CliRunner().invoke(_cli(), _cli_args(case, tmp_path / "out", "--device", "tpu"))
    assert result.exit_code == 2 and "tpu" in result.output  # not a choice
    assert not (tmp_path / "cache").exists()


def test_a_model_in_metres_is_one_line_through_the_cli(case, tmp_path, monkeypatch):
    import trimesh

    metres = tmp_path / "metres.ply"
    m = trimesh.load(case["model"], process=False)
    m.apply_scale(0.001)  # the case's truck, in metres
    m.export(metres)
    monkeypatch.setenv("FREEZE_CACHE", str(tmp_path / "cache"))
    result = CliRunner().invoke(_cli(), _cli_args(case, tmp_path / "out", model=metres))
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output  # no traceback
    assert "Traceback" not in result.output
    [line] = [ln for ln in result.output.splitlines() if ln.startswith("error:")]
    assert str(metres) in line and "looks like metres" in line and line.endswith("pass --model-scale 1000")
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()


@pytest.mark.slow
def test_grey_frame_gets_grey_templates_and_pose_json_names_its_encoders(case, tmp_path, monkeypatch):
    """A grey image (saved single-channel) makes a grey frame: its templates are grey
    (R == G == B) where the colour frame's are not. The encoders chosen by flag reach the
    run and pose.json says which ran, in the sentence the run printed at its start."""
    import cv2
    import yaml

    from pipeline.common.store import load_arrays

    grey = cv2.cvtColor(est.load_rgb(case["rgb"]), cv2.COLOR_RGB2GRAY)
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    monkeypatch.setenv("FREEZE_CACHE", str(case["cache"]))
    out = tmp_path / "grey"
    result = CliRunner().invoke(_cli(), _cli_args(case, out, "--visual", "colortex-intensity", "--device", "cpu",
                                                  *FAST_ARGS, rgb=tmp_path / "grey.png"))
    assert result.exit_code == 0, result.output
    said = result.output.replace("\n", "")
    assert "grey image detected (a single-channel image)" in said
    assert said.count("stand-in") == 1 and "run with --geometric gedi" in said  # fpfh is; colortex-intensity is not
    rec = json.loads((out / "pose.json").read_text())
    assert rec["encoders"]["geometric"] == "fpfh" and rec["encoders"]["visual"] == "colortex-intensity"
    assert rec["encoders"]["device"] == "cpu" and rec["inputs"]["image_mode"] == "gray"
    assert rec["note"].startswith("fpfh + colortex-intensity: fpfh is a weight-free stand-in for the paper's GeDi")
    assert yaml.safe_load((out / "bop" / "model.yaml").read_text())["image_dir"] == "gray"
    # the image is in gray/, one channel, as ITODD's (and `freeze datasets check` expects)
    written = cv2.imread(str(out / "bop" / "model" / "test" / "000001" / "gray" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert written is not None and written.ndim == 2 and np.array_equal(written, grey)
    assert not (out / "bop" / "model" / "test" / "000001" / "rgb").exists()
    templates = load_arrays(out / "render_templates" / "templates.zarr", ["rgb"])["rgb"]
    assert (templates > 0).any() and (templates[..., 0] == templates[..., 1]).all() \
        and (templates[..., 1] == templates[..., 2]).all()
    # the colour frame (default encoders; its model side from the cache of the tests above, or built now)
    colour = _run(case, mask=case["mask"])
    assert colour.record["inputs"]["image_mode"] == "rgb" and colour.record["encoders"]["visual"] == "colortex"
    assert colour.record["note"].startswith("fpfh + colortex: weight-free stand-ins for the paper's GeDi + DINOv2 "
                                            "ViT-g/14; fetch those with `freeze weights fetch gedi dinov2-vitg14`")
    rgb = load_arrays(colour.artifacts["render_templates"] / "templates.zarr", ["rgb"])["rgb"].astype(int)
    assert (np.abs(rgb[..., 0] - rgb[..., 1]) > 10).mean() > 0.01  # the truck's colours
    assert colour.artifacts["render_templates"] != out / "render_templates"

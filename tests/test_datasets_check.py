"""`freeze datasets check ROOT` opens what the stages will open: every model file by
default, a sample of the RGB and depth images with --deep. Each test writes a tiny
dataset in LM-O's layout by hand (two box models, one scene of three 640x480 images),
so that it runs in well under a second, and breaks one thing in it."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from pipeline.formats.bop import (BopFormatError, BopDataset, CameraInfo, GtInfo, GtPose, Target, detection_from_mask,
                          save_depth_png, save_detections, save_rgb, write_camera, write_models_info, write_ply,
                          write_scene_camera, write_scene_gt, write_scene_gt_info, write_targets)
from pipeline.formats.bop.wrap import model_info_from_vertices
from pipeline.commands.cli import app

W, H = 640, 480  # LM-O's image size (manifests/datasets/lmo.yaml), so the layout check stays quiet
K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
DEPTH_SCALE = 0.1  # mm per depth unit
BOXES = {1: (30.0, 40.0, 50.0), 5: (20.0, 20.0, 60.0)}  # LM-O object ids -> box extents (mm)
IMAGES = (0, 1, 2)


def _box(obj_id: int) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=BOXES[obj_id])


def write_lmo(bop_root: Path) -> Path:
    """A healthy tiny dataset ``<bop_root>/lmo`` with its default-detections file;
    returns the dataset folder."""
    ds = bop_root / "lmo"
    infos = {}
    for obj_id in BOXES:
        mesh = _box(obj_id)
        infos[obj_id] = model_info_from_vertices(mesh.vertices)
        for folder in ("models", "models_eval"):
            write_ply(ds / folder / f"obj_{obj_id:06d}.ply", mesh.vertices, mesh.faces)
    for folder in ("models", "models_eval"):
        write_models_info(ds / folder / "models_info.json", infos)
    write_camera(ds, {"K": K, "width": W, "height": H, "depth_scale": DEPTH_SCALE})
    scene = ds / "test" / "000001"
    write_scene_camera(scene / "scene_camera.json", {i: CameraInfo(K, DEPTH_SCALE, W, H) for i in IMAGES})
    pose = {o: GtPose(o, np.eye(3), np.array([60.0 * (o - 3), 0.0, 700.0])) for o in BOXES}
    write_scene_gt(scene / "scene_gt.json", {i: list(pose.values()) for i in IMAGES})
    # the scorer reads each instance's visibility beside the poses (the check asks for it)
    info = GtInfo((280, 200, 80, 80), (280, 200, 80, 80), 6400, 6400, 6400, 1.0)
    write_scene_gt_info(scene / "scene_gt_info.json", {i: [info] * len(BOXES) for i in IMAGES})
    write_targets(ds / "test_targets_bop19.json", [Target(1, i, o, 1) for i in IMAGES for o in BOXES])
    mask = np.zeros((H, W), bool)
    mask[200:280, 280:360] = True
    dets = []
    for i in IMAGES:
        save_rgb(scene / "rgb" / f"{i:06d}.png", np.full((H, W, 3), 90 + i, np.uint8))
        save_depth_png(scene / "depth" / f"{i:06d}.png", np.full((H, W), 700.0), DEPTH_SCALE)
        dets += [detection_from_mask(1, i, o, 0.9, mask) for o in BOXES]
    save_detections(bop_root / "detections" / "cnos-fastsam_lmo-test.json", dets)
    return ds


def check(root: Path, *args: str) -> tuple[int, dict]:
    """(exit code, the lmo report) of `freeze datasets check ROOT --json ARGS`."""
    result = CliRunner().invoke(app, ["datasets", "check", str(root), "--json", *args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    out = json.loads(result.stdout)
    return result.exit_code, next(d for d in out["datasets"] if d["name"] == "lmo")


@pytest.fixture
def lmo(tmp_path) -> tuple[Path, Path]:
    """(bop_root, dataset folder) of a fresh healthy dataset."""
    root = tmp_path / "bop"
    return root, write_lmo(root)


def test_healthy_dataset_passes_in_both_modes(lmo):
    root, _ = lmo
    for args in ((), ("--deep",)):
        code, rep = check(root, *args)
        assert code == 0 and rep["ok"], rep
        assert rep["errors"] == [] and rep["warnings"] == [], rep
        assert rep["summary"]["targets"] == 6 and rep["summary"]["image_size"] == [W, H]
    result = CliRunner().invoke(app, ["datasets", "check", str(root), "--deep"])  # the table
    assert result.exit_code == 0, result.output
    assert "lmo" in result.stdout and "ok" in result.stdout


def test_corrupt_ply(lmo):
    root, ds = lmo
    path = ds / "models" / "obj_000001.ply"
    path.write_bytes(b"\x00\x01 not a mesh")
    code, rep = check(root)
    assert code == 1 and len(rep["errors"]) == 1, rep["errors"]
    assert rep["errors"][0].startswith(f"{path}: not a PLY file")  # the reader's message, one line


def test_truncated_ply(lmo):
    root, ds = lmo
    path = ds / "models_eval" / "obj_000005.ply"
    path.write_bytes(path.read_bytes()[:-40])
    code, rep = check(root)
    assert code == 1 and len(rep["errors"]) == 1
    assert rep["errors"][0].startswith(f"{path}: ") and "truncated" in rep["errors"][0]


def test_ply_without_faces(lmo):
    root, ds = lmo
    path = ds / "models" / "obj_000005.ply"
    write_ply(path, _box(5).vertices, np.zeros((0, 3), np.int64))
    code, rep = check(root)
    assert code == 1 and len(rep["errors"]) == 1, rep["errors"]
    # the reader itself may refuse it (one line naming the file), else the check says so
    assert rep["errors"][0].startswith(f"{path}: ") and "no faces" in rep["errors"][0]


def test_nan_vertex(lmo):
    root, ds = lmo
    path = ds / "models" / "obj_000001.ply"
    mesh = _box(1)
    vertices = mesh.vertices.copy()
    vertices[3] = np.nan
    write_ply(path, vertices, mesh.faces)
    code, rep = check(root)
    assert code == 1 and len(rep["errors"]) == 1, rep["errors"]
    assert rep["errors"][0].startswith(f"{path}: ")
    assert re.search(r"NaN|nan|non-finite", rep["errors"][0]), rep["errors"][0]


def test_model_in_metres(lmo):
    root, ds = lmo
    path = ds / "models" / "obj_000001.ply"
    mesh = _box(1)
    write_ply(path, mesh.vertices / 1000.0, mesh.faces)  # metres, while models_info says mm
    code, rep = check(root)
    assert code == 1
    assert rep["errors"] == [f"{path}: model is about 1000x smaller than models_info's diameter: in metres? "
                                       "(BOP models are in mm; the vertices span 0.0707, the diameter is 70.71)"]


def test_model_problems_when_the_reader_accepts_the_mesh():
    """The check's own tests of a mesh, for what the PLY reader lets through."""
    from pipeline.commands.datasets import model_problems

    class Reader:  # stands in for BopDataset.load_model
        def __init__(self, mesh):
            self.mesh = mesh

        def load_model(self, obj_id, eval=False):
            return self.mesh

    box = _box(1)
    nan = box.vertices.copy()
    nan[[2, 5]] = np.inf
    path = Path("models/obj_000001.ply")
    faceless = trimesh.Trimesh(box.vertices, np.zeros((0, 3), np.int64), process=False)
    assert model_problems(Reader(faceless), 1, False, path, 70.71) == [
        f"{path}: PLY has no faces (a point cloud?): templates and scores need a triangle mesh"]
    assert model_problems(Reader(trimesh.Trimesh(nan, box.faces, process=False)), 1, False, path, 70.71) == [
        f"{path}: 2 of 8 vertices are NaN or inf"]
    assert model_problems(Reader(box), 1, False, path, 70.71) == []
    cm = trimesh.Trimesh(box.vertices / 10, box.faces, process=False)
    assert model_problems(Reader(cm), 1, False, path, 70.71) == [
        f"{path}: model is about 10x smaller than models_info's diameter: in cm? (BOP models are in mm; the vertices "
        "span 7.07, the diameter is 70.71)"]
    assert model_problems(Reader(box), 1, False, path, 20.0) == [
        f"{path}: model is about 2.5x larger than models_info's diameter (the vertices span 50, the diameter is 20)"]


def test_missing_and_non_positive_diameters(lmo):
    """A missing diameter stops the reader; the check still names every bad object and
    still opens the models."""
    root, ds = lmo
    info_path = ds / "models" / "models_info.json"
    info = json.loads(info_path.read_text())
    del info["1"]["diameter"]
    info["5"]["diameter"] = 0
    info_path.write_text(json.dumps(info))
    (ds / "models" / "obj_000005.ply").write_text("ply\nformat ascii 1.0\nend_header\n")
    code, rep = check(root)
    assert code == 1
    assert rep["errors"][:2] == [
        f"{info_path}: object 1: field 'diameter' is missing or not a number: give the model's diameter in mm",
        f"{info_path}: object 5: field 'diameter' is 0: it must be positive (mm)",
    ]
    assert len(rep["errors"]) == 3 and rep["errors"][2].startswith(f"{ds / 'models' / 'obj_000005.ply'}: ")


def test_8bit_and_3channel_depth_with_deep(lmo):
    root, ds = lmo
    depth = ds / "test" / "000001" / "depth"
    cv2.imwrite(str(depth / "000000.png"), np.full((H, W), 70, np.uint8))
    cv2.imwrite(str(depth / "000002.png"), np.full((H, W, 3), 7000, np.uint16))
    assert check(root)[0] == 0  # the default check does not open images
    code, rep = check(root, "--deep")
    assert code == 1
    rule = "depth must be 16-bit single-channel PNG/TIF"
    assert rep["errors"] == [f"{depth / '000000.png'}: {rule}, got uint8",
                             f"{depth / '000002.png'}: {rule}, got 3-channel uint16"]


def test_depth_of_the_wrong_size_with_deep(lmo):
    root, ds = lmo
    path = ds / "test" / "000001" / "depth" / "000001.png"  # the middle image of the scene
    save_depth_png(path, np.full((240, 320), 700.0), DEPTH_SCALE)
    code, rep = check(root, "--deep")
    assert code == 1
    assert rep["errors"] == [f"{path}: depth is 320x240 px, the image 000001.png is 640x480 and camera.json says "
                             "640x480 (fields 'width', 'height')"]


def test_unreadable_rgb_and_zero_depth_with_deep(lmo):
    root, ds = lmo
    scene = ds / "test" / "000001"
    (scene / "rgb" / "000002.png").write_bytes(b"not a png")
    save_depth_png(scene / "depth" / "000000.png", np.zeros((H, W)), DEPTH_SCALE)
    code, rep = check(root, "--deep")
    assert code == 1
    assert rep["errors"] == [f"{scene / 'rgb' / '000002.png'}: cannot decode image"]
    assert rep["warnings"] == [f"{scene / 'depth' / '000000.png'}: depth is zero everywhere: this image will get no "
                               "estimate"]


def test_deep_sample_is_first_middle_last_of_each_scene():
    from pipeline.commands.datasets import deep_sample

    images = [(1, i) for i in (0, 3, 5, 8, 9)] + [(2, 4)] + [(3, 1), (3, 2)]
    assert deep_sample(images) == [(1, 0), (1, 5), (1, 9), (2, 4), (3, 1), (3, 2)]


def test_no_dataset_under_root_exits_1(tmp_path):
    (tmp_path / "unrelated").mkdir()
    message = (f"no BOP dataset found under {tmp_path}; expected folders like lmo/, tless/ with models/ and a "
               "split folder")
    result = CliRunner().invoke(app, ["datasets", "check", str(tmp_path)])
    assert result.exit_code == 1 and result.stdout == ""
    assert result.stderr.strip() == message
    result = CliRunner().invoke(app, ["datasets", "check", str(tmp_path), "--json"])
    assert result.exit_code == 1 and result.stderr.strip() == message
    assert json.loads(result.stdout)["error"] == message


def test_dataset_folder_given_as_root_gets_a_hint(lmo):
    _, ds = lmo
    result = CliRunner().invoke(app, ["datasets", "check", str(ds)])
    assert result.exit_code == 1
    assert result.stderr.strip().endswith(f"({ds} looks like a dataset folder itself: pass its parent)")


def test_reader_refuses_8bit_depth_and_keeps_float_tiff(lmo):
    """One depth rule for the dataset reader and `freeze estimate`'s inputs."""
    from pipeline.commands.estimate.inputs import EstimateError, load_depth

    _, ds = lmo
    depth = ds / "test" / "000001" / "depth"
    cv2.imwrite(str(depth / "000000.png"), np.full((H, W), 70, np.uint8))
    bop = BopDataset(ds)
    with pytest.raises(BopFormatError, match=r"000000\.png: depth must be 16-bit single-channel PNG/TIF, got uint8$"):
        bop.load_depth(1, 0)
    with pytest.raises(EstimateError, match=r"000000\.png: depth must be 16-bit single-channel PNG/TIF, got uint8"):
        load_depth(depth / "000000.png", DEPTH_SCALE)
    np.testing.assert_array_equal(bop.load_depth(1, 1), np.full((H, W), 700.0, np.float32))
    (depth / "000002.png").unlink()
    assert cv2.imwrite(str(depth / "000002.tif"), np.full((H, W), 7000.0, np.float32))  # depth units, as float
    np.testing.assert_allclose(bop.load_depth(1, 2), 700.0)

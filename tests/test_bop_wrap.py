"""One RGB-D frame wrapped as a one-image BOP dataset (pipeline/formats/bop/wrap.py), read back
through the same reader the pipeline uses (BopDataset, load_detections)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline.formats.bop import BopDataset, Target
from pipeline.formats.bop.detections import load_detections
from pipeline.formats.bop.ply import read_ply, write_ply
from pipeline.formats.bop.wrap import box_mask, choose_depth_scale, default_name, detections_path, wrap_frame
from shared_data import shared_dir
SAM6D_BOX = (372, 224, 68, 96)  # the watering can, as in tests/test_estimate.py

H, W = 48, 64
K = np.array([[80.5, 0.0, 31.7], [0.0, 81.25, 23.9], [0.0, 0.0, 1.0]])
EXTENTS = (30.0, 40.0, 50.0)  # mm; the box's space diagonal is the diameter
DIAGONAL = math.sqrt(sum(e * e for e in EXTENTS))


def _check_pipeline_accepts(root: Path, name: str, detector: str = "estimate") -> None:
    """`freeze datasets check`'s test of a BOP dataset (what the stages read) finds no error."""
    from pipeline.common.config import DatasetManifest
    from pipeline.commands.datasets import check_dataset

    man = DatasetManifest(name=name, kind="bop", prior=f"detections/{detector}_{name}-test.json")
    rep = check_dataset(root, man)
    assert rep.errors == [], rep.errors
    assert rep.summary["targets"] == 1 and rep.summary["detections"] == 1


@pytest.fixture
def frame(tmp_path) -> dict:
    """Random RGB, a depth plane with a hole (mm), a box model (mm) and an elliptic mask."""
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    v, u = np.mgrid[:H, :W]
    depth = (600.0 + 1.37 * u + 2.11 * v + 0.03 * u * v).astype(np.float32)
    depth[5:9, 40:50] = 0.0  # no depth there
    mask = ((u - 30) / 12.0) ** 2 + ((v - 20) / 9.0) ** 2 <= 1.0
    box = trimesh.creation.box(extents=EXTENTS)
    write_ply(tmp_path / "box.ply", box.vertices, box.faces)
    return {"rgb": rgb, "depth": depth, "mask": mask, "model": tmp_path / "box.ply", "mesh": box}


def test_round_trip_through_the_bop_reader(frame, tmp_path):
    root = tmp_path / "bop"
    ds_dir = wrap_frame(root, "frame", rgb=frame["rgb"], depth_mm=frame["depth"], K=K, model_path=frame["model"],
                        mask=frame["mask"])
    assert ds_dir == root / "frame"
    ds = BopDataset(ds_dir)
    assert ds.scene_ids() == [1] and ds.image_ids(1) == [0]
    cam = ds.scene_camera(1)[0]
    assert np.array_equal(cam.K, K) and np.array_equal(ds.camera()["K"], K)
    assert (cam.width, cam.height) == (W, H) and cam.depth_scale == 0.1
    assert np.array_equal(ds.load_rgb(1, 0), frame["rgb"])  # lossless PNG
    depth = ds.load_depth(1, 0)
    assert depth.shape == (H, W)
    assert np.abs(depth - frame["depth"]).max() <= 0.05 + 1e-4  # half the depth unit
    assert (depth[5:9, 40:50] == 0).all()
    info = ds.models_info()[1]
    assert info.diameter == pytest.approx(DIAGONAL, rel=1e-9)
    assert np.allclose(info.min_xyz, [-15, -20, -25]) and np.allclose(info.size_xyz, EXTENTS)
    assert ds.model_path(1).read_bytes() == frame["model"].read_bytes()  # model_scale 1: a byte copy
    assert ds.targets() == [Target(1, 0, 1, 1)]
    assert not (ds.scene_dir(1) / "scene_gt.json").exists()  # no ground truth given

    det_file = detections_path(root, "frame")
    assert det_file == root / "detections" / "estimate_frame-test.json"
    (det,) = load_detections(det_file)
    assert (det.scene_id, det.image_id, det.category_id, det.score) == (1, 0, 1, 1.0)
    assert np.array_equal(det.mask(), frame["mask"])
    v, u = np.nonzero(frame["mask"])
    assert det.bbox == (u.min(), v.min(), u.max() - u.min(), v.max() - v.min())  # BOP toolkit convention
    _check_pipeline_accepts(root, "frame")
    assert sorted(p.name for p in root.iterdir()) == ["detections", "frame"]  # no temporary left


def test_model_in_metres_is_written_in_mm(frame, tmp_path):
    metres = frame["mesh"].copy()
    metres.apply_scale(0.001)
    write_ply(tmp_path / "m.ply", metres.vertices, metres.faces)
    ds = BopDataset(wrap_frame(tmp_path / "bop", "m", rgb=frame["rgb"], depth_mm=frame["depth"], K=K,
                               model_path=tmp_path / "m.ply", model_scale=1000.0, mask=frame["mask"]))
    metre_diameter = DIAGONAL / 1000
    assert ds.models_info()[1].diameter == pytest.approx(1000 * metre_diameter, rel=1e-6)
    assert np.allclose(read_ply(ds.model_path(1)).vertices, frame["mesh"].vertices, atol=1e-4)
    with pytest.raises(ValueError, match="metres"):  # without the scale it is refused
        wrap_frame(tmp_path / "bop2", "m", rgb=frame["rgb"], depth_mm=frame["depth"], K=K,
                   model_path=tmp_path / "m.ply", mask=frame["mask"])


def test_box_prior_with_and_without_the_kept_points(frame, tmp_path):
    box = (20.4, 10.0, 25.0, 20.6)  # fractional: the mask covers the pixels it touches
    kept = np.zeros((H, W), bool)
    kept[15:40, 10:40] = True
    common = dict(rgb=frame["rgb"], depth_mm=frame["depth"], K=K, model_path=frame["model"], bbox=box)
    wrap_frame(tmp_path, "boxonly", **common)
    wrap_frame(tmp_path, "boxkept", kept_mask=kept, **common)
    full = np.zeros((H, W), bool)
    full[10:31, 20:46] = True
    assert np.array_equal(box_mask(box, (H, W)), full)
    (d_full,) = load_detections(detections_path(tmp_path, "boxonly"))
    (d_kept,) = load_detections(detections_path(tmp_path, "boxkept"))
    assert d_full.bbox == box and d_kept.bbox == box  # the box given, not the mask's
    assert np.array_equal(d_full.mask(), full)
    assert np.array_equal(d_kept.mask(), full & kept)


def test_ground_truth_when_given(frame, tmp_path):
    R = trimesh.transformations.rotation_matrix(0.3, [1, 2, 3])[:3, :3]
    t = np.array([10.0, -20.0, 650.0])
    ds = BopDataset(wrap_frame(tmp_path, "gt", rgb=frame["rgb"], depth_mm=frame["depth"], K=K,
                               model_path=frame["model"], mask=frame["mask"], gt_R=R, gt_t=t))
    (gt,) = ds.scene_gt(1)[0]
    assert gt.obj_id == 1 and np.allclose(gt.R, R) and np.allclose(gt.t, t)


def test_rewrite_is_idempotent_and_a_different_frame_needs_overwrite(frame, tmp_path):
    kw = dict(rgb=frame["rgb"], depth_mm=frame["depth"], K=K, model_path=frame["model"], mask=frame["mask"])
    first = wrap_frame(tmp_path, "scene", **kw)
    stamp = (first / "camera.json").stat().st_mtime_ns
    assert wrap_frame(tmp_path, "scene", **kw) == first  # the same frame again: left as it is
    assert (first / "camera.json").stat().st_mtime_ns == stamp
    other = dict(kw, rgb=255 - frame["rgb"])
    with pytest.raises(FileExistsError, match="scene"):
        wrap_frame(tmp_path, "scene", **other)
    assert np.array_equal(BopDataset(first).load_rgb(1, 0), frame["rgb"])  # untouched
    wrap_frame(tmp_path, "scene", overwrite=True, **other)
    assert np.array_equal(BopDataset(first).load_rgb(1, 0), 255 - frame["rgb"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box.ply", "detections", "scene"]


def test_names_depth_scale_and_bad_inputs(frame, tmp_path):
    assert default_name("/x/obj_000005.ply") == "obj000005"
    assert default_name("My Can-2.PLY") == "mycan2"
    kw = dict(rgb=frame["rgb"], depth_mm=frame["depth"], K=K, model_path=frame["model"], mask=frame["mask"])
    for bad in ("Can", "obj_5", "a-b", ""):
        with pytest.raises(ValueError, match="lowercase"):
            wrap_frame(tmp_path, bad, **kw)
    with pytest.raises(ValueError, match="mask or its bbox"):
        wrap_frame(tmp_path, "x", **{**kw, "mask": None})
    with pytest.raises(ValueError, match="empty"):
        wrap_frame(tmp_path, "x", **{**kw, "mask": np.zeros((H, W), bool)})
    # a far depth does not fit 0.1 mm units in uint16: the unit becomes 0.2 mm
    assert choose_depth_scale(np.array([6553.0])) == 0.1
    assert choose_depth_scale(np.array([7000.0])) == 0.2
    assert choose_depth_scale(np.array([20000.0])) == 0.5
    far = frame["depth"] + 6500.0
    ds = BopDataset(wrap_frame(tmp_path, "far", **{**kw, "depth_mm": far}))
    assert ds.scene_camera(1)[0].depth_scale == 0.2
    assert np.abs(ds.load_depth(1, 0) - far).max() <= 0.1 + 1e-3


# ----------------------------------------------------------------------- real frame


def test_real_sam6d_frame_reads_back_through_the_bop_reader(tmp_path):
    """SAM-6D's demo frame (LINEMOD, object 5, depth in mm, no ground truth) from
    ../shared/realdata/sam6d-example, loaded with `freeze estimate`'s own loaders,
    wrapped with the can's box."""
    from pipeline.commands import estimate as est

    sam6d = shared_dir("realdata", "sam6d-example", files=["camera.json", "rgb.png", "depth.png", "obj_000005.ply"])
    cam = est.load_camera(sam6d / "camera.json")
    rgb = est.load_rgb(sam6d / "rgb.png")
    depth = est.load_depth(sam6d / "depth.png", cam.depth_scale)
    box = est.parse_bbox(",".join(map(str, SAM6D_BOX)))
    name = default_name(sam6d / "obj_000005.ply")
    assert name == "obj000005"
    ds = BopDataset(wrap_frame(tmp_path, name, rgb=rgb, depth_mm=depth, K=cam.K, model_path=sam6d / "obj_000005.ply",
                               bbox=box))
    c = ds.scene_camera(1)[0]
    assert (c.width, c.height) == (640, 480) and ds.load_rgb(1, 0).shape == (480, 640, 3)
    cam_K = json.loads((sam6d / "camera.json").read_text())["cam_K"]
    assert np.array_equal(c.K, np.reshape(cam_K, (3, 3)))
    assert np.array_equal(ds.load_rgb(1, 0), rgb)
    back = ds.load_depth(1, 0)
    assert np.abs(back - depth).max() <= c.depth_scale / 2 + 1e-3
    assert (back > 0).sum() == (depth > 0).sum()
    (det,) = load_detections(detections_path(tmp_path, name))
    assert det.bbox == SAM6D_BOX
    assert np.array_equal(det.mask(), box_mask(SAM6D_BOX, (480, 640))) and det.mask().sum() == 68 * 96
    _, diameter = est.load_model(sam6d / "obj_000005.ply")
    assert ds.models_info()[1].diameter == pytest.approx(diameter, rel=1e-3)
    assert ds.models_info()[1].diameter == pytest.approx(201.4, abs=0.5)  # LM obj 5
    assert ds.model_path(1).read_bytes() == (sam6d / "obj_000005.ply").read_bytes()
    _check_pipeline_accepts(tmp_path, name)


def test_grey_frame_goes_to_gray_as_one_channel(frame, tmp_path):
    """grey=True: the image is written to gray/ as a one-channel PNG (ITODD's layout), the
    reader gives it back replicated to three channels, and `freeze datasets check` accepts
    it; an image whose channels differ is refused."""
    import cv2

    from pipeline.common.config import DatasetManifest
    from pipeline.commands.datasets import check_dataset

    grey = np.repeat(frame["rgb"][..., :1], 3, axis=2)
    kw = dict(depth_mm=frame["depth"], K=K, model_path=frame["model"], mask=frame["mask"])
    ds_dir = wrap_frame(tmp_path, "grey", rgb=grey, grey=True, **kw)
    scene = ds_dir / "test" / "000001"
    written = cv2.imread(str(scene / "gray" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert written.ndim == 2 and np.array_equal(written, grey[..., 0]) and not (scene / "rgb").exists()
    assert np.array_equal(BopDataset(ds_dir).load_rgb(1, 0), grey)
    man = DatasetManifest(name="grey", kind="bop", prior="detections/estimate_grey-test.json", image_dir="gray")
    assert check_dataset(tmp_path, man).errors == []
    with pytest.raises(ValueError, match="channels differ"):
        wrap_frame(tmp_path, "colour", rgb=frame["rgb"], grey=True, **kw)

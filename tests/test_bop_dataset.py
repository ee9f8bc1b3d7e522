"""BopDataset on a tiny tree written with the package's own writers."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from pipeline.formats.bop import (
    BopDataset,
    BopFormatError,
    CameraInfo,
    GtInfo,
    GtPose,
    ModelInfo,
    Target,
    save_depth_png,
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

H, W = 12, 16
SCALE = 0.1


def _rot(rng):
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.fixture
def tree(tmp_path):
    """A 2-object, 1-scene, 2-image dataset; returns (root, the values written)."""
    rng = np.random.default_rng(7)
    root = tmp_path / "tiny"
    K = np.array([[500.25, 0, 7.5], [0, 501.5, 5.5], [0, 0, 1]])
    write_camera(root, {"K": K, "width": W, "height": H, "depth_scale": SCALE})
    box = trimesh.creation.box(extents=(10, 20, 30))
    colors = rng.integers(0, 256, (len(box.vertices), 3)).astype(np.uint8)
    for obj_id in (1, 2):
        write_ply(root / "models" / f"obj_{obj_id:06d}.ply", box.vertices, box.faces, colors=colors)
        write_ply(root / "models_eval" / f"obj_{obj_id:06d}.ply", box.vertices, box.faces)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    flip[:3, 3] = [0.0, 0.0, 2.5]
    info = {
        1: ModelInfo(37.416, np.array([-5.0, -10.0, -15.0]), np.array([10.0, 20.0, 30.0]), [flip],
                     [{"axis": np.array([0.0, 0.0, 1.0]), "offset": np.array([0.0, 1.0, 0.0])}]),
        2: ModelInfo(37.416, np.array([-5.0, -10.0, -15.0]), np.array([10.0, 20.0, 30.0])),
    }
    write_models_info(root / "models" / "models_info.json", info)
    write_models_info(root / "models_eval" / "models_info.json", info)

    scene = root / "test" / "000003"
    cams = {
        0: CameraInfo(K, SCALE, W, H, _rot(rng), rng.standard_normal(3) * 100),
        5: CameraInfo(K * 1.0, SCALE, W, H),
    }
    gt = {i: [GtPose(1, _rot(rng), rng.standard_normal(3) * 50 + [0, 0, 700]),
              GtPose(2, _rot(rng), rng.standard_normal(3) * 50 + [0, 0, 800])] for i in cams}
    gt_info = {i: [GtInfo((1, 2, 3, 4), (1, 2, 3, 3), 12, 11, 9, 0.75), GtInfo((0, 0, 5, 5), (0, 0, 0, 0), 25, 25, 0, 0.0)]
               for i in cams}
    write_scene_camera(scene / "scene_camera.json", cams)
    write_scene_gt(scene / "scene_gt.json", gt)
    write_scene_gt_info(scene / "scene_gt_info.json", gt_info)
    rgb = {i: rng.integers(0, 256, (H, W, 3)).astype(np.uint8) for i in cams}
    raw_depth = {i: rng.integers(0, 20000, (H, W)).astype(np.uint16) for i in cams}
    masks = {}
    for i in cams:
        save_rgb(scene / "rgb" / f"{i:06d}.png", rgb[i])
        save_depth_png(scene / "depth" / f"{i:06d}.png", raw_depth[i] * SCALE, SCALE)
        for gt_id in range(2):
            for sub in ("mask", "mask_visib"):
                m = rng.random((H, W)) < 0.4
                masks[(i, gt_id, sub)] = m
                save_mask_png(scene / sub / f"{i:06d}_{gt_id:06d}.png", m)
    targets = [Target(3, 0, 1, 1), Target(3, 0, 2, 1), Target(3, 5, 1, 1)]
    write_targets(root / "test_targets_bop19.json", targets)
    return root, dict(K=K, info=info, cams=cams, gt=gt, gt_info=gt_info, rgb=rgb, raw_depth=raw_depth,
                      masks=masks, targets=targets, colors=colors)


def test_reads_back_identical_values(tree):
    root, v = tree
    ds = BopDataset(root)
    cam = ds.camera()
    np.testing.assert_array_equal(cam["K"], v["K"])
    assert (cam["width"], cam["height"], cam["depth_scale"]) == (W, H, SCALE)
    assert ds.obj_ids() == [1, 2]
    info = ds.models_info()
    for obj_id, want in v["info"].items():
        got = info[obj_id]
        assert got.diameter == want.diameter
        np.testing.assert_array_equal(got.min_xyz, want.min_xyz)
        np.testing.assert_array_equal(got.size_xyz, want.size_xyz)
        assert len(got.symmetries_discrete) == len(want.symmetries_discrete)
        for a, b in zip(got.symmetries_discrete, want.symmetries_discrete):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(got.symmetries_continuous, want.symmetries_continuous):
            np.testing.assert_array_equal(a["axis"], b["axis"])
            np.testing.assert_array_equal(a["offset"], b["offset"])
    assert info[1].is_symmetric and not info[2].is_symmetric

    assert ds.scene_ids() == [3]
    assert ds.image_ids(3) == [0, 5]
    for im_id, want in v["cams"].items():
        got = ds.scene_camera(3)[im_id]
        np.testing.assert_array_equal(got.K, want.K)
        assert (got.depth_scale, got.width, got.height) == (SCALE, W, H)
        if want.R_w2c is None:
            assert got.R_w2c is None and got.t_w2c is None
        else:
            np.testing.assert_array_equal(got.R_w2c, want.R_w2c)
            np.testing.assert_array_equal(got.t_w2c, want.t_w2c)
        for g, w in zip(ds.scene_gt(3)[im_id], v["gt"][im_id], strict=True):
            assert g.obj_id == w.obj_id
            np.testing.assert_array_equal(g.R, w.R)  # exact: floats are written in repr form
            np.testing.assert_array_equal(g.t, w.t)
        assert ds.scene_gt_info(3)[im_id] == v["gt_info"][im_id]
        np.testing.assert_array_equal(ds.load_rgb(3, im_id), v["rgb"][im_id])
        depth = ds.load_depth(3, im_id)
        assert depth.dtype == np.float32
        np.testing.assert_array_equal(depth, (v["raw_depth"][im_id].astype(np.float64) * SCALE).astype(np.float32))
        assert ds.has_depth(3, im_id)
        for gt_id in range(2):
            np.testing.assert_array_equal(ds.load_mask(3, im_id, gt_id), v["masks"][(im_id, gt_id, "mask_visib")])
            np.testing.assert_array_equal(ds.load_mask(3, im_id, gt_id, visib=False), v["masks"][(im_id, gt_id, "mask")])
    assert ds.targets() == v["targets"]
    assert ds.image_targets() == [(3, 0), (3, 5)]

    mesh = ds.load_model(2)
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], v["colors"])
    assert ds.model_path(1, eval=True) == root / "models_eval" / "obj_000001.ply"


def test_files_match_bop_field_layout(tree):
    root, _ = tree
    gt = json.loads((root / "test" / "000003" / "scene_gt.json").read_text())
    assert sorted(gt) == ["0", "5"] and sorted(gt["0"][0]) == ["cam_R_m2c", "cam_t_m2c", "obj_id"]
    assert len(gt["0"][0]["cam_R_m2c"]) == 9 and len(gt["0"][0]["cam_t_m2c"]) == 3
    sc = json.loads((root / "test" / "000003" / "scene_camera.json").read_text())
    assert sorted(sc["0"]) == ["cam_K", "cam_R_w2c", "cam_t_w2c", "depth_scale"] and sorted(sc["5"]) == ["cam_K", "depth_scale"]
    mi = json.loads((root / "models" / "models_info.json").read_text())
    assert "symmetries_discrete" not in mi["2"] and len(mi["1"]["symmetries_discrete"][0]) == 16
    assert json.loads((root / "camera.json").read_text()) == {
        "cx": 7.5, "cy": 5.5, "depth_scale": 0.1, "fx": 500.25, "fy": 501.5, "height": 12, "width": 16}


def test_depth_png_overflow_and_gray_images(tree, tmp_path):
    root, v = tree
    with pytest.raises(ValueError, match="larger depth_scale"):
        save_depth_png(tmp_path / "d.png", np.full((2, 2), 7000.0), 0.1)
    # A gray/ folder (ITODD-like) is read as 3 identical channels.
    import cv2

    scene = root / "test" / "000003"
    gray = v["rgb"][0][:, :, 1]
    (scene / "rgb" / "000000.png").unlink()
    (scene / "gray").mkdir()
    cv2.imwrite(str(scene / "gray" / "000000.png"), gray)
    rgb = BopDataset(root).load_rgb(3, 0)
    assert rgb.shape == (H, W, 3) and all((rgb[:, :, c] == gray).all() for c in range(3))


def test_errors_name_file_and_field(tree):
    root, _ = tree
    path = root / "test" / "000003" / "scene_gt.json"
    content = json.loads(path.read_text())
    del content["5"][1]["cam_t_m2c"]
    path.write_text(json.dumps(content))
    with pytest.raises(BopFormatError) as info:
        BopDataset(root).scene_gt(3)
    assert str(path) in str(info.value) and "'5'[1]" in str(info.value) and "'cam_t_m2c'" in str(info.value)

    (root / "test" / "000003" / "depth" / "000005.png").unlink()
    ds = BopDataset(root)
    assert not ds.has_depth(3, 5)
    with pytest.raises(BopFormatError, match="no depth/ image for im_id 5"):
        ds.load_depth(3, 5)
    with pytest.raises(BopFormatError, match="mask_visib/000000_000007.png"):
        ds.load_mask(3, 0, 7)
    with pytest.raises(BopFormatError, match="scene_camera.json: file not found"):
        ds.scene_camera(4)


def test_plan_keys_cover_file_contents_and_remember_hashes(tree, tmp_path, monkeypatch):
    """The keys of a BOP dataset on disk change with any byte the stages read (a model
    replaced by one of the same size, depth overwritten with zeros), the models key only
    with the model side's files; a second plan reads no file again."""
    from pipeline.common import file_hashes
    from pipeline.common.config import DatasetManifest
    from pipeline.workflow.plan import _bop_layout

    root, v = tree
    ds = DatasetManifest(name="tiny", kind="bop", prior="none.json")
    cache = tmp_path / "cache"
    hashed = []
    real_digest = file_hashes.file_digest
    monkeypatch.setattr(file_hashes, "file_digest", lambda p: hashed.append(p) or real_digest(p))

    objs, scenes, data_key, models_key, has_gt = _bop_layout(root, ds, cache)
    assert (objs, scenes, has_gt) == ([1, 2], {3: [0, 5]}, True) and len(data_key) == len(models_key) == 12
    assert len(hashed) > 10 and (cache / file_hashes.DB_NAME).is_file()
    hashed.clear()
    assert _bop_layout(root, ds, cache)[2:4] == (data_key, models_key) and hashed == []  # stat only

    ply = root / "models" / "obj_000002.ply"
    raw = bytearray(ply.read_bytes())
    raw[-1] ^= 0xFF  # same size, one byte differs
    ply.write_bytes(bytes(raw))
    _, _, data2, models2, _ = _bop_layout(root, ds, cache)
    assert models2 != models_key and data2 != data_key and hashed == [str(ply.resolve())]

    depth = root / "test" / "000003" / "depth" / "000005.png"
    save_depth_png(depth, np.zeros_like(v["raw_depth"][5], dtype=np.float64), SCALE)
    _, _, data3, models3, _ = _bop_layout(root, ds, cache)
    assert models3 == models2 and data3 != data2


def test_split_type_selects_folder_and_camera(tree):
    root, v = tree
    (root / "test").rename(root / "test_primesense")
    write_camera(root, {"K": v["K"] * 2, "width": 2 * W, "height": 2 * H, "depth_scale": SCALE}, split_type="primesense")
    ds = BopDataset(root, split="test", split_type="primesense")
    assert ds.scene_ids() == [3]
    assert ds.camera()["width"] == 2 * W and ds.scene_camera(3)[0].width == 2 * W

"""BopDataset on the shared real/synthetic samples in ../shared/realdata, read through
tests/shared_data.py (skipped when ../shared is absent, failing when a file is missing).

synthetic-tinybop/icbin was written by the BOP toolkit; hope-val-scene0000/hope is a
real HOPE validation scene without depth and with models_eval only. See their
SOURCE.txt for what the known values below come from.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from pipeline.formats.bop import BopDataset, BopFormatError, read_estimates_json, read_results_csv, write_results_csv
from pipeline.formats.bop.jsonio import bop_json_text, load_json
from shared_data import shared_dir, shared_file

TINY_JSON = ("camera.json", "models/models_info.json", "test/000001/scene_gt.json", "test/000001/scene_camera.json",
             "test/000001/scene_gt_info.json", "test_targets_bop19.json")


@pytest.fixture
def tiny():
    """../shared/realdata/synthetic-tinybop/icbin, with the toolkit-written files checked."""
    return shared_dir("realdata", "synthetic-tinybop", "icbin", files=[*TINY_JSON, "test_targets_bop24.json"])


@pytest.fixture
def hope():
    """../shared/realdata/hope-val-scene0000/hope (real HOPE val scene, no depth)."""
    return shared_dir("realdata", "hope-val-scene0000", "hope",
                      files=["models_eval/models_info.json", "val/000001/scene_gt.json", "val/000001/rgb/000000.png"])


def test_tinybop_metadata(tiny):
    ds = BopDataset(tiny)
    np.testing.assert_array_equal(ds.camera()["K"], [[572.4114, 0, 325.2611], [0, 573.57043, 242.04899], [0, 0, 1]])
    assert ds.obj_ids() == [1, 2] and ds.scene_ids() == [1] and ds.image_ids(1) == [0, 1, 2]
    cyl = ds.models_info()[1]
    assert cyl.diameter == pytest.approx(138.92443989449805)
    np.testing.assert_array_equal(cyl.size_xyz, [70, 70, 120])
    np.testing.assert_array_equal(cyl.symmetries_continuous[0]["axis"], [0, 0, 1])
    np.testing.assert_array_equal(cyl.symmetries_discrete[0], np.diag([1.0, -1.0, -1.0, 1.0]))
    assert not ds.models_info()[2].is_symmetric
    cam = ds.scene_camera(1)[0]
    assert (cam.width, cam.height, cam.depth_scale) == (640, 480, 0.1)
    for im_id, poses in ds.scene_gt(1).items():
        assert [p.obj_id for p in poses] == [1, 2]
        for p in poses:
            np.testing.assert_allclose(p.R @ p.R.T, np.eye(3), atol=1e-12)
    assert ds.scene_gt_info(1)[2][0].visib_fract == pytest.approx(0.848421052631579)
    assert len(ds.targets()) == 6 and ds.image_targets(tiny / "test_targets_bop24.json") == [(1, 0), (1, 1), (1, 2)]


def test_tinybop_images_agree_with_annotations(tiny):
    ds = BopDataset(tiny)
    for im_id in ds.image_ids(1):
        assert ds.load_rgb(1, im_id).shape == (480, 640, 3)
        depth = ds.load_depth(1, im_id)
        for gt_id, (pose, info) in enumerate(zip(ds.scene_gt(1)[im_id], ds.scene_gt_info(1)[im_id])):
            visib = ds.load_mask(1, im_id, gt_id)
            full = ds.load_mask(1, im_id, gt_id, visib=False)
            # The toolkit computed these counts from the same masks.
            assert visib.sum() == info.px_count_visib and full.sum() == info.px_count_all
            ys, xs = np.nonzero(visib)
            # The toolkit's boxes span max - min (not max - min + 1).
            assert (xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()) == info.bbox_visib
            # Depth in mm: the object centre is near t_z, within the object's radius (+ noise).
            radius = ds.models_info()[pose.obj_id].diameter / 2
            assert abs(np.median(depth[visib]) - pose.t[2]) < radius


def test_tinybop_models_and_json_layout(tiny):
    ds = BopDataset(tiny)
    mesh = ds.load_model(2)
    assert mesh.visual.kind == "vertex"
    np.testing.assert_allclose(mesh.bounds, [[-50, -35, -25], [50, 35, 25]], atol=1e-4)
    assert len(ds.load_model(1, eval=True).vertices) == 5762
    # Files the toolkit wrote are reproduced byte for byte by our writer.
    for rel in TINY_JSON:
        text = (tiny / rel).read_text()
        assert bop_json_text(load_json(tiny / rel)) == text, rel


def test_tinybop_estimates_round_trip(tiny, tmp_path):
    est = read_estimates_json(shared_file("realdata", "synthetic-tinybop", "estimates", "gt_icbin-test.json"))
    gt = BopDataset(tiny).scene_gt(1)
    for _, row in est.iterrows():
        (pose,) = [p for p in gt[row.im_id] if p.obj_id == row.obj_id]
        np.testing.assert_array_equal(row.R, pose.R)
        np.testing.assert_array_equal(row.t, pose.t)
    write_results_csv(tmp_path / "gt_icbin-test.csv", est)
    back = read_results_csv(tmp_path / "gt_icbin-test.csv")
    assert back[["scene_id", "im_id", "obj_id", "score", "time"]].equals(est[["scene_id", "im_id", "obj_id", "score", "time"]])
    assert all(np.array_equal(a, b) for a, b in zip(back["R"], est["R"]))


def test_hope_val_without_depth_and_models(hope):
    ds = BopDataset(hope, split="val")
    assert ds.obj_ids() == list(range(1, 29))
    assert ds.scene_ids() == [1] and ds.image_ids(1) == [0, 1, 2, 3, 4]
    cam = ds.scene_camera(1)[3]
    # No camera.json: the size comes from the images.
    assert (cam.width, cam.height) == (1920, 1080)
    np.testing.assert_array_equal(cam.K, [[1390.53, 0, 964.957], [0, 1386.99, 522.586], [0, 0, 1]])
    gt = ds.scene_gt(1)
    assert all(len(gt[i]) == 18 for i in gt)
    ids = [p.obj_id for p in gt[0]]
    assert sorted(i for i in set(ids) if ids.count(i) == 2) == [2, 15, 27]
    np.testing.assert_array_equal(gt[4][0].R, gt[0][0].R)  # same poses in the 5 lighting captures
    assert ds.load_rgb(1, 0).shape == (1080, 1920, 3)
    assert not ds.has_depth(1, 0)
    with pytest.raises(BopFormatError, match="no depth"):
        ds.load_depth(1, 0)
    with pytest.raises(BopFormatError, match=r"camera\.json: file not found"):
        ds.camera()
    with pytest.warns(UserWarning, match="models_eval"):
        mesh = ds.load_model(2)
    # models_info was computed on HOPE's full model; the eval mesh differs by < 0.05 mm.
    np.testing.assert_allclose(mesh.extents, ds.models_info()[2].size_xyz, atol=0.05)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ds.model_folder().name == "models_eval"  # planning reads it without a warning

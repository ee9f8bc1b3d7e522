"""Semi-real datasets built from the real samples in ../shared/realdata
(pipeline/evaluation/synth/semireal.py): the TYO-L frame with its real depth, and LM-O's real images
with depth rendered from the ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.formats.bop import BopDataset, load_detections
from pipeline.evaluation.synth.semireal import DEPTH_SCALE, build_semireal, prior_file
from shared_data import shared_dir

TYOL_FILES = ["camera.json", "test_targets_bop19.json", "models/obj_000019.ply", "models/models_info.json",
              "test/000019/scene_gt.json", "test/000019/scene_camera.json", "test/000019/rgb/000010.png",
              "test/000019/depth/000010.png"]


def test_tyol_frame_keeps_its_real_depth_and_gets_the_exact_mask(tmp_path):
    src = shared_dir("realdata", "tyol-obj19-frame10", files=TYOL_FILES)
    summary = build_semireal(src, tmp_path / "tyol", "tyol", depth="real", prior="exact", progress=False)
    assert summary["images"] == summary["targets"] == summary["detections"] == 1
    ds, sample = BopDataset(tmp_path / "tyol"), BopDataset(src)
    assert (ds.depth_path(19, 10).read_bytes() == sample.depth_path(19, 10).read_bytes())
    assert np.array_equal(ds.load_rgb(19, 10), sample.load_rgb(19, 10))
    (det,) = load_detections(tmp_path / "tyol" / prior_file("tyol"))
    mask = det.mask()
    assert det.score == 1.0 and np.array_equal(mask, ds.load_mask(19, 10, 0))
    # the SOURCE.txt's box of the basket, "about 340,46,160,217"
    x, y, w, h = det.bbox
    assert abs(x - 340) <= 3 and abs(y - 46) <= 3 and abs(w - 160) <= 4 and abs(h - 217) <= 4
    # and the real depth under it is the basket's: most masked points are near the model at the GT pose
    from pipeline.method.geometry.depth import lift_depth
    from scipy.spatial import cKDTree

    gt = ds.scene_gt(19)[10][0]
    pts, _ = lift_depth(ds.load_depth(19, 10), ds.scene_camera(19)[10].K, mask)
    model = np.asarray(ds.load_model(19).vertices) @ gt.R.T + gt.t
    near = cKDTree(model).query(pts)[0] < 10.0
    assert near.mean() > 0.6, near.mean()


@pytest.mark.slow
def test_semireal_lmo_renders_depth_from_the_ground_truth(tmp_path):
    src = shared_dir("realdata", "lmo-rgb-scene2", files=["test_targets_bop19.json", "test/000002/scene_gt.json",
                                                          "test/000002/scene_gt_info.json", "models/models_info.json"])
    summary = build_semireal(src, tmp_path / "semilmo", "semilmo", seed=3, progress=False)
    assert summary["images"] == 40 and summary["targets"] == 285
    # unannotated occluders (LM-O's other LINEMOD objects) hide more than the visible boxes cut away
    assert summary["mean_visib_fract_sample"] <= summary["mean_visib_fract_here"] < 1.0
    ds = BopDataset(tmp_path / "semilmo")
    assert ds.targets() == BopDataset(src).targets()
    im = ds.image_ids(2)[7]
    cam = ds.scene_camera(2)[im]
    assert cam.depth_scale == DEPTH_SCALE
    depth = ds.load_depth(2, im)
    gts, infos = ds.scene_gt(2)[im], ds.scene_gt_info(2)[im]
    visible = np.zeros(depth.shape, bool)
    for k, (gt, info) in enumerate(zip(gts, infos)):
        m = ds.load_mask(2, im, k)
        visible |= m
        assert m.sum() == info.px_count_visib
        # depth under the visible mask: the object's, within the sensor's noise (1.5 mm at 1 m, z^2)
        z = depth[m & (depth > 0)]
        if len(z) > 50:
            assert abs(np.median(z) - gt.t[2]) < 0.5 * ds.models_info()[gt.obj_id].diameter
    assert not (depth[~visible] > 0).any()  # no depth outside the annotated objects: sensor holes
    assert 0.5 < (depth[visible] > 0).mean() < 1.0  # the sensor model drops edges and blobs
    dets = load_detections(tmp_path / "semilmo" / prior_file("semilmo"))
    assert len(dets) == summary["detections"] > 250
    assert {d.category_id for d in dets} <= set(ds.obj_ids())
    # the same seed gives the same bytes; the sample's files are copied as they are
    again = build_semireal(src, tmp_path / "again", "semilmo", seed=3, progress=False)
    assert again == summary
    for rel in (f"test/000002/depth/{im:06d}.png", prior_file("semilmo"), "test/000002/scene_gt_info.json"):
        assert (tmp_path / "again" / rel).read_bytes() == (tmp_path / "semilmo" / rel).read_bytes(), rel
    assert json.loads((tmp_path / "semilmo" / "test/000002/scene_gt.json").read_text()) == json.loads(
        (src / "test/000002/scene_gt.json").read_text())


def test_semireal_datasets_are_planned_from_the_sample_and_skipped_without_it(tmp_path, monkeypatch):
    from pipeline.common import config as cfg
    from pipeline.workflow.plan import RunPlan

    shared_dir("realdata", "tyol-obj19-frame10", files=TYOL_FILES)
    rp = RunPlan(cfg.load_run({"datasets": "tyol"}))
    assert rp.available("tyol") == (True, "")
    plan = rp["tyol"]
    assert (plan.obj_ids, plan.scene_ids) == ([19], [19])
    assert set(plan["synth"].upstream) == {"source"}  # the sample's content is in the key
    assert plan.prior_paths == [plan.root / "detections" / "gtprior_tyol-test.json"]
    monkeypatch.setenv("FREEZE_SHARED", str(tmp_path / "nowhere"))
    ok, why = RunPlan(cfg.load_run({"datasets": "tyol"})).available("tyol")
    assert not ok and why.startswith("tyol: skipped, its real sample") and "nowhere" in why

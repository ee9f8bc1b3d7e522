"""The real YCB-V frames as a dataset (manifests/datasets/realycbv.yaml, kind ``real``):
the sample read from ../shared, its two priors, the faulty prior's stated rates, and the
checks a user runs before a long run."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.common import config as cfg
from pipeline.evaluation.synth.detector_faults import DetectorFaults, derive_faulty_prior
from pipeline.evaluation.synth.real_sample import build_real, detector_faults, prior_name
from pipeline.formats.bop import BopDataset, detection_from_mask, load_detections
from shared_data import shared_dir

SAMPLE_FILES = ["ycbv/camera_uw.json", "ycbv/targets_train_real.json", "ycbv/models/models_info.json",
                "ycbv/models/obj_000008.ply", "ycbv/models_eval/models_info.json",
                "ycbv/train_real/000000/scene_camera.json", "ycbv/train_real/000000/scene_gt.json",
                "ycbv/train_real/000000/scene_gt_info.json", "ycbv/train_real/000000/rgb/000001.png",
                "ycbv/train_real/000000/depth/000001.png", "ycbv/train_real/000002/depth/000019.png",
                "detections/gtmask_ycbv-train_real.json"]


@pytest.fixture(scope="module")
def sample():
    return shared_dir("realdata", "ycbv-real-train", files=SAMPLE_FILES)


def _disk(shape, cx, cy, r):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


def _exact_prior(n_images: int = 400):
    """Four objects (1-4, of the dataset's 1-8) per image, each a disk of its own place,
    with score 1: an exact prior."""
    shape, dets = (120, 160), []
    for im in range(n_images):
        for k, obj in enumerate((1, 2, 3, 4)):
            dets.append(detection_from_mask(0, im, obj, 1.0, _disk(shape, 25 + 37 * k, 60, 16), 0.0))
    return dets


def _iou(a, b):
    return np.logical_and(a, b).sum() / np.logical_or(a, b).sum()


def test_the_faulty_prior_is_reproducible_and_has_the_stated_rates():
    exact, faults = _exact_prior(), DetectorFaults()
    dets, log = derive_faulty_prior(exact, list(range(1, 9)), np.random.default_rng(3), faults)
    again, _ = derive_faulty_prior(exact, list(range(1, 9)), np.random.default_rng(3), faults)
    other, _ = derive_faulty_prior(exact, list(range(1, 9)), np.random.default_rng(4), faults)
    assert [d.to_json() for d in dets] == [d.to_json() for d in again]
    assert [d.to_json() for d in dets] != [d.to_json() for d in other]
    # measured from the detections alone, independently of the log
    truth = {d.category_id: d.mask() for d in exact[:4]}  # the same four disks in every image
    missed = wrong = stray = eroded = dilated = 0
    for im in range(400):
        mine = [d for d in dets if d.image_id == im]
        seen = set()
        for d in mine:
            m = d.mask()
            if d.category_id not in truth:
                stray += 1
                continue
            best = max(truth, key=lambda o: _iou(m, truth[o]))
            seen.add(best)
            wrong += best != d.category_id
            t = truth[best]
            dilated += bool((m & ~t).any())  # only a dilation adds pixels
            eroded += bool(m.sum() < t.sum() and not (m & ~t).any())  # an erosion or a cut, or both
        missed += 4 - len(seen)
    assert (missed, wrong, stray, dilated) == (log.missed, log.wrong_label, log.stray, log.dilated)
    assert log.eroded <= eroded <= log.eroded + log.cut
    n, kept = 1600, 1600 - log.missed
    for name, count, total in (("miss", log.missed, n), ("erode", log.eroded, kept), ("dilate", log.dilated, kept),
                               ("occlusion_cut", log.cut, kept), ("wrong_label", log.wrong_label, kept)):
        p = getattr(faults, name)
        assert abs(count / total - p) <= 4 * np.sqrt(p * (1 - p) / total), (name, count / total, p)
    lam = faults.stray_per_image
    assert abs(stray / 400 - lam) <= 4 * np.sqrt(lam / 400)  # (blobs too small or no absent object: none here)
    # scores do not follow quality: a stray or wrong label outranks a right detection in some images
    outranked = sum(_bad_above_good([d for d in dets if d.image_id == im], truth) for im in range(400))
    assert outranked > 20
    assert len(dets) == log.detections == 1600 - log.missed + log.stray


def _bad_above_good(dets, truth) -> bool:
    def good(d):
        return d.category_id in truth and _iou(d.mask(), truth[d.category_id]) > 0.5

    bad = [d.score for d in dets if not good(d)]
    ok = [d.score for d in dets if good(d)]
    return bool(bad and ok and max(bad) > min(ok))


def test_fault_rates_out_of_range_are_refused_with_the_field(tmp_path):
    with pytest.raises(ValueError, match="'miss' is 1.5"):
        DetectorFaults(miss=1.5)
    man = cfg.load_dataset_manifest("realycbv")
    data = man.model_dump()
    data["prior_faults"] = {**data["prior_faults"], "cut_fraction": [0.6, 0.3]}
    path = tmp_path / "bad.yaml"
    path.write_text(json.dumps(data))
    with pytest.raises(cfg.ManifestError, match=r"bad.yaml.*cut_fraction"):
        cfg.load_dataset_manifest(str(path))
    del data["prior_faults"]
    path.write_text(json.dumps(data))
    with pytest.raises(cfg.ManifestError, match=r"bad.yaml: field 'prior_faults' is required"):
        cfg.load_dataset_manifest(str(path))


def test_realycbv_is_built_from_the_shared_sample_with_its_two_priors(sample, tmp_path):
    ds = cfg.load_dataset_manifest("realycbv")
    assert (ds.split, ds.targets_file, ds.camera_file, ds.depth_scale) == ("train_real", "targets_train_real.json",
                                                                           "camera_uw.json", 0.1)
    summary = build_real(sample, tmp_path / "a", ds, progress=False)
    assert (summary["images"], summary["targets"], summary["instances"]) == (21, 91, 91)
    root = tmp_path / "a"
    exact = root / prior_name("gtmask", "realycbv", "train_real")
    faulty = root / prior_name("faulty", "realycbv", "train_real")
    assert exact.read_bytes() == (sample / ds.source_prior).read_bytes()
    bop = BopDataset(root, split="train_real", camera_file="camera_uw.json")
    src = BopDataset(sample / "ycbv", split="train_real", camera_file="camera_uw.json")
    assert bop.depth_path(2, 19).read_bytes() == src.depth_path(2, 19).read_bytes()
    cam = bop.scene_camera(0)[1]
    assert cam.depth_scale == 0.1 and abs(cam.K[0, 0] - 1066.778) < 1e-3  # SOURCE.txt's intrinsics
    # a real frame: the depth under the gelatin box's label is the box at its GT pose
    from pipeline.method.geometry.depth import lift_depth
    from scipy.spatial import cKDTree

    det = next(d for d in load_detections(exact) if (d.scene_id, d.image_id, d.category_id) == (0, 1, 8))
    gt = next(g for g in bop.scene_gt(0)[1] if g.obj_id == 8)
    pts, _ = lift_depth(bop.load_depth(0, 1), cam.K, det.mask())
    model = np.asarray(bop.load_model(8).vertices) @ gt.R.T + gt.t
    near = cKDTree(model).query(pts)[0] < 10.0
    assert near.mean() > 0.8, near.mean()
    # the faulty prior: the stated rates' faults, counted, and the same bytes from the same seed
    dets = load_detections(faulty)
    log = json.loads(faulty.with_suffix(".faults.json").read_text())
    assert len(dets) == log["detections"] == summary["detections"]["faulty"] == 91 - log["missed"] + log["stray"]
    assert log["missed"] > 0 and log["wrong_label"] > 0 and log["stray"] > 0 and log["eroded"] + log["dilated"] > 20
    targets = {(t.scene_id, t.im_id): set() for t in bop.targets(root / ds.targets_file)}
    for t in bop.targets(root / ds.targets_file):
        targets[(t.scene_id, t.im_id)].add(t.obj_id)
    absent = sum(d.category_id not in targets[(d.scene_id, d.image_id)] for d in dets)
    assert absent == log["stray"]
    build_real(sample, tmp_path / "b", ds, progress=False)
    assert (tmp_path / "b" / faulty.relative_to(root)).read_bytes() == faulty.read_bytes()
    assert detector_faults(ds).miss == ds.prior_faults.miss == 0.08


def test_the_two_priors_key_the_scene_side_apart(sample):
    from pipeline.workflow.plan import RunPlan

    rp = RunPlan(cfg.load_run({"datasets": "realycbv"}))
    assert rp.available("realycbv") == (True, "")
    exact, faulty = rp["realycbv"], RunPlan(cfg.load_run({"datasets": "realycbv", "priors": "faulty"}))["realycbv"]
    assert exact.obj_ids == [1, 2, 3, 5, 7, 8, 9, 10, 14, 16, 18, 21]
    assert {s: len(v) for s, v in exact.scene_images.items()} == {0: 7, 1: 7, 2: 7}
    assert exact.prior_path.name == "gtmask_realycbv-train_real.json"
    assert faulty.prior_path.name == "faulty_realycbv-train_real.json"
    assert exact["synth"].key == faulty["synth"].key and exact["model_features"].key == faulty["model_features"].key
    assert exact["segment_prior"].key != faulty["segment_prior"].key
    assert exact["render_templates"].params["look_at"] == "bbox_centre"  # YCB-Video's meshes are not re-centred


def test_datasets_check_passes_on_the_sample_and_names_a_wrong_depth_scale(sample):
    from pipeline.commands.datasets import check_dataset, check_root

    reports, absent = check_root(sample)
    (rep,) = reports
    assert rep.name == "realycbv" and rep.ok, rep.errors
    assert {k: rep.summary[k] for k in ("objects", "scenes", "images", "targets", "detections")} == {
        "objects": 12, "scenes": 3, "images": 21, "targets": 91, "detections": 91}
    assert "ycbv" not in absent  # the folder is the sample's, not YCB-V's test split
    wrong = cfg.load_dataset_manifest("realycbv").model_copy(update={"depth_scale": 1.0})
    rep = check_dataset(sample, wrong, [wrong.source_prior])
    assert any("train_real/000000/scene_camera.json: image 1: field 'depth_scale' is 0.1" in e for e in rep.errors)


def test_a_sample_missing_a_file_fails_and_does_not_skip(sample, tmp_path, monkeypatch):
    from pipeline.workflow.plan import RunPlan

    copy = tmp_path / "shared" / "realdata" / "ycbv-real-train"
    shutil.copytree(sample / "ycbv" / "models", copy / "ycbv" / "models")
    for name in ("targets_train_real.json", "camera_uw.json"):
        shutil.copy2(sample / "ycbv" / name, copy / "ycbv" / name)
    monkeypatch.setenv("FREEZE_SHARED", str(tmp_path / "shared"))
    with pytest.raises(cfg.ManifestError, match=r"gtmask_ycbv-train_real.json: not found in the real sample of "
                                                r"dataset 'realycbv'"):
        RunPlan(cfg.load_run({"datasets": "realycbv"})).available("realycbv")
    monkeypatch.setenv("FREEZE_SHARED", str(tmp_path / "nowhere"))
    ok, why = RunPlan(cfg.load_run({"datasets": "realycbv"})).available("realycbv")
    assert not ok and why.startswith("realycbv: skipped, its real sample")

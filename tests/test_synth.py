"""End-to-end checks of the synthetic BOP dataset generator on the ``tiny`` preset."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from pathlib import Path

import numpy as np
import pytest

from pipeline.formats.bop import BopDataset, load_detections, load_json, read_ply, rle_decode
from pipeline.evaluation.synth import PRESETS, build_object, generate, preset_layout
from pipeline.evaluation.synth.annotate import bbox_from_mask
from pipeline.evaluation.synth.verify import SurfaceProbe, axis_rotation

PRESET = PRESETS["tiny"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("synth") / "tiny"
    summary = generate(root, "tiny", "tiny", seed=3, progress=False)
    return root, summary


@pytest.fixture(scope="module")
def ds(tiny) -> BopDataset:
    return BopDataset(tiny[0])


def _instances(ds: BopDataset):
    for sid in ds.scene_ids():
        gts, infos = ds.scene_gt(sid), ds.scene_gt_info(sid)
        for im in ds.image_ids(sid):
            for k, (gt, info) in enumerate(zip(gts[im], infos[im])):
                yield sid, im, k, gt, info


def test_layout_parses_with_bop_reader(tiny, ds):
    root, summary = tiny
    for rel in ("camera.json", "test_targets_bop19.json", "models/models_info.json", "models_eval/models_info.json",
                "test/000001/scene_camera.json", "test/000001/scene_gt.json", "test/000001/scene_gt_info.json",
                "detections/cnos-synth_tiny-test.json"):
        assert (root / rel).is_file(), rel
    assert not list(root.parent.glob(".tiny*")), "temporary directories left behind"
    cam = ds.camera()
    assert (cam["width"], cam["height"], cam["depth_scale"]) == (640, 480, 0.1)
    assert ds.obj_ids() == sorted(PRESET.obj_ids)
    assert ds.scene_ids() == [1] and ds.image_ids(1) == [0, 1]
    for o in ds.obj_ids():
        model, ev = read_ply(ds.model_path(o)), read_ply(ds.model_path(o, eval=True))
        assert model.colors is not None and model.normals is not None
        assert ev.colors is None
        assert np.allclose(model.vertices.min(0) + model.vertices.max(0), 0, atol=1e-3), "origin not at bbox centre"
    for c in ds.scene_camera(1).values():
        np.testing.assert_allclose(c.K, PRESET.K)
        assert c.depth_scale == 0.1
    n_inst = sum(1 for _ in _instances(ds))
    assert n_inst == summary["instances"] == 2 * 4  # 3 objects + 1 duplicate, in 2 images
    # Targets: per image and object, instances at least 10 % visible.
    expect: dict[tuple, int] = {}
    for sid, im, _, gt, info in _instances(ds):
        if info.visib_fract >= 0.1:
            expect[(sid, im, gt.obj_id)] = expect.get((sid, im, gt.obj_id), 0) + 1
    got = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in ds.targets()}
    assert got == expect
    assert max(got.values()) >= 2, "the duplicate instance should make an inst_count of 2"
    assert summary["targets"] == sum(got.values())
    assert summary["detections"] == len(load_detections(root / "detections/cnos-synth_tiny-test.json"))
    assert preset_layout("tiny", seed=3) == (ds.obj_ids(), ds.scene_ids())


def test_visibility_statistics_match_masks(ds):
    for sid, im, k, gt, info in _instances(ds):
        mask, visib = ds.load_mask(sid, im, k, visib=False), ds.load_mask(sid, im, k, visib=True)
        depth = ds.load_depth(sid, im)
        assert not np.any(visib & ~mask)
        assert info.px_count_all == mask.sum() and info.px_count_visib == visib.sum()
        assert info.px_count_valid == np.sum(mask & (depth > 0))
        assert 0.0 <= info.visib_fract <= 1.0
        assert info.visib_fract == pytest.approx(visib.sum() / max(mask.sum(), 1), abs=1e-9)
        assert tuple(info.bbox_visib) == bbox_from_mask(visib)
        ys, xs = np.nonzero(mask)
        if xs.min() > 0 and ys.min() > 0 and xs.max() < 639 and ys.max() < 479:
            assert tuple(info.bbox_obj) == bbox_from_mask(mask)


def test_gt_pose_rerenders_mask(ds):
    from pipeline.method.render import Renderer

    with Renderer(640, 480) as r:
        for o in ds.obj_ids():
            r.add_mesh(o, ds.load_model(o))
        for sid, im, k, gt, info in _instances(ds):
            K = ds.scene_camera(sid)[im].K
            m = r.render_depth(gt.obj_id, gt.R, gt.t, K) > 0
            ref = ds.load_mask(sid, im, k, visib=False)
            iou = np.sum(m & ref) / max(np.sum(m | ref), 1)
            assert iou > 0.99, (sid, im, k, iou)


def test_depth_agrees_with_gt_within_noise(ds):
    from pipeline.method.render import Renderer

    sigma_k = PRESET.sensor.noise_k
    with Renderer(640, 480) as r:
        for o in ds.obj_ids():
            r.add_mesh(o, ds.load_model(o))
        for sid, im, k, gt, info in _instances(ds):
            visib = ds.load_mask(sid, im, k, visib=True)
            if visib.sum() < 200:
                continue
            depth = ds.load_depth(sid, im)
            ref = r.render_depth(gt.obj_id, gt.R, gt.t, ds.scene_camera(sid)[im].K)
            sel = visib & (depth > 0)
            assert sel.sum() > 0.6 * visib.sum(), "too much missing depth on the object"
            diff = depth[sel] - ref[sel]
            sigma = sigma_k * ref[sel] ** 2
            # 5 sigma, plus the 0.05 mm rounding to depth_scale and the renderer's 0.5 mm.
            assert np.all(np.abs(diff) < 5 * sigma + 0.6)
            assert abs(np.median(diff)) < 0.3
            assert np.std(diff / sigma) == pytest.approx(1.0, abs=0.25)


def test_declared_symmetries_hold_on_models_eval(ds):
    info = ds.models_info()
    for o in ds.obj_ids():
        model = ds.load_model(o)
        probe = SurfaceProbe(model)
        ev = read_ply(ds.model_path(o, eval=True)).vertices.astype(np.float64)
        transforms = list(info[o].symmetries_discrete)
        for s in info[o].symmetries_continuous:
            transforms += [axis_rotation(s["axis"], s["offset"], a) for a in (0.4, 2.0, np.pi)]
        built = build_object(o)
        assert len(info[o].symmetries_discrete) == len(built.symmetries_discrete)
        assert len(info[o].symmetries_continuous) == len(built.symmetries_continuous)
        for T in transforms:
            fwd = probe.closest(ev @ T[:3, :3].T + T[:3, 3])[0]
            Ti = np.linalg.inv(T)
            bwd = probe.closest(ev @ Ti[:3, :3].T + Ti[:3, 3])[0]
            chamfer = 0.5 * (fwd.mean() + bwd.mean())
            assert chamfer < 0.02 and max(fwd.max(), bwd.max()) < 0.1, (o, chamfer)
    # The tiny set holds an asymmetric can, a discrete nut (12) and a continuous cup.
    assert not info[2].is_symmetric
    assert len(info[5].symmetries_discrete) == 11 and not info[5].symmetries_continuous
    assert len(info[6].symmetries_continuous) == 1 and not info[6].symmetries_discrete


@pytest.mark.slow
def test_same_seed_same_bytes(tiny, tmp_path):
    root = tiny[0]
    again = generate(tmp_path / "again", "tiny", "tiny", seed=3, progress=False)
    assert {k: v for k, v in again.items() if k != "seconds"} == {k: v for k, v in tiny[1].items() if k != "seconds"}
    for rel in ("test/000001/scene_gt.json", "test/000001/scene_gt_info.json", "test/000001/rgb/000001.png",
                "test/000001/depth/000000.png", "test/000001/mask_visib/000001_000002.png", "models/obj_000002.ply",
                "detections/cnos-synth_tiny-test.json", "test_targets_bop19.json"):
        assert (root / rel).read_bytes() == (tmp_path / "again" / rel).read_bytes(), rel
    other = tmp_path / "other"
    generate(other, "tiny", "tiny", seed=4, progress=False)
    assert (root / "test/000001/scene_gt.json").read_bytes() != (other / "test/000001/scene_gt.json").read_bytes()
    # The objects are fixed designs, independent of the seed.
    assert (root / "models/obj_000005.ply").read_bytes() == (other / "models/obj_000005.ply").read_bytes()


def test_detections_decode_and_match_masks(tiny, ds):
    dets = load_detections(tiny[0] / "detections/cnos-synth_tiny-test.json")
    raw = load_json(tiny[0] / "detections/cnos-synth_tiny-test.json")
    assert all(isinstance(d["segmentation"]["counts"], list) for d in raw), "expected uncompressed RLE"
    times: dict[tuple, set] = {}
    gt_masks = {(sid, im, k): (gt.obj_id, ds.load_mask(sid, im, k)) for sid, im, k, gt, _ in _instances(ds)}
    matched = set()
    for d in dets:
        m = rle_decode(d.segmentation)
        assert m.shape == (480, 640) and m.any()
        x, y, w, h = bbox_from_mask(m)
        assert tuple(d.bbox) == (x, y, w, h)
        assert 0 < d.score < 1
        times.setdefault((d.scene_id, d.image_id), set()).add(d.time)
        best, key = 0.0, None
        for (sid, im, k), (obj_id, gm) in gt_masks.items():
            if (sid, im) != (d.scene_id, d.image_id) or obj_id != d.category_id:
                continue
            iou = np.sum(m & gm) / np.sum(m | gm)
            if iou > best:
                best, key = iou, (sid, im, k)
        if best > 0.7:  # a true positive: its box hugs the visible mask's box
            matched.add(key)
            assert np.max(np.abs(np.subtract(d.bbox, bbox_from_mask(gt_masks[key][1])))) <= 8
    assert all(len(v) == 1 and 0.1 < next(iter(v)) < 1.0 for v in times.values()), "one run time per image"
    visible = [key for key in gt_masks if ds.scene_gt_info(key[0])[key[1]][key[2]].visib_fract >= 0.3]
    assert len(set(visible) & matched) >= 0.75 * len(visible)


def test_refuses_to_overwrite_and_cleans_up_on_failure(tmp_path, monkeypatch):
    import pipeline.evaluation.synth.writer as gen

    out = tmp_path / "ds"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError):
        generate(out, "tiny", "tiny", progress=False)

    def boom(*args, **kwargs):
        raise RuntimeError("killed mid-run")

    monkeypatch.setattr(gen, "_write_scene", boom)
    with pytest.raises(RuntimeError, match="killed"):
        generate(tmp_path / "fresh", "tiny", "tiny", progress=False)
    assert not (tmp_path / "fresh").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"], "partial directory left behind"
    with pytest.raises(ValueError, match="_"):
        generate(tmp_path / "x", "my_set", "tiny", progress=False)


def test_models_are_centred_on_their_bounding_box(ds):
    """render_templates looks at each model's bounding-box centre; for the synthetic
    objects that is exactly the origin (in the written PLY's float32 too), which is why
    their template keys did not change when that rule came (pipeline/workflow/plan.py, _look_at)."""
    from pipeline.method.render.templates import bbox_centre
    from pipeline.evaluation.synth.objects import OBJ_IDS

    for obj_id in OBJ_IDS:
        v = np.asarray(build_object(obj_id).model.vertices).astype(np.float32)
        assert np.array_equal(0.5 * (v.min(axis=0) + v.max(axis=0)), np.zeros(3, np.float32)), obj_id
    for obj_id in ds.obj_ids():
        assert np.array_equal(bbox_centre(ds.load_model(obj_id)), np.zeros(3)), obj_id

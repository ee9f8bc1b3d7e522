"""Unit checks of the synthetic generator's parts: meshes, objects, sensor, layout, prior."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation.synth import OBJ_IDS, PRESETS, build_object, compose_scenes
from pipeline.evaluation.synth.annotate import bbox_from_mask, projected_bbox, silhouette_bbox
from pipeline.evaluation.synth.meshkit import (
    box_patches,
    circle,
    concatenate,
    extrude_patches,
    merged_mesh,
    resample_loop,
    signed_area,
    triangulate_region,
)
from pipeline.evaluation.synth.objects import physics_mesh, rot
from pipeline.evaluation.synth.priors import PriorFaults, VisibleInstance, image_detections
from pipeline.evaluation.synth.scene import _footprint, _separated, kelvin_to_rgb, layout_objects, look_at, project, resting_poses
from pipeline.evaluation.synth.sensor import DepthSensor, simulate_depth
from pipeline.evaluation.synth.verify import SurfaceProbe, axis_rotation, symmetry_residual

K = PRESETS["mini"].K


# ---------------------------------------------------------------------------- meshes


def test_triangulated_region_keeps_boundary_and_area():
    outer = resample_loop(np.array([[0, 0], [50, 0], [50, 30], [20, 30], [20, 60], [0, 60]], float), 2.0)
    hole = resample_loop(circle(6.0, 24, (10, 12)), 2.0)[::-1]
    pts, faces = triangulate_region(outer, [hole], 2.0)
    np.testing.assert_array_equal(pts[: len(outer)], outer)
    p = pts[faces]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    assert np.all(area > 0), "triangles must be counter-clockwise"
    expected = signed_area(outer) + signed_area(hole)  # the hole loop is clockwise
    assert area.sum() == pytest.approx(expected, rel=1e-9)
    edges = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    assert np.median(edges) == pytest.approx(2.0, rel=0.2)


def test_box_and_prism_are_closed_with_exact_volume():
    v, f, _ = concatenate(list(box_patches((30.0, 20.0, 10.0), 2.0).values()))
    box = merged_mesh(v, f)
    assert box.is_watertight and box.volume == pytest.approx(6000.0, rel=1e-9)
    parts = extrude_patches(np.array([[0, 0], [40, 0], [40, 10], [0, 10]], float), [], 0.0, 5.0, 2.0)
    v, f, _ = concatenate([p for ps in parts.values() for p in ps])
    prism = merged_mesh(v, f)
    assert prism.is_watertight and prism.volume == pytest.approx(2000.0, rel=1e-9)


@pytest.mark.parametrize("obj_id", OBJ_IDS)
def test_object_is_a_valid_bop_model(obj_id):
    obj = build_object(obj_id)
    v = np.asarray(obj.model.vertices)
    assert np.allclose(v.min(0) + v.max(0), 0.0, atol=1e-9), "origin must be the bbox centre"
    assert 40.0 <= obj.diameter <= 200.0
    assert len(obj.model.faces) <= 60_000
    assert physics_mesh(obj).is_watertight and obj.eval_mesh.is_watertight
    assert physics_mesh(obj).volume > 0, "faces must point outwards"
    ev = np.asarray(obj.eval_mesh.vertices)
    assert len(ev) < len(v)
    # Eval vertices lie on the model's surface and cover it evenly.
    probe = SurfaceProbe(obj.model)
    assert probe.closest(ev)[0].max() < 0.1
    pts, _ = probe.sample(3000, seed=0)
    from scipy.spatial import cKDTree

    gap = cKDTree(ev).query(pts)[0]
    assert gap.max() < 1.5 * obj.eval_spacing
    info = obj.model_info()
    assert info.diameter == pytest.approx(obj.diameter)
    np.testing.assert_allclose(info.size_xyz, v.max(0) - v.min(0))


CANDIDATES = [rot(a, d) for a in "xyz" for d in (90, 180, 270)] + [rot("z", 60), rot("z", 120), rot("z", 37)]


@pytest.mark.parametrize("obj_id", OBJ_IDS)
def test_declared_symmetries_are_exactly_the_true_ones(obj_id):
    """Declared transforms keep shape and colour; undeclared candidates break one of them."""
    obj = build_object(obj_id)
    probe = SurfaceProbe(obj.model)
    pts, col = probe.sample(3000, seed=1)
    declared = list(obj.symmetries_discrete)
    for s in obj.symmetries_continuous:
        declared += [axis_rotation(s["axis"], s["offset"], a) for a in (0.5, 1.9, np.pi)]
    for T in declared:
        r = symmetry_residual(probe, T, pts, col)
        assert r.geom_max < 0.1 and r.color_mean < 1.0, (obj.name, r)

    def is_declared(T: np.ndarray) -> bool:
        if any(np.allclose(T, S, atol=1e-9) for S in obj.symmetries_discrete):
            return True
        for s in obj.symmetries_continuous:
            a = np.asarray(s["axis"], float)
            for flip in [np.eye(4)] + list(obj.symmetries_discrete):
                R = (np.linalg.inv(flip) @ T)[:3, :3]
                if np.allclose(R @ a, a, atol=1e-9):
                    return True
        return False

    for T in CANDIDATES:
        r = symmetry_residual(probe, T, pts, col)
        truly = r.geom_mean < 0.05 and r.color_mean < 2.0
        assert truly == is_declared(T), (obj.name, np.round(T, 3).tolist(), r)


def test_object_kinds_cover_bop():
    objs = {o: build_object(o) for o in OBJ_IDS}
    nut, cup, spool, can = objs[5], objs[6], objs[7], objs[2]
    assert len(nut.symmetries_discrete) == 11 and not nut.symmetries_continuous
    assert len(cup.symmetries_continuous) == 1 and not cup.symmetries_discrete
    assert len(spool.symmetries_continuous) == 1 and len(spool.symmetries_discrete) == 1
    assert not can.symmetries_discrete and not can.symmetries_continuous
    # Texture-rich objects have many distinct colours, texture-less ones one.
    n_colours = {o: len(np.unique(np.asarray(obj.model.visual.vertex_colors)[:, :3], axis=0)) for o, obj in objs.items()}
    assert n_colours[1] > 200 and n_colours[2] > 200
    assert n_colours[3] == 1 and n_colours[4] == 1 and n_colours[5] == 1


# ---------------------------------------------------------------------------- sensor


def test_depth_noise_grows_with_square_of_depth():
    sensor = DepthSensor(edge_drop_prob=0.0, grazing_cos=0.0, dropout_fraction=0.0)
    for z in (600.0, 1000.0):
        d = simulate_depth(np.full((240, 320), z, np.float32), K, np.random.default_rng(0), sensor)
        assert np.all(d > 0)
        assert np.std(d - z) == pytest.approx(1.5e-3 * z**2 / 1000, rel=0.05)
        assert abs(np.mean(d - z)) < 0.02


def test_projector_shadow_and_edges_remove_depth():
    clean = np.full((480, 640), 1000.0, np.float32)
    clean[200:280, 300:340] = 700.0  # a box 300 mm in front of a wall
    sensor = DepthSensor(noise_k=0.0, edge_drop_prob=0.0, grazing_cos=0.0, dropout_fraction=0.0)
    d = simulate_depth(clean, K, np.random.default_rng(0), sensor)
    shadow = K[0, 0] * 75.0 * (1 / 700 - 1 / 1000)  # 18.4 px left of the box
    assert np.all(d[205:275, int(300 - shadow) + 1 : 300] == 0)
    assert np.all(d[205:275, int(300 - shadow) - 4 : int(300 - shadow) - 1] > 0)
    assert np.all(d[205:275, 341:400] > 0) and np.all(d[200:280, 300:340] > 0)
    np.testing.assert_array_equal(d[d > 0], clean[d > 0])
    edgy = simulate_depth(clean, K, np.random.default_rng(0), DepthSensor(noise_k=0.0, edge_drop_prob=1.0, grazing_cos=0.0, dropout_fraction=0.0))
    assert np.all(edgy[210:270, [339, 340]] == 0) and np.all(edgy[210:270, [337, 342]] > 0)
    far = simulate_depth(np.full((10, 10), 4000.0, np.float32), K, np.random.default_rng(0))
    assert np.all(far == 0), "beyond the working range"


# ---------------------------------------------------------------------------- scene


def test_layout_rests_objects_without_overlap():
    ids = [1, 2, 5, 6, 8, 8]
    objs = {o: build_object(o) for o in set(ids)}
    poses = {o: resting_poses(objs[o]) for o in objs}
    placed = layout_objects(ids, poses, np.random.default_rng(5))
    assert [p.key for p in placed] == ids
    prints = []
    for p in placed:
        np.testing.assert_allclose(p.R @ p.R.T, np.eye(3), atol=1e-9)
        v = np.asarray(objs[p.key].model.vertices) @ p.R.T + p.t
        assert v[:, 2].min() == pytest.approx(0.0, abs=1e-6), "object must touch the table"
        prints.append(_footprint(poses[p.key].hull, p.R, p.t))
    for i in range(len(prints)):
        for j in range(i):
            assert _separated(prints[i], prints[j], 2.9)


def test_resting_poses_are_stable_faces():
    obj = build_object(6)  # cup: upright, upside down, or on its side
    rp = resting_poses(obj)
    assert rp.probs.sum() == pytest.approx(1.0)
    ups = [(R @ np.array([0, 0, 1.0]))[2] for R in rp.rotations]
    assert max(ups) > 0.99 or min(ups) < -0.99


def test_camera_looks_at_target_and_projects_boxes():
    eye, target = np.array([500.0, -300.0, 600.0]), np.array([10.0, 20.0, 30.0])
    R, t = look_at(eye, target, roll=0.1)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    uv = project((R @ target + t)[None], K)[0]
    np.testing.assert_allclose(uv, K[:2, 2], atol=1e-9)
    assert (R @ target + t)[2] == pytest.approx(np.linalg.norm(target - eye))
    # Image "down" points roughly down the world z axis.
    assert (R.T @ np.array([0, 1.0, 0]))[2] < 0
    verts = np.array([[-10, -10, 0], [10, 10, 0], [0, 0, 5.0]])
    x, y, w, h = projected_bbox(verts, np.eye(3), np.array([0, 0, 500.0]), K)
    assert (x, x + w) == (int(np.ceil(K[0, 2] - K[0, 0] * 10 / 500)), int(np.floor(K[0, 2] + K[0, 0] * 10 / 500)))
    assert (y, y + h) == (int(np.ceil(K[1, 2] - K[1, 1] * 10 / 500)), int(np.floor(K[1, 2] + K[1, 1] * 10 / 500)))


def test_bbox_obj_extends_past_the_image_only_where_cut():
    mask = np.zeros((480, 640), bool)
    mask[100:150, 0:40] = True  # cut by the left border
    assert silhouette_bbox(mask, (-25, 101, 64, 48)) == (-25, 100, 64, 49)
    mask[:] = False
    mask[100:150, 200:240] = True  # inside: the raster wins over a 1 px projection tie
    assert silhouette_bbox(mask, (200, 100, 40, 49)) == (200, 100, 39, 49)


def test_lights_and_colour_temperature():
    warm, cold = kelvin_to_rgb(2700), kelvin_to_rgb(7500)
    assert warm[0] > warm[2] and cold[2] > cold[0] - 0.2
    np.testing.assert_allclose(kelvin_to_rgb(6500), [1.0, 249 / 255, 253 / 255])


@pytest.mark.parametrize("name", ["mini", "bench"])
def test_every_object_appears(name):
    preset = PRESETS[name]
    for seed in range(5):
        scenes = compose_scenes(preset, np.random.default_rng([seed, 0]))
        assert len(scenes) == preset.n_scenes
        assert set().union(*map(set, scenes)) == set(preset.obj_ids)
        lo, hi = preset.objects_per_scene
        assert all(lo <= len(set(s)) <= hi for s in scenes)


# ---------------------------------------------------------------------------- prior


def test_prior_has_realistic_faults():
    rng = np.random.default_rng(0)
    faults = PriorFaults()
    n_img, per_img = 40, 6
    n_true = tp = fp = extra = 0
    scores_tp, scores_fp = [], []
    for im in range(n_img):
        table = np.ones((480, 640), bool)
        insts = []
        for k in range(per_img):
            m = np.zeros((480, 640), bool)
            cx, cy = 60 + 100 * k, 100 + 50 * (im % 5)
            m[cy - 30 : cy + 30, cx - 25 : cx + 25] = True
            table &= ~m
            insts.append(VisibleInstance(obj_id=k + 1, mask_visib=m, visib_fract=1.0))
        dets = image_detections(1, im, insts, table, list(range(1, 11)), rng, faults)
        assert len({d.time for d in dets}) <= 1
        assert [d.score for d in dets] == sorted((d.score for d in dets), reverse=True)
        n_true += per_img
        seen = set()
        for d in dets:
            m = d.mask()
            assert tuple(d.bbox) == bbox_from_mask(m)
            ious = [np.sum(m & i.mask_visib) / np.sum(m | i.mask_visib) for i in insts]
            j = int(np.argmax(ious))
            if ious[j] > 0.75 and insts[j].obj_id == d.category_id and j not in seen:
                tp += 1
                seen.add(j)
                scores_tp.append(d.score)
            elif ious[j] > 0.2 and insts[j].obj_id == d.category_id:
                extra += 1  # fragment or duplicate
            else:
                fp += 1
                scores_fp.append(d.score)
    miss = 1 - tp / n_true
    assert 0.01 <= miss <= 0.09
    assert 5 <= extra <= 60
    assert 15 <= fp <= 60
    assert np.mean(scores_tp) > 0.7 and np.mean(scores_fp) < 0.45

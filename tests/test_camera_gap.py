"""The camera-gap model of the `hard` preset (pipeline/evaluation/synth/camera_gap.py): known answers
for each departure, and a generated dataset that departs from the plain one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from pipeline.evaluation.synth.camera_gap import CameraGap, camera_rgb, depth_normals, drift_colours, surface_holes

K = np.array([[500.0, 0.0, 31.5], [0.0, 500.0, 23.5], [0.0, 0.0, 1.0]])
NEUTRAL = CameraGap(colour_drift=0.0, colour_offset=0.0, white_balance=(1.0, 1.0), exposure=(1.0, 1.0),
                    gamma=(1.0, 1.0), blur_sigma=(0.01, 0.01), vignetting=(0.0, 0.0), noise_sigma=(0.0, 0.0),
                    specular=(0.0, 0.0))


def test_colour_drift_moves_colours_and_keeps_the_shape():
    mesh = trimesh.creation.box(extents=(50, 60, 70))
    mesh.visual.vertex_colors = np.tile([100, 150, 200, 255], (len(mesh.vertices), 1))
    rng = np.random.default_rng(0)
    same = drift_colours(mesh, rng, NEUTRAL)
    assert np.array_equal(same.visual.vertex_colors, mesh.visual.vertex_colors)
    shifted = drift_colours(mesh, np.random.default_rng(0), dataclasses.replace(NEUTRAL, colour_offset=20.0))
    assert np.array_equal(shifted.vertices, mesh.vertices)
    delta = shifted.visual.vertex_colors[:, :3].astype(int) - mesh.visual.vertex_colors[:, :3].astype(int)
    assert (delta == delta[0]).all() and np.abs(delta[0]).max() > 5  # one offset for the whole object
    assert np.array_equal(mesh.visual.vertex_colors[0], [100, 150, 200, 255])  # the model is left as it was


def test_neutral_camera_keeps_the_image_and_exposure_scales_it():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 120, (48, 64, 3)).astype(np.uint8)
    depth = np.full((48, 64), 800.0, np.float32)
    objects = np.zeros((48, 64), bool)
    out, highlight = camera_rgb(rgb, depth, objects, K, rng, NEUTRAL)
    assert np.abs(out.astype(int) - rgb).max() <= 1 and not highlight.any()
    brighter, _ = camera_rgb(rgb, depth, objects, K, rng, dataclasses.replace(NEUTRAL, exposure=(2.0, 2.0)))
    assert np.abs(brighter.astype(int) - np.clip(2 * rgb.astype(int), 0, 255)).max() <= 2


def test_normals_of_a_tilted_plane_and_highlights_on_objects_only():
    h, w = 48, 64
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    # the plane z = 800 + 0.5 y (mm), seen by the camera: its normal is (0, -0.5, 1) up to sign
    z = 800.0 / (1.0 - 0.5 * (v - K[1, 2]) / K[1, 1])
    n = depth_normals(z, K)
    expected = np.array([0.0, 0.5, -1.0]) / np.linalg.norm([0.0, 0.5, -1.0])  # towards the camera
    assert np.abs(n[5:-5, 5:-5] - expected).max() < 1e-3
    objects = np.zeros((h, w), bool)
    objects[:, : w // 2] = True
    gap = dataclasses.replace(NEUTRAL, specular=(200.0, 200.0), shininess=(1.0, 1.0))
    out, highlight = camera_rgb(np.full((h, w, 3), 50, np.uint8), z.astype(np.float32), objects, K,
                                np.random.default_rng(2), gap)
    assert (highlight[:, w // 2:] == 0).all() and (highlight[:, : w // 2] > 0).all()
    assert out[:, : w // 2].mean() > out[:, w // 2:].mean() + 20


def test_holes_on_dark_and_shiny_object_surfaces():
    rgb = np.full((10, 10, 3), 200, np.uint8)
    rgb[:, :5] = 10  # dark half
    highlight = np.zeros((10, 10), np.float32)
    highlight[0, 9] = 100.0  # one shiny pixel
    objects = np.ones((10, 10), bool)
    objects[9] = False
    gap = dataclasses.replace(NEUTRAL, dark_hole_prob=1.0)
    holes = surface_holes(rgb, highlight, objects, np.random.default_rng(0), gap)
    assert holes[:9, :5].all() and not holes[9].any() and holes[0, 9] and holes[1:9, 5:].sum() == 0


@pytest.mark.slow
def test_a_generated_hard_dataset_departs_from_the_plain_one(tmp_path):
    from pipeline.formats.bop import BopDataset
    from pipeline.evaluation.synth import PRESETS, SynthPreset, generate

    tiny = PRESETS["tiny"]
    hard = dataclasses.replace(tiny, name="tinyhard", camera_gap=CameraGap(), sensor=PRESETS["hard"].sensor)
    assert isinstance(hard, SynthPreset)
    generate(tmp_path / "plain", "plain", tiny, seed=1, progress=False)
    generate(tmp_path / "hard", "hard", hard, seed=1, progress=False)
    plain, gapped = BopDataset(tmp_path / "plain"), BopDataset(tmp_path / "hard")
    # the same scenes and ground truth; other pixels and more depth holes on the objects
    assert plain.scene_gt(1)[0][0].obj_id == gapped.scene_gt(1)[0][0].obj_id
    assert np.allclose(plain.scene_gt(1)[0][0].t, gapped.scene_gt(1)[0][0].t)
    a, b = plain.load_rgb(1, 0).astype(int), gapped.load_rgb(1, 0).astype(int)
    assert np.abs(a - b).mean() > 10
    masks = [plain.load_mask(1, 0, k) for k in range(len(plain.scene_gt(1)[0]))]
    on = np.any(masks, axis=0)
    assert (gapped.load_depth(1, 0)[on] == 0).mean() > (plain.load_depth(1, 0)[on] == 0).mean()

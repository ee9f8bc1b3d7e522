"""Known-answer tests of pipeline.method.geometry: transforms, sampling, depth, normals."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.method.geometry.depth import lift_depth, project, remove_outliers
from pipeline.method.geometry.normals import estimate_normals
from pipeline.method.geometry.sampling import (
    farthest_point_subsample,
    sample_points,
    sample_surface,
    voxel_subsample,
)
from pipeline.method.geometry.transforms import (
    invert,
    look_at_rotation,
    matrix_to_rt,
    perturb_pose,
    rotation_about_axis,
    rotation_angle_deg,
    rt_to_matrix,
)
from pose_helpers import compose, random_rotation, transform_points

K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])


# --- transforms -------------------------------------------------------------------

def test_compose_invert_round_trip():
    rng = np.random.default_rng(0)
    R1, t1 = random_rotation(rng), rng.normal(size=3) * 100
    R2, t2 = random_rotation(rng), rng.normal(size=3) * 100
    pts = rng.normal(size=(20, 3))
    R12, t12 = compose(R1, t1, R2, t2)
    np.testing.assert_allclose(transform_points(pts, R12, t12),
                               transform_points(transform_points(pts, R1, t1), R2, t2), atol=1e-9)
    Ri, ti = invert(R1, t1)
    np.testing.assert_allclose(transform_points(transform_points(pts, R1, t1), Ri, ti), pts, atol=1e-9)
    T = rt_to_matrix(R1, t1)
    R, t = matrix_to_rt(T)
    np.testing.assert_array_equal(R, R1)
    np.testing.assert_array_equal(t, t1)
    np.testing.assert_allclose(np.linalg.inv(T), rt_to_matrix(Ri, ti), atol=1e-12)


def test_rotation_about_axis_known_matrices():
    # A quarter turn about z takes x to y; about a scaled axis the same as about the unit one.
    np.testing.assert_allclose(rotation_about_axis([0, 0, 5], 90.0), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(rotation_about_axis([1, 1, 1], 120.0) @ [1.0, 0, 0], [0, 1, 0], atol=1e-15)
    rng = np.random.default_rng(3)
    for _ in range(20):
        axis, angle = rng.normal(size=3), float(rng.uniform(-360, 360))
        R = rotation_about_axis(axis, angle)
        np.testing.assert_allclose(R @ axis, axis, atol=1e-12)  # the axis stays put
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        assert rotation_angle_deg(np.eye(3), R) == pytest.approx(abs((angle + 180) % 360 - 180), abs=1e-9)
    with pytest.raises(ValueError, match="non-zero"):
        rotation_about_axis([0, 0, 0], 10.0)


def test_rotation_angle_known_values():
    assert rotation_angle_deg(np.eye(3), rotation_about_axis([0, 0, 1], 30.0)) == pytest.approx(30.0)
    assert rotation_angle_deg(np.eye(3), rotation_about_axis([1, 1, 0], 180.0)) == pytest.approx(180.0)
    R = random_rotation(1)
    assert rotation_angle_deg(R, R) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_perturb_pose_is_exact():
    R, t = random_rotation(3), np.array([10.0, -5.0, 600.0])
    Rp, tp = perturb_pose(R, t, 5.0, 10.0, rng=4)
    assert rotation_angle_deg(R, Rp) == pytest.approx(5.0)
    assert np.linalg.norm(tp - t) == pytest.approx(10.0)


def test_look_at_rotation_centres_origin():
    for cam in ([0, 0, 500.0], [300.0, -200.0, 100.0], [0, -400.0, 0]):
        R = look_at_rotation(np.array(cam))
        t = -R @ np.array(cam)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # The model origin lies on the optical axis at the camera distance.
        np.testing.assert_allclose(t, [0, 0, np.linalg.norm(cam)], atol=1e-9)


# --- sampling ---------------------------------------------------------------------

def test_sample_surface_uniform_seeded_with_outward_normals():
    box = trimesh.creation.box((200.0, 100.0, 10.0))
    p1, n1 = sample_surface(box, 20000, seed=7)
    p2, n2 = sample_surface(box, 20000, seed=7)
    assert p1.dtype == np.float32 and n1.dtype == np.float32 and p1.shape == (20000, 3)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(n1, n2)
    # Uniform over area: the two 200x100 faces hold 40000/46000 of the area.
    on_big = np.abs(np.abs(p1[:, 2]) - 5.0) < 1e-3
    assert on_big.mean() == pytest.approx(40000 / 46000, abs=0.01)
    # Outward: normals point away from the centre.
    assert np.all(np.sum(p1 * n1, axis=1) > 0)
    np.testing.assert_allclose(np.linalg.norm(n1, axis=1), 1.0, atol=1e-6)


def test_farthest_point_subsample_spreads_points():
    rng = np.random.default_rng(0)
    # Dense cluster plus a sparse halo: FPS must reach the halo, random sampling mostly not.
    pts = np.concatenate([rng.normal(size=(5000, 3)), rng.normal(size=(50, 3)) * 50])
    idx = farthest_point_subsample(pts, 60, seed=1)
    assert len(np.unique(idx)) == 60
    assert np.sum(idx >= 5000) >= 45
    np.testing.assert_array_equal(idx, farthest_point_subsample(pts, 60, seed=1))


def test_voxel_subsample_one_point_per_voxel():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, size=(5000, 3))
    idx = voxel_subsample(pts, 25.0)
    cells = np.floor(pts[idx] / 25.0).astype(int)
    assert len(idx) == 64
    assert len(np.unique(cells, axis=0)) == 64


def test_sample_points_sizes_and_padding():
    pts = np.zeros((10, 3))
    idx = sample_points(pts, 25, seed=0)
    assert idx.shape == (25,)
    assert set(range(10)) <= set(idx.tolist())
    assert sample_points(pts, 25, seed=0, pad=False).shape == (10,)
    big = np.random.default_rng(0).normal(size=(3000, 3))
    a = sample_points(big, 1000, seed=5)
    assert len(np.unique(a)) == 1000
    np.testing.assert_array_equal(a, sample_points(big, 1000, seed=5))
    assert len(np.unique(sample_points(big, 100, seed=5, method="fps"))) == 100
    with pytest.raises(ValueError, match="unknown method"):
        sample_points(big, 10, seed=0, method="bogus")


# --- depth ------------------------------------------------------------------------

def test_lift_project_round_trip_exact():
    rng = np.random.default_rng(0)
    depth = rng.uniform(300, 1500, size=(48, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0
    mask = np.ones_like(depth, dtype=bool)
    mask[:, :5] = False
    pts, pix = lift_depth(depth, K, mask)
    assert pts.dtype == np.float32 and pix.dtype == np.int64
    assert len(pts) == np.count_nonzero((depth > 0) & mask)
    np.testing.assert_allclose(project(pts, K), pix, atol=1e-3)
    np.testing.assert_array_equal(pts[:, 2], depth[pix[:, 1], pix[:, 0]])


def test_lift_depth_known_point_and_skew():
    depth = np.zeros((5, 5), np.float32)
    depth[2, 3] = 1000.0
    Ks = np.array([[500.0, 2.0, 1.0], [0.0, 400.0, 2.0], [0, 0, 1]])
    pts, pix = lift_depth(depth, Ks)
    np.testing.assert_array_equal(pix, [[3, 2]])
    # v = cy -> y = 0; u - cx = 2 px at fx = 500 and z = 1000 -> x = 4 mm.
    np.testing.assert_allclose(pts, [[4.0, 0.0, 1000.0]], atol=1e-4)
    depth[4, 0] = 500.0
    pts, pix = lift_depth(depth, Ks)
    np.testing.assert_allclose(project(pts, Ks), pix, atol=1e-6)


def test_lift_depth_rejects_bad_shapes():
    with pytest.raises(ValueError, match="mask shape"):
        lift_depth(np.ones((4, 4)), K, np.ones((4, 5), bool))
    with pytest.raises(ValueError, match="K must be"):
        lift_depth(np.ones((4, 4)), np.eye(4))


def test_remove_outliers_drops_mask_bleed():
    rng = np.random.default_rng(0)
    diameter = 100.0
    # Visible half of a sphere surface (radius 50 mm), as lifted from a depth image.
    d = rng.normal(size=(2000, 3))
    d[:, 2] = -np.abs(d[:, 2])
    obj = 50 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0, 0, 600]
    far = rng.normal(size=(150, 3)) * 5 + [0, 0, 900]  # background 300 mm behind
    near = rng.normal(size=(40, 3)) * 3 + [75, 0, 530]  # a separate occluder blob
    stray = np.array([[0, 0, 640.0 + 200]])
    pts = np.concatenate([obj, far, near, stray])
    keep = remove_outliers(pts, diameter)
    assert keep[:2000].mean() > 0.98
    assert not keep[2000:].any()


# --- normals ----------------------------------------------------------------------

def test_estimate_normals_oriented_towards_camera():
    # A tilted plane seen from the origin: normals are +-(0, sin, -cos); towards the
    # camera means a negative z component.
    rng = np.random.default_rng(0)
    xy = rng.uniform(-50, 50, size=(2000, 2))
    a = np.radians(20)
    pts = np.stack([xy[:, 0], xy[:, 1] * np.cos(a), 600 + xy[:, 1] * np.sin(a)], axis=1)
    n = estimate_normals(pts, 10.0, viewpoint=np.zeros(3))
    np.testing.assert_allclose(n, np.tile([0, np.sin(a), -np.cos(a)], (2000, 1)), atol=1e-4)
    # Closed sphere without viewpoint: outward.
    s = rng.normal(size=(3000, 3))
    s = 50 * s / np.linalg.norm(s, axis=1, keepdims=True)
    ns = estimate_normals(s, 10.0)
    assert np.all(np.sum(ns * s, axis=1) / 50 > 0.95)

"""Unit and property tests of the BOP19 metric building blocks (rendering only in the crop-renderer test)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.evaluation.metrics import (
    VSD_TAUS,
    Crop,
    depth_to_distance,
    greedy_match,
    mspd,
    mssd,
    project,
    sphere_projections_overlap,
    symmetry_transformations,
    valid_gt_mask,
    vsd,
    vsd_crops,
    vsd_from_distances,
)
from pipeline.evaluation.metrics.evaluate import visib_bin
from pipeline.evaluation.metrics.pose_errors import hull_indices, probe_indices

K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
RX180 = np.diag([1.0, -1.0, -1.0, 1.0])


def _cylinder(r: float = 35.0, h: float = 120.0, n: int = 48) -> np.ndarray:
    """Rim vertices (2n, 3) mm of a cylinder about z, centred at the origin."""
    a = np.arange(n) * 2 * np.pi / n
    ring = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    return np.concatenate([np.c_[ring, np.full(n, -h / 2)], np.c_[ring, np.full(n, h / 2)]])


def _box(sx: float = 100.0, sy: float = 70.0, sz: float = 50.0) -> np.ndarray:
    g = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3)
    return g * np.array([sx, sy, sz]) / 2


def _brute(pts, syms, err):
    """min over symmetries of max over points, with plain loops (the definition)."""
    best = math.inf
    for R_s, t_s in zip(*syms):
        best = min(best, max(err(p, R_s, t_s) for p in pts))
    return best


# ---------------------------------------------------------------------------- symmetries


def test_symmetries_discrete_only() -> None:
    Rs, ts = symmetry_transformations([RX180.ravel().tolist()], None)
    assert Rs.shape == (2, 3, 3) and ts.shape == (2, 3)
    np.testing.assert_array_equal(Rs[0], np.eye(3))
    np.testing.assert_array_equal(Rs[1], RX180[:3, :3])


def test_symmetries_continuous_discretisation_matches_bop() -> None:
    offset = np.array([0.0, 0.0, 5.0])
    Rs, ts = symmetry_transformations([RX180], [{"axis": [0, 0, 2], "offset": offset}], 0.01)
    n = math.ceil(math.pi / 0.01)  # 315 samples per turn, identity included
    assert len(Rs) == 2 * n
    np.testing.assert_allclose(Rs[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(ts[0], 0, atol=1e-12)
    # Sample i turns by i * 2pi / n about z, through the offset point.
    np.testing.assert_allclose(Rs[7], Rotation.from_euler("z", 7 * 2 * np.pi / n).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(Rs[7] @ offset + ts[7], offset, atol=1e-12)
    # Second block: the continuous samples composed with the discrete flip (Rc Rd).
    np.testing.assert_allclose(Rs[n + 7], Rs[7] @ RX180[:3, :3], atol=1e-12)
    # Every transformation maps the cylinder's rim onto itself (z -> +-z, radius kept).
    pts = _cylinder()
    for R, t in zip(Rs[:: n // 5], ts[:: n // 5]):
        q = pts @ R.T + t
        np.testing.assert_allclose(np.linalg.norm(q[:, :2], axis=1), 35.0, atol=1e-9)


# ---------------------------------------------------------------------------- MSSD / MSPD


def test_mssd_pure_translation_is_its_length() -> None:
    R = Rotation.from_euler("xyz", [20, -30, 50], degrees=True).as_matrix()
    t = np.array([10.0, -20.0, 700.0])
    d = np.array([3.0, -4.0, 12.0])  # |d| = 13
    assert mssd(R, t + d, R, t, _box()) == pytest.approx(13.0, abs=1e-12)
    # A cylinder with its symmetries still gives exactly |d|: the vertex set is centrally
    # symmetric, so no symmetric variant can shorten every displacement.
    syms = symmetry_transformations([RX180], [{"axis": [0, 0, 1], "offset": [0, 0, 0]}])
    assert mssd(R, t + d, R, t, _cylinder(), *syms) == pytest.approx(13.0, abs=1e-9)


def test_declared_symmetry_scores_zero() -> None:
    syms = symmetry_transformations([RX180], [{"axis": [0, 0, 1], "offset": [0, 0, 0]}])
    R = Rotation.from_euler("xyz", [40, 10, -70], degrees=True).as_matrix()
    t = np.array([-50.0, 30.0, 800.0])
    for k in (5, 400):  # a continuous sample and a flipped one
        R_e, t_e = R @ syms[0][k], R @ syms[1][k] + t
        assert mssd(R_e, t_e, R, t, _cylinder(), *syms) < 1e-9
        assert mspd(R_e, t_e, R, t, K, _cylinder(), *syms) < 1e-9
    # Without declaring the symmetry, the flip (y, z) -> (-y, -z) moves the rim vertex
    # (0, 35, 60) the most: by 2 |(35, 60)|.
    R_flip = R @ RX180[:3, :3]
    assert mssd(R_flip, t, R, t, _cylinder()) == pytest.approx(2 * math.hypot(35, 60), abs=1e-9)


def test_mspd_known_answer_fronto_parallel() -> None:
    """A planar object facing the camera at depth Z moved by dx: every point moves fx dx / Z px."""
    pts = np.c_[np.random.default_rng(0).uniform(-40, 40, (50, 2)), np.zeros(50)]
    t = np.array([0.0, 0.0, 600.0])
    assert mspd(np.eye(3), t + [5.0, 0, 0], np.eye(3), t, K, pts) == pytest.approx(K[0, 0] * 5.0 / 600.0, rel=1e-12)


def test_errors_equal_brute_force_over_symmetries() -> None:
    """The branch and bound returns exactly the min-max of the definition."""
    rng = np.random.default_rng(1)
    pts = np.concatenate([_cylinder(n=24), rng.uniform(-30, 30, (40, 3))])
    syms = symmetry_transformations([RX180], [{"axis": [0, 0, 1], "offset": [0, 0, 3]}], 0.05)
    for _ in range(4):
        R_g = Rotation.random(random_state=rng).as_matrix()
        t_g = rng.uniform([-100, -100, 500], [100, 100, 900])
        R_e = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix() @ R_g
        t_e = t_g + rng.normal(0, 15, 3)

        def surf(p, R_s, t_s):
            return np.linalg.norm(R_e @ p + t_e - (R_g @ (R_s @ p + t_s) + t_g))

        def proj(p, R_s, t_s):
            a, b = K @ (R_e @ p + t_e), K @ (R_g @ (R_s @ p + t_s) + t_g)
            return np.linalg.norm(a[:2] / a[2] - b[:2] / b[2])

        assert mssd(R_e, t_e, R_g, t_g, pts, *syms) == pytest.approx(_brute(pts, syms, surf), rel=1e-12)
        assert mspd(R_e, t_e, R_g, t_g, K, pts, *syms) == pytest.approx(_brute(pts, syms, proj), rel=1e-12)


def test_hull_and_bounds_give_the_same_errors() -> None:
    """MSSD on the convex hull vertices only, and MSPD with the hull as a middle bound,
    equal the plain computation (the scorer uses both)."""
    rng = np.random.default_rng(3)
    pts = np.concatenate([_cylinder(n=64), rng.uniform(-20, 20, (400, 3))])
    hull = hull_indices(pts)
    assert len(hull) == 128  # the rim; no interior point
    syms = symmetry_transformations([RX180], [{"axis": [0, 0, 1], "offset": [0, 0, 0]}], 0.01)
    hull_probes = probe_indices(pts[hull], 16)
    for i in range(6):
        R_g = Rotation.random(random_state=rng).as_matrix()
        t_g = rng.uniform([-100, -100, 500], [100, 100, 900])
        R_e = Rotation.random(random_state=rng).as_matrix() if i % 2 else Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_matrix() @ R_g
        t_e = t_g + rng.normal(0, 15, 3)
        plain = mssd(R_e, t_e, R_g, t_g, pts, *syms, probes=np.arange(0))
        assert mssd(R_e, t_e, R_g, t_g, pts[hull], *syms, hull_probes) == pytest.approx(plain, rel=1e-12, abs=1e-9)
        plain = mspd(R_e, t_e, R_g, t_g, K, pts, *syms, probes=np.arange(0))
        assert mspd(R_e, t_e, R_g, t_g, K, pts, *syms, hull[hull_probes], mid=hull) == pytest.approx(plain, rel=1e-12)
    # Degenerate (flat) point sets keep every point.
    flat = np.c_[rng.uniform(-1, 1, (20, 2)), np.zeros(20)]
    np.testing.assert_array_equal(hull_indices(flat), np.arange(20))


def test_project_matches_pinhole() -> None:
    uv = project(np.array([[10.0, -20.0, 0.0]]), K, np.eye(3), np.array([0.0, 0.0, 500.0]))
    np.testing.assert_allclose(uv, [[K[0, 0] * 10 / 500 + K[0, 2], K[1, 1] * -20 / 500 + K[1, 2]]])


# ---------------------------------------------------------------------------- VSD


def test_depth_to_distance() -> None:
    Kc = np.array([[500.0, 0, 2.0], [0, 400.0, 1.0], [0, 0, 1]])
    depth = np.full((3, 5), 800.0)
    dist = depth_to_distance(depth, Kc)
    assert dist[1, 2] == 800.0  # principal point: distance = depth
    x, y = (4 - 2.0) / 500.0, (0 - 1.0) / 400.0
    assert dist[0, 4] == pytest.approx(800.0 * math.sqrt(x * x + y * y + 1), rel=1e-14)
    # A crop keeps the image coordinates of its pixels.
    np.testing.assert_array_equal(depth_to_distance(depth[:, 3:], Kc, x0=3), dist[:, 3:])


def _square(shape, y0, x0, size, value):
    im = np.zeros(shape)
    im[y0 : y0 + size, x0 : x0 + size] = value
    return im


def test_vsd_shifted_square_known_answer() -> None:
    shape = (30, 30)
    gt = _square(shape, 5, 5, 10, 500.0)
    est = _square(shape, 5, 10, 10, 512.0)  # 5 px to the right, 12 mm further
    test = gt.copy()  # sensor sees the object only; background has no depth
    e = vsd_from_distances(test, est, gt, delta=15.0, taus=VSD_TAUS, diameter=100.0)
    # visible GT = A (100 px), visible estimate = B (100 px; missing depth counts as
    # visible), overlap 50 px at 12 mm = 0.12 diameters.
    expected = np.where(VSD_TAUS <= 0.12, 150 / 150, 100 / 150)
    np.testing.assert_allclose(e, expected, rtol=1e-15)


def test_vsd_occlusion_and_delta() -> None:
    shape = (20, 20)
    gt = _square(shape, 2, 2, 10, 600.0)
    test = gt.copy()
    test[2:12, 2:6] = 400.0  # an occluder hides 40 px of the object
    # Same pose: occluded pixels are invisible to both, error 0.
    np.testing.assert_array_equal(vsd_from_distances(test, gt, gt, 15.0, VSD_TAUS, 100.0), 0.0)
    # An estimate 20 mm behind the surface: beyond delta the sensor explains it as
    # occluded (not visible in the estimate) except where the GT is visible.
    est = np.where(gt > 0, 620.0, 0.0)
    e = vsd_from_distances(test, est, gt, 15.0, VSD_TAUS, 100.0)
    # visible GT = 60 px = visible estimate; all at 0.2 diameters.
    np.testing.assert_allclose(e, np.where(VSD_TAUS <= 0.2, 1.0, 0.0))
    # Nothing visible at all: error 1.
    np.testing.assert_array_equal(vsd_from_distances(test, 0 * gt, 0 * gt, 15.0, VSD_TAUS, 100.0), 1.0)


def test_vsd_crop_equals_full_image() -> None:
    rng = np.random.default_rng(2)
    shape = (48, 64)
    gt = _square(shape, 10, 12, 20, 700.0) + rng.normal(0, 3, shape) * (_square(shape, 10, 12, 20, 1) > 0)
    est = _square(shape, 14, 18, 20, 705.0)
    test = np.where(rng.random(shape) < 0.1, 0.0, gt + rng.normal(0, 1, shape))
    Kc = np.array([[300.0, 0, 31.5], [0, 300.0, 23.5], [0, 0, 1]])
    full = vsd_from_distances(
        depth_to_distance(test, Kc), depth_to_distance(est, Kc), depth_to_distance(gt, Kc), 15.0, VSD_TAUS, 80.0
    )
    np.testing.assert_array_equal(vsd(test, est, gt, Kc, 15.0, 80.0), full)


def test_vsd_crops_equal_full_images() -> None:
    """VSD from crops of the renders (as the scorer renders them) equals VSD on full images."""
    rng = np.random.default_rng(4)
    shape = (48, 64)
    Kc = np.array([[300.0, 0, 31.5], [0, 300.0, 23.5], [0, 0, 1]])
    gt = _square(shape, 10, 12, 20, 700.0)
    test = np.where(rng.random(shape) < 0.1, 0.0, gt + rng.normal(0, 1, shape))
    for est in (_square(shape, 14, 18, 20, 705.0), _square(shape, 30, 50, 25, 702.0), 0 * gt):
        full = vsd(test, est, gt, Kc, 15.0, 80.0)
        # Crops with zero margins, one reaching past the image border.
        crops = []
        for im, pad in ((est, 3), (gt, 0)):
            ys, xs = np.nonzero(im)
            if len(ys) == 0:
                crops.append(None)
                continue
            y0, x0 = ys.min() - pad, xs.min() - pad
            big = np.zeros((shape[0] + 20, shape[1] + 20))
            big[: shape[0], : shape[1]] = im
            crops.append(Crop(big[max(y0, 0) : ys.max() + 1 + pad, max(x0, 0) : xs.max() + 1 + pad], max(x0, 0), max(y0, 0)))
        np.testing.assert_array_equal(vsd_crops(test, crops[0], crops[1], Kc, 15.0, 80.0), full)
    np.testing.assert_array_equal(vsd_crops(test, None, None, Kc, 15.0, 80.0), 1.0)


def test_crop_renders_equal_full_renders() -> None:
    """Renderer.render_depth_crop: the same pixels as the full render inside object_box,
    nothing rendered outside it, depth within the full render's resolution."""
    import trimesh

    from pipeline.method.render.renderer import Renderer

    rng = np.random.default_rng(5)
    mesh = trimesh.creation.cylinder(radius=35.0, height=120.0, sections=48)
    with Renderer(640, 480) as r:
        r.add_mesh(1, mesh, smooth=False)
        r.add_mesh(2, trimesh.creation.box((100.0, 70.0, 50.0)), smooth=False)
        n_pix = n_diff = 0
        for i in range(12):
            key = 1 + i % 2
            R = Rotation.random(random_state=rng).as_matrix()
            t = rng.uniform([-250, -180, 500], [250, 180, 1200])
            full = r.render_depth(key, R, t, K)
            box = r.object_box(key, R, t, K)
            if box is None:
                assert not (full > 0).any()
                continue
            x0, y0, w, h = box
            inside = np.zeros(full.shape, bool)
            inside[y0 : y0 + h, x0 : x0 + w] = True
            assert not (full[~inside] > 0).any()
            crop = r.render_depth_crop(key, R, t, K, box)
            assert crop.shape == (h, w)
            ref = full[y0 : y0 + h, x0 : x0 + w]
            both = (ref > 0) & (crop > 0)
            n_pix += int((ref > 0).sum())
            n_diff += int(((ref > 0) != (crop > 0)).sum())
            np.testing.assert_allclose(crop[both], ref[both], atol=0.05)
        assert n_pix > 10000 and n_diff <= 3
        # Full renders still work after crop renders (same renderer, viewport restored).
        assert r.render_depth(1, np.eye(3), np.array([0.0, 0.0, 800.0]), K).shape == (480, 640)


def test_visibility_bins() -> None:
    np.testing.assert_array_equal(
        visib_bin([0.0, 0.05, 0.1, 0.3, 0.7, 0.8999, 0.9, 0.9999, 1.0]), [0, 0, 1, 3, 7, 8, 9, 9, 9]
    )


def test_sphere_projections_overlap() -> None:
    assert sphere_projections_overlap(50.0, [0, 0, 1000], [90, 0, 1000])
    assert not sphere_projections_overlap(50.0, [0, 0, 1000], [110, 0, 1000])
    assert not sphere_projections_overlap(50.0, [0, 0, 0], [0, 0, 1000])


# ---------------------------------------------------------------------------- matching


def test_valid_gt_mask_modes() -> None:
    objs = [1, 1, 1, 2, 3]
    fr = [0.5, 0.05, 0.9, 0.3, 0.8]
    # Toolkit default: the inst_count most visible instances of each target object.
    np.testing.assert_array_equal(valid_gt_mask(objs, fr, {1: 2, 2: 1}), [True, False, True, True, False])
    # Ties go to the lower gt_id.
    np.testing.assert_array_equal(valid_gt_mask([4, 4], [0.7, 0.7], {4: 1}), [True, False])
    # Fixed threshold.
    np.testing.assert_array_equal(valid_gt_mask(objs, fr, {1: 3, 2: 1}, 0.1), [True, False, True, True, False])


def test_greedy_match() -> None:
    # Two estimates (already in score order) and three GT instances.
    err = np.array([[0.3, 0.1, 0.2], [0.05, 0.15, 0.4]])[:, :, None]
    valid = np.array([True, True, True])
    m = greedy_match(err, valid, np.array([0.5]))
    # The first estimate takes its best GT (1) although the second fits GT 0 better.
    np.testing.assert_array_equal(m, [[1, 0]])
    # Strictly below the threshold: 0.1 does not pass 0.1.
    np.testing.assert_array_equal(greedy_match(err, valid, np.array([0.1])), [[-1, 0]])
    # An invalid GT can't be matched: the first estimate falls back to GT 2.
    np.testing.assert_array_equal(greedy_match(err, np.array([True, False, True]), np.array([0.5])), [[2, 0]])
    # Several settings at once, each with its own errors and threshold.
    err2 = np.concatenate([err, err[:, ::-1]], axis=2)
    np.testing.assert_array_equal(greedy_match(err2, valid, np.array([0.5, 0.5])), [[1, 0], [1, 2]])
    # Ties go to the lower GT index; NaN/inf never match.
    tie = np.array([[[0.2], [0.2], [np.nan]], [[np.inf], [0.3], [0.3]]])
    np.testing.assert_array_equal(greedy_match(tie, valid, np.array([1.0])), [[0, 1]])

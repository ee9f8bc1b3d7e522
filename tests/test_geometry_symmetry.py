"""Known-answer tests of pipeline.method.geometry.symmetry: symmetry estimation from shape.

The ten synthetic objects' geometric symmetries are known exactly (see
``pipeline.evaluation.synth.objects``; the cereal box and the can declare none because of their
print, but their shapes are a box and a cylinder). Estimating all ten takes ~10-15 s on
one core, so those tests are marked slow and share one estimate per object.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
import trimesh

from pipeline.method.geometry.sampling import sample_surface
from pipeline.method.geometry.symmetry import (
    SymmetryParams,
    SymmetrySet,
    continuous_transform,
    estimate_symmetries,
    expand_symmetries,
    super_fibonacci_rotations,
    symmetries_from_dict,
    transform_distance,
)
from pipeline.formats.bop.extent import point_cloud_diameter
from pipeline.method.geometry.transforms import rotation_about_axis
from pose_helpers import random_rotation
from pipeline.evaluation.synth.objects import build_object

N_POINTS = 20000
ANGLE_TOL_DEG = 2.0
TRANS_TOL_MM = 1.0
AXIS_TOL_DEG = 3.0

# (discrete count, continuous count) of each object's geometric symmetry group.
EXPECTED = {
    1: (3, 0),  # box: 180 deg about x, y, z
    2: (1, 1),  # cylinder: continuous about z + one flip
    3: (1, 0),  # U profile: 180 deg about y
    4: (0, 0),
    5: (11, 0),  # hex nut: D6
    6: (0, 1),  # cup: continuous about z
    7: (1, 1),  # spool: continuous about z + flip
    8: (0, 0),
    9: (0, 0),
    10: (3, 0),  # box: D2
}


@functools.lru_cache(maxsize=None)
def _object(obj_id: int):
    return build_object(obj_id)


@functools.lru_cache(maxsize=None)
def _estimate(obj_id: int) -> tuple[SymmetrySet, dict]:
    obj = _object(obj_id)
    points, normals = sample_surface(obj.model, N_POINTS, seed=obj_id)
    details: dict = {}
    sym = estimate_symmetries(points, obj.diameter, normals, details=details)
    return sym, details


def _matches(T: np.ndarray, candidates: list[np.ndarray]) -> bool:
    for U in candidates:
        ang, tr = transform_distance(T, U)
        if ang <= ANGLE_TOL_DEG and tr <= TRANS_TOL_MM:
            return True
    return False


def _axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two axes up to sign, in degrees."""
    c = abs(float(np.dot(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(min(c, 1.0))))


def _rotation_axis(T: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    v = Rotation.from_matrix(T[:3, :3]).as_quat()[:3]
    return v / np.linalg.norm(v)


# ---------------------------------------------------------------------------- fast tests


def test_super_fibonacci_is_uniform_and_covering():
    q = super_fibonacci_rotations(4096)
    assert q.shape == (4096, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    # Uniform on S^3: the second moment is I / 4.
    np.testing.assert_allclose(q.T @ q / len(q), np.eye(4) / 4, atol=0.01)
    # Covering: every random rotation has a grid rotation within ~12 degrees.
    rng = np.random.default_rng(0)
    r = rng.normal(size=(500, 4))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    worst = np.degrees(2 * np.arccos(np.clip(np.abs(r @ q.T).max(axis=1), -1, 1))).max()
    assert worst < 14.0


def test_expand_declared_spool_and_nut():
    spool = SymmetrySet.from_model_info(_object(7).model_info())
    Ts = spool.transforms(30.0)
    assert len(Ts) == 24  # 12 turns x (identity, flip)
    np.testing.assert_allclose(Ts[0], np.eye(4))
    # A group: closed under composition, no duplicates.
    for A in Ts[::5]:
        for B in Ts[::3]:
            assert _matches(A @ B, Ts)
    for i in range(len(Ts)):
        assert not _matches(Ts[i], Ts[:i])
    nut = SymmetrySet.from_model_info(_object(5).model_info())
    assert len(nut.transforms()) == 12
    trivial = SymmetrySet()
    assert trivial.is_trivial
    assert len(trivial.transforms()) == 1
    np.testing.assert_allclose(trivial.transforms()[0], np.eye(4))


def test_expand_composes_about_offset():
    fam = {"axis": np.array([0.0, 0.0, 1.0]), "offset": np.array([10.0, -5.0, 0.0])}
    Ts = expand_symmetries([], [fam], step_deg=90.0)
    assert len(Ts) == 4
    for T in Ts:  # every element fixes the points of the axis
        np.testing.assert_allclose(T[:3, :3] @ [10.0, -5.0, 7.0] + T[:3, 3], [10.0, -5.0, 7.0], atol=1e-9)
    np.testing.assert_allclose(continuous_transform(fam, 90.0), Ts[1], atol=1e-12)


def _three_bump_disc() -> trimesh.Trimesh:
    """A disc (radius 40, height 12, about z) with three spheres on its top at 120 deg:
    rotation group C3 (mirror planes are not rotations; nothing maps top to bottom)."""
    disc = trimesh.creation.cylinder(radius=40.0, height=12.0, sections=96)
    bump = trimesh.creation.icosphere(subdivisions=3, radius=9.0)
    bump.apply_translation([25.0, 0.0, 6.0])
    parts = [disc]
    for k in range(3):
        b = bump.copy()
        T = np.eye(4)
        T[:3, :3] = rotation_about_axis([0, 0, 1], 120.0 * k)
        b.apply_transform(T)
        parts.append(b)
    return trimesh.util.concatenate(parts)


def test_random_pose_three_fold_gives_exactly_c3():
    mesh = _three_bump_disc()
    points, normals = sample_surface(mesh, N_POINTS, seed=3)
    R0 = random_rotation(7)
    t0 = np.array([30.0, -20.0, 55.0])
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = R0, t0
    P = points.astype(np.float64) @ R0.T + t0
    N = normals.astype(np.float64) @ R0.T
    diameter = point_cloud_diameter(P)
    sym = estimate_symmetries(P, diameter, N)
    assert not sym.continuous
    assert len(sym.discrete) == 2
    expected = []
    for k in (1, 2):
        Rz = np.eye(4)
        Rz[:3, :3] = rotation_about_axis([0, 0, 1], 120.0 * k)
        expected.append(T0 @ Rz @ np.linalg.inv(T0))
    for E in expected:
        assert _matches(E, sym.discrete)
    for D in sym.discrete:
        assert _matches(D, expected)
    assert len(sym.transforms()) == 3


def test_estimation_without_normals_three_fold():
    points, _ = sample_surface(_three_bump_disc(), 12000, seed=4)
    sym = estimate_symmetries(points, point_cloud_diameter(points), None, SymmetryParams(seed=1))
    assert len(sym.discrete) == 2 and not sym.continuous


def test_json_round_trip():
    fam = {"axis": np.array([0.0, 0.0, 1.0]), "offset": np.array([0.5, -1.0, 0.0])}
    flip = np.eye(4)
    flip[:3, :3] = rotation_about_axis([1, 0, 0], 180.0)
    flip[:3, 3] = [0.0, -2.0, 0.0]
    sym = SymmetrySet([flip], [fam])
    d = json.loads(json.dumps(sym.to_dict()))
    assert set(d) == {"symmetries_discrete", "symmetries_continuous"}
    assert len(d["symmetries_discrete"][0]) == 16  # BOP: flattened row-major 4x4
    back = SymmetrySet.from_dict(d)
    np.testing.assert_allclose(back.discrete[0], flip)
    np.testing.assert_allclose(back.continuous[0]["axis"], fam["axis"])
    np.testing.assert_allclose(back.continuous[0]["offset"], fam["offset"])
    for A, B in zip(back.transforms(45.0), sym.transforms(45.0)):
        np.testing.assert_allclose(A, B)
    # Missing keys (BOP omits them for asymmetric objects) mean no symmetry.
    assert symmetries_from_dict({}).is_trivial
    assert SymmetrySet().to_dict() == {"symmetries_discrete": [], "symmetries_continuous": []}


def test_contains_continuous_member_and_coset():
    spool = SymmetrySet.from_model_info(_object(7).model_info())
    turn = continuous_transform(spool.continuous[0], 37.0)
    assert spool.contains(turn)
    assert spool.contains(turn @ spool.discrete[0])
    tilt = np.eye(4)
    tilt[:3, :3] = rotation_about_axis([1, 0, 0], 20.0)
    assert not spool.contains(tilt)


# ---------------------------------------------------------------------------- slow: the ten objects


@pytest.mark.slow
@pytest.mark.parametrize("obj_id", sorted(EXPECTED))
def test_group_sizes(obj_id):
    sym, details = _estimate(obj_id)
    assert (len(sym.discrete), len(sym.continuous)) == EXPECTED[obj_id], details
    assert sym.is_trivial == (EXPECTED[obj_id] == (0, 0))


@pytest.mark.slow
@pytest.mark.parametrize("obj_id", [3, 5, 6, 7, 10])
def test_declared_symmetries_are_found(obj_id):
    obj = _object(obj_id)
    sym, _ = _estimate(obj_id)
    Ts = sym.transforms(30.0)
    np.testing.assert_allclose(Ts[0], np.eye(4))
    for D in obj.symmetries_discrete:
        assert _matches(D, Ts), f"{obj.name}: declared {D.round(3)} not in the estimated group"
        assert sym.contains(D, max_angle_deg=ANGLE_TOL_DEG, max_trans_mm=TRANS_TOL_MM)
    for c in obj.symmetries_continuous:
        assert any(_axis_angle_deg(c["axis"], e["axis"]) <= AXIS_TOL_DEG for e in sym.continuous)
        for e in sym.continuous:
            # The estimated offset lies on the declared axis.
            o = e["offset"] - c["offset"]
            assert np.linalg.norm(o - np.dot(o, c["axis"]) * c["axis"]) < TRANS_TOL_MM


@pytest.mark.slow
def test_hex_nut_is_discrete_d6():
    sym, _ = _estimate(5)
    assert not sym.continuous
    angles = sorted(round(transform_distance(np.eye(4), D)[0]) for D in sym.discrete)
    assert angles == [60, 60, 120, 120] + [180] * 7


@pytest.mark.slow
def test_cereal_box_has_d2_geometry():
    sym, _ = _estimate(1)
    axes = []
    for D in sym.discrete:
        assert abs(transform_distance(np.eye(4), D)[0] - 180.0) < ANGLE_TOL_DEG
        axes.append(_rotation_axis(D))
    for e in np.eye(3):
        assert any(_axis_angle_deg(a, e) < ANGLE_TOL_DEG for a in axes)


@pytest.mark.slow
def test_soup_can_is_continuous_with_flip():
    sym, _ = _estimate(2)
    (fam,) = sym.continuous
    assert _axis_angle_deg(fam["axis"], [0, 0, 1]) < AXIS_TOL_DEG
    (flip,) = sym.discrete
    assert abs(transform_distance(np.eye(4), flip)[0] - 180.0) < ANGLE_TOL_DEG
    assert abs(_axis_angle_deg(_rotation_axis(flip), [0, 0, 1]) - 90.0) < ANGLE_TOL_DEG
    # Of the flips (one per horizontal axis), the one about a model axis (x) is kept.
    assert _axis_angle_deg(_rotation_axis(flip), [1, 0, 0]) < ANGLE_TOL_DEG
    assert len(sym.transforms(30.0)) == 24


@pytest.mark.slow
def test_margin_between_symmetries_and_rejections():
    """True symmetries score far below the threshold, the best rejected candidate far
    above it (measured over seeds, with and without normals: true <= 0.00084 d,
    rejected >= 0.0074 d (the toy truck turned 180 deg about z); threshold 0.003 d)."""
    thr = SymmetryParams().threshold
    for obj_id in EXPECTED:
        sym, details = _estimate(obj_id)
        d = _object(obj_id).diameter
        worst_true = max(s for _, s in details["accepted"]) / d
        assert worst_true < thr / 2, (obj_id, worst_true)
        assert details["rejected_best"] / d > 2 * thr, (obj_id, details["rejected_best"] / d)


def test_distinct_under_declared_symmetries():
    """Variants that the declared (shape + texture) symmetries already equate are
    dropped: the cup's print is symmetric too, the can's label is not, and the hex
    nut's declared group is its whole geometric group."""
    from pipeline.method.geometry.symmetry import SymmetrySet, distinct_under, expand_symmetries

    z = {"axis": np.array([0.0, 0.0, 1.0]), "offset": np.zeros(3)}
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    geometric = expand_symmetries([flip], [z], step_deg=30.0)
    assert len(geometric) == 24
    assert len(distinct_under(geometric, SymmetrySet([], []))) == 24  # nothing declared: all distinct
    assert len(distinct_under(geometric, SymmetrySet([], [z]))) == 2  # continuous declared: identity and the flip
    kept = distinct_under(geometric, SymmetrySet([flip], [z]))
    assert len(kept) == 1 and np.allclose(kept[0], np.eye(4))

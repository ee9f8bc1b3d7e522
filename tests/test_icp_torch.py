"""The batched torch ICP (pipeline/method/refinement/icp_torch.py) against the numpy ICP
on the same inputs, on the CPU: every start's pose, fit and iteration count."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pipeline.formats.bop.extent import point_cloud_diameter  # noqa: E402
from pipeline.method.geometry.sampling import sample_surface  # noqa: E402
from pipeline.method.geometry.transforms import perturb_pose, rotation_angle_deg  # noqa: E402
from pipeline.method.refinement.icp import IcpModel, refine_icp  # noqa: E402
from pipeline.method.refinement.icp_torch import refine_icp_batch  # noqa: E402
from registration_scenes import make_object, random_scene_pose, render_scene, scene_inputs, SCENE_WH  # noqa: E402


@pytest.fixture(scope="module", params=["rock", "kettle", "blocks"])
def view(request):
    """A model, its IcpModel of 3000 samples, a rendered partial view's 800 points and its pose."""
    from pipeline.method.render.renderer import Renderer

    mesh = make_object(request.param, seed=2)
    diameter = point_cloud_diameter(mesh.vertices)
    with Renderer(*SCENE_WH) as r:
        r.add_mesh("obj", mesh)
        v = render_scene(r, "obj", *random_scene_pose(np.random.default_rng(5)))
    scene, _, _ = scene_inputs(v, diameter, 800, seed=3)
    return IcpModel(*sample_surface(mesh, 3000, seed=0)), scene, v.R, v.t, diameter


def _starts(R, t, n=12):
    """``n`` starts about the true pose, from 2 deg / 5 mm to 25 deg / 40 mm (the far ones
    end elsewhere, which the comparison must match too)."""
    poses = [perturb_pose(R, t, a, s, rng=i) for i, (a, s) in
             enumerate(zip(np.linspace(2, 25, n), np.linspace(5, 40, n)))]
    return np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses])


@pytest.mark.parametrize("point_to_plane", [True, False])
def test_batch_equals_numpy_icp_per_start(view, point_to_plane):
    model, scene, R, t, diameter = view
    if not point_to_plane:
        model = IcpModel(model.points)
    R0, t0 = _starts(R, t)
    got = refine_icp_batch(model, scene, R0, t0, diameter, point_to_plane=point_to_plane)
    assert len(got) == len(R0)
    for i, res in enumerate(got):
        ref = refine_icp(model, None, scene, R0[i], t0[i], diameter, point_to_plane=point_to_plane)
        assert res.iterations == ref.iterations, i
        assert rotation_angle_deg(res.R, ref.R) < 1e-7, i
        assert np.abs(res.t - ref.t).max() < 1e-6, i
        assert res.fitness == pytest.approx(ref.fitness, abs=1e-12), i
        assert res.inlier_rmse == pytest.approx(ref.inlier_rmse, rel=1e-9, abs=1e-9), i
    # The near start converges (the comparison is not of two failures); point-to-point
    # slides slowly over smooth surfaces and stops degrees away (test_geometry_icp.py).
    assert got[0].fitness > 0.9
    if point_to_plane:
        assert rotation_angle_deg(got[0].R, R) < 1.0


def test_batch_of_one_quick_schedule_and_float32(view):
    """The turns' quick ICP (one stage, few iterations) of one start; and in float32 (a
    GPU's precision) the same pose to a few hundredths of a degree and millimetre."""
    model, scene, R, t, diameter = view
    R0, t0 = _starts(R, t, 3)
    (one,) = refine_icp_batch(model, scene, R0[1:2], t0[1:2], diameter, schedule=(1.0,), iterations=5)
    ref = refine_icp(model, None, scene, R0[1], t0[1], diameter, schedule=(1.0,), iterations=5)
    assert one.iterations == ref.iterations <= 5
    assert rotation_angle_deg(one.R, ref.R) < 1e-7 and np.abs(one.t - ref.t).max() < 1e-6
    single = refine_icp_batch(model, scene, R0, t0, diameter, dtype="float32")
    for i, res in enumerate(single[:1]):
        ref = refine_icp(model, None, scene, R0[i], t0[i], diameter)
        assert rotation_angle_deg(res.R, ref.R) < 0.05 and np.abs(res.t - ref.t).max() < 0.05


def test_batch_rejects_bad_input(view):
    model, scene, R, t, diameter = view
    with pytest.raises(ValueError, match="empty"):
        refine_icp_batch(model, np.zeros((0, 3)), R[None], t[None], diameter)
    with pytest.raises(ValueError, match="normals"):
        refine_icp_batch(IcpModel(model.points), scene, R[None], t[None], diameter)
    with pytest.raises(ValueError, match="translations"):
        refine_icp_batch(model, scene, np.stack([R, R]), t[None], diameter)
    assert refine_icp_batch(model, scene, np.zeros((0, 3, 3)), np.zeros((0, 3)), diameter) == []


def test_neighbours_in_blocks_equal_one_block(monkeypatch):
    """The distance matrix split into blocks of starts and of scene points (the fine ICP's
    2000 x 20000 would not fit one) gives the same neighbours and distances."""
    import torch

    import pipeline.method.refinement.icp_torch as icp_torch

    rng = np.random.default_rng(0)
    q = torch.as_tensor(rng.normal(size=(3, 700, 3)) * 50)
    model = torch.as_tensor(rng.normal(size=(900, 3)) * 50)
    d_one, i_one = icp_torch._nearest(q, model, 30.0)
    monkeypatch.setattr(icp_torch, "NN_CHUNK", 1000)  # one scene point and one start a block
    d_blocks, i_blocks = icp_torch._nearest(q, model, 30.0)
    assert torch.equal(i_one, i_blocks) and torch.equal(d_one, d_blocks)
    assert torch.isinf(d_one).any() and (i_one[torch.isinf(d_one)] == len(model)).all()  # beyond the threshold

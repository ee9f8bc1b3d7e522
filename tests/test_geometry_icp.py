"""ICP refinement on a rendered partial view converges from a small perturbation."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pipeline.geometry.extent import point_cloud_diameter  # noqa: E402
from pipeline.geometry.icp import refine_icp  # noqa: E402
from pipeline.geometry.sampling import sample_surface  # noqa: E402
from pipeline.geometry.transforms import perturb_pose, rotation_angle_deg  # noqa: E402
from registration_scenes import (  # noqa: E402
    SCENE_K,
    SCENE_WH,
    make_object,
    random_scene_pose,
    render_scene,
    scene_inputs,
)


@pytest.fixture(scope="module")
def partial_views():
    from pipeline.render.renderer import Renderer

    mesh = make_object("rock", seed=1)
    diameter = point_cloud_diameter(mesh.vertices)
    rng = np.random.default_rng(11)
    with Renderer(*SCENE_WH) as r:
        r.add_mesh("rock", mesh)
        views = [render_scene(r, "rock", *random_scene_pose(rng)) for _ in range(4)]
    pts, nrm = sample_surface(mesh, 5000, seed=0)
    return pts, nrm, diameter, views


def test_icp_converges_from_5deg_10mm(partial_views):
    pts, nrm, diameter, views = partial_views
    for i, view in enumerate(views):
        scene, _, _ = scene_inputs(view, diameter, 1000, seed=i)
        R0, t0 = perturb_pose(view.R, view.t, 5.0, 10.0, rng=i)
        res = refine_icp(pts, nrm, scene, R0, t0, diameter)
        # Measured: 0.03-0.05 deg and ~0.05 mm. (Point-to-point ICP slides slowly over
        # this smooth surface and stops 0.3-5 deg away, hence point-to-plane by default.)
        assert rotation_angle_deg(res.R, view.R) < 0.3, i
        assert np.linalg.norm(res.t - view.t) < 0.5, i
        assert res.fitness > 0.95
        # Model samples are ~2 mm apart, so scene points lie ~1.5 mm from the nearest one.
        assert res.inlier_rmse < 2.0


@pytest.mark.parametrize("angle, shift", [(10.0, 20.0), (15.0, 30.0)])
def test_icp_and_the_fine_icp_converge_from_larger_perturbations(partial_views, angle, shift):
    """The hypotheses' ICP, then refine's fine ICP (2000 of the candidate's points against
    20000 model samples, from the ICP's pose), from 10 deg / 20 mm and 15 deg / 30 mm."""
    from pipeline.geometry.depth import lift_depth
    from pipeline.scene_side import sample_candidate

    pts, nrm, diameter, views = partial_views
    mesh = make_object("rock", seed=1)
    dense, dense_nrm = sample_surface(mesh, 20000, seed=1)
    for i, view in enumerate(views):
        scene, _, _ = scene_inputs(view, diameter, 1000, seed=i)
        R0, t0 = perturb_pose(view.R, view.t, angle, shift, rng=10 + i)
        res = refine_icp(pts, nrm, scene, R0, t0, diameter)
        assert rotation_angle_deg(res.R, view.R) < 0.5 and np.linalg.norm(res.t - view.t) < 1.0, i
        every, _ = lift_depth(view.depth, SCENE_K, view.mask)
        fine = refine_icp(dense, dense_nrm, every[sample_candidate(len(every), 2000, i)], res.R, res.t, diameter)
        assert rotation_angle_deg(fine.R, view.R) < 0.3 and np.linalg.norm(fine.t - view.t) < 0.5, i


def test_icp_needs_normals_for_point_to_plane(partial_views):
    pts, _, diameter, views = partial_views
    with pytest.raises(ValueError, match="model_normals"):
        refine_icp(pts, None, pts, np.eye(3), np.zeros(3), diameter)

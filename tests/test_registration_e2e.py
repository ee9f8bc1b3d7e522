"""Key test: a textured asymmetric object seen in a rendered partial view is recovered by
features (FPFH + colortex) -> PCA fusion -> RANSAC -> ICP to within 2 deg / 3 mm."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pipeline.method.encoders.lifting import (  # noqa: E402
    lift_model_visual_features,
    lift_scene_visual_features,
    mask_to_bbox,
)
from pipeline.method.encoders.registry import EncoderSpec, build_encoder  # noqa: E402
from pipeline.method.geometry.depth import lift_depth, remove_outliers  # noqa: E402
from pipeline.formats.bop.extent import point_cloud_diameter  # noqa: E402
from pipeline.method.refinement.icp import refine_icp  # noqa: E402
from pipeline.method.geometry.sampling import sample_points, sample_surface  # noqa: E402
from pipeline.method.geometry.transforms import rotation_angle_deg  # noqa: E402
from pipeline.method.registration.fusion import apply_pca, fit_pca, fuse  # noqa: E402
from pipeline.method.registration.ransac import RansacParams, ransac_align  # noqa: E402
from pipeline.method.render.templates import render_templates, template_views  # noqa: E402
from registration_scenes import (  # noqa: E402
    SCENE_K,
    SCENE_WH,
    make_object,
    random_scene_pose,
    render_scene,
)

N_MODEL, M_SCENE, N_TEMPLATES = 5000, 1000, 42



pytestmark = pytest.mark.slow  # model sides and many renders: seconds per test

@pytest.fixture(scope="module", params=["rock", "blocks"])
def case(request):
    """Model-side features and three rendered partial views of one object."""
    from pipeline.method.render.renderer import Renderer

    kind = request.param
    geo = build_encoder(EncoderSpec(name="fpfh"))  # defaults: radii [0.3, 0.4]
    vis = build_encoder(EncoderSpec(name="colortex"))
    mesh = make_object(kind, seed=1)
    diameter = point_cloud_diameter(mesh.vertices)
    pts, nrm = sample_surface(mesh, N_MODEL, seed=0)
    with Renderer(vis.input_size, vis.input_size) as r:
        r.add_mesh(kind, mesh)
        tpl = render_templates(r, kind, template_views(N_TEMPLATES, diameter, vis.input_size))
    templates = list(zip(tpl["rgb"], tpl["depth"], tpl["K"], tpl["R"], tpl["t"]))
    model_visual, count = lift_model_visual_features(pts, templates, vis, diameter=diameter)
    assert (count > 0).mean() > 0.9  # 42 views see all but concave nooks and thin edges
    model = {
        "points": pts,
        "normals": nrm,
        "diameter": diameter,
        "geometric": geo.encode(pts, nrm, diameter),
        "visual": model_visual,
        "pca": fit_pca(model_visual, 64),
    }
    rng = np.random.default_rng(2024)
    with Renderer(*SCENE_WH) as r:
        r.add_mesh(kind, mesh)
        views = [render_scene(r, kind, *random_scene_pose(rng)) for _ in range(3)]
    return kind, geo, vis, model, views


def test_fused_registration_recovers_pose(case):
    kind, geo, vis, model, views = case
    d = model["diameter"]
    f_model = fuse(model["geometric"], apply_pca(model["pca"], model["visual"]))
    for i, view in enumerate(views):
        # Scene side, as the scene-features stage does it.
        cloud, pixels = lift_depth(view.depth, SCENE_K, view.mask)
        keep = remove_outliers(cloud, d)
        cloud, pixels = cloud[keep], pixels[keep]
        idx = sample_points(cloud, M_SCENE, seed=i)
        pts, pix = cloud[idx], pixels[idx]
        g_scene = geo.encode(pts, None, d, viewpoint=np.zeros(3))
        v_scene = lift_scene_visual_features(view.rgb, mask_to_bbox(view.mask), pix, vis)
        f_scene = fuse(g_scene, apply_pca(model["pca"], v_scene))

        reg = ransac_align(model["points"], f_model, pts, f_scene, d, params=RansacParams(), seed=i)
        icp = refine_icp(model["points"], model["normals"], pts, reg.R, reg.t, d)

        rot, trans = rotation_angle_deg(icp.R, view.R), float(np.linalg.norm(icp.t - view.t))
        assert rot < 2.0 and trans < 3.0, f"{kind} view {i}: {rot:.2f} deg, {trans:.2f} mm"
        # RANSAC alone lands close enough for ICP's basin.
        assert rotation_angle_deg(reg.R, view.R) < 15.0
        assert icp.fitness > 0.9

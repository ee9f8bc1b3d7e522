"""The scorer's batched depth renderer (pipeline/evaluation/metrics/depth_render.py) and the VSD on
distance crops: the same pixels and errors as the per-render pyrender path."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from pipeline.evaluation.metrics import VSD_TAUS, Crop, distance_crop, ray_lengths, vsd_crops, vsd_distance_crops
from pipeline.evaluation.metrics import depth_render
from pipeline.evaluation.metrics.depth_render import DepthAtlasRenderer, DepthRequest, is_closed_outward, visible_faces

# The scorer renders with the principal point shifted by half a pixel (render_offset).
K = np.array([[572.4114, 0.0, 324.7611], [0.0, 573.57043, 241.54899], [0.0, 0.0, 1.0]])


def _meshes() -> dict[int, trimesh.Trimesh]:
    """Closed meshes (a cylinder, a subdivided box, a sphere) and an open one (a cup)."""
    box = trimesh.creation.box((100.0, 70.0, 50.0)).subdivide().subdivide()
    cup = trimesh.creation.cylinder(radius=30.0, height=80.0, sections=40)
    top = cup.vertices[cup.faces][:, :, 2].min(axis=1) > 39.0  # faces of the top cap
    return {
        1: trimesh.creation.cylinder(radius=35.0, height=120.0, sections=48),
        2: box,
        3: trimesh.creation.icosphere(3, 40.0),
        4: trimesh.Trimesh(cup.vertices, cup.faces[~top], process=False),
    }


def _poses(rng: np.random.Generator, n: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    poses = []
    for i in range(n):
        key = 1 + i % 4
        t = rng.uniform([-250, -180, 450], [250, 180, 1200]) if i % 9 else np.array([0.0, 0.0, 60.0])
        poses.append((key, Rotation.random(random_state=rng).as_matrix(), t))
    return poses


def test_closed_outward_meshes_are_recognised() -> None:
    m = _meshes()
    assert all(is_closed_outward(m[k].vertices, m[k].faces) for k in (1, 2, 3))
    assert not is_closed_outward(m[4].vertices, m[4].faces)  # open
    assert not is_closed_outward(m[1].vertices, m[1].faces[:, ::-1])  # inside out
    two = trimesh.util.concatenate([m[2], m[3]])
    assert is_closed_outward(two.vertices, two.faces)
    flipped = two.faces.copy()
    flipped[len(m[2].faces):] = flipped[len(m[2].faces):, ::-1]  # one part inside out
    assert not is_closed_outward(two.vertices, flipped)


def test_atlas_renders_equal_pyrender_crop_renders() -> None:
    """Same boxes and silhouettes as Renderer.render_depth_crop, depths within its
    resolution, whether the back faces are drawn or skipped; 9 renders per readback."""
    from pipeline.method.render.renderer import Renderer

    rng = np.random.default_rng(7)
    meshes = _meshes()
    with Renderer(640, 480) as ren, DepthAtlasRenderer(1024, 512) as atlas:
        for key, mesh in meshes.items():
            ren.add_mesh(key, mesh, smooth=False)
            atlas.add_mesh(key, mesh.vertices, mesh.faces)
        requests, refs = [], []
        for key, R, t in _poses(rng, 40):
            box = ren.object_box(key, R, t, K)
            assert box == atlas.box(key, R, t, K, 640, 480)
            if box is None:
                continue
            requests.append(DepthRequest(key, R, t, K, box))
            refs.append(ren.render_depth_crop(key, R, t, K, box))
        crops = atlas.render(requests)
        assert atlas.stats["readbacks"] > 1 and atlas.stats["faces_drawn"] < atlas.stats["faces_total"]
        n_pix = n_diff = 0
        for req, crop, ref in zip(requests, crops, refs):
            assert crop.shape == ref.shape == (req.box[3], req.box[2])
            z = (meshes[req.key].vertices @ req.R.T + req.t)[:, 2]
            if req.key == 4 or z.min() <= 10.0:
                # pyrender culls back faces, the toolkit's renderers (and this one) do
                # not: into the open cup, or from inside a model, they see more.
                assert not ((ref > 0) & ~(crop > 0)).any()
                continue
            both = (ref > 0) & (crop > 0)
            n_pix += int((ref > 0).sum())
            n_diff += int(((ref > 0) != (crop > 0)).sum())
            np.testing.assert_allclose(crop[both], ref[both], atol=0.1)
        assert n_pix > 50000 and n_diff <= 3

        # Skipping the back faces of closed meshes changes no pixel's coverage; depths
        # only at rare silhouette pixels, by float rounding at grazing angles.
        keep = depth_render.visible_faces
        depth_render.visible_faces = lambda mesh, R, t: None
        try:
            every_face = atlas.render(requests)
        finally:
            depth_render.visible_faces = keep
        for a, b in zip(crops, every_face):
            np.testing.assert_array_equal(a > 0, b > 0)
            assert (np.abs(a - b) > 1e-2).sum() <= 2


def test_visible_faces_keeps_every_face_when_needed() -> None:
    m = _meshes()
    with DepthAtlasRenderer(256, 256) as atlas:
        for key in (1, 4):
            atlas.add_mesh(key, m[key].vertices, m[key].faces)
        mesh = atlas._meshes[1]
        front = visible_faces(mesh, np.eye(3), np.array([0.0, 0.0, 800.0]))
        assert 0 < len(front) < len(mesh.faces)
        assert visible_faces(mesh, np.eye(3), np.array([0.0, 0.0, 30.0])) is None  # crosses the near plane
        assert visible_faces(atlas._meshes[4], np.eye(3), np.array([0.0, 0.0, 800.0])) is None  # open mesh


def test_distance_crops_give_the_vsd_of_depth_crops() -> None:
    """vsd_distance_crops (distances once per image / render) equals vsd_crops, bit for bit."""
    rng = np.random.default_rng(3)
    H, W = 48, 64
    Kc = np.array([[300.0, 0, 31.5], [0, 300.0, 23.5], [0, 0, 1]])
    test = np.where(rng.random((H, W)) < 0.1, 0.0, rng.uniform(650, 760, (H, W)))
    rays = ray_lengths(Kc, W, H)
    for _ in range(20):
        crops = []
        for _ in range(2):
            if rng.random() < 0.1:
                crops.append(None)
                continue
            h, w = rng.integers(5, 30, 2)
            x0, y0 = rng.integers(-3, W - 5), rng.integers(-3, H - 5)
            depth = np.where(rng.random((h, w)) < 0.7, rng.uniform(640, 770, (h, w)), 0.0).astype(np.float32)
            crops.append(Crop(depth, int(x0), int(y0)))
        # vsd_crops takes crops reaching past the image; distance crops are clipped to it.
        ref = vsd_crops(test, crops[0], crops[1], Kc, 15.0, 80.0)
        dists = [None if c is None else distance_crop(c, rays) for c in crops]
        got = vsd_distance_crops(test * rays, dists[0], dists[1], 15.0, 80.0, VSD_TAUS)
        np.testing.assert_array_equal(got, ref)


def test_submitted_renders_are_collected_after_other_work_and_after_a_lost_context() -> None:
    """submit + collect (the scorer computes MSSD and MSPD in between, while Mesa
    rasterises) gives the pixels of render; when the EGL context is lost in between
    (pyrender terminating the shared display does that), collect draws them again on a
    new context instead of reading an empty atlas."""
    rng = np.random.default_rng(3)
    meshes = _meshes()
    with DepthAtlasRenderer(1024, 512) as atlas:
        for key, mesh in meshes.items():
            atlas.add_mesh(key, mesh.vertices, mesh.faces)
        requests = []
        for key, R, t in _poses(rng, 12):
            box = atlas.box(key, R, t, K, 640, 480)
            if box is not None:
                requests.append(DepthRequest(key, R, t, K, box))
        assert len(requests) >= 8
        reference = atlas.render(requests)
        assert sum(int((c > 0).sum()) for c in reference) > 20000

        pending = atlas.submit(requests)
        busy = np.linalg.inv(rng.normal(size=(200, 200)) + 200 * np.eye(200))  # other work meanwhile
        assert np.isfinite(busy).all()
        for a, b in zip(atlas.collect(pending), reference):
            np.testing.assert_array_equal(a, b)
        assert atlas.collect(pending) is pending.out  # read once

        pending = atlas.submit(requests)
        atlas._context.destroy()
        for a, b in zip(atlas.collect(pending), reference):
            np.testing.assert_array_equal(a, b)

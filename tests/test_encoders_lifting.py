"""Crop geometry, feature upsampling/sampling and the 2D -> 3D lifting of visual features."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from pipeline.method.encoders.lifting import (  # noqa: E402
    crop_and_resize,
    image_to_crop_coords,
    lift_model_visual_features,
    lift_scene_visual_features,
    mask_to_bbox,
    sample_features_at_pixels,
    square_crop_box,
    upsample_to_crop,
)
from pipeline.method.encoders.registry import VisualEncoder  # noqa: E402
from pipeline.method.geometry.sampling import sample_surface  # noqa: E402
from pipeline.method.geometry.transforms import look_at_rotation  # noqa: E402


class PixelColourEncoder(VisualEncoder):
    """Test stub: each pixel's own colour in [0, 1], a (3, S, S) map at stride 1."""

    name = "pixelcolour"
    version = "0"
    dim = 3

    def __init__(self, input_size: int):
        self.input_size = input_size

    def cache_params(self):
        return {"input_size": self.input_size}

    def encode(self, images):
        return np.asarray(images, dtype=np.float32).transpose(0, 3, 1, 2) / 255.0


def test_square_crop_box_and_bbox():
    mask = np.zeros((100, 120), bool)
    mask[10:30, 50:90] = True  # 40 wide, 20 high
    bbox = mask_to_bbox(mask)
    assert bbox == (50, 10, 40, 20)
    x0, y0, side = square_crop_box(bbox, mask.shape, margin=0.1)
    assert side == 48
    # Centred: the bbox centre (70, 20) is the box centre.
    assert x0 + side / 2 == pytest.approx(70) and y0 + side / 2 == pytest.approx(20)
    with pytest.raises(ValueError, match="outside"):
        square_crop_box((500, 10, 5, 5), mask.shape)


def test_crop_and_resize_pads_and_maps_pixels():
    img = np.arange(20 * 30 * 3, dtype=np.uint8).reshape(20, 30, 3)
    crop = crop_and_resize(img, (-4, 2, 10), 10)  # no resize: a plain padded crop
    np.testing.assert_array_equal(crop[:, :4], 0)
    np.testing.assert_array_equal(crop[:, 4:], img[2:12, 0:6])
    # Upscaling 2x: crop pixel c comes from image coordinate x0 + (c + 0.5)/2 - 0.5,
    # so crop pixels 2k and 2k+1 straddle image pixel k; a constant-per-column image
    # checks the mapping at pixel centres.
    cols = np.tile(np.arange(30, dtype=np.uint8) * 8, (20, 1))
    up = crop_and_resize(np.dstack([cols] * 3), (5, 5, 10), 20)
    assert up.shape == (20, 20, 3)
    np.testing.assert_allclose(image_to_crop_coords(np.array([[5, 5], [14, 14]]), (5, 5, 10), 20),
                               [[0.5, 0.5], [18.5, 18.5]])
    assert up[0, 1, 0] == 8 * 5 + 2 and up[0, 18, 0] == 8 * 14 - 2  # bilinear quarter steps


def test_sample_features_equals_upsampled_map_at_nearest_crop_pixel():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(5, 7, 7)).astype(np.float32)
    size, box = 28, (100, 50, 40)
    up = upsample_to_crop(feats, size)
    ref = torch.nn.functional.interpolate(torch.from_numpy(feats)[None], size=(size, size),
                                          mode="bilinear", align_corners=False)[0].numpy()
    np.testing.assert_allclose(up, ref, atol=1e-6)
    pix = np.stack([rng.integers(90, 150, 500), rng.integers(40, 100, 500)], axis=1)
    got = sample_features_at_pixels(feats, box, size, pix)
    c = np.clip(np.rint(image_to_crop_coords(pix, box, size)), 0, size - 1).astype(int)
    np.testing.assert_allclose(got, up[:, c[:, 1], c[:, 0]].T, atol=1e-5)


def _coloured_sphere() -> tuple[trimesh.Trimesh, np.ndarray]:
    """Bumpy ellipsoid (mm) with smooth vertex colours; returns (mesh, colours (V, 3) in [0, 1])."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v = np.asarray(mesh.vertices)
    mesh = trimesh.Trimesh(v * [60.0, 45.0, 35.0] * (1 + 0.1 * np.sin(3 * v[:, :1])), mesh.faces)
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    col = 0.5 + 0.4 * np.stack([np.sin(2 * u[:, 0] + 1), np.cos(3 * u[:, 1]), np.sin(2 * u[:, 2] - u[:, 0])], 1)
    mesh.visual = trimesh.visual.ColorVisuals(
        mesh, vertex_colors=np.concatenate([np.round(col * 255), np.full((len(v), 1), 255)], 1).astype(np.uint8)
    )
    return mesh, np.round(col * 255) / 255


@pytest.mark.parametrize("render_size, input_size", [(128, 128), (192, 96)])
def test_lift_model_visual_features_reproduces_vertex_colours(render_size, input_size):
    from pipeline.method.render.renderer import Lighting, Renderer

    mesh, colours = _coloured_sphere()
    diameter = 2 * 66.0
    dist = 3 * diameter
    f = render_size * dist / (1.2 * diameter)
    c = (render_size - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    # Ambient-only light of 1: pyrender then outputs the vertex colour gamma-encoded
    # (value ** (1 / 2.2)), with no shading.
    flat = Lighting(ambient=(1.0, 1.0, 1.0), lights=[])
    views = []
    with Renderer(render_size, render_size) as r:
        r.add_mesh("obj", mesh)
        dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                         [1, 1, 1], [-1, -1, 1], [1, -1, -1], [-1, 1, -1]], dtype=float)
        for d in dirs:
            d /= np.linalg.norm(d)
            R = look_at_rotation(d * dist)
            t = np.array([0, 0, dist])
            rgb, depth = r.render([("obj", R, t)], K, lighting=flat)
            views.append((rgb, depth, K, R, t))
    pts, _ = sample_surface(mesh, 3000, seed=0)
    feats, count = lift_model_visual_features(pts, views, PixelColourEncoder(input_size), batch_size=4,
                                              diameter=diameter)
    assert feats.shape == (3000, 3) and feats.dtype == np.float32 and count.shape == (3000,)
    assert count.min() >= 1 and count.max() <= len(views)
    # The renderer interpolates vertex colours over faces (nearest-vertex colours would
    # be off by up to ~0.03 on this 3.5 mm mesh), then gamma-encodes them.
    closest, _, tri = trimesh.proximity.closest_point(mesh, pts)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    expected = np.einsum("pk,pkc->pc", bary, colours[mesh.faces[tri]]) ** (1 / 2.2)
    err = np.abs(feats - expected)
    assert np.median(err) < 0.005
    assert np.quantile(err, 0.95) < 0.02
    assert err.max() < 0.06
    # Nearest-vertex colours (the coarser reference) agree too.
    _, nearest_vertex = cKDTree(mesh.vertices).query(pts)
    assert np.median(np.abs(feats - colours[nearest_vertex] ** (1 / 2.2))) < 0.03


def test_lift_model_visual_features_fills_unseen_points_and_checks_views():
    enc = PixelColourEncoder(8)
    depth = np.zeros((8, 8), np.float32)
    depth[3:5, 3:5] = 100.0
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[3:5, 3:5] = 255
    K = np.array([[100.0, 0, 3.5], [0, 100.0, 3.5], [0, 0, 1]])
    view = (rgb, depth, K, np.eye(3), np.zeros(3))
    pts = np.array([[0.0, 0.0, 100.0], [0.0, 0.0, 160.0]])  # seen, and 60 mm behind
    feats, count = lift_model_visual_features(pts, [view], enc, diameter=100.0, erode_px=0)
    np.testing.assert_array_equal(count, [1, 0])
    np.testing.assert_allclose(feats, np.ones((2, 3)), atol=1e-6)  # unseen copies its neighbour
    with pytest.raises(ValueError, match="square"):
        lift_model_visual_features(pts, [(rgb[:, :6], depth, K, np.eye(3), np.zeros(3))], enc)
    with pytest.raises(ValueError, match="no model point"):
        lift_model_visual_features(pts + 1000, [view], enc, diameter=100.0, erode_px=0)


def test_lift_scene_visual_features_reads_the_right_pixels():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, size=(60, 80, 3), dtype=np.uint8)
    pix = np.array([[30, 20], [41, 33], [35, 25]])
    bbox = (28, 18, 16, 16)
    # The crop side (20 = 16 * 1.25) equals the input size: no resampling, exact values.
    out = lift_scene_visual_features(img, bbox, pix, PixelColourEncoder(20), margin=0.125)
    np.testing.assert_allclose(out, img[pix[:, 1], pix[:, 0]] / 255.0, atol=1e-6)

"""Symmetry-aware refinement (pipeline.method.refinement.sar): crop rendering, symmetric
variants, the similarity score, and known-answer scenes where only the texture tells
the symmetric poses apart (soup can, cereal box) or nothing does (cup)."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402
from PIL import Image  # noqa: E402

from pipeline.method.encoders.lifting import crop_and_resize, image_to_crop_coords, mask_to_bbox, square_crop_box  # noqa: E402
from pipeline.method.encoders.registry import VisualEncoder, build_encoder  # noqa: E402
from pipeline.method.geometry.transforms import (  # noqa: E402
    look_at_rotation,
    perturb_pose,
    rotation_about_axis,
    rotation_angle_deg,
    rt_to_matrix,
)
from pipeline.method.refinement.sar import (  # noqa: E402
    cell_cover,
    coarse_variants,
    crop_intrinsics,
    render_in_crop,
    sar_similarity,
    symmetry_aware_refinement,
    unique_symmetries,
    variant_angles,
    variant_poses,
)
from pipeline.method.render.renderer import Light, Lighting, Renderer  # noqa: E402
from pipeline.evaluation.synth.objects import build_object  # noqa: E402
from pipeline.evaluation.synth.sensor import simulate_rgb  # noqa: E402

W, H = 640, 480
K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
# Scene light unlike the renders' headlight: a warm key light from the upper left, a
# cool lamp on the right, dim ambient (SAR must cope with the colour cast and shading).
SCENE_LIGHT = Lighting(
    ambient=(0.25, 0.24, 0.22),
    lights=[
        Light(kind="directional", direction=(0.5, 0.7, 0.5), color=(1.0, 0.93, 0.8), intensity=3.0),
        Light(kind="point", position=(-300.0, -300.0, 100.0), color=(0.85, 0.92, 1.0), intensity=1.5 * 500.0**2),
    ],
)


def _sym(axis, deg: float) -> np.ndarray:
    return rt_to_matrix(rotation_about_axis(axis, deg), np.zeros(3))


X, Y, Z = np.eye(3)
CAN_SYMS = np.stack([_sym(Z, a) for a in range(0, 360, 30)])  # identity included
BOX_SYMS = np.stack([_sym(X, 180), _sym(Y, 180), _sym(Z, 180)])  # identity left out


def _background(distance: float, rng: np.random.Generator) -> trimesh.Trimesh:
    """A textured wall (coloured tiles) facing the camera at ``distance`` mm."""
    tiles = np.kron(rng.uniform(70, 180, (48, 48, 3)).astype(np.uint8), np.ones((8, 8, 1), np.uint8))
    half = distance  # covers the 640x480 view (f = 600) with room to spare
    v = np.array([[-half, -half, distance], [half, -half, distance], [half, half, distance], [-half, half, distance]])
    mesh = trimesh.Trimesh(v, np.array([[0, 2, 1], [0, 3, 2]]), process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), image=Image.fromarray(tiles))
    return mesh


@pytest.fixture(scope="module")
def objects():
    return {i: build_object(i) for i in (1, 2, 6)}


@pytest.fixture(scope="module")
def renderer(objects):
    # One 640x480 renderer for the scenes and the crops (crops use its top-left
    # 224 x 224 corner). A second EGL renderer alive at the same time is avoided.
    with Renderer(W, H) as r:
        for i, obj in objects.items():
            r.add_mesh(i, obj.model)
        r.add_mesh("wall", _background(1500.0, np.random.default_rng(5)))
        yield r


@pytest.fixture(scope="module")
def colortex():
    return build_encoder({"name": "colortex"})


GT_EYES = {2: (500.0, -250.0, 250.0), 1: (350.0, -400.0, 300.0), 6: (400.0, -300.0, 250.0)}


@pytest.fixture(scope="module")
def scenes(renderer):
    """Per object: (rgb (H, W, 3) uint8, GT R, GT t, GT bbox) of a lit, noisy scene."""
    out = {}
    for obj_id, eye in GT_EYES.items():
        eye = np.asarray(eye)
        R = look_at_rotation(eye)
        t = np.array([15.0, -10.0, np.linalg.norm(eye)])
        color, _ = renderer.render([(obj_id, R, t), ("wall", np.eye(3), np.zeros(3))], K, lighting=SCENE_LIGHT)
        depth = renderer.render_depth(obj_id, R, t, K)
        rgb = simulate_rgb(color, np.random.default_rng(obj_id))
        out[obj_id] = (rgb, R, t, mask_to_bbox(depth > 0))
    return out


# ------------------------------------------------------------------- crop rendering


def test_crop_intrinsics_maps_projections_like_the_crop():
    rng = np.random.default_rng(0)
    Kc = np.array([[610.0, 0.7, 321.3], [0.0, 605.0, 244.1], [0.0, 0.0, 1.0]])
    pts = rng.uniform([-80, -60, 400], [80, 60, 900], (50, 3))
    for box, size in [((250, 170, 130), 224), ((100, -20, 400), 224), ((5, 9, 224), 224)]:
        uv = (pts @ Kc.T)[:, :2] / pts[:, 2:]
        expected = image_to_crop_coords(uv, box, size)
        Kcrop = crop_intrinsics(Kc, box, size)
        got = (pts @ Kcrop.T)[:, :2] / pts[:, 2:]
        np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize("distance", [600.0, 260.0])  # crop enlarged / crop shrunk
def test_render_in_crop_equals_cropped_full_render(renderer, objects, distance):
    R = look_at_rotation(np.array([1.0, -1.2, 0.8]))
    t = np.array([30.0, 20.0, distance])
    full_rgb, full_depth = renderer.render([(1, R, t)], K, lighting=None)
    box = square_crop_box(mask_to_bbox(full_depth > 0), (H, W), 0.1)
    assert (box[2] < 224) == (distance > 400)  # both resampling directions are covered
    ref_mask = crop_and_resize((full_depth > 0).astype(np.uint8) * 255, box, 224) >= 128
    ref_rgb = crop_and_resize(full_rgb, box, 224)
    rgb, mask = render_in_crop(renderer, 1, R, t, K, box, 224, lighting=Lighting())
    assert rgb.shape == (224, 224, 3) and rgb.dtype == np.uint8 and mask.shape == (224, 224)
    iou = (mask & ref_mask).sum() / (mask | ref_mask).sum()
    assert iou > 0.97, iou
    # Colours agree away from the silhouette (where resampling mixes in the background)
    # up to the resampling blur of the printed detail.
    inner = cv2.erode((mask & ref_mask).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    diff = np.abs(rgb.astype(int) - ref_rgb.astype(int))[inner]
    assert diff.mean() < 6.0, diff.mean()
    assert np.median(diff) <= 3


# ------------------------------------------------------------------- variants


def test_unique_symmetries_identity_first_and_deduplicated():
    jitter = _sym(Z, 180.0 + 0.1)
    jitter[:3, 3] = [0.2, 0.0, 0.0]
    S = unique_symmetries(np.concatenate([BOX_SYMS, [np.eye(4)], [jitter]]))
    assert S.shape == (4, 4, 4)
    np.testing.assert_allclose(S[0], np.eye(4))
    np.testing.assert_allclose(S[1:], BOX_SYMS)  # order kept, the near-copy dropped
    assert unique_symmetries(CAN_SYMS).shape == (12, 4, 4)
    assert unique_symmetries(None).shape == (1, 4, 4)
    assert unique_symmetries(np.zeros((0, 4, 4))).shape == (1, 4, 4)
    with pytest.raises(ValueError):
        unique_symmetries([np.diag([1.0, 1.0, -1.0, 1.0])])  # a reflection


def test_variant_poses_compose_on_the_model_side():
    R = look_at_rotation(np.array([0.3, -1.0, 0.5]))
    t = np.array([5.0, -3.0, 700.0])
    # A symmetry about an axis that misses the origin has a translation part.
    off = np.array([10.0, 0.0, 0.0])
    S_off = rt_to_matrix(rotation_about_axis(Z, 90), off - rotation_about_axis(Z, 90) @ off)
    Rs, ts = variant_poses(R, t, [S_off, np.eye(4)])
    assert Rs.shape == (2, 3, 3) and ts.shape == (2, 3)
    np.testing.assert_allclose(Rs[0], R)
    np.testing.assert_allclose(ts[0], t)
    pts = np.random.default_rng(1).normal(size=(20, 3)) * 50
    expected = (rt_to_matrix(R, t) @ S_off @ np.c_[pts, np.ones(20)].T).T[:, :3]
    np.testing.assert_allclose(pts @ Rs[1].T + ts[1], expected, atol=1e-9)


def test_variants_of_a_symmetric_shape_have_the_same_silhouette(renderer, scenes):
    _, R, t, _ = scenes[1]
    Rs, ts = variant_poses(R, t, BOX_SYMS)
    assert len(Rs) == 4
    masks = [renderer.render_depth(1, Rv, tv, K) > 0 for Rv, tv in zip(Rs, ts)]
    for m in masks[1:]:
        assert (m & masks[0]).sum() / (m | masks[0]).sum() > 0.99


# ------------------------------------------------------------------- the score


class GridEncoder(VisualEncoder):
    """Test stub: the crop's mean colour per cell of a 7 x 7 grid over S = 30 (cells
    span fractional pixels), minus mid-grey (127.5) so that colours point different ways."""

    name = "grid"
    version = "0"
    dim = 3
    input_size = 30

    def cache_params(self):
        return {}

    def encode(self, images):
        images = self.check_images(images)
        return np.stack([cv2.resize(im.astype(np.float32) - 127.5, (7, 7), interpolation=cv2.INTER_AREA).transpose(2, 0, 1)
                         for im in images])


def test_cell_cover_and_similarity_known_answers():
    m = np.zeros((1, 4, 4), bool)
    m[0, :2, :] = True
    m[0, 2, 0] = True
    np.testing.assert_allclose(cell_cover(m, (2, 2))[0], [[1.0, 1.0], [0.25, 0.0]])
    # Cells spanning fractional pixels (30 px over 7 cells): cell 3 is [12.86, 17.14).
    m = np.zeros((1, 30, 30), bool)
    m[0, :, :15] = True
    np.testing.assert_allclose(cell_cover(m, (7, 7))[0, 0], [1, 1, 1, 0.5, 0, 0, 0], atol=1e-6)

    enc = GridEncoder()
    rng = np.random.default_rng(0)
    scene = rng.integers(0, 256, (30, 30, 3), dtype=np.uint8)
    renders = np.stack([scene, 255 - scene, scene, scene])
    masks = np.ones((4, 30, 30), bool)
    masks[2] = False  # covers nothing
    masks[3, :, 10:] = False  # covers about a third: scored on those cells only
    for centre in (False, True):
        s = sar_similarity(enc, scene, renders, masks, centre=centre, batch_size=3)
        assert s.shape == (4,)
        np.testing.assert_allclose(s[[0, 1, 3]], [1.0, -1.0, 1.0], atol=1e-5)
        assert s[2] == -np.inf


def test_single_variant_renders_nothing(scenes, colortex):
    rgb, R, t, bbox = scenes[2]
    res = symmetry_aware_refinement(None, 2, colortex, rgb, K, bbox, R, t, [np.eye(4)])
    assert res.index == 0 and not res.changed and len(res.Rs) == 1 and np.isnan(res.similarities).all()


# ------------------------------------------------------------------- known-answer scenes


def _check_sar(renderer, encoder, scene, obj_id, syms, start_sym, perturb_deg=0.0):
    rgb, R_gt, t_gt, bbox = scene
    R0 = R_gt @ start_sym[:3, :3]
    t0 = t_gt + R_gt @ start_sym[:3, 3]
    if perturb_deg:
        # ICP leaves a small error: SAR must still pick the variant next to the truth.
        R0, t0 = perturb_pose(R0, t0, perturb_deg, 1.0, rng=7)
    res = symmetry_aware_refinement(renderer, obj_id, encoder, rgb, K, bbox, R0, t0, syms)
    err = rotation_angle_deg(res.R, R_gt)
    assert err < perturb_deg + 0.5, (err, res.index, np.round(res.similarities, 3))
    assert np.linalg.norm(res.t - t_gt) < 1.5
    return res


@pytest.mark.parametrize("start_deg", [0, 90, 180])
def test_sar_recovers_the_can_label(renderer, colortex, scenes, start_deg):
    res = _check_sar(renderer, colortex, scenes[2], 2, CAN_SYMS, _sym(Z, start_deg), perturb_deg=2.0 if start_deg else 0.0)
    assert len(res.similarities) == 12
    assert res.changed == (start_deg != 0)


def test_coarse_variants_of_a_sampled_axis_and_its_flip():
    """A can's 12 turns about its axis and the same 12 flipped: the coarse pass keeps
    every other turn of each (60 deg) or every third (90 deg); the 4 box variants are all
    at least 180 deg apart and all kept."""
    flip = _sym(X, 180)
    syms = np.concatenate([CAN_SYMS, flip[None] @ CAN_SYMS])
    angles = variant_angles(syms)
    assert angles.shape == (24, 24) and np.allclose(np.diag(angles), 0.0, atol=1e-4)
    assert coarse_variants(angles, 60.0) == [0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22]
    assert coarse_variants(angles, 90.0) == [0, 3, 6, 9, 12, 15, 18, 21]
    box = unique_symmetries(BOX_SYMS)
    assert coarse_variants(variant_angles(box), 60.0) == [0, 1, 2, 3]


@pytest.mark.parametrize("start_deg", [90, 150, 180])
def test_coarse_to_fine_sar_finds_the_label_with_fewer_renders(renderer, colortex, scenes, start_deg):
    """The coarse-to-fine search ends on the variant the exhaustive one chooses, with the
    same similarity for every variant it scored, and at 60 deg scores at most 10 of the
    12 (6 coarse, then 30 deg either side of the two best; at 90 deg two opposite leads
    can need all 12)."""
    rgb, R_gt, t_gt, bbox = scenes[2]
    S = _sym(Z, start_deg)
    R0, t0 = perturb_pose(R_gt @ S[:3, :3], t_gt, 2.0, 1.0, rng=7)
    every = symmetry_aware_refinement(renderer, 2, colortex, rgb, K, bbox, R0, t0, CAN_SYMS)
    for coarse in (60.0, 90.0):
        fast = symmetry_aware_refinement(renderer, 2, colortex, rgb, K, bbox, R0, t0, CAN_SYMS, coarse_deg=coarse)
        assert fast.index == every.index and rotation_angle_deg(fast.R, R_gt) < 2.5
        scored = ~np.isnan(fast.similarities)
        assert scored.sum() <= (10 if coarse == 60.0 else 12), (coarse, scored.sum())
        np.testing.assert_allclose(fast.similarities[scored], every.similarities[scored], rtol=1e-6)


@pytest.mark.parametrize("start", ["identity", "x", "y", "z"])
def test_sar_recovers_the_cereal_box_print(renderer, colortex, scenes, start):
    S = np.eye(4) if start == "identity" else _sym({"x": X, "y": Y, "z": Z}[start], 180)
    res = _check_sar(renderer, colortex, scenes[1], 1, BOX_SYMS, S, perturb_deg=0.0 if start == "identity" else 2.0)
    assert len(res.similarities) == 4
    assert res.changed == (start != "identity")


def test_sar_works_with_the_rgb_encoder(renderer, scenes):
    _check_sar(renderer, build_encoder({"name": "rgb"}), scenes[1], 1, BOX_SYMS, _sym(Y, 180))


@pytest.mark.slow
def test_sar_keeps_the_pose_when_all_variants_look_alike(renderer, colortex, scenes):
    """The cup's colour bands go all the way round: every variant about its axis renders
    the same image up to tessellation, so the scores tie to ~1e-4. With ``min_gain``
    above that, SAR keeps the ICP pose; with ``min_gain=0`` it follows the noise, which
    only turns the cup about its own axis (a pose equivalent under its symmetry)."""
    rgb, R, t, bbox = scenes[6]
    res = symmetry_aware_refinement(renderer, 6, colortex, rgb, K, bbox, R, t, CAN_SYMS, min_gain=0.005)
    assert np.ptp(res.similarities) < 0.002, np.ptp(res.similarities)
    assert res.index == 0 and res.gain == 0.0
    np.testing.assert_allclose(res.R, R)
    res0 = symmetry_aware_refinement(renderer, 6, colortex, rgb, K, bbox, R, t, CAN_SYMS, min_gain=0.0)
    np.testing.assert_allclose(res0.R[:, 2], R[:, 2], atol=1e-9)  # the axis stays put
    np.testing.assert_allclose(res0.t, t)

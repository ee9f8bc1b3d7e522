"""Encoder registry, FPFH and colortex: shapes, determinism and claimed invariances."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from pipeline.method.encoders.colortex import ColorTexEncoder
from pipeline.method.encoders.fpfh import FpfhEncoder
from pipeline.formats.weights.formats import WeightsNotFound
from pipeline.method.encoders.registry import (
    EncoderSpec,
    GeometricEncoder,
    VisualEncoder,
    build_encoder,
    known_encoders,
    register_encoder,
)
from pipeline.method.geometry.sampling import sample_surface
from pose_helpers import random_rotation

# --- registry ---------------------------------------------------------------------


def test_builtin_encoders_are_registered():
    known = known_encoders()
    assert known["fpfh"] == "geometric"
    assert known["colortex"] == "visual"


def test_unknown_encoder_lists_known_ones():
    with pytest.raises(ValueError) as err:
        build_encoder(EncoderSpec(name="gedi-xl"))
    assert "gedi-xl" in str(err.value)
    assert "fpfh" in str(err.value) and "colortex" in str(err.value)


def test_bad_params_are_reported_with_encoder_name():
    with pytest.raises(ValueError, match="fpfh.*invalid params"):
        build_encoder({"name": "fpfh", "params": {"radius": 0.3}})
    with pytest.raises(ValueError, match="plain JSON"):
        EncoderSpec(name="fpfh", params={"radii": np.array([0.3])})
    with pytest.raises(ValueError, match="contain no '_'"):
        register_encoder("my_enc", "visual", ColorTexEncoder)


@pytest.mark.parametrize(
    "spec, kind, dim, signature",
    [
        ({"name": "fpfh"}, "geometric", 66, "fpfh-ms"),
        ({"name": "fpfh", "params": {"radii": [0.1]}}, "geometric", 33, "fpfh"),
        ({"name": "colortex"}, "visual", 30, "colortex"),
        ({"name": "colortex", "params": {"intensity_weight": 0.2, "sigmas": [1, 2]}}, "visual", 18, "colortex"),
        ({"name": "none-geometric"}, "geometric", 0, "nogeo"),
        ({"name": "none-visual"}, "visual", 0, "novis"),
    ],
)
def test_build_encoder_metadata(spec, kind, dim, signature):
    enc = build_encoder(spec)
    assert enc.kind == kind and enc.dim == dim
    assert enc.signature() == signature and "_" not in enc.signature()
    assert isinstance(enc.version, str) and enc.version
    params = enc.cache_params()
    assert json.loads(json.dumps(params)) == params
    # Every spec param shows up in the cache params (so it reaches the cache key).
    for key in spec.get("params", {}):
        assert key in params
    assert isinstance(enc, GeometricEncoder if kind == "geometric" else VisualEncoder)


# --- FPFH -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bumpy_cloud():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v = mesh.vertices
    mesh.vertices = v * (1 + 0.15 * np.sin(3 * v[:, :1]) * np.cos(2 * v[:, 1:2]))[:, :1] * [60, 45, 35]
    pts, nrm = sample_surface(mesh, 1500, seed=0)
    return pts, nrm, float(np.ptp(pts, axis=0).max())


def test_fpfh_shape_norm_and_rigid_invariance(bumpy_cloud):
    pts, nrm, diameter = bumpy_cloud
    enc = FpfhEncoder(radii=[0.15, 0.25])
    f = enc.encode(pts, nrm, diameter)
    assert f.shape == (len(pts), 66) and f.dtype == np.float32
    assert np.isfinite(f).all()
    np.testing.assert_allclose(np.linalg.norm(f[:, :33], axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(f[:, 33:], axis=1), 1.0, atol=1e-5)
    R, t = random_rotation(5), np.array([30.0, -20.0, 700.0])
    f2 = enc.encode((pts @ R.T + t).astype(np.float32), (nrm @ R.T).astype(np.float32), diameter)
    # Equal except where float32 round-off moves a neighbour across the radius.
    diff = np.abs(f2 - f)
    assert np.quantile(diff, 0.99) < 1e-4 and diff.max() < 0.02


def test_fpfh_estimated_normals_match_outward_model_normals(bumpy_cloud):
    """Scene-style call (normals None, camera at the origin) on the visible side gives
    descriptors close to those computed with the true outward normals."""
    pts, nrm, diameter = bumpy_cloud
    cam_pts = pts + np.array([0, 0, 600.0], dtype=np.float32)
    visible = np.sum(nrm * -cam_pts, axis=1) > 0
    enc = FpfhEncoder(radii=[0.25])
    f_true = enc.encode(cam_pts[visible], nrm[visible], diameter)
    f_est = enc.encode(cam_pts[visible], None, diameter, viewpoint=np.zeros(3))
    cos = np.sum(f_true * f_est, axis=1)
    assert np.median(cos) > 0.97
    # With normals flipped inwards the descriptors differ: orientation matters.
    f_flip = enc.encode(cam_pts[visible], -nrm[visible], diameter)
    assert np.median(np.sum(f_true * f_flip, axis=1)) < np.median(cos) - 0.05


def test_fpfh_rejects_bad_input():
    with pytest.raises(ValueError, match="radii"):
        FpfhEncoder(radii=[])
    with pytest.raises(ValueError, match="normals shape"):
        FpfhEncoder().encode(np.zeros((5, 3), np.float32), np.zeros((4, 3), np.float32), 10.0)


# --- colortex ---------------------------------------------------------------------


def _textured_patch(S: int = 96, seed: int = 0) -> np.ndarray:
    """Asymmetric smooth colour texture (S, S, 3) uint8 with values in ~[40, 200]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:S, 0:S].astype(np.float64)
    img = np.full((S, S, 3), 120.0)
    for c in range(3):
        for _ in range(4):
            k = rng.normal(size=2) * 0.15
            img[..., c] += 20 * np.sin(k[0] * x + k[1] * y + rng.uniform(0, 6.3))
    blob = np.exp(-((x - 0.3 * S) ** 2 + (y - 0.6 * S) ** 2) / (2 * (0.08 * S) ** 2))
    img[..., 0] += 60 * blob
    img[..., 2] -= 50 * blob
    return np.clip(img, 0, 255).round().astype(np.uint8)


def test_colortex_shape_and_finite():
    enc = ColorTexEncoder(input_size=96, stride=4, sigmas=[1, 2, 4, 8])
    imgs = np.stack([_textured_patch(96, s) for s in range(3)])
    imgs[2] = 0  # a black image must not produce NaNs
    f = enc.encode(imgs)
    assert f.shape == (3, 20, 24, 24) and f.dtype == np.float32
    assert np.isfinite(f).all()
    with pytest.raises(ValueError, match="expected images"):
        enc.encode(imgs[:, :64])


def test_colortex_rotation_by_90_degrees_rotates_the_map():
    enc = ColorTexEncoder(input_size=96, stride=4, sigmas=[1, 2, 4, 8], intensity_weight=1.0)
    img = _textured_patch(96, 1)
    f = enc.encode(img[None])[0]
    for k in (1, 2, 3):
        fr = enc.encode(np.ascontiguousarray(np.rot90(img, k))[None])[0]
        np.testing.assert_allclose(fr, np.rot90(f, k, axes=(1, 2)), atol=1e-5)


def test_colortex_brightness_invariance():
    enc = ColorTexEncoder(input_size=96, stride=4, sigmas=[1, 2, 4, 8], intensity_weight=1.0)
    img = _textured_patch(96, 2)
    f = enc.encode(img[None])[0]
    rms = np.sqrt(np.mean(f.reshape(enc.dim, -1) ** 2, axis=1))
    # Illumination 40 % dimmer. Left: uint8 rounding and the small offsets that keep
    # dark pixels stable (e, e_L in the docstring): a few % of each channel's magnitude.
    dark = np.round(img.astype(np.float64) * 0.6).astype(np.uint8)
    fd = enc.encode(dark[None])[0]
    err = np.abs(fd - f).reshape(enc.dim, -1)
    mean_rel, max_rel = err.mean(axis=1) / rms, err.max(axis=1) / rms
    names = enc.channel_names()
    assert np.all(mean_rel < 0.04), dict(zip(names, mean_rel.round(3)))
    assert np.all(max_rel < 0.2), dict(zip(names, max_rel.round(3)))
    # A colour change (not a brightness change) does alter the chromaticity channels.
    tinted = img.copy()
    tinted[..., 2] = (tinted[..., 2] * 0.6).astype(np.uint8)
    ft = enc.encode(tinted[None])[0]
    assert np.abs(ft[0:2] - f[0:2]).mean() > 10 * np.abs(fd[0:2] - f[0:2]).mean()


def test_empty_encoders_give_zero_channels_and_lifting_skips_them():
    from pipeline.method.encoders.lifting import lift_model_visual_features, sample_features_at_pixels

    geo, vis = build_encoder({"name": "none-geometric"}), build_encoder({"name": "none-visual"})
    pts = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)
    assert geo.encode(pts, None, 1.0).shape == (7, 0)
    assert vis.encode(np.zeros((2, 224, 224, 3), np.uint8)).shape == (2, 0, 1, 1)
    assert sample_features_at_pixels(np.zeros((0, 1, 1), np.float32), (0, 0, 224), 224, np.zeros((5, 2))).shape == (5, 0)

    class Exploding(type(vis)):
        def encode(self, images):
            raise AssertionError("a 0-d encoder must not be called")

    # one view looking at a flat square at z = 100 mm: every point is seen
    depth = np.full((32, 32), 100.0, np.float32)
    K = np.array([[32.0, 0, 15.5], [0, 32.0, 15.5], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(4, 28, 4), np.arange(4, 28, 4))
    model = np.stack([(u.ravel() - 15.5) * 100 / 32, (v.ravel() - 15.5) * 100 / 32, np.zeros(u.size)], 1)
    view = (np.zeros((32, 32, 3), np.uint8), depth, K, np.eye(3), np.array([0.0, 0.0, 100.0]))
    feats, count = lift_model_visual_features(model, [view], Exploding(), diameter=100.0)
    assert feats.shape == (len(model), 0) and (count == 1).all()


def test_every_encoder_manifest_builds_or_names_its_missing_weights(tmp_path, monkeypatch):
    """Each manifest validates; built against an empty weights folder it either needs no
    weights or fails with WeightsNotFound listing the paths it looked in."""
    from pipeline.common.config import MANIFEST_DIR, load_encoder_manifest
    from pipeline.method.encoders.registry import needs_weights

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # no hub-cache weights either
    names = sorted(p.stem for p in (MANIFEST_DIR / "encoders").glob("*.yaml"))
    assert {"fpfh", "colortex", "gedi", "dinov2-vits14", "none-visual", "none-geometric"} <= set(names)
    for name in names:
        man = load_encoder_manifest(name)
        spec = EncoderSpec(name=man.encoder, params=dict(man.params))
        if needs_weights(man.encoder):
            with pytest.raises(WeightsNotFound) as err:
                build_encoder(spec, weights_dir=tmp_path / "empty")
            assert err.value.looked_in and all(str(tmp_path) in str(p) or "hub" in str(p) for p in err.value.looked_in)
        else:
            assert build_encoder(spec, weights_dir=tmp_path / "empty").kind == man.kind


def test_encoder_manifests_extend_a_base_that_is_not_listed(tmp_path):
    """`extends:` in an encoder manifest merges the file over its base (a nested mapping
    key by key, a list replaced); the bases under encoders/base/ are not encoders."""
    from pipeline.common.config import encoder_manifest_names, load_encoder_manifest

    names = encoder_manifest_names()
    assert "dinov2-vits14" in names and not any(n.startswith("base") or "/" in n for n in names)
    fp32, bf16 = load_encoder_manifest("dinov2-vits14-fp32"), load_encoder_manifest("dinov2-vits14")
    assert fp32.params["precision"] == "fp32" and bf16.params["precision"] == "auto"
    assert fp32.params["model"] == bf16.params["model"] == "vits14"
    assert fp32.params["input_size"] == 224  # from base/dinov2.yaml, two levels up
    (tmp_path / "encoders" / "base").mkdir(parents=True)
    (tmp_path / "encoders" / "base" / "b.yaml").write_text("encoder: fpfh\nkind: geometric\nparams: {a: 1, b: 2}\n")
    (tmp_path / "encoders" / "x.yaml").write_text("extends: base/b.yaml\nparams: {b: 3}\n")
    assert load_encoder_manifest("x", tmp_path).params == {"a": 1, "b": 3}
    assert encoder_manifest_names(tmp_path) == ["x"]

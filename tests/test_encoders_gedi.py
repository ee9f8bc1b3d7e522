"""GeDi: torch PointNet++ ops against brute-force references of the CUDA kernels' rules."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from pipeline.method.encoders.gedi_ops import (
    ball_query,
    ball_query_hits,
    first_of_each_key,
    furthest_point_sample,
    furthest_point_sample_with_sqdist,
    gather_points,
    group_points,
)

# --- brute-force references (one point at a time, as the kernels loop) ---------------


def _fps_ref(xyz: np.ndarray, m: int) -> list[int]:
    xyz = xyz.astype(np.float32)
    n = len(xyz)
    temp = [np.float32(1e10)] * n
    idx = [0]
    old = 0
    for _ in range(1, m):
        x1, y1, z1 = xyz[old]
        best, besti = np.float32(-1), 0
        for k in range(n):
            x2, y2, z2 = xyz[k]
            if float(x2 * x2 + y2 * y2 + z2 * z2) <= 1e-3:  # float mag against the double 1e-3
                continue
            d = (x2 - x1) * (x2 - x1) + (y2 - y1) * (y2 - y1) + (z2 - z1) * (z2 - z1)
            d2 = min(d, temp[k])
            temp[k] = d2
            if d2 > best:
                best, besti = d2, k
        old = besti
        idx.append(old)
    return idx


def _ball_ref(radius: float, nsample: int, xyz: np.ndarray, query: np.ndarray) -> np.ndarray:
    xyz = xyz.astype(np.float32)
    r2 = np.float32(radius) * np.float32(radius)  # the kernel's float radius * radius
    out = np.zeros((len(query), nsample), dtype=np.int64)
    for j, (x1, y1, z1) in enumerate(query.astype(np.float32)):
        cnt = 0
        for k in range(len(xyz)):
            x2, y2, z2 = xyz[k]
            d2 = (x2 - x1) * (x2 - x1) + (y2 - y1) * (y2 - y1) + (z2 - z1) * (z2 - z1)
            if d2 < r2:
                if cnt == 0:
                    out[j, :] = k
                out[j, cnt] = k
                cnt += 1
                if cnt >= nsample:
                    break
    return out


# --- farthest-point sampling -------------------------------------------------------------


def test_fps_matches_reference_batched():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, size=(3, 300, 3)).astype(np.float32)
    xyz[1, :40] *= 0.01  # points near the origin are skipped by the kernel
    got = furthest_point_sample(torch.from_numpy(xyz), 64).numpy()
    assert got.shape == (3, 64) and got.dtype == np.int64
    for b in range(3):
        assert got[b].tolist() == _fps_ref(xyz[b], 64)
    assert got[:, 0].tolist() == [0, 0, 0]
    near = set(range(1, 40))
    assert not near & set(got[1, 1:].tolist())
    assert len(set(got[0].tolist())) == 64


def test_fps_ties_go_to_lowest_index_and_all_skipped_gives_zero():
    # duplicated points: equal running distances, the lower index wins
    xyz = np.array([[1, 0, 0], [0, 1, 0], [0, 1, 0], [-1, 0, 0], [-1, 0, 0]], np.float32)
    got = furthest_point_sample(torch.from_numpy(xyz)[None], 5)[0].tolist()
    assert got == _fps_ref(xyz, 5)
    assert got[1] == 3 and got[2] == 1
    tiny = np.full((1, 6, 3), 0.001, np.float32)
    assert furthest_point_sample(torch.from_numpy(tiny), 4)[0].tolist() == [0, 0, 0, 0]


def test_fps_asks_more_than_available():
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(1, 10, 3)).astype(np.float32)
    got = furthest_point_sample(torch.from_numpy(xyz), 16)[0].tolist()
    assert got == _fps_ref(xyz[0], 16)
    assert sorted(set(got)) == list(range(10))


# --- ball query ---------------------------------------------------------------------------


@pytest.mark.parametrize("radius, nsample", [(0.2, 32), (0.4, 16), (0.05, 8), (3.0, 4)])
def test_ball_query_matches_reference(radius, nsample):
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-1, 1, size=(2, 400, 3)).astype(np.float32)
    query = np.concatenate([xyz[:, :20], rng.uniform(-1.5, 1.5, size=(2, 20, 3)).astype(np.float32)], axis=1)
    got = ball_query(radius, nsample, torch.from_numpy(xyz), torch.from_numpy(query)).numpy()
    assert got.shape == (2, 40, nsample) and got.dtype == np.int64
    for b in range(2):
        np.testing.assert_array_equal(got[b], _ball_ref(radius, nsample, xyz[b], query[b]))


def test_ball_query_padding_and_no_hit():
    xyz = np.array([[5, 0, 0], [0, 0, 0], [0.1, 0, 0], [9, 9, 9]], np.float32)
    query = np.array([[0, 0, 0], [-7, -7, -7]], np.float32)
    got = ball_query(0.5, 5, torch.from_numpy(xyz)[None], torch.from_numpy(query)[None])[0].tolist()
    assert got == [[1, 2, 1, 1, 1], [0, 0, 0, 0, 0]]
    # strict inequality: a point exactly at the radius is outside
    edge = np.array([[1, 0, 0], [0.5, 0, 0]], np.float32)
    got = ball_query(1.0, 2, torch.from_numpy(edge)[None], torch.zeros(1, 1, 3))[0].tolist()
    assert got == [[1, 1]]


def test_ball_query_nsample_larger_than_cloud():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-1, 1, size=(1, 6, 3)).astype(np.float32)
    q = xyz[:, :2]
    got = ball_query(10.0, 9, torch.from_numpy(xyz), torch.from_numpy(q))[0].numpy()
    np.testing.assert_array_equal(got, _ball_ref(10.0, 9, xyz[0], q[0]))
    assert got[0].tolist() == [0, 1, 2, 3, 4, 5, 0, 0, 0]


def test_fps_distances_are_the_ball_query_distances():
    rng = np.random.default_rng(8)
    xyz = rng.uniform(-1, 1, size=(2, 200, 3)).astype(np.float32)
    xyz[0, :30] *= 0.01  # skipped by the sampling, still in the distances
    t = torch.from_numpy(xyz)
    idx, sq = furthest_point_sample_with_sqdist(t, 48)
    assert torch.equal(idx, furthest_point_sample(t, 48)) and sq.shape == (2, 48, 200)
    centres = gather_points(t, idx).numpy()
    d = centres[:, :, None, :] - xyz[:, None, :, :]  # float32, summed as the kernels: x + y, then + z
    expected = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    np.testing.assert_array_equal(sq.numpy(), expected)
    for radius, nsample in [(0.3, 32), (0.6, 8)]:
        reused = ball_query_hits(radius, nsample, t, gather_points(t, idx), sq)
        fresh = ball_query_hits(radius, nsample, t, gather_points(t, idx))
        assert all(torch.equal(a, b) for a, b in zip(reused, fresh))


@pytest.mark.parametrize("radius, nsample", [(0.2, 32), (0.05, 8)])
def test_ball_query_hits_are_the_ball_query_without_padding(radius, nsample):
    rng = np.random.default_rng(9)
    xyz = rng.uniform(-1, 1, size=(2, 300, 3)).astype(np.float32)
    query = np.concatenate([xyz[:, :10], rng.uniform(-1.5, 1.5, size=(2, 10, 3)).astype(np.float32)], axis=1)
    q, p = ball_query_hits(radius, nsample, torch.from_numpy(xyz), torch.from_numpy(query))
    assert (torch.diff(q * 300 + p) > 0).all()  # sorted by query, then point; no repeats
    for b in range(2):
        ref = _ball_ref(radius, nsample, xyz[b], query[b])
        for s in range(20):
            # the padding repeats the first hit; a query without hits gets point 0
            assert p[q == b * 20 + s].tolist() == sorted(set(ref[s].tolist())), (b, s)


def test_first_of_each_key():
    group = torch.tensor([0, 0, 0, 1, 1, 2, 2, 2])
    key = torch.tensor([5, 3, 5, 5, 5, 0, 7, 0])
    assert first_of_each_key(group, key).tolist() == [0, 1, 3, 5, 6]
    assert first_of_each_key(group[:0], key[:0]).tolist() == []


def test_gather_and_group():
    rng = np.random.default_rng(4)
    pts = torch.from_numpy(rng.normal(size=(2, 7, 3)).astype(np.float32))
    idx = torch.tensor([[[0, 6], [3, 3]], [[1, 2], [5, 0]]])
    g = gather_points(pts, idx)
    assert g.shape == (2, 2, 2, 3)
    assert torch.equal(g[1, 1, 0], pts[1, 5])
    feats = pts.transpose(1, 2)
    grouped = group_points(feats, idx)
    assert grouped.shape == (2, 3, 2, 2)
    assert torch.equal(grouped[0, :, 0, 1], pts[0, 6])
    assert torch.equal(grouped.permute(0, 2, 3, 1), g)


# --- GeDi network, frame and encoder --------------------------------------------------------

from pipeline.method.encoders.gedi import (  # noqa: E402
    STATE_KEY,
    GeDiEncoder,
    GeDiInference,
    GeDiNet,
    fold_layers,
    load_gedi_net,
    local_reference_frame,
    save_random_checkpoint,
    torch_threads,
)
from pipeline.method.encoders.registry import build_encoder, known_encoders  # noqa: E402

# parameter names of the official pnet_model_state_dict (a sample; the strict load checks all)
OFFICIAL_KEYS = [
    "qnet.conv1.0.weight", "qnet.conv1.1.running_var", "qnet.conv3.1.num_batches_tracked",
    "qnet.fc1.0.weight", "qnet.fc2.1.bias", "qnet.fc3.weight", "qnet.fc3.bias",
    "samodule1.mlps.0.0.weight", "samodule1.mlps.0.1.running_mean", "samodule1.mlps.0.6.weight",
    "samodule2.mlps.0.0.weight", "samodule3.mlps.0.7.bias",
    "fc_layer.0.weight", "fc_layer.1.running_mean", "fc_layer.3.weight", "fc_layer.4.weight",
    "fc_layer.7.weight", "fc_layer.7.bias",
]


@pytest.fixture(scope="module")
def gedi_weights(tmp_path_factory):
    """Random weights saved in the official checkpoint layout, with batch-norm statistics
    calibrated on random patches (as training would leave them; with the default
    statistics a random net maps every patch to almost the same descriptor)."""
    return save_random_checkpoint(tmp_path_factory.mktemp("gedi") / "chkpt.tar", seed=0, extra={"epoch": 3})


def test_network_has_official_parameter_names(gedi_weights):
    keys = set(GeDiNet().state_dict())
    assert set(OFFICIAL_KEYS) <= keys
    assert len([k for k in keys if k.startswith("qnet.")]) == 5 * 6 + 2  # 5 conv/fc + BN (5 entries) blocks, fc3
    net = load_gedi_net(gedi_weights)
    saved = torch.load(gedi_weights, weights_only=True)[STATE_KEY]
    for k, v in net.state_dict().items():
        assert torch.equal(v, saved[k]), k


def test_strict_load_rejects_other_layouts(tmp_path, gedi_weights):
    state = torch.load(gedi_weights, weights_only=True)[STATE_KEY]
    bad = tmp_path / "bad.tar"
    torch.save({STATE_KEY: {k: v for k, v in state.items() if not k.startswith("fc_layer.7")}}, bad)
    with pytest.raises(RuntimeError, match="fc_layer.7"):
        load_gedi_net(bad)
    torch.save(state, bad)
    with pytest.raises(ValueError, match=STATE_KEY):
        load_gedi_net(bad)


def test_missing_weights_fail_at_build_with_clear_message(tmp_path):
    missing = tmp_path / "nowhere" / "chkpt.tar"
    with pytest.raises(FileNotFoundError, match="weights file not found.*chkpt.tar.*'weights' parameter"):
        build_encoder({"name": "gedi", "params": {"weights": str(missing)}})
    assert known_encoders()["gedi"] == "geometric"


def test_relative_weights_are_taken_from_the_weights_folder(tmp_path, monkeypatch, gedi_weights):
    wdir = tmp_path / "w"
    (wdir / "gedi").mkdir(parents=True)
    shutil.copy(gedi_weights, wdir / "gedi" / "chkpt.tar")
    monkeypatch.delenv("FREEZE_WEIGHTS", raising=False)
    enc = build_encoder({"name": "gedi", "params": {"weights": "gedi/chkpt.tar"}}, weights_dir=wdir)
    assert enc.weights == (wdir / "gedi" / "chkpt.tar").resolve()
    monkeypatch.setenv("FREEZE_WEIGHTS", str(wdir))
    assert build_encoder({"name": "gedi"}).weights == enc.weights  # default: gedi/chkpt.tar there
    direct = build_encoder({"name": "gedi", "params": {"weights": str(gedi_weights)}})
    assert direct.cache_params() == enc.cache_params()  # keyed on the checksum, not the place
    with pytest.raises(FileNotFoundError) as err:
        build_encoder({"name": "gedi"}, weights_dir=tmp_path / "empty")
    assert err.value.looked_in == [(tmp_path / "empty" / "gedi" / "chkpt.tar").resolve()]


def test_network_output_shape_and_norm(gedi_weights):
    net = load_gedi_net(gedi_weights)
    torch.manual_seed(1)
    with torch.inference_mode():
        scales = torch.tensor([0.1, 0.3, 0.6, 1.0, 1.5]).view(5, 1, 1)
        out = net((torch.rand(5, 3, 256) * 2 - 1) * scales)
    assert out.shape == (5, 32)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(5))
    assert (out @ out.T)[torch.triu_indices(5, 5, 1).unbind()].max() < 0.999  # patches are told apart


def _frame_cloud(seed: int) -> np.ndarray:
    """A curved, asymmetric patch around the origin (the keypoint at index 0)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-1, 1, size=(800, 2))
    h = 0.3 * uv[:, 0] ** 2 + 0.1 * uv[:, 1] ** 2 + 0.15 * uv[:, 0] * uv[:, 1] + 0.05 * uv[:, 0] ** 3
    pts = np.column_stack([uv, h])
    pts[0] = 0
    return pts


def test_lrf_is_rotation_equivariant_and_orthonormal():
    pts = _frame_cloud(0)
    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    t = np.array([3.0, -2.0, 7.0])
    a = local_reference_frame(torch.from_numpy(pts[:1]), torch.from_numpy(pts[None]), 1.5)[0].numpy()
    moved = pts @ R.T + t
    b = local_reference_frame(torch.from_numpy(moved[:1]), torch.from_numpy(moved[None]), 1.5)[0].numpy()
    np.testing.assert_allclose(a.T @ a, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(b, R @ a, atol=1e-9)  # same axes, carried by the rotation
    # z: smallest-variance direction, pointing so that sum z.(p - q) >= 0
    assert abs(a[2, 2]) > 0.9 and (pts[:1] - pts) @ a[:, 2] @ np.ones(len(pts)) >= 0


def test_lrf_planar_guard():
    rng = np.random.default_rng(6)
    flat = np.column_stack([rng.uniform(-1, 1, (300, 2)) * [1.0, 0.4], np.zeros(300)])
    flat[0] = 0
    f = local_reference_frame(torch.from_numpy(flat[:1]), torch.from_numpy(flat[None]), 1.5)[0].numpy()
    assert np.isfinite(f).all()
    np.testing.assert_allclose(f.T @ f, np.eye(3), atol=1e-12)
    assert abs(f[0, 0]) > 0.99  # the long direction of the patch


@pytest.mark.slow
def test_encoder_shape_norm_and_rigid_invariance(gedi_weights):
    import trimesh

    from pipeline.method.geometry.sampling import sample_surface

    mesh = trimesh.creation.capsule(height=60.0, radius=20.0)
    mesh.vertices[:, 0] *= 1.4
    mesh.vertices[:, 2] += 0.002 * mesh.vertices[:, 0] ** 2
    pts, _ = sample_surface(mesh, 40, seed=1)
    diameter = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    enc = build_encoder({"name": "gedi", "params": {"weights": str(gedi_weights), "n_lrf": 200, "n_patch": 128, "batch_size": 32}})
    assert isinstance(enc, GeDiEncoder) and enc.dim == 64 and enc.signature() == "gedi-ms"
    assert len(enc.cache_params()["weights_sha1"]) == 40
    d0 = enc.encode(pts, None, diameter)
    assert d0.shape == (40, 64) and d0.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d0[:, :32], axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(d0[:, 32:], axis=1), 1, atol=1e-5)
    rng = np.random.default_rng(7)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    moved = (pts.astype(np.float64) @ R.T + [100.0, -40.0, 250.0]).astype(np.float32)
    d1 = enc.encode(moved, None, diameter)
    cos = (d0[:, :32] * d1[:, :32]).sum(1), (d0[:, 32:] * d1[:, 32:]).sum(1)
    assert min(cos[0].min(), cos[1].min()) > 0.99999, (cos[0].min(), cos[1].min())
    np.testing.assert_allclose(d1, d0, atol=2e-4)  # fixed seeds: same neighbours drawn
    # and descriptors do tell points apart
    assert (d0[:, :32] @ d0[:, :32].T)[np.triu_indices(40, 1)].mean() < 0.999


# --- the inference path against the reference forward ------------------------------------


def test_folded_layers_equal_the_modules():
    torch.manual_seed(2)
    block = torch.nn.Sequential(
        torch.nn.Conv2d(5, 7, 1, bias=False), torch.nn.BatchNorm2d(7), torch.nn.ReLU(),
        torch.nn.Conv2d(7, 4, 1, bias=True), torch.nn.BatchNorm2d(4),
    )
    for m in block.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-1, 1), m.running_var.uniform_(0.2, 3), m.weight.data.uniform_(-2, 2), m.bias.data.uniform_(-1, 1)
    block.eval()
    x = torch.randn(3, 5, 6, 2)
    expected = block(x).permute(0, 2, 3, 1).reshape(-1, 4)
    rows = x.permute(0, 2, 3, 1).reshape(-1, 5)
    layers = fold_layers(block)
    assert [layer.relu for layer in layers] == [True, False]
    for layer in layers:
        rows = layer(rows)
    torch.testing.assert_close(rows, expected, rtol=1e-5, atol=1e-5)


def _patches_with_repeats(seed: int, batch: int, distinct: int, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Curved patches (batch, 3, n) drawn with replacement from ``distinct`` points each,
    and the index of each drawn point (batch, n) (equal index: equal point)."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(batch, 2, distinct, generator=g) * 2 - 1
    bend = torch.rand(batch, 1, 1, generator=g) - 0.5
    base = torch.cat([xy, bend * (xy[:, :1] ** 2 - xy[:, 1:] ** 2)], 1)
    pick = torch.randint(0, distinct, (batch, n), generator=g)
    return torch.gather(base, 2, pick.unsqueeze(1).expand(-1, 3, -1)).contiguous(), pick


@pytest.mark.parametrize("distinct", [300, 40])  # 40: fewer points than the first level's 128 centres
def test_inference_equals_the_reference_forward(gedi_weights, distinct):
    net = load_gedi_net(gedi_weights)
    fast = GeDiInference(net)
    patches, ids = _patches_with_repeats(3, 6, distinct, 512)
    with torch.inference_mode(), torch_threads(1):  # one thread: quicker on a busy machine
        ref = net(patches)
        for got in (fast(patches), fast(patches, ids)):
            assert got.shape == (6, 32)
            assert (ref * got).sum(1).min() > 0.99999
            torch.testing.assert_close(got, ref, rtol=0, atol=1e-4)
        assert torch.equal(fast(patches, ids), fast(patches, ids))  # deterministic


def _v1_descriptors(enc: GeDiEncoder, pts: np.ndarray, radius: float) -> np.ndarray:
    """Version 1's loop: draws in groups of batch_size (each keypoint's neighbours, then
    each keypoint's patch), the reference forward on each group."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(enc.seed)
    hits = cKDTree(pts).query_ball_point(pts, radius, return_sorted=True)
    cloud = torch.from_numpy(pts)
    out = []
    for start in range(0, len(pts), enc.batch_size):
        group = range(start, min(start + enc.batch_size, len(pts)))
        nbr = torch.from_numpy(np.stack([enc._draw(np.asarray(hits[i], dtype=np.int64), rng) for i in group]))
        pick = torch.from_numpy(np.stack([rng.choice(enc.n_lrf, enc.n_patch, replace=False) for _ in group]))
        kp, nbrs = cloud[start : group.stop], cloud[nbr]
        lrf = local_reference_frame(kp, nbrs, radius)
        local = (torch.gather(nbrs, 1, pick.unsqueeze(-1).expand(-1, -1, 3)) - kp.unsqueeze(1)) / radius
        with torch.inference_mode(), torch_threads(1):
            out.append(enc.net((lrf.transpose(1, 2) @ local.transpose(1, 2)).float()).numpy())
    return np.concatenate(out)


def _bent_cloud(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-30, 30, size=(n, 2))
    return np.column_stack([uv, 0.02 * uv[:, 0] ** 2 - 0.01 * uv[:, 0] * uv[:, 1]])


def test_encoder_equals_version_1(gedi_weights):
    """Same seeded patches as version 1 (several draw groups per network call, a short
    last call), same descriptors up to float rounding."""
    pts = _bent_cloud(40, 10)
    enc = build_encoder({"name": "gedi", "params": {"weights": str(gedi_weights), "radii": [0.3], "n_lrf": 200,
                                                    "n_patch": 128, "batch_size": 8, "net_batch": 20}})
    assert enc.net_batch == 24
    diameter = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    got = enc.encode(pts, None, diameter)
    ref = _v1_descriptors(enc, pts, 0.3 * diameter)
    assert (got * ref).sum(1).min() > 0.99999
    np.testing.assert_allclose(got, ref, atol=1e-4)


def test_encoder_output_does_not_depend_on_threads_or_calls(gedi_weights):
    pts = _bent_cloud(40, 11)
    params = {"weights": str(gedi_weights), "radii": [0.3], "n_lrf": 200, "n_patch": 128, "batch_size": 8}
    enc = build_encoder({"name": "gedi", "params": {**params, "net_batch": 16}})
    before = torch.get_num_threads()
    try:
        runs = []
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            runs.append(enc.encode(pts, None, 50.0))
            assert torch.get_num_threads() == threads  # restored after the call
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(runs[0], runs[1]) and np.array_equal(runs[1], runs[2])
    other = build_encoder({"name": "gedi", "params": {**params, "net_batch": 40}}).encode(pts, None, 50.0)
    np.testing.assert_allclose(other, runs[0], atol=1e-5)

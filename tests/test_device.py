"""The run's device (``--config device=auto|cpu|cuda``) and ``allow_download``: the
device reaches the torch encoders (DINOv2, GeDi, and SAR through the visual encoder),
``cuda`` without CUDA is a one-line error, keys do not depend on the device, stage
manifests record the device and precision, and DINOv2 loads from the Hugging Face hub
only when the run allows it.

The tests taking the ``device`` fixture run on the CPU, and also on CUDA when
``FREEZE_TEST_DEVICE=cuda`` (``scripts/gpu_check.sh`` sets it); without a CUDA device
those are skipped ("no CUDA")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

transformers = pytest.importorskip("transformers")

from pipeline.common import config as cfg  # noqa: E402
from pipeline.method.encoders import dinov2 as d2  # noqa: E402
from pipeline.method.encoders import registry  # noqa: E402
from pipeline.method.encoders.gedi import GeDiEncoder, save_random_checkpoint  # noqa: E402
from pipeline.method.encoders.gedi_ops import ball_query, furthest_point_sample_with_sqdist  # noqa: E402
from pipeline.method.encoders.registry import build_encoder  # noqa: E402
from pipeline.workflow.plan import RunPlan, build_encoders, encoder_runtime, obj_item  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TEST_DEVICE = os.environ.get("FREEZE_TEST_DEVICE", "cpu")
DEVICES = ["cpu"] + (["cuda"] if TEST_DEVICE == "cuda" else [])
# a 32-d, 2-layer DINOv2 standing in for ViT-S/14 (the manifests' dinov2-vits14)
TINY = {"hidden_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2, "use_swiglu_ffn": False, "image_size": 56}


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """``cpu``, and ``cuda`` when FREEZE_TEST_DEVICE=cuda (skipped without a CUDA device)."""
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA")
    return request.param


@pytest.fixture
def tiny_vits14(monkeypatch):
    """Make ``vits14`` the tiny architecture, so that the manifests' dinov2-vits14 loads
    the tiny models made here."""
    monkeypatch.setitem(d2.MODEL_CONFIGS, "vits14", dict(TINY))
    return "vits14"


def _tiny_dinov2(seed: int = 0):
    torch.manual_seed(seed)
    net = transformers.Dinov2Model(transformers.Dinov2Config(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_ratio=4, patch_size=14, image_size=56,
        layerscale_value=1.0))
    with torch.no_grad():  # random biases and layer scales: features that differ from cell to cell
        for name, p in net.named_parameters():
            if "lambda1" in name or name.endswith("bias") or "token" in name:
                p.copy_(torch.randn_like(p) * 0.5)
    return net.eval()


def _gedi_checkpoint(path: Path) -> Path:
    """Random GeDi weights in the official checkpoint layout, batch-norm statistics set
    on random curved patches (else every patch gets about the same descriptor, and
    agreement would say little)."""
    return save_random_checkpoint(path, seed=0)


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    """A weights folder as the default manifests look it up: gedi/chkpt.tar and a
    Hugging Face copy of the (tiny) dinov2-small."""
    wd = tmp_path_factory.mktemp("weights")
    _gedi_checkpoint(wd / "gedi" / "chkpt.tar")
    _tiny_dinov2().save_pretrained(wd / "dinov2-small")
    return wd


def _run(weights_dir: Path | None = None, **overrides: str) -> cfg.RunManifest:
    base = {"datasets": "synthtiny", "geometric": "gedi", "visual": "dinov2-vits14"}
    if weights_dir is not None:
        base["weights_dir"] = str(weights_dir)
    return cfg.load_run({**base, **overrides})


def _bent_cloud(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-30, 30, size=(n, 2))
    return np.column_stack([uv, 0.02 * uv[:, 0] ** 2 - 0.01 * uv[:, 0] * uv[:, 1]])


def _cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)


# --- the run's device reaches the encoders ------------------------------------------------


@pytest.fixture
def no_cuda(monkeypatch):
    """torch sees no CUDA device (as on this machine), also where it does."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_run_device_replaces_the_manifests_device(weights, tiny_vits14, no_cuda):
    """A manifest saying cuda fails without CUDA; the run's cpu replaces it; auto (or
    no run device) leaves the manifest's value; weight-free encoders ignore it."""
    specs = {"dinov2": {"name": "dinov2", "params": {"model": "vits14", "device": "cuda"}},
             "gedi": {"name": "gedi", "params": {"device": "cuda", "radii": [0.3]}}}
    for name, spec in specs.items():
        for device in (None, "auto"):
            with pytest.raises(ValueError, match=f"{name}: device 'cuda' was asked for, but no CUDA device is visible"):
                build_encoder(spec, weights_dir=weights, device=device)
        enc = build_encoder(spec, weights_dir=weights, device="cpu")
        assert str(enc.device) == "cpu" and encoder_runtime(enc)["device"] == "cpu"
    fpfh = build_encoder({"name": "fpfh"}, device="cpu")
    assert encoder_runtime(fpfh) == {"encoder": "fpfh", "device": "cpu", "precision": None}


def test_the_scene_side_takes_the_torch_paths_only_where_the_device_is_cuda(monkeypatch):
    """plan.scene_device: None (the numpy RANSAC and ICP) for device=cpu, and for auto
    without CUDA, whether torch is the CPU wheel (not even imported) or a CUDA build that
    sees no GPU; ``cuda`` for device=cuda, and for auto where CUDA is visible."""
    import importlib.metadata

    from pipeline.workflow.plan import scene_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert scene_device(_run(device="cpu")) is None
    assert scene_device(_run(device="cuda")) == "cuda"
    real_version = importlib.metadata.version
    monkeypatch.setattr(importlib.metadata, "version",
                        lambda name: "2.13.0+cu128" if name == "torch" else real_version(name))
    assert scene_device(_run(device="auto")) == "cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert scene_device(_run(device="auto")) is None
    monkeypatch.setattr(importlib.metadata, "version",
                        lambda name: "2.13.0+cpu" if name == "torch" else real_version(name))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: pytest.fail("the CPU wheel needs no CUDA check"))
    assert scene_device(_run(device="auto")) is None


def test_build_encoders_pass_the_run_device_and_download_permission(weights, tiny_vits14, monkeypatch):
    calls = []
    real = registry.build_encoder

    def spy(spec, weights_dir=None, **kw):
        calls.append((spec.name, kw))
        return real(spec, weights_dir=weights_dir, **kw)

    monkeypatch.setattr(registry, "build_encoder", spy)
    geo, vis = build_encoders(_run(weights, device="cpu", allow_download="true"))
    assert calls == [("gedi", {"device": "cpu", "allow_download": True}),
                     ("dinov2", {"device": "cpu", "allow_download": True})]
    assert isinstance(geo, GeDiEncoder) and geo.device.type == "cpu" and vis.device == "cpu"
    calls.clear()
    build_encoders(_run(weights))  # auto: the manifests' own device (auto: cuda when present)
    assert calls == [("gedi", {"device": None, "allow_download": False}),
                     ("dinov2", {"device": None, "allow_download": False})]
    enc = RunPlan(_run(weights, device="cpu")).encoders
    assert enc["geometric"]["runtime"] == {"encoder": "gedi", "device": "cpu", "precision": "fp32"}
    assert enc["visual"]["runtime"] == {"encoder": "dinov2", "device": "cpu",
                                        "precision": "bf16" if d2.cpu_supports_bf16() else "fp32"}


def test_cuda_without_cuda_is_a_one_line_error(weights, tiny_vits14, no_cuda):
    for run in (_run(weights, device="cuda"), cfg.load_run({"datasets": "synthtiny", "device": "cuda"})):
        for attempt in (lambda: build_encoders(run), lambda: RunPlan(run)["synthtiny"]):
            with pytest.raises(cfg.ManifestError) as err:
                attempt()
            msg = str(err.value)
            assert "--config device=cuda" in msg and "no CUDA device is visible" in msg and "\n" not in msg


@pytest.mark.slow
def test_cuda_without_cuda_stops_snakemake_and_a_stage_with_one_line(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env.update(FREEZE_CACHE=str(tmp_path / "cache"), CUDA_VISIBLE_DEVICES="", HF_HUB_OFFLINE="1")
    snakemake = Path(sys.executable).parent / "snakemake"
    proc = subprocess.run([str(snakemake), "-s", str(ROOT / "Snakefile"), "--directory", str(tmp_path), "--cores", "1",
                           "-n", "bop_all", "--config", "datasets=synthtiny", "device=cuda"],
                          env=env, capture_output=True, text=True, timeout=600)
    lines = [ln for ln in proc.stderr.splitlines() if "no CUDA device is visible" in ln]
    assert proc.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: --config device=cuda"), proc.stderr
    assert "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "pipeline.commands.cli", "stage", "symmetries", "--dataset", "synthtiny",
                           "--item", "obj_000002", "--config", "datasets=synthtiny", "--config", "device=cuda"],
                          env=env, capture_output=True, text=True, timeout=600, cwd=ROOT)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "--config device=cuda: no CUDA device is visible" in out and "Traceback" not in out


# --- keys do not depend on the device; manifests record it -----------------------------------


def _keys(run: cfg.RunManifest) -> dict[str, str]:
    return {s: sp.key for s, sp in RunPlan(run)["synthtiny"].stages.items()}


def test_keys_do_not_depend_on_the_device_or_the_download_permission(weights, tiny_vits14, no_cuda):
    """On a machine without CUDA (as this one; simulated elsewhere) auto means cpu."""
    auto = _keys(_run(weights))
    assert _keys(_run(weights, device="cpu")) == auto
    assert _keys(_run(weights, allow_download="true")) == auto  # local weights: the same files, the same key
    assert _keys(cfg.load_run({"datasets": "synthtiny", "device": "cpu"})) == _keys(cfg.load_run({"datasets": "synthtiny"}))
    # the precision is keyed (it changes the features): fp32 DINOv2 has other keys where auto means bf16
    fp32 = _keys(_run(weights, visual="dinov2-vits14-fp32"))
    assert (fp32["model_features"] != auto["model_features"]) == d2.cpu_supports_bf16()


def test_keys_are_the_same_on_every_device_at_the_same_precision(weights, tiny_vits14, device):
    """The device is never keyed: fp32 DINOv2 and GeDi on ``device`` have the CPU's keys
    (with precision auto they differ exactly where the resolved precision does)."""
    on_cpu = _keys(_run(weights, visual="dinov2-vits14-fp32", device="cpu"))
    assert _keys(_run(weights, visual="dinov2-vits14-fp32", device=device)) == on_cpu
    same = d2.resolve_precision("auto", device) == d2.resolve_precision("auto", "cpu")
    assert (_keys(_run(weights, device=device)) == _keys(_run(weights, device="cpu"))) == same


@pytest.mark.slow
def test_stage_manifests_record_device_and_precision(weights, tiny_vits14, tmp_path):
    """model_features and scene_features record where their encoders ran, refine where
    SAR's visual encoder, the ICP and the verification ran, register where RANSAC ran (synthtiny with small stage parameters, GeDi at one radius)."""
    from pipeline.workflow.stage_graph import run_stage

    data = _run(weights, geometric="gedi-r03", device="cpu").model_dump()
    data["stages"]["render_templates"].update(n_views=4, image_size=64)
    data["stages"]["symmetries"].update(n_points=1000)
    data["stages"]["model_features"].update(n_points=100)
    data["stages"]["scene_features"].update(n_points=50)
    plan = RunPlan(cfg.RunManifest.model_validate(data), cache=tmp_path / "cache")["synthtiny"]
    objects = [obj_item(o) for o in plan.obj_ids]
    jobs = [("synth", "dataset")] + [(stage, item) for item in objects
                                     for stage in ("render_templates", "symmetries", "model_features")]
    jobs += [("segment_prior", "all")] + [(stage, "scene_000001") for stage in ("scene_features", "register", "refine")]
    for stage, item in jobs:
        run_stage(plan, stage, item, progress=False)
    precision = "bf16" if d2.cpu_supports_bf16() else "fp32"
    want = {"geometric": {"encoder": "gedi", "device": "cpu", "precision": "fp32"},
            "visual": {"encoder": "dinov2", "device": "cpu", "precision": precision}}
    for stage, item in (("model_features", objects[0]), ("scene_features", "scene_000001")):
        manifest = json.loads((plan[stage].item_dir(item) / "_manifest.json").read_text())
        assert manifest["runtime"] == want, stage
        assert "device" not in json.dumps(manifest["params"])  # recorded, not keyed
        assert manifest["params"]["encoders"]["visual"]["params"]["precision"] == precision  # keyed
    refine = json.loads((plan["refine"].item_dir("scene_000001") / "_manifest.json").read_text())
    assert refine["summary"]["n_sar"] > 0 and refine["runtime"] == {"visual": want["visual"], "icp": "numpy",
                                                                "verification": "numpy"}
    register = json.loads((plan["register"].item_dir("scene_000001") / "_manifest.json").read_text())
    assert register["runtime"] == {"ransac": "numpy"}  # device=cpu: the numpy paths


# --- the encoders compute on the device ------------------------------------------------------


def test_dinov2_runs_on_the_device(tmp_path, device):
    hf = tmp_path / "hf"
    net = _tiny_dinov2(seed=3)
    net.save_pretrained(hf)
    common = {"model": "vitt14", "weights": str(hf), "input_size": 56}
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(d2.MODEL_CONFIGS, "vitt14", dict(TINY))
        ref = d2.Dinov2Encoder(device="cpu", precision="fp32", **common)
        enc = d2.Dinov2Encoder(device=device, precision="fp32", **common)
        auto = d2.Dinov2Encoder(device=device, precision="auto", **common)
        images = np.random.default_rng(4).integers(0, 256, (3, 56, 56, 3), dtype=np.uint8)
        a, b, c = ref.encode(images), enc.encode(images), auto.encode(images)
    assert next(enc._net.parameters()).device.type == device == enc.device
    assert encoder_runtime(auto) == {"encoder": "dinov2", "device": device, "precision": d2.resolve_precision("auto", device)}
    flat = [x.transpose(0, 2, 3, 1).reshape(-1, 32) for x in (a, b, c)]
    assert _cosines(flat[0], flat[1]).min() > 0.999  # fp32 here and there
    assert _cosines(flat[0], flat[2]).min() > 0.99  # bf16 where the device has it


def test_gedi_runs_on_the_device(tmp_path, device):
    ckpt = _gedi_checkpoint(tmp_path / "chkpt.tar")
    params = {"weights": str(ckpt), "radii": [0.3, 0.4], "n_lrf": 200, "n_patch": 128, "batch_size": 8, "net_batch": 16}
    ref = build_encoder({"name": "gedi", "params": {**params, "device": "cpu"}})
    enc = build_encoder({"name": "gedi", "params": {**params, "device": device}})
    # the network's folded layers, on the device, equal to the CPU's (folded on the CPU)
    layers = [d for part in (enc.inference.q_points, enc.inference.q_head, enc.inference.global_level,
                             enc.inference.head, *[lv for _, lv in enc.inference.levels]) for d in part]
    ref_layers = [d for part in (ref.inference.q_points, ref.inference.q_head, ref.inference.global_level,
                                 ref.inference.head, *[lv for _, lv in ref.inference.levels]) for d in part]
    assert enc.device.type == device and {d.weight.device.type for d in layers} == {device}
    assert all(torch.equal(d.weight.cpu(), r.weight) and torch.equal(d.bias.cpu(), r.bias)
               for d, r in zip(layers, ref_layers, strict=True))
    pts = _bent_cloud(60, 1)
    # frames and patches are made on the device too (the k-d tree and the draws stay on the CPU)
    nbr, pick = next(enc._network_calls(pts, cKDTree(pts), 20.0, len(pts)))[1:]
    patches, ids = enc._patches(torch.from_numpy(pts).to(enc.device), 0, nbr, pick, 20.0)
    assert patches.device.type == ids.device.type == device
    a, b = ref.encode(pts, None, 60.0), enc.encode(pts, None, 60.0)
    assert ref.cache_params() == enc.cache_params() and ref.signature() == enc.signature()  # the device is not keyed
    assert encoder_runtime(enc) == {"encoder": "gedi", "device": device, "precision": "fp32"}
    assert min(_cosines(a[:, :32], b[:, :32]).min(), _cosines(a[:, 32:], b[:, 32:]).min()) > 0.9999
    if device == "cpu":
        assert np.array_equal(a, b)


def test_gedi_sampling_and_grouping_on_the_device_equal_the_cpu(device):
    """Farthest-point sampling and ball query follow the reference kernels' float32
    arithmetic on every device: the same samples and groups as on the CPU."""
    xyz = torch.from_numpy(np.random.default_rng(2).uniform(-1, 1, (3, 400, 3)).astype(np.float32))
    idx_c, sq_c = furthest_point_sample_with_sqdist(xyz, 64)
    idx_d, sq_d = furthest_point_sample_with_sqdist(xyz.to(device), 64)
    assert idx_d.device.type == device
    assert torch.equal(idx_d.cpu(), idx_c) and torch.equal(sq_d.cpu(), sq_c)
    centres = torch.gather(xyz, 1, idx_c.unsqueeze(-1).expand(-1, -1, 3))
    group_c = ball_query(0.3, 16, xyz, centres)
    group_d = ball_query(0.3, 16, xyz.to(device), centres.to(device))
    assert group_d.device.type == device and torch.equal(group_d.cpu(), group_c)


# --- allow_download: the Hugging Face hub, only when the run allows it ----------------------


@pytest.fixture
def offline(monkeypatch):
    """The hub is unreachable: offline mode, as the tests always run."""
    import huggingface_hub.constants as hf_constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(hf_constants, "HF_HUB_OFFLINE", True)


def test_missing_weights_offline_by_default_and_with_allow_download(tmp_path, offline, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    empty = tmp_path / "empty"
    with pytest.raises(d2.WeightsNotFound) as err:
        d2.Dinov2Encoder(model="vits14", weights_dir=str(empty))
    msg = str(err.value)
    assert "freeze weights fetch dinov2-vits14" in msg and "--config allow_download=true" in msg
    assert not (empty / "hub").exists()  # nothing was tried
    with pytest.raises(d2.WeightsNotFound) as err:
        build_encoder({"name": "dinov2", "params": {"model": "vits14_reg"}}, weights_dir=empty, allow_download=True)
    msg = str(err.value)
    assert "facebook/dinov2-with-registers-small could not be loaded" in msg
    assert "the hub could not be reached: offline mode is on" in msg
    assert "freeze weights fetch dinov2-vits14-reg" in msg and "\n" not in msg


def test_allow_download_loads_from_the_hub_into_the_weights_folder(tmp_path, tiny_vits14, offline, monkeypatch):
    """from_pretrained (faked: no network in tests) fills the hub cache in the weights
    folder; its model is used; the key is the checksum of the cached files, as for a
    local copy; a later build finds the cache without the hub, and only with the option."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    wd = tmp_path / "w"
    net = _tiny_dinov2(seed=5)
    calls = []

    def from_pretrained(repo, cache_dir=None, **kw):
        calls.append((repo, cache_dir))
        repo_dir = Path(cache_dir) / ("models--" + repo.replace("/", "--"))
        net.save_pretrained(repo_dir / "snapshots" / "0123abcd")
        (repo_dir / "refs").mkdir(parents=True)
        (repo_dir / "refs" / "main").write_text("0123abcd")
        return net

    def no_reload(path):
        raise AssertionError("the model loaded from the hub is loaded again")

    monkeypatch.setattr(transformers.Dinov2Model, "from_pretrained", from_pretrained)
    monkeypatch.setattr(d2, "load_hf_dir", no_reload)
    run = cfg.load_run({"datasets": "synthtiny", "geometric": "fpfh", "visual": "dinov2-vits14-fp32",
                        "weights_dir": str(wd), "allow_download": "true", "device": "cpu"})
    vis = build_encoders(run)[1]
    snapshot = wd / "hub" / "models--facebook--dinov2-small" / "snapshots" / "0123abcd"
    assert calls == [("facebook/dinov2-small", str(wd / "hub"))]
    assert vis.weights_path == snapshot.resolve() and vis.hf_dir
    image = np.random.default_rng(6).integers(0, 256, (1, 224, 224, 3), dtype=np.uint8)
    out = vis.encode(image)  # the model from the hub, not loaded again (no_reload)
    x = torch.from_numpy(image).permute(0, 3, 1, 2).float() / 255.0
    x = (x - torch.tensor(d2.IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(d2.IMAGENET_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        tokens = net(pixel_values=x).last_hidden_state[:, 1:]
    np.testing.assert_allclose(out, tokens.reshape(1, 16, 16, 32).permute(0, 3, 1, 2).numpy(), rtol=1e-4, atol=1e-5)
    # keyed on the cached files' checksum, like a local copy of the same files
    params = vis.cache_params()
    assert params["weights_sha1"] == d2.weights_checksum(snapshot) and params["weights_format"] == "hf"
    copy = tmp_path / "copy"
    net.save_pretrained(copy / "dinov2-small")
    assert d2.Dinov2Encoder(model="vits14", precision="fp32", weights_dir=str(copy)).cache_params() == params
    # later: the cache is used without the hub; without the option it is not looked at
    monkeypatch.setattr(transformers.Dinov2Model, "from_pretrained", lambda *a, **k: pytest.fail("hub asked again"))
    again = build_encoder({"name": "dinov2", "params": {"model": "vits14", "precision": "fp32"}}, weights_dir=wd,
                          allow_download=True)
    assert again.weights_path == snapshot.resolve() and again.cache_params() == params
    with pytest.raises(d2.WeightsNotFound, match="a copy downloaded earlier is in .*0123abcd"):
        build_encoder({"name": "dinov2", "params": {"model": "vits14"}}, weights_dir=wd)

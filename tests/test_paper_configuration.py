"""The paper's configuration, GeDi + DINOv2 ViT-g/14 (issue 27), run end to end through
``freeze estimate``'s Python API on one synthetic RGB-D frame, so that CI exercises its
whole path: the official-layout checkpoints found in the weights folder, ViT-g's SwiGLU
blocks and the official position-embedding resize (a 37 x 37 grid to the 16 x 16 of a
224 px crop), GeDi at 0.3 and 0.4 of the diameter, every stage. The architecture is
ViT-g's with a reduced width and depth (48-d, 2 blocks; the real sizes are compared with
the official code in ``test_dinov2_official.py``), the weights random: the pose is not
expected to be right, only to be a pose of the object in front of the camera."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pipeline.method.encoders import dinov2 as d2
from pipeline.method.encoders.gedi import save_random_checkpoint
from pipeline.common.stand_in import paper_configuration
from test_encoders_dinov2 import _to_official
from test_estimate import FAST, case  # noqa: F401  (the synthetic frame fixture)

pytestmark = pytest.mark.slow

TINY_G = {"hidden_size": 48, "num_hidden_layers": 2, "num_attention_heads": 2, "use_swiglu_ffn": True, "image_size": 518}


@pytest.fixture
def paper_weights(tmp_path, monkeypatch):
    """A weights folder holding random GeDi and tiny ViT-g/14 checkpoints in the official
    layouts, where the paper's manifests look for them."""
    from transformers import Dinov2Config, Dinov2Model

    monkeypatch.setitem(d2.MODEL_CONFIGS, "vitg14", dict(TINY_G))
    wd = tmp_path / "weights"
    save_random_checkpoint(wd / "gedi" / "chkpt.tar", seed=0)
    torch.manual_seed(0)
    net = Dinov2Model(Dinov2Config(hidden_size=48, num_hidden_layers=2, num_attention_heads=2, mlp_ratio=4,
                                   patch_size=14, image_size=518, layerscale_value=1.0, use_swiglu_ffn=True))
    with torch.no_grad():  # random position embeddings, so that their resize matters
        net.embeddings.position_embeddings.normal_(0.0, 0.5)
    torch.save(_to_official(net), wd / d2.official_filename("vitg14"))
    return wd


def test_the_paper_s_configuration_runs_end_to_end(case, paper_weights, tmp_path):  # noqa: F811
    from pipeline.commands.estimate.command import estimate
    from pipeline.common.store import load_arrays, read_manifest

    paper = paper_configuration()
    assert (paper["geometric"][0], paper["visual"][0]) == ("gedi", "dinov2-vitg14")
    out = tmp_path / "out"
    overrides = {**FAST, "model_features.n_points": "300", "scene_features.n_points": "300",
                 "weights_dir": str(paper_weights), "device": "cpu"}
    result = estimate(case["model"], case["rgb"], case["depth"], case["camera"], mask=case["mask"],
                      overrides=overrides, geometric="gedi", visual="dinov2-vitg14", out_dir=out,
                      cache=tmp_path / "cache")
    rec = json.loads((out / "pose.json").read_text())
    assert rec["note"] == "gedi + dinov2-vitg14: the paper's configuration (GeDi + DINOv2 ViT-g/14)"
    assert rec["encoders"]["geometric"] == "gedi" and rec["encoders"]["visual"] == "dinov2-vitg14"
    # the manifests name the encoders' parameters: ViT-g/14 at 224 px from the official file, GeDi at 0.3/0.4 d
    man = read_manifest(out / "model_features")
    text = json.dumps(man)
    assert '"model": "vitg14"' in text and '"input_size": 224' in text and '"weights_format": "official"' in text
    assert "[0.3, 0.4]" in text.replace("\n", "").replace(" ", "").replace(",", ", ")
    # GeDi: 2 x 32-d per point; DINOv2 ViT-g (reduced): 48-d lifted per point
    feats = load_arrays(out / "model_features" / "features.zarr")
    assert feats["points"].shape == (300, 3)
    assert feats["geometric"].shape == (300, 64) and feats["visual"].shape == (300, 48)
    assert np.isfinite(feats["geometric"]).all() and np.isfinite(feats["visual"]).all()
    # a rotation, and a translation on the object (within a diameter of the truth)
    R, t = np.array(rec["R"]), np.array(rec["t"])
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
    assert np.linalg.norm(t - case["t"]) < case["diameter"]
    assert result.record["encoders"] == rec["encoders"]

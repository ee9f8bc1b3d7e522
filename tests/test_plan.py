"""Cache-key rules: which stages get new keys when a manifest value changes."""

from __future__ import annotations

import pytest

from pipeline.common import config as cfg
from pipeline.workflow.plan import RunPlan
from pipeline.common.store import make_key

MODEL_SIDE = ("synth", "render_templates", "segment_prior")
ENCODER_DEPENDENT = ("model_features", "scene_features", "register", "refine", "score")


def _keys(**overrides) -> dict[str, str]:
    run = cfg.load_run({"datasets": "synthtiny", **overrides})
    return {name: sp.key for name, sp in RunPlan(run)["synthtiny"].stages.items()}


def test_plan_is_deterministic():
    assert _keys() == _keys()


def test_visual_encoder_swap_changes_exactly_the_dependent_stages():
    base, swapped = _keys(), _keys(visual_encoder="colortex-coarse")
    for stage in MODEL_SIDE:
        assert base[stage] == swapped[stage], stage
    for stage in ENCODER_DEPENDENT:
        assert base[stage] != swapped[stage], stage


def test_stage_parameter_change_propagates_downstream_only():
    run = cfg.load_run({"datasets": "synthtiny"})
    data = run.model_dump()
    data["stages"]["scene_features"]["n_points"] = 500
    changed = RunPlan(cfg.RunManifest.model_validate(data))["synthtiny"]
    base = RunPlan(run)["synthtiny"]
    for stage in ("synth", "render_templates", "model_features", "segment_prior"):
        assert changed[stage].key == base[stage].key, stage
    for stage in ("scene_features", "register", "refine", "score"):
        assert changed[stage].key != base[stage].key, stage


def test_signature_is_readable_and_keyed():
    plan = RunPlan(cfg.load_run({"datasets": "synthtiny"}))["synthtiny"]
    mf = plan["model_features"]
    assert mf.signature.startswith("fpfh") and "+colortex" in mf.signature
    assert mf.signature.endswith(mf.key[:8])
    assert "_" not in mf.signature


def test_key_covers_params_code_version_and_upstream():
    k = make_key("s", 1, {"a": 1, "b": [2, 3]}, {"u": "x"})
    assert k != make_key("s", 2, {"a": 1, "b": [2, 3]}, {"u": "x"})
    assert k != make_key("s", 1, {"a": 2, "b": [2, 3]}, {"u": "x"})
    assert k != make_key("s", 1, {"a": 1, "b": [2, 3]}, {"u": "y"})
    assert k == make_key("s", 1, {"b": [2, 3], "a": 1}, {"u": "x"})  # key order is irrelevant


def test_bad_manifest_names_file_and_field(tmp_path):
    (tmp_path / "runs").mkdir()
    bad = tmp_path / "runs" / "bad.yaml"
    bad.write_text("datasets: [synthtiny]\nstages: {scene_features: {n_points: -3}}\n")
    with pytest.raises(cfg.ManifestError) as e:
        cfg.load_run({"run": str(bad)})
    assert "bad.yaml" in str(e.value) and "stages.scene_features.n_points" in str(e.value)


def test_unknown_encoder_lists_known_ones():
    with pytest.raises(cfg.ManifestError, match="known: .*colortex"):
        RunPlan(cfg.load_run({"datasets": "synthtiny", "visual_encoder": "nosuch"}))["synthtiny"]


def test_short_encoder_keys_none_and_weights_dir(tmp_path):
    run = cfg.load_run({"datasets": "synthtiny", "geometric": "fpfh-r03", "visual": "none", "weights_dir": str(tmp_path)})
    assert (run.geometric_encoder, run.visual_encoder, run.weights_dir) == ("fpfh-r03", "none", str(tmp_path.resolve()))
    enc = RunPlan(run).encoders
    assert enc["visual"]["manifest"] == "none-visual" and enc["visual"]["signature"] == "novis"
    with pytest.raises(cfg.ManifestError, match="both 'none'"):
        cfg.load_run({"datasets": "synthtiny", "geometric": "none", "visual": "none"})
    with pytest.raises(cfg.ManifestError, match="both 'visual' and 'visual_encoder'"):
        cfg.load_run({"datasets": "synthtiny", "visual": "rgb", "visual_encoder": "colortex"})
    # where the weights live is not part of any key
    assert _keys(weights_dir=str(tmp_path)) == _keys()
    geo_only, base = _keys(visual="none"), _keys()
    assert geo_only["render_templates"] == base["render_templates"] and geo_only["model_features"] != base["model_features"]


# The main job's keys (default run, synthmini). They change only when a stage's code
# version, parameters or upstreams change, which reruns the stage and everything after
# it; update this table deliberately when that is intended, and say why in the commit.
# refine 3 (ICP on one thread, bit-reproducible) changed refine's and score's keys; the
# declaration of the stage graph and the renames changed none. register 4 and refine 4
# (hypotheses, modality weights, verification, fine ICP; issue 13) changed register's,
# refine's and score's. The symmetry threshold 0.003 -> 0.005 (issue 13: the TYO-L
# basket's half turn) changed symmetries', refine's and score's (synthmini's AR stayed
# 0.788). symmetries 2 (near-symmetries in the record) and refine 6 (the turns of each
# candidate's best hypothesis, refine.turns) changed symmetries', refine's and score's;
# images_per_job and the rules' threads and memory changed none. Issue 29 (artifacts with
# one name each: candidates.parquet and images.parquet renamed per stage) bumped the code
# versions of segment_prior (3 -> 4), scene_features (1 -> 2), register (5 -> 6) and
# refine (8 -> 9), which changed their keys, and score's, which follows refine's; the
# random draws come from the seed keys (StagePlan.seed_key), which are the keys before
# issue 29 (MAIN_JOB_SEED_KEYS), so every value in every artifact stayed the same.
# Issue 30 (SAR skips untextured models) bumped refine (9 -> 10): refine's and score's keys
# changed, their seed keys did not. So did the fine ICP's depth points chosen near
# scene_features' points (10 -> 11).
MAIN_JOB_KEYS = {
    "synth": "42e22634980724b4b02cc270abefe72cd6af6e03",
    "render_templates": "4c687dcea59bf855850770f05da8aafca91cd386",
    "symmetries": "569ebc51646a54831def1fb2a67375cf63ccaa88",
    "model_features": "ed46f2a57508857849305f0fa7847a1bb0ad85fe",
    "segment_prior": "4a14217dd176647e1b98d9ec86ec8a85f58ea295",
    "scene_features": "af3ff781b440ad7c2e852f5269dc4d6ae7364a2a",
    "register": "607d9ce2a11874799482e4c56618510af66f9291",
    "refine": "76b3360854a4a87a9760fd25e1be045cbd4d5021",
    "score": "5a8577dae8caad156a02b59a08f4e0dd03a13861",
}
MAIN_JOB_SEED_KEYS = {
    **MAIN_JOB_KEYS,
    "segment_prior": "cb98a60a90478c1373a838b74f1b032f44df3b57",
    "scene_features": "1fb7016d520a9e4c243b2714fd6d0fd53bc3c6e0",
    "register": "94255dac2bdc93f8b69cd94ffa44e7c966436302",
    "refine": "ce7d6010663c1119277b47600aa3f0f8b995f2cf",
    "score": "181e84ccb08d3b3edfdfed8343fee74e1f057617",
}
"""The main job's seed keys: the keys before issue 29 (which renamed files only)."""


def test_main_job_keys_are_pinned():
    plan = RunPlan(cfg.load_run({}))["synthmini"]
    assert {s: sp.key for s, sp in plan.stages.items()} == MAIN_JOB_KEYS
    assert plan["refine"].signature == "icp+sar-byverification-76b33608"


def test_main_job_seed_keys_are_the_keys_before_the_renames():
    """Issue 29 bumped code versions for file renames alone: the draws (and so every value
    in every artifact) still come from the keys the stages had before."""
    plan = RunPlan(cfg.load_run({}))["synthmini"]
    assert {s: sp.seed_key for s, sp in plan.stages.items()} == MAIN_JOB_SEED_KEYS


def test_renamed_values_keep_their_keys():
    """select_by 'score' was renamed 'evidence'; both spellings are accepted and hash alike."""
    data = cfg.load_run({"datasets": "synthtiny"}).model_dump()
    data["stages"]["refine"]["select_by"] = "evidence"
    new = cfg.RunManifest.model_validate(data)
    assert new.stages.refine.select_by == "evidence"
    data["stages"]["refine"]["select_by"] = "score"
    old = cfg.RunManifest.model_validate(data)
    assert old.stages.refine.select_by == "evidence"
    assert RunPlan(old)["synthtiny"]["refine"].key == RunPlan(new)["synthtiny"]["refine"].key


def test_labels_and_parameters_come_from_the_declarations(monkeypatch):
    """The plan takes each stage's signature label and keyed parameters from its
    declaration (pipeline/workflow/stage_graph.py), in declaration order."""
    import dataclasses

    from pipeline.workflow import stage_graph

    base = RunPlan(cfg.load_run({"datasets": "synthtiny"}))["synthtiny"]
    assert list(base.stages) == list(stage_graph.STAGES)
    specs = dict(stage_graph.STAGES)
    specs["register"] = dataclasses.replace(specs["register"], label=lambda c: "custom",
                                            params=lambda c: {**c.stage_params("register"), "extra": 1})
    monkeypatch.setattr(stage_graph, "STAGES", specs)
    changed = RunPlan(cfg.load_run({"datasets": "synthtiny"}))["synthtiny"]
    assert changed["register"].signature.startswith("custom-") and changed["register"].params["extra"] == 1
    for stage in ("synth", "render_templates", "symmetries", "model_features", "segment_prior", "scene_features"):
        assert changed[stage].key == base[stage].key, stage
    for stage in ("register", "refine", "score"):  # the new parameter reaches every key after it
        assert changed[stage].key != base[stage].key, stage


def test_a_bop_dataset_without_ground_truth_is_scored_apart(tmp_path):
    """A BOP dataset on disk whose scenes lack ground truth: score's key says so (added
    ground truth must rescore), and a grey one has grey templates and refinement."""
    import shutil

    from pathlib import Path

    root = tmp_path / "bop"
    shutil.copytree(Path(__file__).parent / "data" / "tinybop" / "icbin", root / "itodd")
    for p in (root / "itodd").rglob("scene_gt.json"):
        p.unlink()
    (root / "detections").mkdir()
    (root / "detections" / "cnos-fastsam_itodd-test_x.json").write_text("[]")
    plan = RunPlan(cfg.load_run({"datasets": "itodd", "bop_root": str(root)}), cache=tmp_path / "cache")["itodd"]
    assert "synth" not in plan.stages
    assert plan["score"].params["ground_truth"] is False
    assert plan["render_templates"].params["image_mode"] == "gray" and plan["refine"].params["image_mode"] == "gray"
    assert plan["render_templates"].params["look_at"] == "bbox_centre"
    assert plan["segment_prior"].signature.startswith("cnos-fastsam-top3-")
    assert plan["render_templates"].upstream == {"dataset": plan.models_key}  # the models alone
    assert plan["segment_prior"].upstream == {"dataset": plan.dataset_key, "prior": plan.prior_key}


def test_a_dataset_manifest_given_as_a_path(tmp_path):
    """`datasets=path/to/name.yaml` (what `freeze estimate` writes) plans like a named one."""
    from pipeline.common.config import load_dataset_manifest

    text = (cfg.MANIFEST_DIR / "datasets" / "synthtiny.yaml").read_text()
    path = tmp_path / "mytiny.yaml"
    path.write_text(text)
    run = cfg.load_run({"datasets": str(path)})
    assert run.datasets == [str(path.resolve())]
    rp = RunPlan(run)
    assert rp.dataset_names == ["synthtiny"]
    assert rp["synthtiny"]["score"].key == RunPlan(cfg.load_run({"datasets": "synthtiny"}))["synthtiny"]["score"].key
    assert load_dataset_manifest(str(path)).name == "synthtiny"
    with pytest.raises(cfg.ManifestError, match="nope.yaml: dataset manifest not found"):
        RunPlan(cfg.load_run({"datasets": str(tmp_path / "nope.yaml")})).dataset_names

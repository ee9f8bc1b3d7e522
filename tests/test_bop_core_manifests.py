"""The seven BOP core dataset manifests, and running over whichever of them a user has
under `bop_root` (a tiny dataset in the LM-O layout stands in for the download)."""

from __future__ import annotations

import shutil

import pytest

from conftest import run_snakemake
from pipeline.common import config as cfg
from pipeline.workflow.plan import RunPlan

CORE = {"lmo": (None, 15.0), "tless": ("primesense", 15.0), "tudl": (None, 15.0), "icbin": (None, 15.0),
        "itodd": (None, 5.0), "hb": ("primesense", 15.0), "ycbv": (None, 15.0)}


def test_core_manifests_carry_what_differs():
    for name, (split_type, vsd_delta) in CORE.items():
        ds = cfg.load_dataset_manifest(name)
        assert (ds.kind, ds.folder, ds.split, ds.split_type, ds.vsd_delta) == ("bop", name, "test", split_type, vsd_delta)
        assert ds.prior_patterns() == [f"detections/cnos-fastsam_{name}-test*.json"]
        assert ds.prior_patterns(["sam6d-fastsam"]) == [f"detections/sam6d-fastsam_{name}-test*.json"]
        assert ds.prior_patterns(["cnos-fastsam", "mine/{dataset}.json"]) == [
            f"detections/cnos-fastsam_{name}-test*.json", f"mine/{name}.json"]
    # what differs between them, as BOP distributes them
    man = {name: cfg.load_dataset_manifest(name) for name in CORE}
    assert man["lmo"].obj_ids == [1, 5, 6, 8, 9, 10, 11, 12] and man["tless"].models == "models_cad"
    assert (man["itodd"].image_dir, man["itodd"].image_ext, man["itodd"].depth_ext, man["itodd"].image_size) == (
        "gray", ".tif", ".tif", (1280, 960))
    assert man["itodd"].image_mode == "gray" and man["lmo"].image_mode == "rgb"
    assert man["tless"].image_size == (720, 540) and man["ycbv"].camera_file == "camera_uw.json"
    assert [n for n in CORE if not man[n].public_gt] == ["itodd", "hb"]


@pytest.fixture(scope="module")
def bop_root(tmp_path_factory):
    """A bop_root holding only 'lmo' (a tiny synthetic dataset in its folder) and its
    default-detections file."""
    from pipeline.evaluation.synth import generate

    root = tmp_path_factory.mktemp("bop")
    generate(root / "lmo", name="lmo", preset="tiny", seed=0, progress=False)
    (root / "detections").mkdir()
    # named as BOP distributes default detections: method_dataset-test plus a suffix
    shutil.move(root / "lmo" / "detections" / "cnos-synth_lmo-test.json",
                root / "detections" / "cnos-fastsam_lmo-test_0a1b2c3d.json")
    return root


@pytest.mark.slow
def test_only_the_datasets_found_are_planned(bop_root):
    rp = RunPlan(cfg.load_run({"datasets": ",".join(CORE), "bop_root": str(bop_root)}))
    found = {name: rp.available(name) for name in CORE}
    assert found["lmo"] == (True, "")
    for name in set(CORE) - {"lmo"}:
        ok, why = found[name]
        assert not ok and why == f"{name}: skipped, {bop_root / name / 'test_targets_bop19.json'} not found"
    plan = rp["lmo"]
    assert plan.obj_ids == [2, 5, 6] and plan.scene_ids == [1]
    assert plan.prior_path == (bop_root / "detections" / "cnos-fastsam_lmo-test_0a1b2c3d.json").resolve()
    assert "synth" not in plan.stages  # a dataset on disk: its fingerprint heads the chain


@pytest.mark.slow
def test_bop_all_dry_run_over_a_bop_root(bop_root, tmp_path):
    out = run_snakemake(tmp_path, f"bop_root={bop_root}", "datasets=lmo,tless,itodd", dry=True)
    assert f"tless: skipped, {bop_root / 'tless' / 'test_targets_bop19.json'} not found" in out
    assert "itodd: skipped" in out
    jobs = out.split("Job stats:", 1)[1]
    for rule in ("render_templates", "symmetries", "model_features", "segment_prior", "scene_features", "register",
                 "refine", "score", "bop_all"):
        assert rule in jobs
    assert "synth" not in jobs.split()


@pytest.mark.slow
def test_datasets_check_summarises_and_names_problems(bop_root, tmp_path):
    import json

    from typer.testing import CliRunner

    from pipeline.commands.cli import app

    result = CliRunner().invoke(app, ["datasets", "check", str(bop_root), "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert [d["name"] for d in out["datasets"]] == ["lmo"]
    assert sorted(out["absent"]) == sorted(set(CORE) - {"lmo"})
    lmo = out["datasets"][0]
    assert lmo["ok"] and lmo["errors"] == []
    assert lmo["summary"] | {"detections": None} == {
        "objects": 3, "scenes": 1, "images": 2, "targets": 5, "instances": 7,
        "instances_per_target": {"1": 3, "2": 2}, "images_with_problems": 0, "detections": None,
        "image_size": [640, 480], "ground_truth": True}
    # the synthetic objects 2, 5, 6 stand in for LM-O's: object 2 is not one of LM-O's
    assert any("target objects [2] are not among BOP's lmo objects" in w for w in lmo["warnings"])

    # A broken copy: metre models, a missing depth image, no prior.
    broken = tmp_path / "bop"
    shutil.copytree(bop_root / "lmo", broken / "lmo")
    info_path = broken / "lmo" / "models" / "models_info.json"
    info = json.loads(info_path.read_text())
    info["2"]["diameter"] = 0.09
    info_path.write_text(json.dumps(info))
    depth = sorted((broken / "lmo" / "test" / "000001" / "depth").iterdir())[0]
    depth.unlink()
    result = CliRunner().invoke(app, ["datasets", "check", str(broken), "--json"])
    assert result.exit_code == 1
    errors = json.loads(result.stdout)["datasets"][0]["errors"]
    assert any("object 2: field 'diameter' is 0.09" in e and "metres" in e for e in errors)
    assert any("no depth/ image for target image 0" in e for e in errors)
    assert any("cnos-fastsam_lmo-test*.json: the prior pattern (field 'prior') must match exactly one file, "
               "found no file" in e for e in errors)


def test_prior_pattern_must_match_one_file(tmp_path):
    from pipeline.workflow.plan import resolve_prior

    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "cnos-fastsam_lmo-test_a.json").write_text("[]")
    assert resolve_prior(tmp_path, "d/cnos-fastsam_lmo-test*.json").name == "cnos-fastsam_lmo-test_a.json"
    assert resolve_prior(tmp_path, "d/plain.json") == (tmp_path / "d" / "plain.json").resolve()  # no pattern: as is
    (tmp_path / "d" / "cnos-fastsam_lmo-test_b.json").write_text("[]")
    with pytest.raises(cfg.ManifestError, match="must match exactly one file, found .*_a.json, .*_b.json"):
        resolve_prior(tmp_path, "d/cnos-fastsam_lmo-test*.json")


def test_a_relative_prior_must_stay_inside_bop_root(tmp_path):
    from pipeline.workflow.plan import resolve_prior

    root = tmp_path / "bop"
    root.mkdir()
    (tmp_path / "elsewhere.json").write_text("[]")
    with pytest.raises(cfg.ManifestError, match=r"prior '\.\./\.\./\.\./etc/passwd' resolves to .*/etc/passwd, outside "
                                                r"bop_root .*give the absolute path"):
        resolve_prior(root, "../../../etc/passwd")  # the case
    with pytest.raises(cfg.ManifestError, match="outside bop_root"):
        resolve_prior(root, "../else*.json")
    # an absolute path is the user's explicit choice
    assert resolve_prior(root, str(tmp_path / "elsewhere.json")) == (tmp_path / "elsewhere.json").resolve()
    assert resolve_prior(root, str(tmp_path / "else*.json")) == (tmp_path / "elsewhere.json").resolve()


@pytest.mark.slow
def test_bop_root_from_the_environment(bop_root, monkeypatch):
    monkeypatch.setenv("BOP_ROOT", str(bop_root))
    run = cfg.load_run({"datasets": "lmo"})
    assert run.bop_root == str(bop_root.resolve()) and RunPlan(run).available("lmo") == (True, "")
    monkeypatch.delenv("BOP_ROOT")
    assert RunPlan(cfg.load_run({"datasets": "lmo"})).available("lmo") == (
        False, "lmo: skipped, no bop_root set (--config bop_root=/path/to/bop, or $BOP_ROOT)")

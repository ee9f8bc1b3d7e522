"""The seven BOP core dataset manifests, and running over whichever of them a user has
under `bop_root` (a tiny dataset in the LM-O layout stands in for the download)."""

from __future__ import annotations

import shutil

import pytest

from conftest import run_snakemake
from pipeline import config as cfg
from pipeline.plan import RunPlan

CORE = {"lmo": (None, 15.0), "tless": ("primesense", 15.0), "tudl": (None, 15.0), "icbin": (None, 15.0),
        "itodd": (None, 5.0), "hb": ("primesense", 15.0), "ycbv": (None, 15.0)}


def test_core_manifests_carry_what_differs():
    for name, (split_type, vsd_delta) in CORE.items():
        ds = cfg.load_dataset_manifest(name)
        assert (ds.kind, ds.folder, ds.split, ds.split_type, ds.vsd_delta) == ("bop", name, "test", split_type, vsd_delta)
        assert ds.prior == f"detections/cnos-fastsam_{name}-test.json"


@pytest.fixture(scope="module")
def bop_root(tmp_path_factory):
    """A bop_root holding only 'lmo' (a tiny synthetic dataset in its folder) and its
    default-detections file."""
    from pipeline.synth import generate

    root = tmp_path_factory.mktemp("bop")
    generate(root / "lmo", name="lmo", preset="tiny", seed=0, progress=False)
    (root / "detections").mkdir()
    shutil.move(root / "lmo" / "detections" / "cnos-synth_lmo-test.json", root / "detections" / "cnos-fastsam_lmo-test.json")
    return root


def test_only_the_datasets_found_are_planned(bop_root):
    rp = RunPlan(cfg.load_run({"datasets": ",".join(CORE), "bop_root": str(bop_root)}))
    found = {name: rp.available(name) for name in CORE}
    assert found["lmo"] == (True, "")
    for name in set(CORE) - {"lmo"}:
        ok, why = found[name]
        assert not ok and why == f"{name}: skipped, {bop_root / name / 'test_targets_bop19.json'} not found"
    plan = rp["lmo"]
    assert plan.obj_ids == [2, 5, 6] and plan.scene_ids == [1]
    assert plan.prior_path == (bop_root / "detections" / "cnos-fastsam_lmo-test.json").resolve()
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

"""End to end: `snakemake bop_all` on the tiny synthetic dataset, then the cache rules
seen from Snakemake's own dry-run job lists."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.bop import read_results_csv

ROOT = Path(__file__).resolve().parent.parent
SNAKEMAKE = Path(sys.executable).parent / "snakemake"


def _snakemake(workdir: Path, *args: str, dry: bool = False) -> str:
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env.update(FREEZE_CACHE=str(workdir / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1")
    cmd = [str(SNAKEMAKE), "-s", str(ROOT / "Snakefile"), "--directory", str(workdir), "--cores", "2", "bop_all"]
    if dry:
        cmd.append("-n")
    proc = subprocess.run(cmd + ["--config", "datasets=synthtiny", *args], env=env,
                          capture_output=True, text=True, timeout=900)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    return out


def _planned_jobs(out: str) -> dict[str, int]:
    """Rule -> job count from the 'Job stats' table of a dry run ({} if nothing to do)."""
    if "Nothing to be done" in out:
        return {}
    table = out.split("Job stats:", 1)[1]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)$", table, re.M) if m.group(1) != "total"}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("pipeline")
    out = _snakemake(work)
    return work, out


@pytest.mark.slow
def test_bop_all_produces_scores_and_a_bop_csv(tiny_run):
    work, out = tiny_run
    assert "BOP19 average recall" in out
    manifests = sorted((work / "cache" / "synthtiny" / "score").glob("*/all/_manifest.json"))
    assert len(manifests) == 1
    summary = json.loads(manifests[0].read_text())["summary"]
    for key in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD"):
        assert 0.0 <= summary[key] <= 1.0
    assert summary["AR"] == pytest.approx((summary["AR_VSD"] + summary["AR_MSSD"] + summary["AR_MSPD"]) / 3)
    csv = next((work / "cache" / "synthtiny" / "refine").glob("*/all/freeze_synthtiny-test.csv"))
    results = read_results_csv(csv)
    assert len(results) == summary["n_estimates"] > 0
    # One time per image, as BOP requires.
    assert (results.groupby(["scene_id", "im_id"]).time.nunique() == 1).all()
    assert (work / "results" / "ar_table.md").read_text().count("synthtiny") == 1
    # The per-object PCA bases are stored and orthonormal.
    from pipeline.store import load_arrays

    pca = load_arrays(next((work / "cache" / "synthtiny" / "register").glob("*/scene_*/pca.zarr")))
    assert len(pca["obj_id"]) >= 2
    for comps in pca["components"]:
        assert np.allclose(comps @ comps.T, np.eye(len(comps)), atol=1e-4)
    # No temporary folder of an atomic publish is left anywhere.
    assert not list((work / "cache").rglob(".tmp-*"))


@pytest.mark.slow
def test_second_run_does_nothing(tiny_run):
    work, _ = tiny_run
    assert _planned_jobs(_snakemake(work, dry=True)) == {}


@pytest.mark.slow
def test_visual_encoder_swap_reruns_only_dependent_stages(tiny_run):
    work, _ = tiny_run
    jobs = _planned_jobs(_snakemake(work, "visual_encoder=colortex-coarse", dry=True))
    assert set(jobs) == {"model_features", "scene_features", "register", "refine", "refine_collect", "score", "bop_all"}
    assert jobs["model_features"] == 3  # the three objects of the tiny preset


@pytest.mark.slow
def test_stage_parameter_change_reruns_from_that_stage(tiny_run, tmp_path):
    work, _ = tiny_run
    run = (ROOT / "manifests" / "runs" / "default.yaml").read_text()
    assert "scene_features: {n_points: 1000" in run
    other = tmp_path / "fewer_points.yaml"
    other.write_text(run.replace("scene_features: {n_points: 1000", "scene_features: {n_points: 500"))
    jobs = _planned_jobs(_snakemake(work, f"run={other}", dry=True))
    assert set(jobs) == {"scene_features", "register", "refine", "refine_collect", "score", "bop_all"}


@pytest.mark.slow
def test_geometry_only_and_vision_only_runs(tiny_run):
    """`visual=none` / `geometric=none` (the paper's ablations) run the same pipeline with
    one part switched off; the other stages are reused."""
    from pipeline.store import load_arrays, read_table

    work, _ = tiny_run
    jobs = _planned_jobs(_snakemake(work, "visual=none", dry=True))
    assert set(jobs) == {"model_features", "scene_features", "register", "refine", "refine_collect", "score", "bop_all"}
    out = _snakemake(work, "visual=none")
    assert "BOP19 average recall" in out
    cache = work / "cache" / "synthtiny"
    feats = load_arrays(next((cache / "model_features").glob("fpfh-ms+novis-*/obj_000005/features.zarr")))
    assert feats["visual"].shape == (5000, 0) and feats["geometric"].shape == (5000, 66)
    assert (feats["view_count"] > 0).mean() > 0.9  # visibility is still computed
    pca = load_arrays(next((cache / "register").glob("fpfh-ms+novis-*/scene_000001/pca.zarr")))
    assert len(pca["obj_id"]) == 0
    geo_only = read_table(next((cache / "register").glob("fpfh-ms+novis-*/scene_000001/candidates.parquet")))

    _snakemake(work, "geometric=none")
    feats = load_arrays(next((cache / "scene_features").glob("nogeo+colortex-*/scene_000001/features.zarr")))
    assert feats["geometric"].shape[2] == 0 and feats["visual"].shape[2] == 30
    vis_only = read_table(next((cache / "register").glob("nogeo+colortex-*/scene_000001/candidates.parquet")))
    pca = load_arrays(next((cache / "register").glob("nogeo+colortex-*/scene_000001/pca.zarr")))
    informative = dict(zip(pca["obj_id"].tolist(), pca["informative"].tolist()))
    # The grey hex nut's colour features carry nothing: vision alone finds no inlier for
    # it, geometry alone does; the textured can and cup register either way.
    assert informative == {2: True, 5: False, 6: True}
    assert (vis_only[vis_only.obj_id == 5].n_inliers == 0).all()
    assert (geo_only[geo_only.obj_id == 5].n_inliers > 0).all()
    assert (vis_only[vis_only.obj_id != 5].n_inliers > 10).all()

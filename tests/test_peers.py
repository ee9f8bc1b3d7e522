"""The classical peers of ``benchmarks/peers.py``: the FPFH + RANSAC + ICP peer end to end on
synthtiny (a CSV the project's scorer scores, above a measured AR), and the PPF worker's
exchange on a known pose (where its virtual environment exists)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
PEERS = ROOT / "benchmarks" / "peers.py"
sys.path.insert(0, str(ROOT / "benchmarks"))

FPFH_SYNTHTINY_AR_FLOOR = 0.28
"""Measured with the defaults (2026-12, one thread, seed 0): AR 0.324 on synthtiny's 7
targets, the same in two runs from fresh caches (poses equal to 1e-12). The coarser
voxel of 0.04 d gave 0.531 here but 0.496 against 0.611 on semilmo's first 4 images: the
defaults are tuned on the realistic sets, not on this tiny one (docstring of peers.py)."""


@pytest.mark.slow
def test_fpfh_peer_on_synthtiny(tmp_path):
    env = {**os.environ, "FREEZE_CACHE": str(tmp_path / "cache"), "PYOPENGL_PLATFORM": "egl", "HF_HUB_OFFLINE": "1"}
    env.pop("OMP_NUM_THREADS", None)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(PEERS), "--datasets", "synthtiny,nosuchdataset", "--peers", "fpfh",
                           "--out", str(out), "--no-progress"], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # a dataset that cannot run is one line, not a traceback
    assert "Traceback" not in proc.stderr and "nosuchdataset" in proc.stderr
    lines = [json.loads(x) for x in proc.stdout.splitlines() if x.startswith("{")]
    assert len(lines) == 1
    summary = lines[0]
    assert summary["peer"] == "fpfh" and summary["dataset"] == "synthtiny" and summary["n_targets"] == 7
    assert summary["AR"] > FPFH_SYNTHTINY_AR_FLOOR, summary
    assert summary["threads"] == "1" and summary["n_images"] == 2
    assert set(summary["onboarding_s"]) == {"2", "5", "6"}

    csv = out / "fpfh_synthtiny-test.csv"
    assert Path(summary["csv"]) == csv and json.loads(csv.with_suffix(".json").read_text())["AR"] == summary["AR"]
    from pipeline.formats.bop.results import read_results_csv

    rows = read_results_csv(csv)
    # one estimate per candidate that got a pose: synthtiny's prior keeps 10 candidates
    assert len(rows) == summary["n_estimates"] == summary["n_candidates"] - summary["n_failed"] == 10
    for R in rows.R:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) > 0
    per_image = rows.groupby(["scene_id", "im_id"]).time.nunique()
    assert (per_image == 1).all() and (rows.time > 0).all()
    assert rows.time.groupby([rows.scene_id, rows.im_id]).first().mean() == pytest.approx(summary["s_per_image"])

    # the CSV round-trips through the project's scorer to the same numbers
    os.environ["FREEZE_CACHE"] = str(tmp_path / "cache")
    try:
        import peers

        again = peers.score_peer_csv(peers.dataset_plan("synthtiny"), csv)
    finally:
        os.environ.pop("FREEZE_CACHE")
    assert again["AR"] == pytest.approx(summary["AR"]) and again["n_targets"] == 7


def _box_cloud(n: int, seed: int) -> np.ndarray:
    """(n, 6) float32 points and outward normals on an 80 x 50 x 30 mm box with a 30 mm
    block on one corner (no symmetry)."""
    import trimesh

    from pipeline.method.geometry.sampling import sample_surface

    a = trimesh.creation.box((80, 50, 30))
    b = trimesh.creation.box((30, 30, 30))
    b.apply_translation((25, 10, 30))
    mesh = trimesh.util.concatenate([a, b])
    pts, normals = sample_surface(mesh, n, seed)
    return np.hstack([pts, normals]).astype(np.float32)


@pytest.mark.slow
def test_ppf_worker_finds_a_known_pose(tmp_path):
    """The worker's exchange for real: the model and a scene (the model at a known pose,
    its camera-facing half) in, poses out, and the best pose puts the model on the scene.
    The worker's environment is built as the benchmark builds it (on a new machine: a
    venv and one pip install from PyPI, about a minute)."""
    import peers

    python = peers.ensure_ppf_env()
    from pipeline.method.geometry.transforms import rotation_about_axis

    model = _box_cloud(6000, 0)
    R = rotation_about_axis(np.array([1.0, 2.0, 0.5]), 40.0)
    t = np.array([10.0, -20.0, 600.0])
    scene_all = _box_cloud(6000, 1)
    pts = scene_all[:, :3] @ R.T + t
    normals = scene_all[:, 3:] @ R.T
    facing = np.sum(normals * pts, axis=1) < 0
    scene = np.hstack([pts, normals])[facing].astype(np.float32)
    params = {k: peers.DEFAULTS["ppf"][k] for k in ("rel_sampling", "rel_distance", "num_angles", "scene_sample_step",
                                                     "rel_scene_distance", "n_icp", "icp_iterations", "icp_tolerance",
                                                     "icp_rejection", "icp_levels")}
    params.update(rel_sampling=0.1, rel_scene_distance=0.08)  # coarser than the defaults: a second, not ten
    inp, outp = tmp_path / "in.npz", tmp_path / "out.npz"
    np.savez(inp, params=np.asarray(json.dumps(params)), model_7=model, icpmodel_7=model[::3],
             cand_ids=np.asarray([42], np.int64), cand_obj=np.asarray([7], np.int64), scene_42=scene)
    proc = subprocess.run([str(python), str(peers.PPF_WORKER), str(inp), str(outp)], capture_output=True, text=True,
                          timeout=120, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["done", "42"]
    out = np.load(outp)
    assert out["train_obj"].tolist() == [7] and out["train_s"][0] > 0
    assert out["cand_ids"].tolist() == [42] and out["poses"].shape == (1, params["n_icp"], 4, 4)
    k = int(out["n_poses"][0])
    assert 1 <= k <= params["n_icp"] and out["votes"][0, 0] > 0 and out["match_s"][0] > 0
    T = out["poses"][0, 0]
    np.testing.assert_allclose(T[3], [0, 0, 0, 1], atol=1e-9)
    posed = model[:, :3] @ T[:3, :3].T + T[:3, 3]
    truth = model[:, :3] @ R.T + t
    # the model's points where they should be (the shape has no symmetry): mean error in mm
    assert np.mean(np.linalg.norm(posed - truth, axis=1)) < 3.0

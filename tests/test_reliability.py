"""Faults and bad options, as a user meets them (issue 14): each test sets up the fault,
runs the real command, and checks the message and the exit code.

The fixture ``damaged_copy`` copies the finished synthtiny cache of the session's
``tiny_run`` (tests/conftest.py) so that a test can damage it without touching the
others' copy."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from conftest import ROOT, current_dir
from pipeline.commands.verify import verify_cache
from pipeline.commands.cli import app
from pipeline.common.config import ManifestError, load_run
from pipeline.common.store import (DamagedArtifact, MANIFEST_NAME, ensure_sound, publish, read_manifest,
                            save_arrays, verify_item, write_table)

FREEZE = Path(sys.executable).parent / "freeze"
runner = CliRunner()


def _env(work: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env.update(FREEZE_CACHE=str(work / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1")
    return env


def _freeze(work: Path, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([str(FREEZE), *args], cwd=work, env=_env(work), capture_output=True, text=True,
                          timeout=timeout)


def _publish_item(folder: Path) -> Path:
    item = folder / "scene_000001"
    with publish(item, stage="register", item="scene_000001", key="k" * 40, signature="x-kkkkkkkk", params={},
                 upstream={}, code_version=1, dataset="d") as w:
        save_arrays(w.dir / "features.zarr", {"points": np.arange(3000, dtype=np.float32).reshape(10, 100, 3)})
        write_table(pd.DataFrame({"a": [1, 2, 3]}), w.dir / "coarse_hypotheses.parquet")
    return item


# ------------------------------------------------------------------- checksums


def test_manifest_records_every_file_and_verify_names_the_damage(tmp_path):
    item = _publish_item(tmp_path)
    files = read_manifest(item)["files"]
    assert "coarse_hypotheses.parquet" in files and any(k.startswith("features.zarr/points/") for k in files)
    assert all(len(v["sha256"]) == 64 and v["size"] > 0 for v in files.values())
    assert verify_item(item) == []
    ensure_sound(item)

    chunk = next(p for p in sorted((item / "features.zarr" / "points").rglob("*")) if p.is_file()
                 and p.name != "zarr.json")
    data = chunk.read_bytes()
    chunk.write_bytes(data[: len(data) // 2])  # truncated
    problems = verify_item(item)
    assert len(problems) == 1 and chunk.relative_to(item).as_posix() in problems[0] and "bytes" in problems[0]
    with pytest.raises(DamagedArtifact, match="freeze verify --repair"):
        ensure_sound(item)

    chunk.write_bytes(bytes(len(data)))  # same size, other bytes
    assert "checksum" in verify_item(item)[0]
    assert verify_item(item, checksums=False) == []

    shutil.rmtree(item / "features.zarr" / "points")  # a deleted array
    assert any("features.zarr/points" in p and "missing" in p for p in verify_item(item))

    (item / MANIFEST_NAME).write_text('{"key": "kkk", "fil')  # a truncated manifest
    (problem,) = verify_item(item)
    assert str(item) in problem and "not valid JSON" in problem


def test_verify_cache_repair_removes_damaged_items_and_leftovers(tmp_path):
    cache = tmp_path / "cache"
    good = _publish_item(cache / "d" / "register" / "sig-a")
    bad = _publish_item(cache / "d" / "register" / "sig-b")
    (bad / "coarse_hypotheses.parquet").write_bytes(b"PAR1")
    leftover = cache / "d" / "register" / "sig-a" / ".tmp-scene_000002-1234abcd"
    leftover.mkdir()
    assert verify_cache(cache).leftovers == []  # it may be a running job's
    os.utime(leftover, (time.time() - 7200, time.time() - 7200))
    report = verify_cache(cache)
    assert report.checked == 2 and list(report.damaged) == [bad] and report.leftovers == [leftover]
    report = verify_cache(cache, repair=True)
    assert not bad.exists() and not leftover.exists() and good.exists()
    assert verify_cache(cache).ok


@pytest.fixture
def damaged_copy(tiny_run, tmp_path) -> Path:
    """A work folder holding a copy of the finished synthtiny cache (to damage)."""
    work, _ = tiny_run
    shutil.copytree(work / "cache", tmp_path / "cache", symlinks=True)
    return tmp_path


@pytest.mark.slow
def test_a_stage_refuses_a_damaged_input_naming_the_file(damaged_copy):
    work = damaged_copy
    feats = current_dir(work, "scene_features") / "scene_000001" / "features.zarr"
    chunk = next(p for p in sorted((feats / "geometric").rglob("*")) if p.is_file() and p.name != "zarr.json")
    chunk.write_bytes(chunk.read_bytes()[:10])
    proc = _freeze(work, "stage", "register", "--dataset", "synthtiny", "--item", "scene_000001", "-c",
                   "datasets=synthtiny", "--no-progress")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "damaged artifact" in out and "geometric" in out and "freeze verify --repair" in out
    assert "Traceback" not in out


@pytest.mark.slow
def test_verify_inspect_and_table_name_a_damaged_score_and_a_rerun_rebuilds_it(damaged_copy, tiny_run):
    work = damaged_copy
    score = current_dir(work, "score") / "all"
    ar = read_manifest(score)["summary"]["AR"]
    (score / "scores.json").write_text('{"summ')  # truncated

    res = runner.invoke(app, ["table", "-c", "datasets=synthtiny"], env=_env(work))
    assert res.exit_code == 1 and "scores.json" in res.output and f"{ar:.3f}" not in res.output
    res = runner.invoke(app, ["inspect", str(score / "scores.json")], env=_env(work))
    assert res.exit_code == 1 and "scores.json" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["report", "--dataset", "synthtiny", "-c", "datasets=synthtiny", "--out",
                              str(work / "r.html")], env=_env(work))
    assert res.exit_code == 1 and "scores.json" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["verify", "--cache", str(work / "cache"), "--no-progress"])
    assert res.exit_code == 1 and "1 damaged" in res.output and "scores.json" in res.output

    res = runner.invoke(app, ["verify", "--cache", str(work / "cache"), "--repair", "--no-progress"])
    assert res.exit_code == 0 and not score.exists()
    proc = _freeze(work, "run", "-c", "datasets=synthtiny")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert read_manifest(score)["summary"]["AR"] == ar
    assert runner.invoke(app, ["verify", "--cache", str(work / "cache"), "--no-progress"]).exit_code == 0


@pytest.mark.slow
def test_a_killed_run_resumes_with_freeze_run_and_gives_the_clean_result(tiny_run, tmp_path):
    """kill -9 of the whole run as a scene job publishes; `freeze run` resumes without
    help (stale lock, incomplete marks), reruns only what was not published, and ends
    with the clean run's poses and AR."""
    clean, _ = tiny_run
    work = tmp_path
    shutil.copytree(clean / "cache", work / "cache", symlinks=True)
    for stage in ("refine", "score"):  # the model side, scene features and registration stay
        shutil.rmtree(current_dir(work, stage))
    env = _env(work)
    snakemake = Path(sys.executable).parent / "snakemake"
    proc = subprocess.Popen([str(snakemake), "-s", str(ROOT / "Snakefile"), "--directory", str(work), "--cores", "2",
                             "bop_all", "--config", "datasets=synthtiny"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    refined = current_dir(work, "refine") / "scene_000001" / MANIFEST_NAME
    deadline = time.time() + 600
    while not refined.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)  # as soon as the scene's refine publishes: the dataset's has not
    proc.wait()
    assert any((work / ".snakemake" / "locks").iterdir()), "a killed run leaves its lock"

    res = _freeze(work, "run", "-c", "datasets=synthtiny")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    assert "removed the lock" in out
    for stage, name in (("refine", "poses.parquet"), ("register", "coarse_hypotheses.parquet")):
        a = pd.read_parquet(current_dir(clean, stage) / "scene_000001" / name)
        b = pd.read_parquet(current_dir(work, stage) / "scene_000001" / name)
        pd.testing.assert_frame_equal(a.drop(columns=["time_s"], errors="ignore"),
                                      b.drop(columns=["time_s"], errors="ignore"))
    ar = lambda w: read_manifest(current_dir(w, "score") / "all")["summary"]["AR"]  # noqa: E731
    assert ar(work) == ar(clean)
    assert verify_cache(work / "cache").ok
    # and now a plain rerun has nothing left to do
    again = _freeze(work, "run", "-c", "datasets=synthtiny", "--dry-run")
    planned = again.stdout + again.stderr
    assert again.returncode == 0 and not any(f"rule {s}" in planned for s in ("register", "refine", "score"))


# -------------------------------------------------------------- bad options


def test_unknown_config_keys_are_refused_with_a_suggestion():
    with pytest.raises(ManifestError, match=r"unknown key 'visaul' \(did you mean 'visual'\?\).*known keys: "):
        load_run({"datasets": "synthtiny", "visaul": "none"})
    with pytest.raises(ManifestError, match="unknown keys 'visaul' .*'foo'"):
        load_run({"visaul": "none", "foo": "bar"})
    res = runner.invoke(app, ["plan", "-c", "datasets=synthtiny", "-c", "foo=bar"])
    assert res.exit_code != 0 and "unknown key 'foo'" in res.output


def test_a_run_with_no_dataset_exits_non_zero(tmp_path):
    env = _env(tmp_path)
    snakemake = Path(sys.executable).parent / "snakemake"
    proc = subprocess.run([str(snakemake), "-s", str(ROOT / "Snakefile"), "--directory", str(tmp_path), "--cores", "1",
                           "bop_all", "-n", "--config", f"bop_root={tmp_path / 'nonexistent'}", "datasets=lmo"],
                          env=env, capture_output=True, text=True, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "no dataset of the run can be run" in out and "Traceback" not in out
    proc = subprocess.run([str(snakemake), "-s", str(ROOT / "Snakefile"), "--directory", str(tmp_path), "--cores", "1",
                           "bop_all", "-n", "--config", "visaul=none"], env=env, capture_output=True, text=True,
                          timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "did you mean 'visual'" in out and "Traceback" not in out
    res = _freeze(tmp_path, "run", "-c", f"bop_root={tmp_path / 'nonexistent'}", "-c", "datasets=lmo")
    assert res.returncode == 1 and "no dataset of the run can be run" in res.stderr


def test_a_full_disk_is_one_line_naming_what_was_being_published(tmp_path, monkeypatch):
    """ENOSPC while an item is written: a StorageError naming the item, the previous
    version intact, no temporary folder left."""
    import errno

    from pipeline.common.store import StorageError

    item = _publish_item(tmp_path)
    before = read_manifest(item)["files"]

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("pipeline.common.store.write_table", full)
    with pytest.raises(StorageError, match=r"scene_000001: cannot write it \(no space left on the device\); nothing "
                                           "was published"):
        with publish(item, stage="register", item="scene_000001", key="k" * 40, signature="x-kkkkkkkk", params={},
                     upstream={}, code_version=1, dataset="d") as w:
            from pipeline.common import store

            store.write_table(pd.DataFrame({"a": [1]}), w.dir / "coarse_hypotheses.parquet")
    assert read_manifest(item)["files"] == before and verify_item(item) == []
    assert [p.name for p in tmp_path.iterdir()] == ["scene_000001"]


@pytest.mark.slow
def test_a_dataset_whose_candidates_are_all_dropped_says_why_next_to_the_table(damaged_copy):
    """Every candidate dropped (as with negative detection scores): refine's results say
    why, with the counts per reason, and the AR table printed by the run carries it."""
    work = damaged_copy
    prior = current_dir(work, "segment_prior") / "all"
    manifest = read_manifest(prior)
    manifest["summary"]["dropped"] = {"low_score": 7}  # the reason segment_prior records for scores < min_score
    st = (prior / MANIFEST_NAME).stat()
    (prior / MANIFEST_NAME).write_text(json.dumps(manifest))
    os.utime(prior / MANIFEST_NAME, ns=(st.st_atime_ns, st.st_mtime_ns))  # else Snakemake reruns what follows it
    scene = current_dir(work, "refine") / "scene_000001"
    poses = pd.read_parquet(scene / "poses.parquet")
    with publish(scene, **{k: read_manifest(scene)[k] for k in ("stage", "item", "key", "signature", "params",
                                                                "upstream", "code_version", "dataset")}) as w:
        for f in scene.iterdir():
            if f.name != MANIFEST_NAME:
                shutil.copy(f, w.dir / f.name)
        poses.iloc[:0].to_parquet(w.dir / "poses.parquet")  # no estimate survived
    for stage, item in (("refine", "all"), ("score", "all")):
        shutil.rmtree(current_dir(work, stage) / item)
    proc = _freeze(work, "run", "-c", "datasets=synthtiny")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    note = "no estimate: every candidate was dropped"
    assert note in read_manifest(current_dir(work, "refine") / "all")["summary"]["notes"][0]
    table = (work / "results" / "ar_table.md").read_text()
    assert note in table and "segment_prior: low_score (7)" in table


def test_readers_name_the_damaged_file(tmp_path):
    """Read without verifying first (a library user, a report), a truncated table or a
    deleted array is still one error naming the file, not ArrowInvalid or KeyError."""
    from pipeline.common.store import load_arrays, read_table

    item = _publish_item(tmp_path)
    table = item / "coarse_hypotheses.parquet"
    table.write_bytes(table.read_bytes()[:40])
    with pytest.raises(DamagedArtifact, match=r"coarse_hypotheses.parquet: cannot read the Parquet table .*freeze verify"):
        read_table(table)
    shutil.rmtree(item / "features.zarr" / "points")
    with pytest.raises(DamagedArtifact, match=r"features.zarr: no array 'points'"):
        load_arrays(item / "features.zarr", ["points"])

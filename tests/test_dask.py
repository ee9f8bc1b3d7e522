"""Dask inside a job (:mod:`pipeline.common.parallel`): register's and refine's candidates and
score's images on a loopback dask cluster, and on threads, give the artifacts of the
in-process run; an unreachable scheduler fails at once with one line."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from conftest import ROOT, current_dir
from pipeline.common import config as cfg
from pipeline.common.parallel import SCHEDULER_ENV, SchedulerUnreachable, scheduler_address, work_mapper
from pipeline.workflow.plan import RunPlan

STAGES = ("register", "refine", "score")
TIME_COLUMNS = {"time_s", "time"}


def _closed_port() -> int:
    """A local TCP port nobody listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tables(folder: Path) -> dict[str, pd.DataFrame]:
    """Every Parquet table under an artifact folder, without its time columns."""
    out = {}
    for path in sorted(folder.rglob("*.parquet")):
        df = pd.read_parquet(path)
        out[str(path.relative_to(folder))] = df.drop(columns=[c for c in df.columns if c in TIME_COLUMNS])
    return out


def _csv_rows(folder: Path) -> list[list[str]]:
    """The results CSV's rows without its last column (time)."""
    (path,) = folder.glob("all/*.csv")
    return [line.split(",")[:-1] for line in path.read_text().splitlines()]


def _rerun(work: Path, dest: Path, **overrides: str) -> Path:
    """``work``'s cache copied to ``dest`` without register, refine and score, which are
    run again in this process with ``overrides``; returns the new cache."""
    shutil.copytree(work / "cache", dest / "cache", symlinks=True)
    plan = RunPlan(cfg.load_run({"datasets": "synthtiny", **overrides}), cache=dest / "cache")["synthtiny"]
    for stage in STAGES:
        shutil.rmtree(plan[stage].dir)
    from pipeline.workflow.stage_graph import run_stage

    for stage in STAGES:
        for item in (plan.scene_items if stage in ("register", "refine") else []) + (
                ["all"] if stage in ("refine", "score") else []):
            run_stage(plan, stage, item, progress=False)
    return dest


def _same_artifacts(before: Path, after: Path) -> None:
    for stage in STAGES:
        a, b = _tables(current_dir(before, stage)), _tables(current_dir(after, stage))
        assert a.keys() == b.keys() and a, stage
        for name in a:
            pd.testing.assert_frame_equal(a[name], b[name], check_exact=True, obj=f"{stage}/{name}")
    assert _csv_rows(current_dir(before, "refine")) == _csv_rows(current_dir(after, "refine"))
    s0 = json.loads((current_dir(before, "score") / "all" / "scores.json").read_text())["summary"]
    s1 = json.loads((current_dir(after, "score") / "all" / "scores.json").read_text())["summary"]
    assert s1["AR"] == s0["AR"] is not None


@pytest.mark.slow
def test_a_loopback_cluster_and_threads_give_the_in_process_artifacts(tiny_run, tmp_path, monkeypatch):
    from distributed import LocalCluster

    import stages.refine
    import stages.register
    import stages.score

    work, _ = tiny_run  # Snakemake's run: register, refine, score on one thread each
    monkeypatch.delenv(SCHEDULER_ENV, raising=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        on_cluster = _rerun(work, tmp_path / "cluster", dask_scheduler=cluster.scheduler_address)
    _same_artifacts(work, on_cluster)
    for module in (stages.register, stages.refine, stages.score):
        monkeypatch.setattr(module, "THREADS_HELP", True)
    monkeypatch.setenv("FREEZE_THREADS", "2")
    _same_artifacts(work, _rerun(work, tmp_path / "threads"))


def test_an_unreachable_scheduler_fails_at_once_naming_the_address_and_the_option(monkeypatch):
    address = f"tcp://127.0.0.1:{_closed_port()}"
    t0 = time.perf_counter()
    with pytest.raises(SchedulerUnreachable, match=f"dask scheduler at {address}.*dask_scheduler"):
        with work_mapper(address):
            pass
    assert time.perf_counter() - t0 < 10
    monkeypatch.setenv(SCHEDULER_ENV, address)
    assert scheduler_address(None) == address and scheduler_address("tcp://other:1") == "tcp://other:1"
    monkeypatch.delenv(SCHEDULER_ENV)
    assert scheduler_address(None) is None and scheduler_address("") is None


@pytest.mark.slow
def test_freeze_stage_exits_non_zero_with_one_line_on_an_unreachable_scheduler(tiny_run, tmp_path):
    work, _ = tiny_run
    address = f"tcp://127.0.0.1:{_closed_port()}"
    env = {k: v for k, v in os.environ.items() if k not in ("FREEZE_RUN_JSON", SCHEDULER_ENV)}
    env.update(FREEZE_CACHE=str(work / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1", COLUMNS="200")
    env[SCHEDULER_ENV] = address  # the environment's address, as Snakemake's jobs inherit it
    t0 = time.perf_counter()
    # The item's inputs exist (tiny_run), so the job gets as far as the mapper and fails
    # there, before writing anything.
    proc = subprocess.run([sys.executable, "-m", "pipeline.commands.cli", "stage", "register", "--dataset", "synthtiny",
                           "--item", "scene_000001", "--no-progress"], env=env, cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    elapsed = time.perf_counter() - t0
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    errors = [line for line in out.splitlines() if "dask scheduler" in line]
    assert len(errors) == 1 and address in errors[0] and "dask_scheduler" in errors[0], out
    assert "Traceback" not in out
    assert elapsed < 60, elapsed  # start-up and the inputs included; the connection itself fails at once

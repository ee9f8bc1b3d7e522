"""`freeze run` and the Snakefile under faults (issue 28, part A): hostile paths in the
shell commands, a cache repaired by `freeze verify --repair`, signals, stale marks of
unfinished jobs, a second start, planning errors, a lost dask scheduler and bad `-c`
values. Each test sets up the fault, runs the real command and checks the message, the
exit code and what was (not) written.

The pipeline tests copy the finished synthtiny cache of the session's ``tiny_run``
(tests/conftest.py) and remove or damage a few stages, so that they rerun only those."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from base64 import urlsafe_b64encode
from pathlib import Path

import pandas as pd
import pytest

from conftest import ROOT, current_dir, run_snakemake
from pipeline.commands.run import incomplete_marks, snakemake_processes
from pipeline.common.store import MANIFEST_NAME, read_manifest

FREEZE = Path(sys.executable).parent / "freeze"
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
SCENE_STAGES = ("scene_features", "register", "refine", "score")


def _env(work: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("FREEZE_RUN_JSON", "DASK_SCHEDULER_ADDRESS")}
    env.update(FREEZE_CACHE=str(work / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1", COLUMNS="200")
    return env


def _freeze(work: Path, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([str(FREEZE), *args], cwd=work, env=_env(work), capture_output=True, text=True,
                          timeout=timeout)


def _snakemake(work: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([str(SNAKEMAKE), "-s", str(ROOT / "Snakefile"), "--directory", str(work), *args],
                          cwd=work, env=_env(work), capture_output=True, text=True, timeout=timeout)


def _copy(tiny_run, work: Path, drop: tuple[str, ...] = ()) -> Path:
    """``work`` holding a copy of tiny_run's cache without the stages in ``drop``."""
    clean, _ = tiny_run
    shutil.copytree(clean / "cache", work / "cache", symlinks=True)
    for stage in drop:
        shutil.rmtree(current_dir(work, stage))
    return work


def _ar(work: Path) -> float:
    return read_manifest(current_dir(work, "score") / "all")["summary"]["AR"]


def _one_error_line(out: str) -> str:
    """The output's only line starting with 'error:' (failing the test otherwise)."""
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in out, out[-3000:]
    return errors[0]


def _processes_in(folder: Path) -> list[str]:
    """Command lines of the processes whose current folder is ``folder`` (Linux /proc)."""
    folder = folder.resolve()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if Path(os.readlink(entry / "cwd")) == folder:
                found.append((entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"))
        except OSError:
            continue
    return found


# ------------------------------------------------------------ paths in the shell


@pytest.mark.slow
def test_a_cache_path_with_a_space_a_quote_and_a_semicolon_runs_and_writes_nothing_outside(tiny_run, tmp_path):
    """The cache (and so results/ and logs/, and every job's log) under a folder named
    ``a b;touch pwned;'q``: the stage jobs and bop_all run through the shell with their
    paths quoted, give the clean run's AR, and nothing is written outside that folder (an
    unquoted path truncated a file at its prefix ``a`` and ran ``touch pwned``)."""
    work = tmp_path / "a b;touch pwned;'q"
    _copy(tiny_run, work, drop=("score",))
    shutil.rmtree(current_dir(work, "refine") / "all")  # refine_collect, score and bop_all run
    cwd_before = sorted(p.name for p in Path.cwd().iterdir())
    out = run_snakemake(work)
    assert "rule refine_collect" in out and "rule score" in out
    assert _ar(work) == _ar(tiny_run[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == [work.name]  # no file 'a' beside it
    assert not any(p.name == "pwned" for p in tmp_path.rglob("*"))
    assert sorted(p.name for p in Path.cwd().iterdir()) == cwd_before
    assert (work / "results" / "ar_table.md").is_file() and (work / "results" / "report_synthtiny.html").is_file()
    assert (work / "logs" / "bop_all.log").is_file()


def test_a_cache_path_with_a_brace_is_refused_in_one_line(tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    env = {**_env(work), "FREEZE_CACHE": str(tmp_path / "x{y}" / "cache")}
    proc = subprocess.run([str(SNAKEMAKE), "-s", str(ROOT / "Snakefile"), "--directory", str(work), "--cores", "1",
                           "-n", "bop_all", "--config", "datasets=synthtiny"], env=env, capture_output=True,
                          text=True, timeout=300)
    line = _one_error_line(proc.stdout + proc.stderr)
    assert proc.returncode == 1 and "x{y}" in line and "brace" in line and "FREEZE_CACHE" in line


# ------------------------------------------------------- rebuilding after a repair


def _damage_one_file(item: Path) -> str:
    """Truncate the largest file that ``item``'s manifest lists; returns its name."""
    files = read_manifest(item)["files"]
    rel = max(sorted(files), key=lambda r: files[r]["size"])
    path = item / rel
    path.write_bytes(path.read_bytes()[: files[rel]["size"] // 2])
    return rel


@pytest.mark.slow
def test_the_run_after_a_repair_rebuilds_what_it_removed_and_gives_the_clean_results(tiny_run, tmp_path):
    """One file of one item of every stage damaged, `freeze verify --repair`, `freeze run`:
    every removed item is back, with the clean run's tables and AR (a score that existed
    kept Snakemake from scheduling what was missing upstream, and a missing refine/all
    failed bop_all with a FileNotFoundError). Plain `snakemake` plans the same rebuild."""
    clean, _ = tiny_run
    work = _copy(tiny_run, tmp_path)
    items = {"synth": "dataset", "render_templates": "obj_000002", "symmetries": "obj_000005",
             "model_features": "obj_000006", "segment_prior": "all", "scene_features": "scene_000001",
             "register": "scene_000001", "refine": "all", "score": "all"}
    damaged = {}
    for stage, item in items.items():
        folder = current_dir(work, stage) / item
        damaged[folder] = _damage_one_file(folder)

    proc = _freeze(work, "verify", "--cache", str(work / "cache"), "--repair", "--no-progress")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert not any(folder.exists() for folder in damaged)

    # plain snakemake schedules every removed item (a dry run: the same Snakefile runs below)
    planned = _snakemake(work, "--cores", "2", "-n", "bop_all", "--config", "datasets=synthtiny")
    assert planned.returncode == 0, (planned.stdout + planned.stderr)[-3000:]
    for folder in damaged:
        assert str(folder / MANIFEST_NAME) in planned.stdout + planned.stderr, folder

    proc = _freeze(work, "run", "-c", "datasets=synthtiny", timeout=1200)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "Traceback" not in out
    assert all((folder / MANIFEST_NAME).is_file() for folder in damaged)
    assert _ar(work) == _ar(clean)
    for stage, name in (("scene_features", "candidate_status.parquet"), ("register", "coarse_hypotheses.parquet"),
                        ("refine", "poses.parquet")):
        a = pd.read_parquet(current_dir(clean, stage) / "scene_000001" / name)
        b = pd.read_parquet(current_dir(work, stage) / "scene_000001" / name)
        pd.testing.assert_frame_equal(a.drop(columns=["time_s"], errors="ignore"),
                                      b.drop(columns=["time_s"], errors="ignore"))
    a, b = (json.loads((current_dir(w, "score") / "all" / "scores.json").read_text())["summary"] for w in (clean, work))
    same = lambda d: {k: v for k, v in d.items() if k.startswith("AR") or isinstance(v, int)}  # noqa: E731
    assert same(a) == same(b) and "AR_VSD" in same(a)
    proc = _freeze(work, "verify", "--cache", str(work / "cache"), "--no-progress")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]


# ------------------------------------------------------ signals, marks, second start


def _start_run(work: Path) -> subprocess.Popen:
    """`freeze run -c datasets=synthtiny` in ``work``, started in a session of its own
    (so that the test can end whatever is left), its output in ``work/run.out``."""
    return subprocess.Popen([str(FREEZE), "run", "-c", "datasets=synthtiny"], cwd=work, env=_env(work),
                            stdout=open(work / "run.out", "w"), stderr=subprocess.STDOUT, start_new_session=True)


def _wait_for_a_job(work: Path, proc: subprocess.Popen, timeout: float = 300) -> None:
    """Until a stage job of the run (`python -m pipeline.commands.cli stage ...`) is running."""
    deadline = time.time() + timeout
    while proc.poll() is None and time.time() < deadline:
        if any("pipeline.commands.cli stage" in cmd for cmd in _processes_in(work)):
            return
        time.sleep(0.05)
    raise AssertionError(f"no job running (exit {proc.poll()}): {(work / 'run.out').read_text()[-2000:]}")


@pytest.mark.slow
def test_sigterm_stops_the_run_and_its_jobs_and_a_second_start_is_refused_meanwhile(tiny_run, tmp_path):
    """While a run works, a second `freeze run` in the folder says so in one line with the
    first's pid (never Snakemake's advice to --unlock). SIGTERM to the first then stops
    Snakemake and its jobs (no orphan starting more jobs), exits 143 within seconds, and
    the next run resumes to the clean AR, leaving no stale mark behind: the run after it
    does not check the cache "after an interrupted run" again."""
    work = _copy(tiny_run, tmp_path, drop=("refine", "score"))
    first = _start_run(work)
    try:
        _wait_for_a_job(work, first)
        second = _freeze(work, "run", "-c", "datasets=synthtiny", timeout=300)
        out = second.stdout + second.stderr
        line = _one_error_line(out)
        assert second.returncode == 1 and f"pid {first.pid}" in line and str(work) in line, out
        assert "unlock" not in out.lower()
        assert first.poll() is None, "the second start disturbed the first"

        _wait_for_a_job(work, first)
        t0 = time.time()
        first.send_signal(signal.SIGTERM)
        code = first.wait(timeout=120)
        elapsed = time.time() - t0
        out = (work / "run.out").read_text()
        assert code == 143, out[-3000:]
        assert elapsed < 60, elapsed
        assert "stopped by SIGTERM" in out and "Traceback" not in out
        time.sleep(1)
        assert snakemake_processes(work) == [] and _processes_in(work) == [], _processes_in(work)
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
            first.wait()

    # The stopped job's mark names its output, as Snakemake wrote it. (A job may just have
    # ended as the signal came, leaving no mark: the test after this one makes its own.)
    marks = incomplete_marks(work / ".snakemake")
    assert all(out is not None and out.name == MANIFEST_NAME and out.is_relative_to(work / "cache")
               for _, out in marks), marks
    resumed = _freeze(work, "run", "-c", "datasets=synthtiny")
    out = resumed.stdout + resumed.stderr
    assert resumed.returncode == 0, out[-3000:]
    assert ("after an interrupted run" in out) == bool(marks)
    assert _ar(work) == _ar(tiny_run[0])
    assert incomplete_marks(work / ".snakemake") == []
    again = _freeze(work, "run", "-c", "datasets=synthtiny", "--dry-run")
    out = again.stdout + again.stderr
    assert again.returncode == 0 and "interrupted run" not in out, out[-3000:]


@pytest.mark.slow
def test_a_mark_left_on_a_published_output_is_judged_once_then_removed(tiny_run, tmp_path):
    """A job killed after it published but before Snakemake saw it finish leaves a mark on
    a whole output, which no rerun clears (the job does not rerun). `freeze run` verifies
    the outputs once, removes the mark, and the next run does not verify them again."""
    work = _copy(tiny_run, tmp_path)
    output = current_dir(work, "refine") / "all" / MANIFEST_NAME
    # Snakemake's file persistence: the output's path, URL-safe base64, as the mark's name
    mark = work / ".snakemake" / "incomplete" / urlsafe_b64encode(str(output).encode()).decode()
    mark.parent.mkdir(parents=True)
    mark.write_text(json.dumps({"external_jobid": None}))
    assert incomplete_marks(work / ".snakemake") == [(mark, output)]

    proc = _freeze(work, "run", "-c", "datasets=synthtiny")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "after an interrupted run" in out and "0 damaged" in out
    assert not mark.exists() and output.is_file()
    again = _freeze(work, "run", "-c", "datasets=synthtiny")
    out = again.stdout + again.stderr
    assert again.returncode == 0 and "interrupted run" not in out, out[-3000:]
    assert _ar(work) == _ar(tiny_run[0])


# ---------------------------------------------------------------- planning errors


@pytest.fixture(scope="module")
def bop_without_prior(tmp_path_factory) -> Path:
    """A bop_root holding 'lmo' (the tiny synthetic dataset) without its default
    detections file, and a dataset manifest whose prior escapes the root."""
    from pipeline.evaluation.synth import generate

    root = tmp_path_factory.mktemp("bop")
    generate(root / "lmo", name="lmo", preset="tiny", seed=0, progress=False)
    shutil.rmtree(root / "lmo" / "detections")
    (root / "escaping.yaml").write_text(
        "name: lmo\nkind: bop\nfolder: lmo\nsplit: test\ntargets_file: test_targets_bop19.json\nvsd_delta: 15.0\n"
        "prior: ../../../../../../../../etc/passwd\nobj_ids: [2, 5, 6]\nimage_size: [640, 480]\n")
    return root


@pytest.mark.slow
@pytest.mark.parametrize("case", ["missing", "escaping"])
def test_a_missing_or_escaping_prior_is_one_line_under_freeze_run_and_snakemake(bop_without_prior, tmp_path, case):
    root = bop_without_prior
    config = [f"bop_root={root}", "datasets=lmo" if case == "missing" else f"datasets={root / 'escaping.yaml'}"]
    expect = "must match exactly one file" if case == "missing" else "outside bop_root"
    proc = _freeze(tmp_path, "run", *[a for c in config for a in ("-c", c)], "--dry-run", timeout=300)
    assert proc.returncode == 1 and expect in _one_error_line(proc.stdout + proc.stderr)
    proc = _snakemake(tmp_path, "--cores", "1", "-n", "bop_all", "--config", *config)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and expect in _one_error_line(out) and 'File "' not in out


# ---------------------------------------------------------------------- dask


def _slow_item(shared: float, item: int) -> int:
    time.sleep(shared)
    return item


def _failing_item(shared: None, item: int) -> int:
    raise ValueError(f"item {item} is bad")


@pytest.mark.slow
def test_a_dask_scheduler_lost_mid_job_is_one_line_naming_it_and_the_resume_command(capfd):
    from distributed import LocalCluster

    from pipeline.common.parallel import SchedulerLost, work_mapper

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    address = cluster.scheduler_address
    with work_mapper(address) as mapper:  # a task's own error still arrives as itself
        with pytest.raises(ValueError, match="item 0 is bad"):
            mapper.map(_failing_item, [0, 1], None)
    closer = threading.Timer(1.0, cluster.close)
    try:
        with pytest.raises(SchedulerLost) as lost:
            with work_mapper(address) as mapper:
                closer.start()
                mapper.map(_slow_item, list(range(40)), 0.2)
    finally:
        closer.join()
        cluster.close()
    message = str(lost.value)
    assert "\n" not in message and address in message and "freeze run" in message and "dask_scheduler" in message
    assert "Traceback" not in capfd.readouterr().err


# ------------------------------------------------------------------ -c values


@pytest.mark.parametrize("value", ["register.seed=[1,", "register.seed=!!python/object/apply:os.system ['touch PWNED']",
                                   "register.seed=inf", "images_per_job=.inf", "images_per_job=[1,",
                                   "images_per_job=!!python/object/apply:os.system ['touch PWNED']"])
def test_bad_config_values_are_one_line_under_freeze_run(tmp_path, value):
    proc = _freeze(tmp_path, "run", "-c", "datasets=synthtiny", "-c", value, "--dry-run", timeout=300)
    line = _one_error_line(proc.stdout + proc.stderr)
    assert proc.returncode == 1 and value.split("=")[0] in line
    assert not (tmp_path / "PWNED").exists()


@pytest.mark.parametrize("value", ["images_per_job=inf", "images_per_job=.inf", "images_per_job=[1,",
                                   "images_per_job=!!python/object/apply:os.system ['touch PWNED']"])
def test_bad_config_values_are_one_line_under_snakemake(tmp_path, value):
    """Snakemake's own --config parser takes flat keys only (a dotted key is its
    ValueError, before the Snakefile runs); the values of flat keys reach the Snakefile,
    which says what is wrong in one line."""
    proc = _snakemake(tmp_path, "--cores", "1", "-n", "bop_all", "--config", "datasets=synthtiny", value)
    line = _one_error_line(proc.stdout + proc.stderr)
    assert proc.returncode == 1 and "images_per_job" in line
    assert not (tmp_path / "PWNED").exists()


# ------------------------------------------------------------ cluster-generic


def test_a_generic_profile_whose_status_script_path_needs_quoting_is_quoted_or_refused(tmp_path):
    """The cluster-generic executor runs its status command unquoted in a shell: from a
    clone under ``a b;x``, `freeze run` would pass it quoted, and a plain `snakemake
    --profile` stops before any job with one line (here with an `sbatch` that fails, so
    that nothing could be submitted anyway)."""
    from pipeline.workflow.cluster_submit import needs_quoting, profile_status_command, unquoted_status_command

    clone = tmp_path / "a b;touch pwned"
    shutil.copytree(ROOT / "profiles" / "slurm-generic", clone / "profiles" / "slurm-generic")
    (clone / "scripts" / "slurm").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "slurm" / "status.py", clone / "scripts" / "slurm" / "status.py")
    status = profile_status_command(clone / "profiles" / "slurm-generic")
    assert status is not None and Path(status).resolve() == (clone / "scripts" / "slurm" / "status.py").resolve()
    assert needs_quoting(status) and not needs_quoting(str(ROOT / "scripts" / "slurm" / "status.py").replace(
        str(ROOT), "/srv/freeze"))
    assert unquoted_status_command("cluster-generic", status) and unquoted_status_command("slurm", status) is None

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text("#!/bin/sh\nexit 1\n")
    (bin_dir / "sbatch").chmod(0o755)
    work = tmp_path / "work"
    env = {**_env(work), "PATH": f"{bin_dir}:{os.environ['PATH']}"}
    proc = subprocess.run([str(SNAKEMAKE), "-s", str(ROOT / "Snakefile"), "--directory", str(work), "--profile",
                           str(clone / "profiles" / "slurm-generic"), "bop_all", "--config", "datasets=synthtiny"],
                          env=env, capture_output=True, text=True, timeout=300)
    line = _one_error_line(proc.stderr)
    assert proc.returncode == 1 and "status command" in line and "freeze run --profile" in line
    assert not any(p.name == "pwned" for p in tmp_path.rglob("*")) and not (work / "cache").exists()

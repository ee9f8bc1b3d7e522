"""Shared fixtures: one `snakemake bop_all` run on the tiny synthetic dataset per test
session, used by the pipeline, report and other end-to-end tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SNAKEMAKE = Path(sys.executable).parent / "snakemake"


def run_snakemake(workdir: Path, *args: str, dry: bool = False, datasets: str | None = "synthtiny",
                  targets: tuple[str, ...] = ("bop_all",)) -> str:
    """`snakemake bop_all --config datasets=synthtiny ARGS` in ``workdir`` (its cache in
    ``workdir/cache``); returns the output, failing the test on a non-zero exit.
    ``datasets=None`` runs the run manifest's own datasets (the main job's synthmini);
    ``targets``: other Snakemake targets (e.g. manifests of one stage) than bop_all."""
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env.update(FREEZE_CACHE=str(workdir / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1")
    cmd = [str(SNAKEMAKE), "-s", str(ROOT / "Snakefile"), "--directory", str(workdir), "--cores", "2", *targets]
    if dry:
        cmd.append("-n")
    config = ([f"datasets={datasets}"] if datasets else []) + list(args)
    proc = subprocess.run(cmd + (["--config", *config] if config else []), env=env,
                          capture_output=True, text=True, timeout=1800)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    return out


#: Session fixtures that run the pipeline: the tests using one run on the same worker.
SHARED_RUNS = ("main_run", "tiny_run")


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (`scripts/test.sh` runs `-n 2 --dist loadgroup`), a worker
    takes whole groups: the tests sharing one of the :data:`SHARED_RUNS` form one group
    (so each run happens once), and every other test goes with its module (so a
    module's fixtures are built once)."""
    for item in items:
        names = set(getattr(item, "fixturenames", ()))
        group = next((run for run in SHARED_RUNS if run in names), item.module.__name__)
        item.add_marker(pytest.mark.xdist_group(group))


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> tuple[Path, str]:
    """(work dir, output) of the main job on `synthtiny` with the default run manifest."""
    work = tmp_path_factory.mktemp("pipeline")
    return work, run_snakemake(work)


@pytest.fixture(scope="session")
def main_run(tmp_path_factory) -> tuple[Path, str]:
    """(work dir, output) of the README's main job, `snakemake --cores 2 bop_all` (synthmini)."""
    work = tmp_path_factory.mktemp("main_job")
    return work, run_snakemake(work, datasets=None)


def current_dir(work: Path, stage: str, **overrides: str) -> Path:
    """The artifact folder of ``stage`` in the synthtiny plan of the default run (with
    ``overrides``) under ``work/cache``: other configurations' folders may sit beside it."""
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan

    return RunPlan(load_run({"datasets": "synthtiny", **overrides}), cache=work / "cache")["synthtiny"][stage].dir


@pytest.fixture
def umask_022():
    """The process umask set to 022 (and read again) for the test, restored after."""
    import os

    from pipeline.common import published_files as files

    old = os.umask(0o022)
    files.forget_umask()
    try:
        yield
    finally:
        os.umask(old)
        files.forget_umask()

"""The CPU threads a stage job may use: Snakemake gives each rule's jobs ``threads``
(declared in each stage's ``StageSpec``), and the job keeps its numeric libraries within them, so
that jobs running side by side do not oversubscribe the cores."""

from __future__ import annotations

import os
import sys

ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""Read by OpenMP (torch's intra-op pool), OpenBLAS and MKL when they load."""
JOB_THREADS = "FREEZE_THREADS"


def use_threads(n: int) -> None:
    """Keep this process (and its children) to ``n`` threads: the environment for the
    libraries not loaded yet, torch and OpenCV directly when they are."""
    if n < 1:
        raise ValueError(f"threads must be at least 1, got {n}")
    for var in (*ENV_VARS, JOB_THREADS):
        os.environ[var] = str(n)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(n)


def job_threads() -> int | None:
    """The threads this job was given (:func:`use_threads`), or None outside a job."""
    value = os.environ.get(JOB_THREADS)
    return int(value) if value and value.isdigit() else None

"""Whether a Snakemake executor can submit jobs from this machine.

A SLURM profile used where SLURM's client commands are missing (a laptop, a compute
node image without them) would otherwise fail job after job with a shell error deep
in Snakemake's log. :func:`missing_submitter` is asked once, before any job: by
``freeze run --profile DIR`` and by the Snakefile's ``onstart`` (a plain
``snakemake --profile profiles/slurm``).
"""

from __future__ import annotations

import shlex
import shutil
from pathlib import Path

import yaml

#: Executors whose jobs go through SLURM's ``sbatch`` (``cluster-generic`` only when its
#: submit command calls ``sbatch``, as ``profiles/slurm-generic`` does).
SLURM_EXECUTORS = ("slurm", "cluster-generic")


def submits_with(executor: str | None, submit_cmd: str | None = None) -> str | None:
    """The command the executor submits jobs with, when it is one we check (``sbatch``)."""
    if executor == "slurm":
        return "sbatch"
    if executor == "cluster-generic" and submit_cmd and "sbatch" in shlex.split(submit_cmd.replace("&&", " ")):
        return "sbatch"
    return None


def missing_submitter(executor: str | None, submit_cmd: str | None = None, where: str = "") -> str | None:
    """One line saying why jobs cannot be submitted from here, or None when they can.

    where: how the user chose the executor (e.g. ``profile profiles/slurm``), named in
    the message."""
    command = submits_with(executor, submit_cmd)
    if command is None or shutil.which(command):
        return None
    chosen = f" ({where})" if where else ""
    return (f"the {executor} executor{chosen} submits jobs with `{command}`, which is not on this machine's PATH: "
            "run on a login node of your SLURM cluster (where `sbatch`, `squeue` and `scontrol` work), or leave "
            "out the profile to run here (see docs/cluster.md)")


def profile_executor(profile: Path) -> tuple[str | None, str | None]:
    """(executor, cluster-generic submit command) of a Snakemake profile folder.

    Raises ValueError naming the file when the folder holds no readable config.yaml."""
    cfg_file = profile / "config.yaml"
    if not cfg_file.is_file():
        raise ValueError(f"--profile {profile}: no config.yaml in that folder (a Snakemake profile is a folder "
                         "holding config.yaml, e.g. profiles/slurm)")
    try:
        cfg = yaml.safe_load(cfg_file.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{cfg_file}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(cfg, dict):
        raise ValueError(f"{cfg_file}: expected a mapping of Snakemake options, got {type(cfg).__name__}")
    executor = cfg.get("executor")
    submit = cfg.get("cluster-generic-submit-cmd")
    return (str(executor) if executor else None), (str(submit) if submit else None)


def profile_status_command(profile: Path) -> str | None:
    """The cluster-generic status command of a profile as Snakemake reads it: a value
    naming a file relative to the profile's folder becomes that file's path."""
    cfg = yaml.safe_load((profile / "config.yaml").read_text()) or {}
    value = cfg.get("cluster-generic-status-cmd") if isinstance(cfg, dict) else None
    if not value:
        return None
    value = str(value)
    return str(profile / value) if (profile / value).exists() else value


def needs_quoting(command: str | None) -> bool:
    """Whether ``command`` is the path of a file that the shell would split or read as
    commands: the cluster-generic executor runs its status command as
    ``{statuscmd} '{jobid}'`` in a shell, unquoted, so a clone under ``/home/me/my work``
    fails every status query, and a ``;`` in the path runs what follows it."""
    return bool(command) and shlex.quote(command) != command and Path(command).is_file()


def unquoted_status_command(executor: str | None, status_cmd: str | None) -> str | None:
    """One line saying why the cluster-generic status command cannot be run as given (see
    :func:`needs_quoting`), or None. ``freeze run --profile`` passes the quoted path
    instead; a plain ``snakemake --profile`` stops with this line (the Snakefile's
    ``onstart``)."""
    if executor != "cluster-generic" or not needs_quoting(status_cmd):
        return None
    return (f"the cluster-generic status command {status_cmd} is a path holding characters that the shell splits "
            "or runs (the executor calls it unquoted): run `freeze run --profile DIR`, which quotes it, or give "
            "snakemake --cluster-generic-status-cmd with the path inside quotes")

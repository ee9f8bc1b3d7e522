"""``freeze run``: Snakemake's ``bop_all`` with the checks and the crash recovery that a
plain ``snakemake`` call lacks.

Before Snakemake starts:

- the options are checked (an unknown ``--config`` key, a bad manifest: one line, exit 1)
  and a run with no dataset it can run stops with exit 1;
- a lock left by a killed run is removed (``snakemake --unlock``), but only when no
  Snakemake process is running in the same working folder;
- what is complete is said by our own manifests, not by Snakemake's metadata: every
  output is a ``_manifest.json`` written atomically after its item, so one that exists
  and whose files match it (:func:`pipeline.store.verify_item`) was published whole.
  After an interrupted run (Snakemake's marks of unfinished jobs are present) every
  existing output of the plan is verified and a damaged one deleted.

Then Snakemake runs with ``--ignore-incomplete`` (its marks can only be stale: missing
outputs rerun), and its exit code is ours.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Iterable, Optional

import typer
from rich.console import Console

from pipeline.cli_common import USER_ERRORS, parse_overrides

PROJECT_ROOT = Path(__file__).resolve().parent.parent
SNAKEFILE = PROJECT_ROOT / "Snakefile"


def _console() -> Console:
    return Console(stderr=True, highlight=False, soft_wrap=True)


def snakemake_processes(workdir: Path, exclude: Iterable[int] = ()) -> list[int]:
    """PIDs of the Snakemake processes (Linux ``/proc``) working in ``workdir``: their
    current folder, or the ``--directory`` they were given, is ``workdir``."""
    workdir = workdir.resolve()
    skip = {os.getpid(), *exclude}
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) in skip:
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            cwd = Path(os.readlink(entry / "cwd"))
        except OSError:  # exited meanwhile, or not ours to read
            continue
        words = [a.decode(errors="replace") for a in argv if a]
        if not any(Path(w).name == "snakemake" or w.endswith("/snakemake") for w in words[:3]):
            continue
        dirs = [cwd]
        for i, w in enumerate(words[:-1]):
            if w in ("--directory", "-d"):
                dirs.append((cwd / words[i + 1]).resolve())
        if workdir in dirs:
            found.append(int(entry.name))
    return sorted(found)


def _snakemake(workdir: Path, *args: str, env: dict[str, str] | None = None,
               capture: bool = False) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "snakemake"
    cmd = [str(exe), "-s", str(SNAKEFILE), "--directory", str(workdir), *args]
    return subprocess.run(cmd, env=env, capture_output=capture, text=True)


def planned_manifests(run_plan, datasets: list[str]) -> list[Path]:
    """The output manifest of every job of ``bop_all`` for ``datasets``."""
    from pipeline.stage_graph import STAGES

    out = []
    for ds in datasets:
        plan = run_plan[ds]
        for stage, spec in STAGES.items():
            if stage not in plan.stages:
                continue
            for kind in spec.items:
                items = {"obj": [f"obj_{o:06d}" for o in plan.obj_ids],
                         "scene": plan.scene_items}.get(kind, [kind])
                out += [plan[stage].manifest(item) for item in items]
    return out


def recover(workdir: Path, run_plan, datasets: list[str], config_args: list[str]) -> list[str]:
    """Undo what a killed run left (see the module docstring); returns what was done,
    one line each. Raises RuntimeError when another Snakemake runs in ``workdir``."""
    import shutil

    from pipeline.store import verify_item

    done: list[str] = []
    meta = workdir / ".snakemake"
    locks = meta / "locks"
    if locks.is_dir() and any(locks.iterdir()):
        live = snakemake_processes(workdir)
        if live:
            raise RuntimeError(f"another Snakemake run (pid {', '.join(map(str, live))}) is working in {workdir}; "
                               "wait for it to finish, or stop it first")
        proc = _snakemake(workdir, "--unlock", "--config", *config_args, capture=True)
        if proc.returncode != 0:
            raise RuntimeError(f"snakemake --unlock failed in {workdir}: {(proc.stderr or proc.stdout).strip()[-500:]}")
        done.append(f"removed the lock that a killed run left in {meta}")
    incomplete = meta / "incomplete"
    if incomplete.is_dir() and any(incomplete.iterdir()):
        whole = damaged = 0
        for manifest in planned_manifests(run_plan, datasets):
            if not manifest.exists():
                continue
            if verify_item(manifest.parent):
                shutil.rmtree(manifest.parent)
                done.append(f"deleted the damaged artifact {manifest.parent} (it will be rebuilt)")
                damaged += 1
            else:
                whole += 1
        done.append(f"checked the {whole + damaged} published artifacts against their manifests after an interrupted "
                    f"run: {whole} whole, {damaged} damaged")
    return done


def add_commands(app: typer.Typer, show_app: typer.Typer) -> None:
    """Add ``run`` to ``app``."""

    @app.command("run", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
    def run_cmd(
        ctx: typer.Context,
        target: str = typer.Argument("bop_all", help="Snakemake target (default: every stage of every dataset)"),
        cores: int = typer.Option(2, "--cores", "-j", help="cores Snakemake may use"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value, as "
                                                   "Snakemake's --config (datasets=, visual=, run=, bop_root=, ...)"),
        directory: Path = typer.Option(Path("."), "--directory", help="working folder (logs, results, .snakemake)"),
        profile: Optional[Path] = typer.Option(None, "--profile", help="Snakemake profile folder, e.g. profiles/slurm "
                                               "to submit the jobs to SLURM (docs/cluster.md)"),
    ) -> None:
        """Run the pipeline (`snakemake --cores N bop_all`), resuming cleanly after a crash or a kill: it removes a
        stale lock when no other Snakemake works in the folder, keeps every artifact that was published whole
        (checked against its manifest) and rebuilds the rest. Options after the known ones go to Snakemake
        (e.g. --dry-run)."""
        from pipeline.config import load_run
        from pipeline.plan import RunPlan

        out = _console()
        overrides = parse_overrides(config)
        dotted = [k for k in overrides if "." in k]
        if dotted:
            out.print(f"[red]error: --config {dotted[0]}=...: stage parameters go in a run manifest (run=FILE with "
                      "'extends: manifests/runs/default.yaml' and the stage's key), as Snakemake takes flat keys only")
            raise typer.Exit(1)
        workdir = directory.resolve()
        profile_args: list[str] = []
        if profile is not None:
            # Checked before anything else runs: a SLURM profile where `sbatch` is
            # missing would otherwise fail job by job (pipeline/cluster_submit.py).
            from pipeline.cluster_submit import missing_submitter, profile_executor
            try:
                executor, submit = profile_executor(profile)
            except ValueError as e:
                out.print(f"[red]error: {e}")
                raise typer.Exit(1) from None
            why = missing_submitter(executor, submit, where=f"profile {profile}")
            if why:
                out.print(f"[red]error: {why}")
                raise typer.Exit(1)
            profile_args = ["--profile", str(profile.resolve())]
        try:
            rp = RunPlan(load_run(overrides))
            datasets = []
            for ds in rp.dataset_names:
                ok, why = rp.available(ds)
                if ok:
                    datasets.append(ds)
                else:
                    out.print(f"[yellow]{why}")
        except USER_ERRORS as e:
            out.print(f"[red]error: {e}")
            raise typer.Exit(1) from None
        if not datasets:
            out.print("[red]error: no dataset of the run can be run (see above); nothing to do")
            raise typer.Exit(1)
        args = [f"{k}={v}" for k, v in overrides.items()]
        from pipeline.stand_in import stand_in_notice

        notice = stand_in_notice(rp.run.geometric_encoder, rp.run.visual_encoder, form="freeze")
        if notice:
            out.print(notice, markup=False)
        try:
            for line in recover(workdir, rp, datasets, args):
                out.print(line)
        except RuntimeError as e:
            out.print(f"[red]error: {e}")
            raise typer.Exit(1) from None
        # Every output is a manifest published atomically after its item, and every
        # existing one was just verified when the killed run left marks: Snakemake's
        # marks of unfinished jobs can only be stale, and the missing outputs rerun.
        # the Snakefile's onstart would print the stand-in notice again, with Snakemake's options
        env = {**os.environ, "FREEZE_STAND_IN_SHOWN": "1"}
        proc = _snakemake(workdir, "--cores", str(cores), *profile_args, target, "--ignore-incomplete",
                          *(["--config", *args] if args else []), *ctx.args, env=env)
        raise typer.Exit(proc.returncode)

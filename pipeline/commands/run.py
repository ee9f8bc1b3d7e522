"""``freeze run``: Snakemake's ``bop_all`` with the checks and the crash recovery that a
plain ``snakemake`` call lacks.

Before Snakemake starts:

- the options are checked (an unknown ``--config`` key, a bad manifest: one line, exit 1)
  and a run with no dataset it can run stops with exit 1;
- a lock left by a killed run is removed (``snakemake --unlock``), but only when no
  Snakemake process is running in the same working folder;
- what is complete is said by our own manifests, not by Snakemake's metadata: every
  output is a ``_manifest.json`` written atomically after its item, so one that exists
  and whose files match it (:func:`pipeline.common.store.verify_item`) was published whole.
  After an interrupted run (Snakemake's marks of unfinished jobs are present) every
  existing output of the plan is verified and a damaged one deleted.

  The marks are then removed, so that the next run does not verify everything again:
  each one names an output (:func:`incomplete_marks`), which was just verified (or is
  missing and reruns).

Then Snakemake runs with ``--ignore-incomplete`` (its marks can only be stale: missing
outputs rerun), and its exit code is ours.

While it runs:

- one ``freeze run`` works in a folder at a time (an exclusive ``flock`` on
  ``.snakemake/freeze_run.lock``, held from the checks to Snakemake's end), and none
  starts while another Snakemake process works there: a second start says so in one
  line, with the other's pid, instead of Snakemake's advice to ``--unlock`` a live run;
- Snakemake runs in a process group of its own, and a SIGINT, SIGTERM or SIGHUP that
  reaches ``freeze run`` goes to that whole group (Snakemake and its jobs, as Ctrl-C in
  a terminal does); ``freeze run`` waits for Snakemake to end and exits 128 + the
  signal's number. Nothing is left running, and the next ``freeze run`` resumes.
  Should ``freeze run`` itself be killed (``kill -9``), Snakemake gets a SIGTERM from
  the kernel (``PR_SET_PDEATHSIG``): it starts no further job and ends with its
  running ones.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, Optional

import typer
from rich.console import Console

from pipeline.commands.common import USER_ERRORS, parse_overrides
from pipeline.common.config import PROJECT_ROOT

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


def _snakemake_cmd(workdir: Path, *args: str) -> list[str]:
    exe = Path(sys.executable).parent / "snakemake"
    return [str(exe), "-s", str(SNAKEFILE), "--directory", str(workdir), *args]


def _snakemake(workdir: Path, *args: str, env: dict[str, str] | None = None,
               capture: bool = False) -> subprocess.CompletedProcess:
    return subprocess.run(_snakemake_cmd(workdir, *args), env=env, capture_output=capture, text=True)


#: Signals that ``freeze run`` passes on to Snakemake's process group (see the module docstring).
FORWARDED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _term_with_parent(parent: int) -> None:
    """In the child before it starts: SIGTERM it when its parent dies (Linux
    ``PR_SET_PDEATHSIG``). In a process group of its own, Snakemake would otherwise go on
    starting jobs after a ``kill -9`` of ``freeze run``; on SIGTERM it starts none and
    ends once its running jobs have."""
    import ctypes

    pr_set_pdeathsig = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the signals are still passed on
        return
    if os.getppid() != parent:  # the parent died before the setting took
        os.kill(os.getpid(), signal.SIGTERM)


def run_forwarding_signals(cmd: list[str], env: dict[str, str] | None = None) -> tuple[int, int | None]:
    """Run ``cmd`` in a process group of its own until it ends; a signal of
    :data:`FORWARDED_SIGNALS` received meanwhile is sent to that whole group (the child
    and whatever it started, which a terminal's Ctrl-C reaches the same way).

    Returns (exit status, the first signal received or None). The status is 128 + that
    signal when one was received (a stopped run never exits 0, whatever the child made
    of the signal); else the child's code, or 128 + the signal that killed it."""
    received: list[int] = []
    child: list[subprocess.Popen] = []

    def forward(signum: int, _frame) -> None:
        received.append(signum)
        if child:
            try:
                os.killpg(child[0].pid, signum)
            except ProcessLookupError:  # the group has ended meanwhile
                pass

    # The handlers go in before the child starts, so that a signal in between is
    # recorded and then passed on, not lost (and never kills us with the child alive).
    previous = {sig: signal.signal(sig, forward) for sig in FORWARDED_SIGNALS}
    try:
        child.append(subprocess.Popen(cmd, env=env, process_group=0,
                                      preexec_fn=functools.partial(_term_with_parent, os.getpid())))
        if received:
            os.killpg(child[0].pid, received[0])
        code = child[0].wait()  # retried after each handler (PEP 475)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if received:
        return 128 + received[0], received[0]
    return (128 - code if code < 0 else code), None


@contextmanager
def exclusive_run(workdir: Path) -> Iterator[None]:
    """Hold the folder's ``freeze run`` lock (``.snakemake/freeze_run.lock``, an exclusive
    ``flock`` that the kernel drops when this process ends, however it ends) for the
    block; raises RuntimeError naming the holder's pid when another process holds it."""
    import fcntl

    meta = workdir / ".snakemake"
    path = meta / "freeze_run.lock"
    try:
        meta.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise RuntimeError(f"cannot write {path} ({e.strerror}): freeze run needs a writable working folder "
                           "(--directory)") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise RuntimeError(f"another freeze run (pid {holder}) is working in {workdir}: wait for it to finish, "
                               f"or stop it (kill {holder}) and run again") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)


def incomplete_marks(meta: Path) -> list[tuple[Path, Path | None]]:
    """Snakemake's marks of unfinished jobs in ``meta`` (a ``.snakemake`` folder, file
    persistence): (the mark's file, the output it names, or None when its name cannot be
    read). A mark's path is the URL-safe base64 of the output's path, cut into folders
    whose names but the last start with ``@`` (Snakemake's ``FilePersistence``)."""
    from base64 import urlsafe_b64decode

    root = meta / "incomplete"
    if not root.is_dir():
        return []
    out: list[tuple[Path, Path | None]] = []
    for mark in sorted(root.rglob("*")):
        rel = mark.relative_to(root)
        if not mark.is_file() or rel.as_posix() == "migration_underway":
            continue
        parts = rel.parts
        try:
            name = urlsafe_b64decode("".join(p.removeprefix("@") for p in parts[:-1]) + parts[-1]).decode()
        except (ValueError, UnicodeDecodeError):
            out.append((mark, None))
            continue
        out.append((mark, meta.parent / name))  # a relative output is relative to the working folder
    return out


def failed_job_lines(logs: Path, since: float, limit: int = 5) -> list[str]:
    """The one-line errors that jobs wrote to their logs under ``logs`` (modified at or
    after ``since``, a time.time()): a stage's ``stage X failed on DS/ITEM: ...`` and a
    command's ``error: ...``, each followed by its log's path, at most ``limit``. Snakemake
    says only "check the log file(s)"; the cause belongs in front of the user."""
    found: list[str] = []
    if not logs.is_dir():
        return found
    recent = []
    for log in logs.rglob("*.log"):
        try:
            if log.is_file() and log.stat().st_mtime >= since:
                recent.append(log)
        except OSError:
            continue
    for log in sorted(recent):
        try:
            text = log.read_text(encoding="utf-8", errors="replace")
        except OSError:
            continue
        lines = [ln.strip() for ln in text.splitlines()
                 if (ln.startswith("stage ") and " failed on " in ln) or ln.startswith("error:")]
        if lines:
            found.append(f"{lines[-1]}  (log: {log})")
        if len(found) >= limit:
            break
    return found


def planned_manifests(run_plan, datasets: list[str]) -> list[Path]:
    """The output manifest of every job of ``bop_all`` for ``datasets``."""
    from pipeline.workflow.stage_graph import STAGES

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

    from pipeline.common.store import MANIFEST_NAME, verify_item

    done: list[str] = []
    meta = workdir / ".snakemake"
    locks = meta / "locks"
    live = snakemake_processes(workdir)
    if live:  # whether or not it has taken its lock yet: its marks and lock are live
        raise RuntimeError(f"another Snakemake run (pid {', '.join(map(str, live))}) is working in {workdir}; "
                           "wait for it to finish, or stop it first")
    if locks.is_dir() and any(locks.iterdir()):
        proc = _snakemake(workdir, "--unlock", *(["--config", *config_args] if config_args else []), capture=True)
        if proc.returncode != 0:
            raise RuntimeError(f"snakemake --unlock failed in {workdir}: {(proc.stderr or proc.stdout).strip()[-500:]}")
        done.append(f"removed the lock that a killed run left in {meta}")
    marks = incomplete_marks(meta)
    if marks:
        whole = damaged = 0
        # The plan's outputs, and those of other plans that a mark names (a killed run
        # of another configuration in this folder).
        outputs = list(dict.fromkeys([*planned_manifests(run_plan, datasets),
                                      *(out for _, out in marks if out is not None and out.name == MANIFEST_NAME)]))
        for manifest in outputs:
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
        # Every output a mark names is now whole or missing (and reruns): the marks are
        # stale, and left in place they would bring this check back on every run.
        for mark, _ in marks:
            mark.unlink(missing_ok=True)
        for folder in sorted((p for p in (meta / "incomplete").rglob("*") if p.is_dir()), reverse=True):
            if not any(folder.iterdir()):
                folder.rmdir()
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
        from pipeline.common.config import load_run
        from pipeline.workflow.plan import RunPlan

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
            # missing would otherwise fail job by job (pipeline/workflow/cluster_submit.py).
            from pipeline.workflow.cluster_submit import missing_submitter, profile_executor
            try:
                executor, submit = profile_executor(profile)
            except ValueError as e:
                out.print(f"error: {e}", style="red", markup=False)
                raise typer.Exit(1) from None
            why = missing_submitter(executor, submit, where=f"profile {profile}")
            if why:
                out.print(f"[red]error: {why}")
                raise typer.Exit(1)
            profile_args = ["--profile", str(profile.resolve())]
            # The cluster-generic executor runs its status command unquoted in a shell: a
            # clone's path with a space or a `;` would break or inject (cluster_submit.py).
            from pipeline.workflow.cluster_submit import needs_quoting, profile_status_command

            status = profile_status_command(profile.resolve()) if executor == "cluster-generic" else None
            if needs_quoting(status):
                import shlex

                profile_args += ["--cluster-generic-status-cmd", shlex.quote(status)]
        try:
            rp = RunPlan(load_run(overrides))
            datasets = []
            for ds in rp.dataset_names:
                ok, why = rp.available(ds)
                if ok:
                    rp[ds]  # planned here: a missing or escaping prior is found while planning
                    datasets.append(ds)
                else:
                    out.print(f"[yellow]{why}")
        except USER_ERRORS as e:
            out.print(f"error: {e}", style="red", markup=False)
            raise typer.Exit(1) from None
        if not datasets:
            out.print("[red]error: no dataset of the run can be run (see above); nothing to do")
            raise typer.Exit(1)
        args = [f"{k}={v}" for k, v in overrides.items()]
        from pipeline.common.stand_in import stand_in_notice

        notice = stand_in_notice(rp.run.geometric_encoder, rp.run.visual_encoder, form="freeze")
        if notice:
            out.print(notice, markup=False)
        import time

        started = time.time() - 1.0  # log times have a second's resolution on some file systems
        try:
            with exclusive_run(workdir):
                for line in recover(workdir, rp, datasets, args):
                    out.print(line)
                # Every output is a manifest published atomically after its item, and every
                # existing one was just verified when the killed run left marks: Snakemake's
                # marks of unfinished jobs can only be stale, and the missing outputs rerun.
                # the Snakefile's onstart would print the stand-in notice again, with Snakemake's options
                env = {**os.environ, "FREEZE_STAND_IN_SHOWN": "1"}
                code, stopped_by = run_forwarding_signals(
                    _snakemake_cmd(workdir, "--cores", str(cores), *profile_args, target, "--ignore-incomplete",
                                   *(["--config", *args] if args else []), *ctx.args), env=env)
        except RuntimeError as e:
            out.print(f"error: {e}", style="red", markup=False)
            raise typer.Exit(1) from None
        if stopped_by is not None:
            out.print(f"[yellow]stopped by {signal.Signals(stopped_by).name}: Snakemake and its jobs were stopped; "
                      "run the same command again to resume")
        elif code != 0:
            logs = Path(rp.cache).parent / "logs"  # the Snakefile's LOGS
            for line in failed_job_lines(logs, started):
                out.print(line, style="red", markup=False)
        raise typer.Exit(code)

#!/usr/bin/env python3
"""Job status for Snakemake's cluster-generic executor on SLURM.

Snakemake calls ``status.py JOBID`` (``cluster-generic-status-cmd`` in
``profiles/slurm-generic/config.yaml``) with what ``sbatch --parsable`` printed
(``12345`` or ``12345;cluster``) and expects exactly one line on stdout:
``success``, ``running`` or ``failed``; any other output or a non-zero exit stops the
whole run, so this script always exits 0 and prints one of the three.

Where the state comes from, in order:

1. ``scontrol show job -o JOBID`` (the controller; it knows a job until MinJobAge
   seconds after it ended, 300 by default);
2. ``squeue -h -j JOBID --states=all -o %T`` (the same source, another client: used
   when scontrol's output carries no JobState);
3. ``sacct -X -n -P -j JOBID -o State`` (accounting, if the cluster has it), for a
   job the controller has forgotten.

A controller that does not answer (timeout, connection refused) gives ``running``:
Snakemake asks again later. A job that no source knows any more gives ``failed`` with
the reason on stderr (Snakemake then reruns it, or the user reruns the workflow,
which rebuilds only missing outputs).

Stdlib only, so that it runs with any python3 on the login node.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time

SUCCESS, RUNNING, FAILED = "success", "running", "failed"

# SLURM job states (squeue(1) "JOB STATE CODES", scontrol's JobState, sacct's State).
RUNNING_STATES = frozenset({
    "PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "SUSPENDED", "REQUEUED",
    "REQUEUE_FED", "REQUEUE_HOLD", "RESIZING", "SIGNALING", "STAGE_OUT", "STOPPED",
    "RESV_DEL_HOLD", "POWER_UP_NODE", "UPDATE_DB",
})
SUCCESS_STATES = frozenset({"COMPLETED"})
FAILED_STATES = frozenset({
    "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "BOOT_FAIL",
    "DEADLINE", "PREEMPTED", "REVOKED", "SPECIAL_EXIT",
})

TIMEOUT_S = 20          # per SLURM command
ATTEMPTS = 3            # per command, on a controller that does not answer
PAUSE_S = 2.0           # between attempts

_UNREACHABLE = re.compile(
    r"timed out|timeout|Unable to contact slurm controller|Connection refused|"
    r"Socket timed out|Zero Bytes were transmitted|Communication connection failure",
    re.IGNORECASE)
_UNKNOWN_JOB = re.compile(r"Invalid job id specified|Invalid job id|Unknown job", re.IGNORECASE)


def state_to_status(state: str) -> str | None:
    """``success``/``running``/``failed`` for one SLURM state word, None if empty.

    Accepts what the three commands print: ``COMPLETED``, ``CANCELLED by 0``,
    ``CANCELLED+``, ``OUT_OF_ME+`` (sacct truncates to its column width without -P),
    ``RUNNING`` ... A state this script does not know is a failure (said on stderr by
    the caller) rather than a job waited on forever.
    """
    word = state.strip().split()[0] if state.strip() else ""
    word = word.rstrip("+").upper()
    if not word:
        return None
    if word in SUCCESS_STATES:
        return SUCCESS
    if word in RUNNING_STATES:
        return RUNNING
    if word in FAILED_STATES:
        return FAILED
    # sacct without -P truncates long names (OUT_OF_ME+, NODE_FAIL fits): match prefixes.
    for states, status in ((FAILED_STATES, FAILED), (RUNNING_STATES, RUNNING)):
        if len(word) >= 6 and any(s.startswith(word) for s in states):
            return status
    return FAILED


def parse_scontrol(text: str) -> str | None:
    """The JobState of ``scontrol show job [-o]`` output (one job), or None."""
    m = re.search(r"\bJobState=(\S+)", text)
    return m.group(1) if m else None


def parse_squeue(text: str) -> str | None:
    """The state of ``squeue -h -o %T`` output (one job), or None."""
    for line in text.splitlines():
        if line.strip():
            return line.strip()
    return None


def parse_sacct(text: str) -> str | None:
    """The main job's state from ``sacct -X -n -P -o State`` output, or None. With -X
    there is one line per job allocation; a requeued job has one per attempt: the
    last one is the current."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1].split("|")[0] if lines else None


def split_jobid(raw: str) -> tuple[str, str | None]:
    """``12345`` or ``12345;cluster`` (what ``sbatch --parsable`` prints)."""
    raw = raw.strip().strip("'\"")
    jobid, _, cluster = raw.partition(";")
    return jobid.strip(), (cluster.strip() or None)


class Unreachable(Exception):
    """The controller (or accounting) did not answer."""


def _run(cmd: list[str]) -> tuple[int, str, str]:
    last = ""
    for attempt in range(ATTEMPTS):
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S)
        except FileNotFoundError:
            return 127, "", f"{cmd[0]}: command not found"
        except subprocess.TimeoutExpired:
            last = f"{' '.join(cmd)}: timed out after {TIMEOUT_S} s"
        else:
            if p.returncode == 0 or not _UNREACHABLE.search(p.stderr + p.stdout):
                return p.returncode, p.stdout, p.stderr
            last = (p.stderr or p.stdout).strip()
        if attempt + 1 < ATTEMPTS:
            time.sleep(PAUSE_S)
    raise Unreachable(last)


def job_state(jobid: str, cluster: str | None = None, run=None) -> tuple[str | None, str]:
    """(state word or None, where it came from / why none). ``run``: runs one command,
    returns (returncode, stdout, stderr) (tests pass canned answers)."""
    run = run or _run
    cl = ["-M", cluster] if cluster else []
    notes = []
    rc, out, err = run(["scontrol", *cl, "show", "job", "-o", jobid])
    if rc == 0 and parse_scontrol(out):
        return parse_scontrol(out), "scontrol"
    notes.append(f"scontrol: {(err or out).strip() or 'no JobState'}")
    if rc == 0 or not _UNKNOWN_JOB.search(err + out):
        rc, out, err = run(["squeue", *cl, "-h", "-j", jobid, "--states=all", "-o", "%T"])
        if rc == 0 and parse_squeue(out):
            return parse_squeue(out), "squeue"
        notes.append(f"squeue: {(err or out).strip() or 'no line'}")
    rc, out, err = run(["sacct", *cl, "-X", "-n", "-P", "-j", jobid, "-o", "State"])
    if rc == 0 and parse_sacct(out):
        return parse_sacct(out), "sacct"
    notes.append(f"sacct: {(err or out).strip() or 'no line'}")
    return None, "; ".join(notes)


def status_of(raw_jobid: str, run=None) -> tuple[str, str]:
    """(status to print, note for stderr or '')."""
    jobid, cluster = split_jobid(raw_jobid)
    if not re.fullmatch(r"\d+(_\d+)?", jobid):
        return FAILED, f"status.py: not a SLURM job id: {raw_jobid!r}"
    try:
        state, source = job_state(jobid, cluster, run=run)
    except Unreachable as e:
        return RUNNING, f"status.py: SLURM did not answer for job {jobid} ({e}); asking again later"
    if state is None:
        return FAILED, (f"status.py: SLURM no longer knows job {jobid} (it ended more than MinJobAge "
                        f"ago and there is no accounting): {source}")
    status = state_to_status(state)
    if status is None:
        return FAILED, f"status.py: empty state for job {jobid} from {source}"
    known = state.split()[0].rstrip("+").upper() in SUCCESS_STATES | RUNNING_STATES | FAILED_STATES
    note = "" if known else f"status.py: unknown SLURM state {state!r} of job {jobid} taken as failed"
    if status == FAILED and known:
        note = f"status.py: SLURM job {jobid} ended {state} ({source})"
    return status, note


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: status.py JOBID  (prints success, running or failed)", file=sys.stderr)
        return 2
    status, note = status_of(argv[1])
    if note:
        print(note, file=sys.stderr)
    print(status)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

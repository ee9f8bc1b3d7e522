"""A newcomer's first run, before and after a change, side by side (run by hand).

    .venv/bin/python benchmarks/onboarding.py --before b41618c --after HEAD

For each commit, in order: a clean clone in a temporary folder, then the README's first
command in two timed phases, ``bash scripts/install.sh`` (with empty pip and uv caches of
its own, as on a new machine) and ``.venv/bin/snakemake --cores 2 bop_all``. The Debian
packages that install.sh needs are installed (and timed) once, before the first clone,
so that neither commit's install is charged for them; on a machine that has them that
phase is zero. Per stage of the main job it reports

- **span**: from the first job's start to the last job's end, as Snakemake's log stamps
  them (whole seconds), which shows where the run's wall time goes, and
- **job time**: the summed ``wall_time_s`` of the stage's artifact manifests (each job's
  own run, inputs to publish); jobs side by side make the sum exceed the span.

It writes ``benchmarks/results/onboarding.md``. Run it on an idle machine: the two
commits run one after the other, not side by side, so that they do not share cores.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
RULE = re.compile(r"^(?:local)?rule (\w+):$")
JOBID = re.compile(r"^\s+jobid: (\d+)$")
FINISHED = re.compile(r"^Finished jobid: (\d+)")


@dataclass
class Run:
    """The timed phases of one commit's first run (s) and the job's AR."""

    commit: str
    install_s: float = 0.0
    job_s: float = 0.0
    ar: float = float("nan")
    spans: dict[str, tuple[float, float]] = field(default_factory=dict)
    job_time: dict[str, float] = field(default_factory=dict)
    jobs: dict[str, int] = field(default_factory=dict)


def timed(cmd: list[str], cwd: Path, env: dict[str, str], what: str) -> tuple[float, str]:
    """Run ``cmd``; (wall time in s, its stdout and stderr). A failure stops the benchmark."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{what} failed ({proc.returncode}):\n{(proc.stdout + proc.stderr)[-3000:]}")
    return wall, proc.stdout + proc.stderr


def rule_spans(log: str) -> dict[str, tuple[float, float]]:
    """Per rule, (first job's start, last job's end) in s since the log's first stamp."""
    stamp = t0 = None
    rule_of: dict[str, str] = {}
    start: dict[str, float] = {}
    spans: dict[str, list[float]] = {}
    pending = None
    for line in log.splitlines():
        if m := STAMP.match(line.strip()):
            stamp = datetime.strptime(m.group(1), "%a %b %d %H:%M:%S %Y").timestamp()
            t0 = stamp if t0 is None else t0
        elif (m := RULE.match(line.strip())) and stamp is not None:
            pending = m.group(1)
        elif (m := JOBID.match(line)) and pending:
            rule_of[m.group(1)], start[m.group(1)], pending = pending, stamp - t0, None
        elif (m := FINISHED.match(line.strip())) and m.group(1) in rule_of:
            rule, begun, end = rule_of[m.group(1)], start[m.group(1)], stamp - t0
            lo, hi = spans.get(rule, (begun, end))
            spans[rule] = [min(lo, begun), max(hi, end)]
    return {rule: (lo, hi) for rule, (lo, hi) in spans.items()}


def manifest_times(cache: Path) -> tuple[dict[str, float], dict[str, int], float]:
    """Per stage, the summed job wall time (s) and job count of the cache's manifests; the AR."""
    secs: dict[str, float] = defaultdict(float)
    jobs: dict[str, int] = defaultdict(int)
    ar = float("nan")
    for path in sorted(cache.glob("*/*/*/*/_manifest.json")):
        m = json.loads(path.read_text())
        stage = path.parts[-4]
        secs[stage] += float(m.get("wall_time_s", 0.0))
        jobs[stage] += 1
        if stage == "score":
            ar = float(m["summary"]["AR"])
    return dict(secs), dict(jobs), ar


def first_run(commit: str, work: Path) -> Run:
    """Clone ``commit`` into ``work`` and time its install and main job."""
    clone = work / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(ROOT), str(clone)], check=True)
    subprocess.run(["git", "-C", str(clone), "checkout", "-q", commit], check=True)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "FREEZE_CACHE")}
    env |= {"PIP_CACHE_DIR": str(work / "pip-cache"), "UV_CACHE_DIR": str(work / "uv-cache")}
    run = Run(commit)
    run.install_s, _ = timed(["bash", "scripts/install.sh"], clone, env, f"{commit}: install.sh")
    print(f"{commit}: install {run.install_s:.1f} s", flush=True)
    run.job_s, log = timed([str(clone / ".venv/bin/snakemake"), "--cores", "2", "bop_all"], clone, env,
                           f"{commit}: the main job")
    run.spans = rule_spans(log)
    run.job_time, run.jobs, run.ar = manifest_times(clone / "cache")
    print(f"{commit}: main job {run.job_s:.1f} s, AR {run.ar:.3f}", flush=True)
    return run


def debian_packages() -> float:
    """Install (timed) the Debian packages that the current install.sh lists and the machine lacks."""
    text = (ROOT / "scripts" / "install.sh").read_text()
    wanted = re.search(r'^DEB_PACKAGES="([^"]+)"', text, re.M).group(1).split()
    missing = [p for p in wanted if subprocess.run(["dpkg-query", "-W", "-f=${Status}", p], capture_output=True,
                                                  text=True).stdout.find("install ok installed") < 0]
    if not missing:
        return 0.0
    sudo = [] if os.geteuid() == 0 else ["sudo"]
    t0 = time.perf_counter()
    subprocess.run([*sudo, "apt-get", "update", "-qq"], check=True, capture_output=True)
    subprocess.run([*sudo, "apt-get", "install", "-y", "-qq", *missing], check=True, capture_output=True,
                   env=os.environ | {"DEBIAN_FRONTEND": "noninteractive"})
    return time.perf_counter() - t0


def table(runs: list[Run], apt_s: float) -> str:
    """The phases of ``runs`` side by side, as Markdown."""
    a, b = runs
    lines = [
        "# A fresh machine to the AR table",
        "",
        f"`benchmarks/onboarding.py --before {a.commit} --after {b.commit}`: each commit a clean clone, then "
        "the README's first command (`bash scripts/install.sh && .venv/bin/snakemake --cores 2 bop_all`) with "
        "empty pip and uv caches, one after the other on an idle 2-core machine"
        f"{' (PYTHONDONTWRITEBYTECODE set, as in CI)' if os.environ.get('PYTHONDONTWRITEBYTECODE') else ''}.",
        "",
        f"Debian packages (installed once, before both): {apt_s:.1f} s.",
        "",
        f"| phase | {a.commit} (s) | {b.commit} (s) | after / before |",
        "|---|---|---|---|",
    ]

    def row(name: str, x: float, y: float) -> None:
        lines.append(f"| {name} | {x:.1f} | {y:.1f} | {y / x:.2f} |" if x else f"| {name} | {x:.1f} | {y:.1f} | |")

    row("install.sh", a.install_s, b.install_s)
    row("main job", a.job_s, b.job_s)
    row("**first command, in all**", a.install_s + a.job_s + apt_s, b.install_s + b.job_s + apt_s)
    lines += ["", f"AR of the main job: {a.ar:.3f} before, {b.ar:.3f} after.", "",
              "Per stage: jobs, the summed job time of the manifests, and the span in the run "
              "(first start to last end, s from the job's start).", "",
              f"| stage | jobs | job time {a.commit} | job time {b.commit} | span {a.commit} | span {b.commit} |",
              "|---|---|---|---|---|---|"]
    rules = list(dict.fromkeys([*a.spans, *b.spans]))
    for rule in rules:
        stage = "refine" if rule == "refine_collect" else rule
        ja = a.job_time.get(stage, 0.0) if rule != "refine_collect" else 0.0
        jb = b.job_time.get(stage, 0.0) if rule != "refine_collect" else 0.0
        sa, sb = a.spans.get(rule), b.spans.get(rule)
        fmt = lambda s: f"{s[0]:.0f}-{s[1]:.0f}" if s else "-"  # noqa: E731
        n = b.jobs.get(stage, "-") if rule != "refine_collect" else 1
        lines.append(f"| {rule} | {n} | {ja:.1f} | {jb:.1f} | {fmt(sa)} | {fmt(sb)} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True, help="the commit of the old first run")
    ap.add_argument("--after", default="HEAD", help="the commit of the new first run")
    ap.add_argument("--keep", action="store_true", help="keep the clones (printed) instead of deleting them")
    args = ap.parse_args()
    apt_s = debian_packages()
    print(f"Debian packages: {apt_s:.1f} s", flush=True)
    runs = []
    commits = [subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", c], check=True, capture_output=True,
                              text=True).stdout.strip() for c in (args.before, args.after)]
    for commit in commits:
        work = Path(tempfile.mkdtemp(prefix=f"onboarding-{commit}-"))
        try:
            runs.append(first_run(commit, work))
        finally:
            if args.keep:
                print(f"kept {work}")
            else:
                shutil.rmtree(work, ignore_errors=True)
    text = table(runs, apt_s)
    out = ROOT / "benchmarks" / "results" / "onboarding.md"
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

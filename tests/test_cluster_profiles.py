"""The SLURM profiles and their helper scripts, without a SLURM: the profiles parse
(as YAML and as Snakemake reads them), name only rules that exist and give every rule
a wall time; the cluster-generic status script maps scontrol/squeue/sacct answers to
success/running/failed; the run comparison of scripts/cluster_check.sh finds a
difference. The check itself (a one-node SLURM, the main job through it) is
scripts/cluster_check.sh, run by hand or in CI as root (docs/cluster.md)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
PROFILES = {"slurm": ROOT / "profiles" / "slurm", "slurm-generic": ROOT / "profiles" / "slurm-generic"}


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


status = _load("slurm_status", ROOT / "scripts" / "slurm" / "status.py")
compare = _load("slurm_compare_runs", ROOT / "scripts" / "slurm" / "compare_runs.py")


def rule_names() -> set[str]:
    """The stage rules (generated from the declarations) and the Snakefile's own."""
    from pipeline.workflow.stage_graph import stage_rules

    names = {r.name for r in stage_rules()}
    return names | set(re.findall(r"^rule (\w+):", (ROOT / "Snakefile").read_text(), flags=re.M))


# ---------------------------------------------------------------- profiles

@pytest.mark.parametrize("name", sorted(PROFILES))
def test_profile_is_yaml_and_names_existing_rules(name):
    cfg = yaml.safe_load((PROFILES[name] / "config.yaml").read_text())
    assert cfg["executor"] == {"slurm": "slurm", "slurm-generic": "cluster-generic"}[name]
    rules = rule_names()
    assert {"synth", "scene_features", "refine", "refine_collect", "score", "bop_all"} <= rules
    assert set(cfg.get("set-resources") or {}) <= rules, set(cfg["set-resources"]) - rules
    # the rules declare their own wall time and memory; the defaults cover the others
    assert int(cfg["default-resources"]["runtime"]) > 0 and int(cfg["default-resources"]["mem_mb"]) > 0
    assert int(cfg["jobs"]) >= 1 and int(cfg["latency-wait"]) >= 5


def test_every_stage_rule_declares_threads_memory_and_wall_time_from_its_stage():
    """Each stage rule takes threads, mem_mb and runtime from its StageSpec (declared
    once); bop_all runs where Snakemake runs (a local rule), not as a cluster job."""
    from pipeline.workflow.stage_graph import STAGES

    snakefile = (ROOT / "Snakefile").read_text()  # one rule template for every stage rule
    assert "threads: STAGES[r.stage].threads" in snakefile
    assert "mem_mb=STAGES[r.stage].mem_mb" in snakefile
    assert "runtime=STAGES[r.stage].runtime_min" in snakefile
    for stage, spec in STAGES.items():
        assert spec.threads >= 1 and spec.mem_mb >= 500 and 10 <= spec.runtime_min <= 24 * 60
    assert re.search(r"^localrules:\s*\n\s+bop_all,", (ROOT / "Snakefile").read_text(), flags=re.M)


def test_generic_profile_submits_with_sbatch_and_its_status_script_exists():
    cfg = yaml.safe_load((PROFILES["slurm-generic"] / "config.yaml").read_text())
    submit = cfg["cluster-generic-submit-cmd"]
    assert "sbatch --parsable" in submit
    for field in ("{threads}", "{resources.mem_mb}", "{resources.runtime}"):
        assert field in submit
    script = (PROFILES["slurm-generic"] / cfg["cluster-generic-status-cmd"]).resolve()
    assert script == ROOT / "scripts" / "slurm" / "status.py"
    assert os.access(script, os.X_OK)
    assert cfg["cluster-generic-cancel-cmd"] == "scancel"


@pytest.mark.slow
def test_snakemake_reads_both_profiles():
    """Snakemake's own command line parser takes every key of both profiles (a key of
    a plugin that is not installed, or a misspelt one, is an error there)."""
    pytest.importorskip("snakemake_executor_plugin_slurm")
    pytest.importorskip("snakemake_executor_plugin_cluster_generic")
    code = (
        "import sys\n"
        "from snakemake.cli import parse_args\n"
        "out = {}\n"
        "for p in sys.argv[1:]:\n"
        "    _, a = parse_args(['--profile', p, 'bop_all'])\n"
        "    out[p] = [a.executor, a.jobs, sorted(a.set_resources),\n"
        "              str(a.default_resources['runtime']), str(a.cluster_generic_status_cmd)]\n"
        "print(repr(out))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(PROFILES["slurm"]), str(PROFILES["slurm-generic"])],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = eval(proc.stdout.strip().splitlines()[-1])  # noqa: S307 - our own repr
    slurm, generic = out[str(PROFILES["slurm"])], out[str(PROFILES["slurm-generic"])]
    assert slurm[0] == "slurm" and generic[0] == "cluster-generic"
    assert slurm[2] == [] and "60" in slurm[3]
    assert generic[4].endswith("scripts/slurm/status.py")


def test_cluster_check_script_is_valid_bash():
    proc = subprocess.run(["bash", "-n", str(ROOT / "scripts" / "cluster_check.sh")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


# ---------------------------------------------------------------- status.py

@pytest.mark.parametrize("state, expected", [
    ("COMPLETED", "success"),
    ("PENDING", "running"), ("RUNNING", "running"), ("CONFIGURING", "running"),
    ("COMPLETING", "running"), ("SUSPENDED", "running"), ("REQUEUED", "running"),
    ("FAILED", "failed"), ("CANCELLED", "failed"), ("CANCELLED by 0", "failed"),
    ("CANCELLED+", "failed"), ("TIMEOUT", "failed"), ("NODE_FAIL", "failed"),
    ("OUT_OF_MEMORY", "failed"), ("OUT_OF_ME+", "failed"), ("BOOT_FAIL", "failed"),
    ("DEADLINE", "failed"), ("PREEMPTED", "failed"),
    ("SOMETHING_NEW", "failed"),
])
def test_state_mapping(state, expected):
    assert status.state_to_status(state) == expected


SCONTROL = ("JobId={id} JobName=freeze-refine UserId=me(1000) GroupId=me(1000) MCS_label=N/A "
            "Priority=4294901750 Nice=0 Account=(null) QOS=(null) JobState={state} Reason=None "
            "Dependency=(null) Requeue=1 Restarts=0 BatchFlag=1 Reboot=0 ExitCode=0:0 RunTime=00:00:31\n")
UNKNOWN = "slurm_load_jobs error: Invalid job id specified\n"
NO_ACCOUNTING = "Slurm accounting storage is disabled\n"


class FakeSlurm:
    """Answers the commands status.py runs from a table {command: (rc, out, err)}."""

    def __init__(self, answers):
        self.answers = answers
        self.calls = []

    def __call__(self, cmd):
        self.calls.append(cmd)
        for prog, answer in self.answers.items():
            if cmd[0] == prog:
                if isinstance(answer, Exception):
                    raise answer
                return answer
        raise AssertionError(f"unexpected command {cmd}")


@pytest.mark.parametrize("state, expected", [
    ("COMPLETED", "success"), ("RUNNING", "running"), ("PENDING", "running"),
    ("FAILED", "failed"), ("TIMEOUT", "failed"), ("OUT_OF_MEMORY", "failed"), ("CANCELLED", "failed"),
])
def test_status_from_scontrol(state, expected):
    fake = FakeSlurm({"scontrol": (0, SCONTROL.format(id=42, state=state), "")})
    got, note = status.status_of("42", run=fake)
    assert got == expected
    assert fake.calls == [["scontrol", "show", "job", "-o", "42"]]
    assert (note != "") == (expected == "failed")


def test_status_falls_back_to_squeue_when_scontrol_gives_no_state():
    fake = FakeSlurm({"scontrol": (0, "", ""), "squeue": (0, "COMPLETED\n", "")})
    assert status.status_of("7", run=fake)[0] == "success"
    assert fake.calls[1] == ["squeue", "-h", "-j", "7", "--states=all", "-o", "%T"]


def test_forgotten_job_uses_accounting_or_fails():
    # the controller forgot the job (MinJobAge) but accounting has it
    fake = FakeSlurm({"scontrol": (1, "", UNKNOWN), "sacct": (0, "FAILED\nCOMPLETED\n", "")})
    assert status.status_of("9", run=fake)[0] == "success"      # last line: the requeued attempt
    assert [c[0] for c in fake.calls] == ["scontrol", "sacct"]   # squeue asks the same controller
    # no accounting: nobody knows the job any more, which is a failure, said on stderr
    fake = FakeSlurm({"scontrol": (1, "", UNKNOWN), "sacct": (1, "", NO_ACCOUNTING)})
    got, note = status.status_of("9", run=fake)
    assert got == "failed" and "no longer knows job 9" in note


def test_unreachable_controller_means_ask_again():
    fake = FakeSlurm({"scontrol": status.Unreachable("Unable to contact slurm controller")})
    got, note = status.status_of("11", run=fake)
    assert got == "running" and "did not answer" in note


def test_cluster_suffix_and_bad_ids():
    fake = FakeSlurm({"scontrol": (0, SCONTROL.format(id=5, state="COMPLETED"), "")})
    assert status.status_of("5;gpu", run=fake)[0] == "success"
    assert fake.calls[0] == ["scontrol", "-M", "gpu", "show", "job", "-o", "5"]
    assert status.status_of("Submitted batch job 5", run=FakeSlurm({}))[0] == "failed"


def test_run_retries_only_an_unreachable_controller(monkeypatch):
    calls = []

    def fake_run(cmd, **kw):
        calls.append(cmd)
        return subprocess.CompletedProcess(cmd, 1, "", "slurm_load_jobs error: Unable to contact slurm controller (connect failure)")

    monkeypatch.setattr(status.subprocess, "run", fake_run)
    monkeypatch.setattr(status, "PAUSE_S", 0.0)
    with pytest.raises(status.Unreachable):
        status._run(["scontrol", "show", "job", "-o", "1"])
    assert len(calls) == status.ATTEMPTS
    calls.clear()
    monkeypatch.setattr(status.subprocess, "run", lambda cmd, **kw: subprocess.CompletedProcess(cmd, 1, "", UNKNOWN))
    assert status._run(["scontrol", "show", "job", "-o", "1"])[0] == 1


def test_main_prints_one_word_and_exits_zero(monkeypatch, capsys):
    monkeypatch.setattr(status, "_run", FakeSlurm({"scontrol": (0, SCONTROL.format(id=3, state="TIMEOUT"), "")}))
    assert status.main(["status.py", "3"]) == 0
    out, err = capsys.readouterr()
    assert out == "failed\n" and "TIMEOUT" in err
    assert status.main(["status.py"]) == 2


# ---------------------------------------------------------------- compare_runs.py

HEADER = "scene_id,im_id,obj_id,score,R,t,time\n"
ROW = "1,0,2,0.98,1 0 0 0 1 0 0 0 1,1.5 -45.2 977.6,{time}\n"


def fake_run(cache: Path, *, time="3.2", r="1 0 0 0 1 0 0 0 1", ar=0.85):
    csv = cache / "synthtiny/refine/icp-abc/all/freeze_synthtiny-test.csv"
    scores = cache / "synthtiny/score/bop19-def/all/scores.json"
    csv.parent.mkdir(parents=True)
    scores.parent.mkdir(parents=True)
    csv.write_text(HEADER + ROW.format(time=time).replace("1 0 0 0 1 0 0 0 1", r))
    scores.write_text(json.dumps({"summary": {"AR": ar, "AR_VSD": ar, "AR_MSSD": ar, "AR_MSPD": ar,
                                              "n_targets": 7, "n_estimates": 6, "mean_time_per_image": float(time)},
                                  "recalls": {"vsd": [[ar]]}, "per_object": [{"obj_id": 2, "AR": ar}],
                                  "per_visibility": []}))


def test_compare_ignores_time_only(tmp_path):
    fake_run(tmp_path / "a", time="3.2")
    fake_run(tmp_path / "b", time="9.9")
    line = compare.compare_runs(tmp_path / "a", tmp_path / "b", "synthtiny")
    assert line.startswith("identical") and "AR 0.8500" in line
    fake_run(tmp_path / "c", r="0 1 0 1 0 0 0 0 1")
    with pytest.raises(compare.Different, match="line 2 differs in R"):
        compare.compare_runs(tmp_path / "a", tmp_path / "c", "synthtiny")
    fake_run(tmp_path / "d", ar=0.84)
    with pytest.raises(compare.Different, match="summary.AR"):
        compare.compare_runs(tmp_path / "a", tmp_path / "d", "synthtiny")
    (tmp_path / "e").mkdir()
    with pytest.raises(compare.Different, match="is missing"):
        compare.compare_runs(tmp_path / "a", tmp_path / "e", "synthtiny")
    assert compare.main([str(tmp_path / "a"), str(tmp_path / "c"), "--dataset", "synthtiny"]) == 1


# ---------------------------------------------------------------- no sbatch here

def test_missing_submitter_names_sbatch_only_for_slurm_executors(monkeypatch):
    from pipeline.workflow import cluster_submit

    monkeypatch.setattr(cluster_submit.shutil, "which", lambda cmd: None)
    why = cluster_submit.missing_submitter("slurm", where="profile profiles/slurm")
    assert why is not None and "`sbatch`" in why and "profile profiles/slurm" in why
    generic = yaml.safe_load((PROFILES["slurm-generic"] / "config.yaml").read_text())["cluster-generic-submit-cmd"]
    assert cluster_submit.missing_submitter("cluster-generic", generic) is not None
    assert cluster_submit.missing_submitter("cluster-generic", "qsub -V") is None   # not a SLURM submit
    assert cluster_submit.missing_submitter("local") is None
    assert cluster_submit.missing_submitter(None) is None
    monkeypatch.setattr(cluster_submit.shutil, "which", lambda cmd: f"/usr/bin/{cmd}")
    assert cluster_submit.missing_submitter("slurm") is None


def _path_without_sbatch(tmp_path: Path) -> str:
    """This PATH with every program but ``sbatch`` (linked into one folder): the
    machine as it would be without SLURM's client commands."""
    folder = tmp_path / "bin"
    folder.mkdir()
    for d in os.environ.get("PATH", "").split(os.pathsep):
        if not os.path.isdir(d):
            continue
        for entry in os.scandir(d):
            target = folder / entry.name
            if entry.name != "sbatch" and not target.exists() and os.access(entry.path, os.X_OK):
                target.symlink_to(entry.path)
    assert not (folder / "sbatch").exists()
    return f"{Path(sys.executable).parent}:{folder}"


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_freeze_run_with_a_slurm_profile_and_no_sbatch_says_so_in_one_line(tmp_path, name):
    env = {**os.environ, "PATH": _path_without_sbatch(tmp_path), "FREEZE_CACHE": str(tmp_path / "cache")}
    proc = subprocess.run([str(Path(sys.executable).parent / "freeze"), "run", "--profile", str(PROFILES[name]),
                           "--directory", str(tmp_path / "work"), "-c", "datasets=synthtiny"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 1
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert len(lines) == 1 and "sbatch" in lines[0] and "Traceback" not in proc.stderr, proc.stdout + proc.stderr
    assert not (tmp_path / "cache").exists()   # nothing ran


def test_freeze_run_refuses_a_profile_folder_without_config(tmp_path):
    proc = subprocess.run([str(Path(sys.executable).parent / "freeze"), "run", "--profile", str(tmp_path),
                           "-c", "datasets=synthtiny"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "no config.yaml" in proc.stdout + proc.stderr


@pytest.mark.slow
def test_plain_snakemake_with_the_generic_profile_and_no_sbatch_stops_before_any_job(tmp_path):
    """The Snakefile's onstart asks the same check: exit 1, the one line, no job run and
    no lock left behind."""
    pytest.importorskip("snakemake_executor_plugin_cluster_generic")
    work = tmp_path / "work"
    env = {**os.environ, "PATH": _path_without_sbatch(tmp_path), "FREEZE_CACHE": str(tmp_path / "cache"),
           "PYOPENGL_PLATFORM": "egl"}
    env.pop("FREEZE_RUN_JSON", None)
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-s", str(ROOT / "Snakefile"),
                           "--directory", str(work), "--profile", str(PROFILES["slurm-generic"]), "bop_all",
                           "--config", "datasets=synthtiny"], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "error: the cluster-generic executor submits jobs with `sbatch`" in proc.stderr
    assert not (tmp_path / "cache").exists()
    assert not (work / ".snakemake" / "locks").exists() or not any((work / ".snakemake" / "locks").iterdir())

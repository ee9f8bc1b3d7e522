"""The one line that says which encoders stand in for the paper's (pipeline/common/stand_in.py),
where a run prints it (Snakefile onstart, `freeze run`), the report, and `freeze encoders`."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from pipeline.common.stand_in import encoders_sentence, paper_configuration, paper_line, stand_in_notice

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_NOTICE = ("note: fpfh + colortex are weight-free stand-ins for the paper's GeDi + DINOv2 ViT-g/14; fetch those "
                  "with `freeze weights fetch gedi dinov2-vitg14` and run with --config geometric=gedi "
                  "visual=dinov2-vitg14")


def test_the_default_encoders_are_named_as_stand_ins_for_the_paper_s():
    assert paper_configuration() == {"geometric": ("gedi", "GeDi"), "visual": ("dinov2-vitg14", "DINOv2 ViT-g/14")}
    assert stand_in_notice("fpfh", "colortex") == DEFAULT_NOTICE
    # each command says how to switch with its own options
    assert stand_in_notice("fpfh", "colortex", form="estimate").endswith("run with --geometric gedi --visual dinov2-vitg14")
    assert stand_in_notice("fpfh", "colortex", form="freeze").endswith("run with -c geometric=gedi -c visual=dinov2-vitg14")
    # one stand-in: only it is named, with the one paper encoder that replaces it
    assert stand_in_notice("gedi", "colortex") == (
        "note: colortex is a weight-free stand-in for the paper's DINOv2 ViT-g/14; fetch it with "
        "`freeze weights fetch dinov2-vitg14` and run with --config visual=dinov2-vitg14")
    assert stand_in_notice("fpfh", "none") == (
        "note: fpfh is a weight-free stand-in for the paper's GeDi; fetch it with `freeze weights fetch gedi` and run "
        "with --config geometric=gedi")


@pytest.mark.parametrize("geometric, visual", [("gedi", "dinov2-vitg14"), ("gedi", "dinov2-vitl14"),
                                               ("none", "dinov2-vitb14"), ("gedi", "no-such-manifest")])
def test_no_notice_when_no_encoder_is_a_stand_in(geometric, visual):
    assert stand_in_notice(geometric, visual) is None


def test_pose_sentence_names_the_encoders_that_ran():
    assert encoders_sentence("gedi", "dinov2-vitg14") == "gedi + dinov2-vitg14: the paper's configuration (GeDi + DINOv2 ViT-g/14)"
    assert encoders_sentence("fpfh", "colortex", form="estimate") == (
        "fpfh + colortex: weight-free stand-ins for the paper's GeDi + DINOv2 ViT-g/14; fetch those with "
        "`freeze weights fetch gedi dinov2-vitg14` and run with --geometric gedi --visual dinov2-vitg14")
    # not the paper's size, not a stand-in: nothing false, the paper's configuration named beside
    assert encoders_sentence("gedi", "dinov2-vits14") == (
        "gedi + dinov2-vits14; the paper's configuration is GeDi + DINOv2 ViT-g/14")
    # ViT-L/14 is a lighter option, not the paper's
    assert encoders_sentence("gedi", "dinov2-vitl14") == (
        "gedi + dinov2-vitl14; the paper's configuration is GeDi + DINOv2 ViT-g/14")
    assert encoders_sentence("fpfh", "colortex-intensity").startswith(
        "fpfh + colortex-intensity: fpfh is a weight-free stand-in for the paper's GeDi;")


def test_names_come_from_the_manifests_flags(tmp_path):
    """Move the flags and the sentence follows: nothing is hard-coded."""
    enc = tmp_path / "encoders"
    enc.mkdir()
    docs = {"deep3d": {"encoder": "gedi", "kind": "geometric", "paper": True},
            "bigvit": {"encoder": "dinov2", "kind": "visual", "paper": True, "params": {"model": "vitg14"}},
            "cheap3d": {"encoder": "fpfh", "kind": "geometric", "stand_in": True},
            "colortex": {"encoder": "colortex", "kind": "visual"}}
    for name, doc in docs.items():
        (enc / f"{name}.yaml").write_text(yaml.safe_dump(doc))
    assert stand_in_notice("cheap3d", "colortex", manifest_dir=tmp_path) == (
        "note: cheap3d is a weight-free stand-in for the paper's GeDi; fetch it with `freeze weights fetch deep3d` "
        "and run with --config geometric=deep3d")
    assert encoders_sentence("deep3d", "bigvit", manifest_dir=tmp_path) == (
        "deep3d + bigvit: the paper's configuration (GeDi + DINOv2 ViT-g/14)")
    assert paper_line(manifest_dir=tmp_path) == (
        "the paper's configuration is deep3d + bigvit (GeDi + DINOv2 ViT-g/14): fetch it with "
        "`freeze weights fetch deep3d bigvit` and run with --config geometric=deep3d visual=bigvit")


def test_encoders_command_marks_the_paper_s_and_the_stand_ins(monkeypatch, tmp_path):
    from pipeline.commands.cli import app

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    result = CliRunner().invoke(app, ["encoders", "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    roles = {r["manifest"]: r["role"] for r in doc["manifests"]}
    assert {m for m, r in roles.items() if r == "paper"} == {"gedi", "dinov2-vitg14"}
    assert {m for m, r in roles.items() if r == "stand-in"} == {"fpfh", "colortex"}
    assert roles["dinov2-vits14"] == roles["gedi-r03"] == ""
    paper = doc["paper_configuration"]
    assert (paper["geometric"], paper["visual"]) == ("gedi", "dinov2-vitg14")
    assert paper["fetch"] == "freeze weights fetch gedi dinov2-vitg14"
    text = CliRunner().invoke(app, ["encoders"])
    assert text.exit_code == 0, text.output
    after_table = text.output[text.output.rindex("└"):]
    [line] = [ln for ln in after_table.splitlines() if "paper's configuration" in ln]
    assert line == paper_line() and "freeze weights fetch gedi dinov2-vitg14" in line


def test_report_says_it_once_under_the_run_s_encoders(tmp_path, monkeypatch):
    from test_report import _fake_run  # a run plan with empty artifacts

    from pipeline.views import html

    rp = _fake_run(tmp_path, "empty", monkeypatch)
    rp.encoders = {k: {"manifest": m, "signature": m, "version": 1} for k, m in (("geometric", "fpfh"),
                                                                                  ("visual", "colortex"))}
    text = html.build_report(rp, "fake", samples=0)
    assert text.count("weight-free stand-ins") == 1
    assert html.stand_in_note(rp.encoders) in text and "freeze weights fetch gedi dinov2-vitg14" in text
    assert text.index("stand-ins") < text.index("<h2>1.")  # with the encoders, at the top
    rp.encoders = {k: {"manifest": m, "signature": m, "version": 1} for k, m in (("geometric", "gedi"),
                                                                                  ("visual", "dinov2-vitg14"))}
    assert "stand-in" not in html.build_report(rp, "fake", samples=0)


# ------------------------------------------------------------------- at a run's start


def _synth_target(cache: Path) -> str:
    """The manifest of synthtiny's synth job (a few seconds) under ``cache``."""
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan

    return str(RunPlan(load_run({"datasets": "synthtiny"}), cache=cache)["synthtiny"]["synth"].manifest("dataset"))


def _env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("FREEZE_RUN_JSON", "FREEZE_STAND_IN_SHOWN")}
    env.update(FREEZE_CACHE=str(tmp_path / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1")
    return env


@pytest.mark.slow
def test_snakemake_says_it_once_at_the_start_and_not_in_each_cluster_job(tmp_path):
    """On a cluster every job parses the Snakefile again: the notice is the main
    process's (onstart), not the jobs'. A fake cluster-generic executor runs each job
    script in the background, its output in a log of its own."""
    pytest.importorskip("snakemake_executor_plugin_cluster_generic")
    logs = tmp_path / "joblogs"
    logs.mkdir()
    submit = tmp_path / "submit.sh"
    submit.write_text(f'#!/bin/bash\nid=$RANDOM$RANDOM\nbash "$1" > {logs}/$id.log 2>&1 &\necho $id\n')
    submit.chmod(0o755)
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-s", str(ROOT / "Snakefile"),
                           "--directory", str(tmp_path / "work"), "--executor", "cluster-generic",
                           "--cluster-generic-submit-cmd", str(submit), "--jobs", "1", "--latency-wait", "5",
                           _synth_target(tmp_path / "cache"), "--config", "datasets=synthtiny"],
                          env=_env(tmp_path), capture_output=True, text=True, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert out.count(DEFAULT_NOTICE) == 1 and out.count("stand-in") == 1
    jobs = list(logs.glob("*.log"))
    assert len(jobs) == 1 and "rule synth" in jobs[0].read_text()  # the job parsed the Snakefile ...
    assert "stand-in" not in jobs[0].read_text()  # ... and said nothing


@pytest.mark.slow
def test_freeze_run_says_it_once_with_its_own_options(tmp_path):
    proc = subprocess.run([str(Path(sys.executable).parent / "freeze"), "run", _synth_target(tmp_path / "cache"),
                           "--directory", str(tmp_path / "work"), "-c", "datasets=synthtiny"],
                          env=_env(tmp_path), capture_output=True, text=True, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "rule synth" in out  # Snakemake ran a job (its onstart ran) ...
    assert out.count("stand-in") == 1  # ... and did not repeat the notice
    assert "run with -c geometric=gedi -c visual=dinov2-vitg14" in out.replace("\n", "")


def test_weights_fetch_without_names_gives_the_paper_s_fetch():
    from pipeline.formats.weights.catalog import UnknownWeights, select

    with pytest.raises(UnknownWeights, match=r"the paper's configuration: `freeze weights fetch gedi dinov2-vitg14`$"):
        select([])

"""The `freeze` command line, as a user calls it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.bop.results import read_estimates_json, write_results_csv
from pipeline.cli import app

DATA = Path(__file__).parent / "data" / "tinybop"
runner = CliRunner()


def test_score_command_reproduces_the_reference_toolkit(tmp_path):
    est = read_estimates_json(DATA / "estimates" / "tx20_icbin-test.json")
    csv = tmp_path / "tx20_icbin-test.csv"
    write_results_csv(csv, est)
    out = tmp_path / "scores"
    result = runner.invoke(app, ["score", str(csv), "--dataset-root", str(DATA / "icbin"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    ref = json.loads((DATA / "reference_scores_tinybop.json").read_text())["variants"]["tx20"]["bop19"]
    scores = json.loads((out / "scores.json").read_text())
    summary = scores["summary"]
    assert summary["AR"] == pytest.approx(ref["bop19_average_recall"], abs=1e-3)
    assert summary["AR_VSD"] == pytest.approx(ref["bop19_average_recall_vsd"], abs=1e-3)
    assert (out / "errors.parquet").exists()
    assert "0.531" in result.output


def test_plan_command_lists_every_stage():
    result = runner.invoke(app, ["plan", "--config", "datasets=synthtiny"])
    assert result.exit_code == 0, result.output
    for stage in ("synth", "render_templates", "model_features", "segment_prior", "scene_features",
                  "register", "refine", "score"):
        assert stage in result.output


def test_stage_command_rejects_a_stale_signature():
    result = runner.invoke(app, ["stage", "score", "--dataset", "synthtiny", "--item", "all", "--expect-sig", "bop19-00000000"])
    assert result.exit_code == 2
    assert "signature" in result.output


def test_score_command_names_the_bad_line(tmp_path):
    est = read_estimates_json(DATA / "estimates" / "gt_icbin-test.json")
    csv = tmp_path / "bad_icbin-test.csv"
    write_results_csv(csv, est)
    lines = csv.read_text().splitlines()
    lines[2] = lines[2].replace(",", ",x", 1)
    csv.write_text("\n".join(lines) + "\n")
    result = runner.invoke(app, ["score", str(csv), "--dataset-root", str(DATA / "icbin")])
    assert result.exit_code == 1
    assert "line 3" in result.output


def test_encoders_command_reports_weights(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # an empty hub cache
    result = runner.invoke(app, ["encoders", "--json"])
    assert result.exit_code == 0, result.output
    rows = {r["manifest"]: r for r in json.loads(result.output)["manifests"]}
    assert rows["fpfh"]["ok"] and rows["fpfh"]["dim"] == 66 and rows["fpfh"]["weights"] == "none needed"
    assert rows["colortex"]["ok"] and rows["colortex"]["kind"] == "visual"
    assert not rows["dinov2-vits14"]["ok"]
    assert "dinov2_vits14_pretrain.pth" in rows["dinov2-vits14"]["weights"]
    assert str(tmp_path / "torch") in rows["dinov2-vits14"]["weights"]

"""The `freeze` command line, as a user calls it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.formats.bop.results import read_estimates_json, write_results_csv
from pipeline.commands.cli import app

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


def test_score_command_refuses_an_r_that_is_not_a_rotation(tmp_path):
    import numpy as np

    from pipeline.evaluation.metrics import ROTATION_TOLERANCE

    est = read_estimates_json(DATA / "estimates" / "gt_icbin-test.json")
    est.at[3, "R"] = np.zeros((3, 3))
    est.at[5, "R"] = 1.01 * est.at[5, "R"]
    csv = tmp_path / "zero_icbin-test.csv"
    write_results_csv(csv, est)
    out = tmp_path / "scores"
    result = runner.invoke(app, ["score", str(csv), "--dataset-root", str(DATA / "icbin"), "--out", str(out),
                                 "--no-progress"])  # (with progress, each step done is a line before it)
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit)  # no traceback
    r = est.iloc[3]
    assert result.output == (f"{csv}: 2 of 6 estimates have an R that is not a rotation (max|R^T R - I| or "
                             f"|det R - 1| above 0.001); first: estimate 4 (scene_id {r.scene_id}, im_id {r.im_id}, "
                             f"obj_id {r.obj_id}) with max|R^T R - I| = 1, |det R - 1| = 1\n")
    assert not out.exists()
    # the help states the tolerance, the module constant's value
    assert ROTATION_TOLERANCE == 1e-3
    help_text = " ".join(runner.invoke(app, ["score", "--help"]).output.split())
    assert f"max|R^T R - I| <= {ROTATION_TOLERANCE:g} and |det R - 1| <= {ROTATION_TOLERANCE:g}" in help_text


def test_published_results_table_and_scores_follow_the_umask(tmp_path, monkeypatch, umask_022):
    """The results CSV `freeze table --csv-dir` publishes, the AR table of --out and the
    files of `freeze score --out` get 0o666 & ~umask (0644 under umask 022), even when
    the temporary file they are written to was created 0600."""
    import contextlib
    import os
    import stat
    from types import SimpleNamespace

    from pipeline.commands import cli
    from pipeline.evaluation.metrics.evaluate import score_results_file
    from pipeline.common import published_files as files
    from pipeline.common.store import atomic_path

    @contextlib.contextmanager
    def private(path):  # as a secure temporary file would be created
        with atomic_path(path) as tmp:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            yield tmp

    refine = tmp_path / "cache" / "refine" / "all"
    refine.mkdir(parents=True)
    write_results_csv(refine / "freeze_icbin-test.csv", read_estimates_json(DATA / "estimates" / "gt_icbin-test.json"))

    class Plan:  # what _publish_csv reads of a dataset plan
        results_csv_name = "freeze_icbin-test.csv"

        def __getitem__(self, stage):
            return SimpleNamespace(item_dir=lambda item: refine)

    plan = Plan()
    for label, patch in (("open", False), ("private", True)):
        if patch:
            monkeypatch.setattr(files, "atomic_path", private)
        results = tmp_path / label
        dst = cli._publish_csv(plan, results)
        assert dst.read_text() == (refine / "freeze_icbin-test.csv").read_text()
        table = files.write_text_published(results / "ar_table.md", "| results |\n")
        assert stat.S_IMODE(dst.stat().st_mode) == 0o644, label
        assert stat.S_IMODE(table.stat().st_mode) == 0o644, label
        assert sorted(p.name for p in results.iterdir()) == ["ar_table.md", "freeze_icbin-test.csv"]
    score_results_file(dst, DATA / "icbin", out_dir=tmp_path / "scores")
    for name in ("scores.json", "errors.parquet"):
        assert stat.S_IMODE((tmp_path / "scores" / name).stat().st_mode) == 0o644, name

"""The artifact declarations (pipeline/workflow/artifact_schema.py) are what the files
hold: every artifact of a real run matches its declaration, every file of an item
folder is declared, and a stage writing a table or arrays that differ from their
declaration fails, publishing nothing."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.common.store import MANIFEST_NAME, load_arrays, read_table
from pipeline.workflow.artifact_schema import ArtifactMismatch, check_arrays, check_table
from pipeline.workflow.stage_graph import STAGES, item_kind


def _plan(work):
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan

    return RunPlan(load_run({"datasets": "synthtiny"}), cache=work / "cache")["synthtiny"]


def _items(plan, stage: str) -> list[str]:
    folder = plan[stage].dir
    return sorted(p.name for p in folder.iterdir() if (p / MANIFEST_NAME).exists())


@pytest.mark.slow
def test_every_artifact_of_a_run_matches_its_declaration(tiny_run):
    work, _ = tiny_run
    plan = _plan(work)
    checked = {"table": 0, "arrays": 0, "json": 0, "csv": 0, "dataset": 0}
    for stage, spec in STAGES.items():
        items = _items(plan, stage)
        assert items, f"{stage}: no item in {plan[stage].dir}"
        for item in items:
            kind = item_kind(item)
            folder = plan[stage].item_dir(item)
            files = {p.name for p in folder.iterdir() if p.name != MANIFEST_NAME}
            declared = {plan.file_name(f) for f in spec.writes_for(kind)}
            assert files == declared, f"{stage}/{item}: files {sorted(files)}, declared {sorted(declared)}"
            for art in spec.artifacts_for(kind):
                where = f"{stage}/{item}"
                if art.kind == "table":
                    check_table(art, read_table(plan[stage].path(item, art.name)), where)
                elif art.kind == "arrays":
                    check_arrays(art, load_arrays(plan[stage].path(item, art.name)), where)
                elif art.kind == "json":
                    json.loads(plan[stage].path(item, art.name).read_text())
                checked[art.kind] += 1
    # every kind was seen: 13 tables (one table per scene item of 4 stages, ...), the arrays, ...
    assert all(checked.values()), checked


def test_the_checks_name_the_file_and_the_column():
    poses = STAGES["refine"].artifact("poses")
    ok = pd.DataFrame({f.name: pd.Series(dtype=f.dtype if f.dtype not in ("str", "list") else object)
                       for f in poses.fields})
    check_table(poses, ok, "here")  # an empty table: the columns alone
    with pytest.raises(ArtifactMismatch, match=r"here: poses.parquet has columns \['scene_id'\]"):
        check_table(poses, pd.DataFrame({"scene_id": [1]}), "here")
    times = STAGES["register"].artifact("image_times")
    bad = pd.DataFrame({"scene_id": [1], "im_id": [2], "time_s": ["slow"]})
    with pytest.raises(ArtifactMismatch, match="image_times.parquet column 'time_s' is .+, declared float64"):
        check_table(times, bad, "here")
    pca = STAGES["register"].artifact("pca")
    arrays = {"obj_id": np.zeros(2, np.int64), "mean": np.zeros((2, 3), np.float32),
              "components": np.zeros((2, 3, 3), np.float32), "explained_variance": np.zeros((2, 3), np.float32),
              "informative": np.zeros(2, bool)}
    check_arrays(pca, arrays, "here")
    with pytest.raises(ArtifactMismatch, match="array 'mean' is float64"):
        check_arrays(pca, {**arrays, "mean": np.zeros((2, 3))}, "here")
    errors = STAGES["score"].artifact("errors")  # a prefix field covers vsd_tau_0.05, ...
    cols = [f.name for f in errors.fields[:-1]] + ["vsd_tau_0.05", "vsd_tau_0.10"]
    check_table(errors, pd.DataFrame(columns=cols), "here")


def test_a_stage_writing_an_undeclared_column_publishes_nothing(tmp_path):
    from pipeline.common.config import load_run
    from pipeline.workflow.plan import RunPlan

    plan = RunPlan(load_run({"datasets": "synthtiny"}), cache=tmp_path / "cache")["synthtiny"]
    io = plan.io("register", plan.scene_items[0])
    with pytest.raises(ArtifactMismatch, match="image_times.parquet has columns"):
        with io.publish() as w:
            w.write("image_times", pd.DataFrame({"scene_id": [1], "im_id": [0], "time_s": [0.1], "extra": [1]}))
    assert not io.out.item_dir(plan.scene_items[0]).exists()
    with pytest.raises(KeyError, match="stage register writes no artifact 'candidates'"):
        with io.publish() as w:
            w.write("candidates", pd.DataFrame())

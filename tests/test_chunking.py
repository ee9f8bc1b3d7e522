"""Scene-side jobs over chunks of a scene's images (``images_per_job``): the items, and
results that do not depend on the chunking."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from conftest import current_dir, run_snakemake
from pipeline.common import config as cfg
from pipeline.workflow.plan import RunPlan, image_chunks, parse_item, scene_item
from pipeline.workflow.stage_graph import STAGES


def test_image_chunks_cut_a_scene_into_consecutive_runs():
    assert image_chunks([5, 1, 3, 2, 4], 2) == [[1, 2], [3, 4], [5]]
    assert image_chunks([3, 1], 0) == [[1, 3]] and image_chunks([3, 1], 2) == [[1, 3]]
    assert scene_item(2) == "scene_000002" and scene_item(2, 11) == "scene_000002-011"
    assert parse_item("scene_000002-011") == ("scene", 2) and parse_item("obj_000005") == ("obj", 5)


def test_scene_items_follow_images_per_job_and_leave_the_keys_alone():
    whole = RunPlan(cfg.load_run({"datasets": "synthbench"}))["synthbench"]
    chunked = RunPlan(cfg.load_run({"datasets": "synthbench", "images_per_job": "3"}))["synthbench"]
    assert whole.scene_items == [scene_item(s) for s in range(1, 13)]
    # 12 scenes of 7 images: chunks of 3, 3 and 1 image
    assert len(chunked.scene_items) == 36 and chunked.scene_items[:3] == [f"scene_000001-00{k}" for k in range(3)]
    assert chunked.item_images("scene_000004-002") == {6}
    assert set().union(*(chunked.item_images(i) for i in chunked.items_of_scene(4))) == whole.item_images("scene_000004")
    assert {s: p.key for s, p in chunked.stages.items()} == {s: p.key for s, p in whole.stages.items()}
    # refine's collection reads every chunk of refine, register and scene_features
    assert len(chunked.input_manifests("refine", "all")) == len(whole.input_manifests("refine", "all")) + 3 * 24
    with pytest.raises(ValueError, match="cut into 3 chunks"):
        chunked.item_images("scene_000004")
    with pytest.raises(ValueError, match="no scene item 'scene_000004-003'"):
        chunked.item_images("scene_000004-003")
    with pytest.raises(cfg.ManifestError):
        cfg.load_run({"datasets": "synthbench", "images_per_job": "-1"})


def _estimates(csv_path: Path) -> list[dict]:
    """The results CSV's rows without the time column (timing differs run to run)."""
    with open(csv_path) as f:
        return [{k: v for k, v in row.items() if k != "time"} for row in csv.DictReader(f)]


@pytest.mark.slow
def test_a_scene_cut_into_one_image_jobs_gives_the_same_estimates_and_ar(tiny_run, tmp_path):
    work, _ = tiny_run
    before_csv = next((current_dir(work, "refine") / "all").glob("*.csv"))
    before_scores = json.loads((current_dir(work, "score") / "all" / "scores.json").read_text())
    shutil.copytree(work / "cache", tmp_path / "cache", symlinks=True)
    for stage in ("scene_features", "register", "refine", "score"):  # the model side and the dataset are reused
        shutil.rmtree(current_dir(tmp_path, stage))
    out = run_snakemake(tmp_path, "images_per_job=1")
    assert "localrule scene_features" in out or "rule scene_features" in out
    refine = current_dir(tmp_path, "refine")
    assert sorted(p.name for p in refine.glob("scene_*")) == ["scene_000001-000", "scene_000001-001"]
    for k in range(2):  # each chunk job saw only its image, with the threads its rule declares
        table = pd.read_parquet(refine / f"scene_000001-00{k}" / "candidate_choices.parquet")
        assert set(table.im_id) == {k}
        for stage in ("scene_features", "refine"):
            manifest = json.loads((current_dir(tmp_path, stage) / f"scene_000001-00{k}" / "_manifest.json").read_text())
            assert manifest["threads"] == STAGES[stage].threads
    after_csv = next((refine / "all").glob("*.csv"))
    assert _estimates(after_csv) == _estimates(before_csv) and len(_estimates(after_csv)) > 0
    after_scores = json.loads((current_dir(tmp_path, "score") / "all" / "scores.json").read_text())
    assert after_scores["summary"]["AR"] == before_scores["summary"]["AR"] is not None


def test_a_job_keeps_its_libraries_to_the_threads_it_is_given():
    """What `freeze stage --threads N` does before the stage imports torch (it reads
    OMP_NUM_THREADS when it loads) and after (set directly)."""
    import subprocess
    import sys

    code = ("from pipeline.common.threads import use_threads, job_threads; use_threads(1); import torch; "
            "a = torch.get_num_threads(); use_threads(2); print(a, torch.get_num_threads(), job_threads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parent.parent).stdout.split()
    assert out == ["1", "2", "2"]

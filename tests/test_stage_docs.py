"""The docs' generated blocks (pipeline/workflow/stage_docs.py) are what the stage
declarations give: the stage table of docs/architecture.md."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.workflow import stage_docs
from pipeline.workflow.stage_docs import BLOCKS, MarkerError, between, replace_between, stage_table
from pipeline.workflow.stage_graph import STAGES

ROOT = Path(__file__).resolve().parent.parent
UPDATE = ".venv/bin/python scripts/update_docs.py"


@pytest.mark.parametrize("block", BLOCKS, ids=lambda b: f"{b.path}:{b.name}")
def test_generated_blocks_are_up_to_date(block):
    try:
        now, want = stage_docs.rendered(block, ROOT)
    except MarkerError as e:
        pytest.fail(f"{e}: add the two marker lines around the block, then run {UPDATE}")
    assert between(now, block.name) == between(want, block.name), (
        f"{block.path}: the generated block '{block.name}' differs from what pipeline/workflow/stage_graph.py "
        f"declares: run {UPDATE} (and do not edit the block by hand)")


def test_the_stage_table_has_a_row_per_stage_and_item_kind():
    table = stage_table()
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    assert [r.split(" | ")[0].strip("| `") for r in rows] == [n for n, s in STAGES.items() for _ in s.items]
    refine_all = rows[[n for n, s in STAGES.items() for _ in s.items].index("refine") + 1]
    assert "dataset (item `all`" in refine_all and "`<method>_<dataset>-<split>.csv`" in refine_all
    assert "refine (`all`), dataset" in rows[-1]  # score reads refine's last item kind
    assert "`pipeline.method.estimator.Estimator.refine` (then `refine_by_symmetry`)" in table
    for s in STAGES.values():
        assert f"`{s.algorithm}`" in table


def test_replace_between_markers():
    text = "intro\n<!-- t:start -->\nold\nlines\n<!-- t:end -->\nrest\n"
    new = replace_between(text, "t", "| a |\n")
    assert new == "intro\n<!-- t:start -->\n\n| a |\n\n<!-- t:end -->\nrest\n"
    assert replace_between(new, "t", "| a |") == new  # idempotent
    assert between(new, "t") == "\n| a |\n\n"
    for bad in ("no markers\n", "<!-- t:end -->\n<!-- t:start -->\n",
                "<!-- t:start -->\n<!-- t:end -->\n<!-- t:start -->\n<!-- t:end -->\n"):
        with pytest.raises(MarkerError, match="doc.md: the generated block 't' needs"):
            replace_between(bad, "t", "x", where="doc.md")
    # another block's markers are left alone
    two = text + "<!-- u:start -->\nkeep\n<!-- u:end -->\n"
    assert "keep" in replace_between(two, "t", "x")


def test_update_docs_rewrites_a_stale_copy(tmp_path):
    """scripts/update_docs.py --check fails on a stale block and the script rewrites it,
    leaving the rest of the file as it was."""
    doc = tmp_path / "docs" / "architecture.md"
    doc.parent.mkdir()
    start, end = stage_docs.markers("stage-table")
    doc.write_text(f"# Title\n\nbefore\n\n{start}\n| stale | table |\n{end}\n\nafter\n")
    a_start, a_end = stage_docs.markers("artifact-list")
    (tmp_path / "docs" / "artifacts.md").write_text(f"{a_start}\n{a_end}\n")  # the other generated doc
    script = [sys.executable, str(ROOT / "scripts" / "update_docs.py"), "--root", str(tmp_path)]
    check = subprocess.run(script + ["--check"], capture_output=True, text=True, timeout=120)
    assert check.returncode == 1 and "out of date; run .venv/bin/python scripts/update_docs.py" in check.stdout
    assert subprocess.run(script, capture_output=True, text=True, timeout=120).returncode == 0
    text = doc.read_text()
    assert text.startswith("# Title\n\nbefore\n\n") and text.endswith(f"{end}\n\nafter\n")
    assert between(text, "stage-table").strip() == stage_table().strip()
    assert subprocess.run(script + ["--check"], capture_output=True, text=True, timeout=120).returncode == 0
    doc.write_text("no markers\n")
    broken = subprocess.run(script, capture_output=True, text=True, timeout=120)
    assert broken.returncode == 2 and "needs one line '<!-- stage-table:start -->'" in broken.stderr

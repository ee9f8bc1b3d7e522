"""Atomic publishing and the Zarr/Parquet helpers of the artifact store."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.common.store import (
    load_arrays, load_attrs, publish, read_manifest, read_table, save_arrays, table_metadata, write_table,
)

KW = dict(stage="s", item="obj_000001", key="k" * 40, signature="x-kkkkkkkk", params={"n": 1},
          upstream={"u": "y"}, code_version=1, dataset="d")


def test_publish_writes_manifest_last_and_renames(tmp_path):
    final = tmp_path / "stage" / "sig" / "obj_000001"
    with publish(final, **KW) as w:
        (w.dir / "data.txt").write_text("new")
        assert not final.exists()
        w.summary["n"] = np.int64(3)
    m = read_manifest(final)
    assert m["key"] == "k" * 40 and m["summary"] == {"n": 3} and m["params"] == {"n": 1}
    assert (final / "data.txt").read_text() == "new"
    assert not list(final.parent.glob(".tmp-*"))


def test_failed_publish_keeps_previous_artifact_and_leaves_nothing(tmp_path):
    final = tmp_path / "obj_000001"
    with publish(final, **KW) as w:
        (w.dir / "data.txt").write_text("old")
    before = (final / "_manifest.json").read_text()
    with pytest.raises(RuntimeError):
        with publish(final, **KW) as w:
            (w.dir / "data.txt").write_text("half-written")
            raise RuntimeError("killed")
    assert (final / "data.txt").read_text() == "old"
    assert (final / "_manifest.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obj_000001"]


def test_republish_replaces_the_old_copy(tmp_path):
    final = tmp_path / "obj_000001"
    for text in ("one", "two"):
        with publish(final, **KW) as w:
            (w.dir / "data.txt").write_text(text)
    assert (final / "data.txt").read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obj_000001"]


def test_zarr_round_trip_is_exact_and_chunked_per_item(tmp_path):
    rng = np.random.default_rng(0)
    arrays = {"points": rng.normal(size=(4, 10, 3)).astype(np.float32), "ids": np.arange(4, dtype=np.int64),
              "mask": rng.random((4, 5, 5)) > 0.5}
    save_arrays(tmp_path / "a.zarr", arrays, attrs={"key": "abc", "shape": (1, 2)})
    back = load_arrays(tmp_path / "a.zarr")
    for k, v in arrays.items():
        assert back[k].dtype == v.dtype and np.array_equal(back[k], v)
    assert load_attrs(tmp_path / "a.zarr") == {"key": "abc", "shape": [1, 2]}
    import zarr

    assert zarr.open_group(str(tmp_path / "a.zarr"), mode="r")["points"].chunks == (1, 10, 3)


def test_parquet_keeps_key_in_schema_metadata(tmp_path):
    df = pd.DataFrame({"a": [1, 2], "R": [[1.0] * 9, [2.0] * 9]})
    write_table(df, tmp_path / "t.parquet", metadata={"key": "abc"})
    back = read_table(tmp_path / "t.parquet")
    assert back.a.tolist() == [1, 2] and list(back.R[1]) == [2.0] * 9
    assert table_metadata(tmp_path / "t.parquet") == {"key": "abc"}
    assert json.loads(json.dumps(table_metadata(tmp_path / "t.parquet")))["key"] == "abc"


def test_atomic_file_and_folder_writes_leave_the_old_version_on_failure(tmp_path):
    from pipeline.common.store import atomic_dir, atomic_path, atomic_write_text

    path = tmp_path / "sub" / "table.csv"
    atomic_write_text(path, "one\n")
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert path.read_text() == "one\n" and sorted(p.name for p in path.parent.iterdir()) == ["table.csv"]
    with atomic_path(path) as tmp:
        assert tmp.parent == path.parent and tmp.name.startswith(".")
        tmp.write_text("two\n")
    assert path.read_text() == "two\n"

    folder = tmp_path / "dataset"
    with atomic_dir(folder) as tmp:
        (tmp / "a.txt").write_text("a")
    with pytest.raises(RuntimeError):
        with atomic_dir(folder) as tmp:
            (tmp / "b.txt").write_text("b")
            raise RuntimeError("killed")
    assert sorted(p.name for p in folder.iterdir()) == ["a.txt"]
    with atomic_dir(folder) as tmp:
        (tmp / "c.txt").write_text("c")
    assert sorted(p.name for p in folder.iterdir()) == ["c.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dataset", "sub"]  # no .tmp-/.old- leftovers


def test_there_is_one_atomic_write_in_the_project():
    """Every atomic write goes through pipeline.common.store (atomic_path / atomic_dir / swap_entries)."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    # hidden folders are not the project's code (benchmarks/.peers-venv: the PPF peer's venv)
    offenders = [p.relative_to(root).as_posix() for folder in ("pipeline", "stages", "benchmarks")
                 for p in sorted((root / folder).rglob("*.py"))
                 if not any(part.startswith(".") for part in p.relative_to(root).parts)
                 and p.name != "store.py" and any(s in p.read_text() for s in ("os.replace(", "mkstemp(", ".rename(tmp"))]
    assert offenders == []


def test_swap_entries_puts_everything_back_when_a_move_fails(tmp_path, monkeypatch):
    """swap_entries replaces several entries; a move the file system refuses midway
    leaves the previous entries in place and the new ones in staging."""
    import errno
    import os

    from pipeline.common.store import swap_entries

    out, staging = tmp_path / "out", tmp_path / "out" / ".staging"
    (out / "a").mkdir(parents=True)
    (out / "a" / "old.txt").write_text("old a")
    (out / "b.json").write_text("old b")
    staging.mkdir()
    (staging / "a").mkdir()
    (staging / "a" / "new.txt").write_text("new a")
    (staging / "b.json").write_text("new b")

    real, calls = os.replace, []

    def refusing(src, dst):
        calls.append(src)
        if len(calls) == 3:  # a's two moves done, b's first refused
            raise OSError(errno.ENOSPC, "No space left on device", str(src))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", refusing)
    with pytest.raises(OSError):
        swap_entries(staging, out, ("a", "b.json"), out / ".aside")
    monkeypatch.setattr(os, "replace", real)
    assert (out / "a" / "old.txt").read_text() == "old a" and (out / "b.json").read_text() == "old b"
    assert (staging / "a" / "new.txt").read_text() == "new a" and (staging / "b.json").read_text() == "new b"

    swap_entries(staging, out, ("a", "b.json"), out / ".aside2")
    assert (out / "a" / "new.txt").read_text() == "new a" and (out / "b.json").read_text() == "new b"
    assert (out / ".aside2" / "b.json").read_text() == "old b"

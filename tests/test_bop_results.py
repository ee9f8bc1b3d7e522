"""BOP results CSV."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.formats.bop import BopFormatError, read_results_csv, write_results_csv


def _rows(n=5, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        rows.append(dict(scene_id=1 + i // 3, im_id=i // 2, obj_id=i + 1, score=float(rng.random()),
                         R=q, t=rng.standard_normal(3) * 300, time=0.125 * (i // 2)))
    return rows


def _check(df, rows):
    assert list(df.columns) == ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
    assert len(df) == len(rows)
    for (_, got), want in zip(df.iterrows(), rows):
        for k in ("scene_id", "im_id", "obj_id", "score", "time"):
            assert got[k] == want[k]
        assert got["R"].shape == (3, 3) and got["t"].shape == (3,)
        np.testing.assert_array_equal(got["R"], want["R"])  # exact float round trip
        np.testing.assert_array_equal(got["t"], want["t"])


def test_round_trip_dicts_and_dataframe(tmp_path):
    rows = _rows()
    write_results_csv(tmp_path / "a.csv", rows)
    df = read_results_csv(tmp_path / "a.csv")
    _check(df, rows)
    write_results_csv(tmp_path / "b.csv", df)
    assert (tmp_path / "b.csv").read_text() == (tmp_path / "a.csv").read_text()
    assert (tmp_path / "a.csv").read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"


def test_known_line_format(tmp_path):
    write_results_csv(tmp_path / "k.csv", [dict(scene_id=2, im_id=7, obj_id=5, score=0.5, R=np.eye(3), t=[1, 2.5, 700])])
    assert (tmp_path / "k.csv").read_text() == (
        "scene_id,im_id,obj_id,score,R,t,time\n2,7,5,0.5,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,1.0 2.5 700.0,-1.0\n"
    )


def test_malformed_line_names_line_and_field(tmp_path):
    path = tmp_path / "m.csv"
    write_results_csv(path, _rows(3))
    lines = path.read_text().splitlines()
    parts = lines[2].split(",")
    parts[4] = " ".join(parts[4].split()[:8])  # R with 8 values
    lines[2] = ",".join(parts)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(BopFormatError, match=r"m\.csv: line 3, field 'R': expected 9 values, got 8"):
        read_results_csv(path)
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,0,x,0.5,1 0 0 0 1 0 0 0 1,0 0 0,1\n")
    with pytest.raises(BopFormatError, match="line 2, field 'obj_id'"):
        read_results_csv(path)
    path.write_text("scene,im\n")
    with pytest.raises(BopFormatError, match="line 1: header"):
        read_results_csv(path)


def test_header_without_time_and_inconsistent_times(tmp_path):
    path = tmp_path / "n.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t\n1,0,3,0.5,1 0 0 0 1 0 0 0 1,0 0 10\n")
    df = read_results_csv(path)
    assert df["time"].tolist() == [-1.0] and df["obj_id"].dtype == np.int64
    rows = _rows(2)
    rows[1]["time"] = rows[0]["time"] + 1  # same image (im_id 0), different time
    with pytest.raises(ValueError, match="one time per image"):
        write_results_csv(tmp_path / "x.csv", rows)
    assert not (tmp_path / "x.csv").exists()
    assert isinstance(read_results_csv(path), pd.DataFrame)

"""BOP toolkit JSON layout."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.formats.bop import BopFormatError, load_json, save_bop_json


def test_dict_layout_byte_exact(tmp_path):
    path = tmp_path / "a.json"
    content = {10: [], 2: {"b": 1, "a": [1.5, np.float32(2.0)]}, 9: np.array([1, 2])}
    save_bop_json(path, content)
    expected = '{\n  "2": {"a": [1.5, 2.0], "b": 1},\n  "9": [1, 2],\n  "10": []\n}'
    assert path.read_text() == expected


def test_string_keys_sorted_as_strings(tmp_path):
    path = tmp_path / "cam.json"
    save_bop_json(path, {"width": 640, "cx": 1.25, "depth_scale": 0.1})
    assert path.read_text() == '{\n  "cx": 1.25,\n  "depth_scale": 0.1,\n  "width": 640\n}'


def test_list_and_empty_layout(tmp_path):
    p = tmp_path / "l.json"
    save_bop_json(p, [{"b": 1, "a": 2}, 3])
    assert p.read_text() == '[\n  {"a": 2, "b": 1},\n  3\n]'
    save_bop_json(p, {})
    assert p.read_text() == "{\n}"
    save_bop_json(p, [])
    assert p.read_text() == "[\n]"


def test_atomic_write_leaves_no_temporary(tmp_path):
    save_bop_json(tmp_path / "x.json", {"1": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]
    assert load_json(tmp_path / "x.json") == {"1": 1}


def test_load_json_errors_name_file_and_line(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{\n  "a": 1,\n  "b": \n}')
    with pytest.raises(BopFormatError, match=r"bad\.json: invalid JSON at line 4"):
        load_json(bad)
    with pytest.raises(BopFormatError, match="missing.json: file not found"):
        load_json(tmp_path / "missing.json")

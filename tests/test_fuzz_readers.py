"""Property-based tests of the readers of user-supplied files (issue 14, parts 6 and 8).

Every reader either reads a file or fails with the project's own error type:
``BopFormatError`` (a ValueError whose one-line message starts with the file's path)
for BOP files, ``ManifestError`` (naming the file) for run manifests; never a raw
KeyError, IndexError, TypeError, UnicodeDecodeError, OverflowError, RecursionError or
numpy error. Inputs are random files and random mutations (flipped, inserted and
deleted bytes, truncations, "interesting" tokens such as NaN, huge integers, a BOM) of
valid files written by the package's own writers; where a valid file is read back,
the round trip must be exact.

Hypothesis runs derandomized (the same examples on every run, so CI is reproducible)
and bounded by ``max_examples`` so the whole file takes about half a minute. The
focused regression tests at the end pin the issue's cases and each escape the fuzzing
found.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import struct
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pipeline.formats.bop import (
    BopDataset,
    BopFormatError,
    CameraInfo,
    GtInfo,
    GtPose,
    ModelInfo,
    Target,
    degenerate_mesh_problem,
    load_json,
    load_mesh,
    read_estimates_json,
    read_ply,
    read_results_csv,
    write_camera,
    write_models_info,
    write_ply,
    write_results_csv,
    write_scene_camera,
    write_scene_gt,
    write_scene_gt_info,
    write_targets,
)
from pipeline.formats.bop.detections import (
    detection_from_mask,
    load_detections,
    rle_counts_from_string,
    rle_counts_to_string,
    rle_decode,
    rle_encode,
    save_detections,
)
from pipeline.common.config import MANIFEST_DIR, ManifestError, RunManifest, load_run

# Bounded and reproducible: the same examples on every run (derandomize) and no example
# database (a failure found once must not change later runs), no per-example deadline
# (the first example of a test pays for imports and caches). FREEZE_FUZZ_EXAMPLES=N runs
# N random (not derandomized) examples per test, for a deeper search by hand.
_DEEP = int(os.environ.get("FREEZE_FUZZ_EXAMPLES", "0"))
# A numpy RuntimeWarning in a reader (NaN cast to int, overflow in a cast) is a value
# slipping through unchecked: an error here. load_mesh's warning about uv without a
# TextureFile (it renders grey) is expected.
pytestmark = [pytest.mark.filterwarnings("error::RuntimeWarning"),
              pytest.mark.filterwarnings("ignore:.*texture coordinates without a TextureFile comment")]
FUZZ = settings(max_examples=_DEEP or 75, deadline=None, derandomize=not _DEEP, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FEW = settings(FUZZ, max_examples=_DEEP or 40)

# ---------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    """One folder per module; each example overwrites its test's file. (Hypothesis
    refuses function-scoped fixtures such as ``tmp_path``: they would not be reset
    between the examples of one test.)"""
    return tmp_path_factory.mktemp("fuzz")


def read_or_format_error(call: Callable[[], Any], prefix: Path | str) -> Any:
    """``call()``'s result, or None when it raised ``BopFormatError`` with a proper message:
    one line, starting with a path under ``prefix``. Any other exception fails the test."""
    try:
        return call()
    except BopFormatError as e:
        msg = str(e)
        assert msg.startswith(str(prefix)), msg
        assert "\n" not in msg and "\r" not in msg, msg
        return None


def read_or_manifest_error(path: Path, folder: Path) -> RunManifest | None:
    """``load_run(path=path)``, or None on a ``ManifestError`` naming a file of ``folder``."""
    try:
        return load_run(path=path)
    except ManifestError as e:
        assert str(e).startswith(str(folder)), str(e)
        return None


# Tokens that break naive parsers: non-finite and huge numbers, a 4400-digit integer
# (beyond Python's int-from-str limit), NUL, invalid UTF-8, a BOM, a UTF-16 BOM,
# separators of the formats, Unicode digits and line separators.
TOKENS = [b"", b"0", b"-1", b"1.5", b"nan", b"NaN", b"inf", b"-Infinity", b"1e999", b"-1e-400",
          b"99999999999999999999", b"9" * 4400, b"\x00", b"\xff", b"\xef\xbb\xbf", b"\xff\xfe", b"\xc3(",
          b"\n", b"\r", b",", b" ", b"\t", b'"', b"[", b"]", b"{", b"}", b":", b"null", b"true", b"[" * 1100,
          b"\xe2\x80\xa8", b"\xd9\xa3", b"\xc2\xb2", b"-", b"e", b"."]
# PyYAML's pure-Python parser is quadratic in nesting: 600 levels already overflow it.
YAML_TOKENS = [t for t in TOKENS if not t.startswith(b"[[")] + [b"[" * 600, b"- " * 600]
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@st.composite
def mutated(draw, data: bytes, max_ops: int = 4, tokens: list[bytes] = TOKENS) -> bytes:
    """``data`` after 1..max_ops random edits: bit flips, inserted/deleted/repeated bytes,
    a truncation, an interesting token over some bytes or over one number."""
    buf = bytearray(data)
    for _ in range(draw(st.integers(1, max_ops))):
        op = draw(st.sampled_from(("flip", "insert", "delete", "truncate", "token", "number", "repeat")))
        pos = draw(st.integers(0, len(buf)))
        if op == "flip" and buf:
            buf[min(pos, len(buf) - 1)] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            buf[pos:pos] = draw(st.binary(min_size=1, max_size=4))
        elif op == "delete":
            del buf[pos:pos + draw(st.integers(1, 16))]
        elif op == "truncate":
            del buf[pos:]
        elif op == "token":
            buf[pos:pos + draw(st.integers(0, 4))] = draw(st.sampled_from(tokens))
        elif op == "number":
            spans = [m.span() for m in _NUMBER.finditer(bytes(buf))]
            if spans:
                a, b = draw(st.sampled_from(spans))
                buf[a:b] = draw(st.sampled_from(tokens))
        elif op == "repeat":
            buf[pos:pos] = buf[pos:pos + draw(st.integers(1, 40))]
    return bytes(buf)


SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-(2 ** 70), 2 ** 70), st.floats(), st.text(max_size=6),
    st.sampled_from([0, 1, -1, 2, 1.0, 0.5, -0.0, float("nan"), float("inf"), 10 ** 30, 10 ** 400, "1", "", "nan"]),
)
JSON = st.recursive(SCALARS, lambda kids: st.lists(kids, max_size=5) | st.dictionaries(st.text(max_size=5), kids, max_size=4),
                    max_leaves=16)
FINITE = st.floats(allow_nan=False, allow_infinity=False)
IDS = st.integers(0, 2 ** 31 - 1)


def numbers(n: int) -> st.SearchStrategy:
    """A list of n finite JSON numbers (ints or floats)."""
    return st.lists(st.one_of(FINITE, st.integers(-1000, 1000)), min_size=n, max_size=n)


def records(fields: dict[str, st.SearchStrategy]) -> st.SearchStrategy:
    """An object with these fields: all valid; some missing or replaced by random JSON;
    or random JSON instead of the object."""
    valid = st.fixed_dictionaries(fields)
    mixed = st.fixed_dictionaries({}, optional={k: st.one_of(v, v, JSON) for k, v in fields.items()})
    return st.one_of(valid, mixed, JSON)


def id_keyed(values: st.SearchStrategy) -> st.SearchStrategy:
    """A JSON object keyed by (mostly valid) image/object id strings."""
    keys = st.one_of(IDS.map(str), st.sampled_from(["0", "01", "-1", "1_0", " 2", "x", "", "1.5", "\u0663", "9" * 4400]),
                     st.text(max_size=4))
    return st.one_of(st.dictionaries(keys, values, max_size=4), JSON)


def dump_json(value: Any) -> bytes:
    return json.dumps(value).encode()


# ---------------------------------------------------------------------------- results CSV


@st.composite
def result_rows(draw) -> list[dict]:
    """Rows for write_results_csv; ids span int64, one time per (scene, image)."""
    ids = st.integers(-(2 ** 63), 2 ** 63 - 1) | IDS
    rows, times = [], {}
    for _ in range(draw(st.integers(0, 6))):
        key = (draw(ids), draw(ids))
        if key not in times:
            times[key] = draw(st.one_of(st.just(-1.0), FINITE))
        rows.append({"scene_id": key[0], "im_id": key[1], "obj_id": draw(ids), "score": draw(FINITE),
                     "R": np.array(draw(st.lists(FINITE, min_size=9, max_size=9))).reshape(3, 3),
                     "t": np.array(draw(st.lists(FINITE, min_size=3, max_size=3))), "time": times[key]})
    return rows


def _valid_results_csv(path: Path) -> bytes:
    rng = np.random.default_rng(0)
    rows = [{"scene_id": 1, "im_id": i // 2, "obj_id": i + 1, "score": float(rng.random()),
             "R": np.linalg.qr(rng.standard_normal((3, 3)))[0], "t": rng.standard_normal(3) * 300, "time": 0.5}
            for i in range(3)]
    write_results_csv(path, rows)
    return path.read_bytes()


@FUZZ
@given(rows=result_rows())
def test_results_csv_round_trip(scratch, rows):
    path = scratch / "round.csv"
    write_results_csv(path, rows)
    df = read_results_csv(path)
    assert len(df) == len(rows)
    for (_, got), want in zip(df.iterrows(), rows):
        for k in ("scene_id", "im_id", "obj_id", "score", "time"):
            assert got[k] == want[k]
        assert np.array_equal(got["R"], want["R"]) and np.array_equal(got["t"], want["t"])


@FUZZ
@given(data=st.data())
def test_results_csv_mutations(scratch, data):
    path = scratch / "mut.csv"
    valid = _valid_results_csv(path)
    path.write_bytes(data.draw(mutated(valid)))
    read_or_format_error(lambda: read_results_csv(path), path)


CSV_FIELDS = st.one_of(
    st.sampled_from(["1", "0", "-1", "2.5", "nan", "inf", "1e999", "99999999999999999999", "9" * 4400, "", " ", "1_0",
                     "\u0663", "1 0 0 0 1 0 0 0 1", "1 0 0 0 1 0 0 0 nan", "0 0 0", "1 2", "-1.0"]),
    st.text(alphabet="0123456789 .-+einaf,\t", max_size=12),
)


@FUZZ
@given(header=st.sampled_from(["scene_id,im_id,obj_id,score,R,t,time", "scene_id,im_id,obj_id,score,R,t",
                               " scene_id , im_id,obj_id,score,R,t,time", "scene_id,im_id", ""]),
       lines=st.lists(st.lists(CSV_FIELDS, min_size=5, max_size=8).map(",".join), max_size=4),
       encoding=st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "utf-16-le", "latin-1"]))
def test_results_csv_random_lines(scratch, header, lines, encoding):
    path = scratch / "lines.csv"
    path.write_bytes("\n".join([header] + lines).encode(encoding, errors="replace"))
    df = read_or_format_error(lambda: read_results_csv(path), path)
    if df is not None:  # whatever was read is what BOP expects
        assert df.score.map(math.isfinite).all() and all(r.shape == (3, 3) and np.isfinite(r).all() for r in df.R)


@FEW
@given(raw=st.binary(max_size=300))
def test_results_csv_random_bytes(scratch, raw):
    path = scratch / "bytes.csv"
    path.write_bytes(raw)
    read_or_format_error(lambda: read_results_csv(path), path)


ESTIMATE_FIELDS = {"scene_id": IDS, "im_id": IDS, "obj_id": IDS, "score": FINITE, "cam_R_m2c": numbers(9),
                   "cam_t_m2c": numbers(3), "time": FINITE}


@FUZZ
@given(entries=st.one_of(st.lists(records(ESTIMATE_FIELDS), max_size=4), JSON))
def test_estimates_json_random_entries(scratch, entries):
    path = scratch / "estimates.json"
    path.write_bytes(dump_json(entries))
    df = read_or_format_error(lambda: read_estimates_json(path), path)
    if df is not None:  # read values are the written ones
        for (_, got), want in zip(df.iterrows(), entries):
            assert got.scene_id == want["scene_id"] and got.score == want["score"]
            assert np.array_equal(got.R.reshape(-1), np.asarray(want["cam_R_m2c"], float))
            assert got.time == (-1.0 if want.get("time") is None else want["time"])  # absent or null: -1


# ---------------------------------------------------------------------------- detections and RLE


@FUZZ
@given(mask=hnp.arrays(np.bool_, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=12)))
def test_rle_round_trip(mask):
    rle = rle_encode(mask)
    assert np.array_equal(rle_decode(rle), mask)
    compressed = {"counts": rle_counts_to_string(rle["counts"]), "size": rle["size"]}
    assert rle_counts_from_string(compressed["counts"]) == rle["counts"]
    assert np.array_equal(rle_decode(compressed), mask)


@FUZZ
@given(counts=st.lists(st.integers(0, 2 ** 40), max_size=12))
def test_rle_counts_string_round_trip(counts):
    assert rle_counts_from_string(rle_counts_to_string(counts)) == counts


def _rle_error(e: ValueError) -> None:
    """RLE functions take no file; their errors are plain ValueErrors saying 'RLE'."""
    assert type(e) in (ValueError, BopFormatError), repr(e)
    assert re.match(r"(compressed )?RLE", str(e)), str(e)


@FUZZ
@given(s=st.one_of(st.text(max_size=30), st.text(alphabet=st.characters(min_codepoint=40, max_codepoint=120), max_size=30)))
def test_rle_counts_from_random_string(s):
    try:
        counts = rle_counts_from_string(s)
    except ValueError as e:
        _rle_error(e)
    else:
        assert all(isinstance(c, int) for c in counts)


@FUZZ
@given(rle=st.one_of(
    st.fixed_dictionaries({}, optional={
        "counts": st.one_of(st.lists(st.integers(-2, 2 ** 70) | st.floats(), max_size=6), st.text(max_size=8),
                            st.binary(max_size=8), JSON),
        "size": st.one_of(st.lists(st.integers(-1, 6) | st.sampled_from([1.0, 2.5, 2 ** 40, 10 ** 20, True]),
                                   max_size=3), JSON)}),
    JSON))
def test_rle_decode_random(rle):
    try:
        mask = rle_decode(rle)
    except ValueError as e:
        _rle_error(e)
    else:
        assert mask.dtype == np.bool_ and list(mask.shape) == [int(v) for v in rle["size"]]


def _valid_detections(path: Path) -> bytes:
    rng = np.random.default_rng(1)
    save_detections(path, [detection_from_mask(1, i, i + 1, 0.25 * i, rng.random((5, 7)) < 0.4, time=0.5)
                           for i in range(3)])
    return path.read_bytes()


SEGMENTATIONS = st.one_of(
    hnp.arrays(np.bool_, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=5)).map(rle_encode),
    hnp.arrays(np.bool_, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=5)).map(rle_encode).map(
        lambda r: {"counts": rle_counts_to_string(r["counts"]), "size": r["size"]}),
    records({"counts": st.lists(st.integers(0, 30), max_size=4), "size": st.lists(st.integers(0, 6), min_size=2, max_size=2)}),
)
DETECTION_FIELDS = {"scene_id": IDS, "image_id": IDS, "im_id": IDS, "category_id": IDS, "score": FINITE,
                    "bbox": numbers(4), "segmentation": SEGMENTATIONS, "time": FINITE | st.none()}


@FUZZ
@given(entries=st.one_of(st.lists(records(DETECTION_FIELDS), max_size=4), JSON))
def test_detections_random_entries(scratch, entries):
    path = scratch / "dets.json"
    path.write_bytes(dump_json(entries))
    dets = read_or_format_error(lambda: load_detections(path), path)
    if dets:  # what was read saves and reads back equal, masks included
        again = scratch / "dets_again.json"
        save_detections(again, dets)
        back = load_detections(again)
        assert back == dets
        for a, b in zip(dets, back):
            assert np.array_equal(a.mask(), b.mask())


@FUZZ
@given(data=st.data())
def test_detections_mutations(scratch, data):
    path = scratch / "dets_mut.json"
    valid = _valid_detections(path)
    path.write_bytes(data.draw(mutated(valid)))
    dets = read_or_format_error(lambda: load_detections(path), path)
    for d in dets or []:
        d.mask()  # every mask that was accepted decodes


# ---------------------------------------------------------------------------- PLY


def _f32(shape: tuple[int, ...]) -> st.SearchStrategy:
    return hnp.arrays(np.float32, shape, elements=st.floats(width=32, allow_nan=False, allow_infinity=False))


@st.composite
def meshes(draw) -> dict:
    """write_ply arguments: V vertices, F faces in range, optional normals/colours/uv."""
    n_v = draw(st.integers(0, 8))
    n_f = draw(st.integers(0, 6)) if n_v else 0
    out = {"vertices": draw(_f32((n_v, 3))),
           "faces": draw(hnp.arrays(np.int64, (n_f, 3), elements=st.integers(0, max(n_v - 1, 0))))}
    if draw(st.booleans()):
        out["normals"] = draw(_f32((n_v, 3)))
    if draw(st.booleans()):
        out["colors"] = draw(hnp.arrays(np.uint8, (n_v, 3)))
    if draw(st.booleans()):
        out["texture_uv"] = draw(_f32((n_v, 2)))
    return out


@FUZZ
@given(mesh=meshes(), binary=st.booleans())
def test_ply_round_trip(scratch, mesh, binary):
    path = scratch / "round.ply"
    write_ply(path, **mesh, binary=binary)
    ply = read_ply(path)
    assert np.array_equal(ply.vertices, mesh["vertices"]) and np.array_equal(ply.faces, mesh["faces"])
    for name, got in (("normals", ply.normals), ("colors", ply.colors), ("texture_uv", ply.texture_uv)):
        assert (got is None) == (name not in mesh)
        if got is not None:
            assert got.dtype == mesh[name].dtype and np.array_equal(got, mesh[name])
    if len(mesh["faces"]) and degenerate_mesh_problem(mesh["vertices"], mesh["faces"]):
        with pytest.raises(BopFormatError, match="spans no"):  # a point, a line, or triangles without area
            load_mesh(path)
    elif len(mesh["faces"]):
        assert np.array_equal(load_mesh(path).vertices, mesh["vertices"].astype(np.float64))
    else:
        with pytest.raises(BopFormatError, match="has no faces"):
            load_mesh(path)


def _valid_ply(path: Path, binary: bool) -> bytes:
    rng = np.random.default_rng(2)
    v = (rng.standard_normal((6, 3)) * 30).astype(np.float32)
    write_ply(path, v, [[0, 1, 2], [2, 3, 4], [4, 5, 0]], normals=v, colors=rng.integers(0, 256, (6, 3)), binary=binary)
    return path.read_bytes()


def _read_both(path: Path) -> None:
    """read_ply and load_mesh either read the file or raise BopFormatError naming it."""
    ply = read_or_format_error(lambda: read_ply(path), path)
    if ply is not None:
        assert ply.vertices.ndim == 2 and ply.vertices.shape[1] == 3 and np.isfinite(ply.vertices).all()
        assert ply.faces.ndim == 2 and ply.faces.shape[1] == 3
        assert ply.faces.size == 0 or (ply.faces.min() >= 0 and ply.faces.max() < len(ply.vertices))
    read_or_format_error(lambda: load_mesh(path), path)


@FUZZ
@given(data=st.data(), binary=st.booleans())
def test_ply_mutations(scratch, data, binary):
    path = scratch / "mut.ply"
    valid = _valid_ply(path, binary)
    path.write_bytes(data.draw(mutated(valid)))
    _read_both(path)


PLY_TYPES = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8", "int16", "uint16",
             "int32", "uint32", "float32", "float64", "int64", "bogus"]
PLY_NAMES = ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha", "texture_u", "texture_v", "vertex_indices",
             "vertex_index", "quality", "x#n"]
ASCII_TOKENS = ["0", "1", "2", "3", "4", "-1", "0.5", "3.5", "nan", "inf", "-inf", "1e999", "255", "256", "1e38", "1e39",
                "99999999999999999999", "abc", "\u0663"]


@st.composite
def ply_files(draw) -> bytes:
    """A PLY with a random header (formats, element counts, scalar and list properties of
    any type, good and bad) and a random body fitting its format more or less."""
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "binary", ""]))
    lines = ["ply", f"format {fmt} 1.0"]
    if draw(st.booleans()):
        lines.append("comment TextureFile " + draw(st.sampled_from(["tex.png", "", "missing.png", "bad.png"])))
    types = st.sampled_from(PLY_TYPES)
    for i in range(draw(st.integers(0, 3))):
        name = draw(st.sampled_from(["vertex", "face", "material"]))
        count = draw(st.one_of(st.integers(0, 5).map(str), st.sampled_from(["99999999999999999999", "\u00b2", "-1", "x"])))
        lines.append(f"element {name} {count}")
        if i == 0 and draw(st.booleans()):
            xyz = draw(st.sampled_from(["float", "double", "uchar", "int"]))
            lines += [f"property {xyz} {a}" for a in "xyz"]
        for _ in range(draw(st.integers(0, 4))):
            prop = draw(st.sampled_from(PLY_NAMES))
            if draw(st.integers(0, 2)) == 0:
                lines.append(f"property list {draw(types)} {draw(types)} {prop}")
            else:
                lines.append(f"property {draw(types)} {prop}")
    if draw(st.integers(0, 5)) == 0:
        lines.append(draw(st.sampled_from(["obj_info x", "bogus", "property float z", "element", "property list uchar"])))
    head = ("\n".join(lines) + "\nend_header\n").encode()
    if fmt == "ascii":
        body = " ".join(draw(st.lists(st.sampled_from(ASCII_TOKENS), max_size=60))).encode()
    else:  # small byte values keep list lengths short, so lists get read past their count
        body = draw(st.one_of(st.binary(max_size=200), st.lists(st.integers(0, 4), max_size=200).map(bytes)))
    return head + body


@FUZZ
@given(raw=ply_files())
def test_ply_random_headers(scratch, raw):
    path = scratch / "random.ply"
    if not (scratch / "tex.png").exists():  # the texture images the headers may name
        from PIL import Image

        Image.new("RGB", (2, 2)).save(scratch / "tex.png")
        (scratch / "bad.png").write_bytes(b"not an image")
    path.write_bytes(raw)
    _read_both(path)


# ---------------------------------------------------------------------------- BOP dataset JSON


def _rot(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return q


@pytest.fixture(scope="module")
def bop_tree(tmp_path_factory) -> tuple[Path, dict[str, bytes]]:
    """(root, {file name: valid bytes}) of a one-scene dataset without images (the reads
    under test use only the JSON files)."""
    root = tmp_path_factory.mktemp("bop") / "tiny"
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    write_camera(root, {"K": K, "width": 640, "height": 480, "depth_scale": 0.1})
    write_models_info(root / "models" / "models_info.json",
                      {1: ModelInfo(50.0, np.array([-1.0, -2, -3]), np.array([2.0, 4, 6]), [np.eye(4)],
                                    [{"axis": np.array([0.0, 0, 1]), "offset": np.zeros(3)}]),
                       2: ModelInfo(30.0, np.zeros(3), np.ones(3))})
    scene = root / "test" / "000001"
    write_scene_camera(scene / "scene_camera.json", {0: CameraInfo(K, 0.1, 640, 480, _rot(0), np.ones(3)),
                                                     3: CameraInfo(K, 1.0, 640, 480)})
    write_scene_gt(scene / "scene_gt.json", {0: [GtPose(1, _rot(1), np.array([1.0, 2, 700]))], 3: []})
    write_scene_gt_info(scene / "scene_gt_info.json", {0: [GtInfo((1, 2, 3, 4), (1, 2, 3, 3), 12, 11, 9, 0.75)], 3: []})
    write_targets(root / "test_targets_bop19.json", [Target(1, 0, 1, 1)])
    return root, {name: (root / name).read_bytes() for name in FILES}


FILES = {
    "camera.json": "camera", "models/models_info.json": "models_info", "test/000001/scene_camera.json": "scene_camera",
    "test/000001/scene_gt.json": "scene_gt", "test/000001/scene_gt_info.json": "scene_gt_info",
    "test_targets_bop19.json": "targets",
}
READERS: dict[str, Callable[[BopDataset], Any]] = {
    "camera": lambda ds: (ds.camera(), ds.scene_camera(1)),
    "models_info": lambda ds: ds.models_info(),
    "scene_camera": lambda ds: ds.scene_camera(1),
    "scene_gt": lambda ds: ds.scene_gt(1),
    "scene_gt_info": lambda ds: ds.scene_gt_info(1),
    "targets": lambda ds: (ds.targets(), ds.image_targets()),
}


def _read_dataset_file(root: Path, valid: dict[str, bytes], name: str, raw: bytes) -> Any:
    """Restore every file, write ``raw`` as ``name``, read it through a fresh BopDataset."""
    for n, content in valid.items():
        (root / n).write_bytes(content)
    (root / name).write_bytes(raw)
    return read_or_format_error(lambda: READERS[FILES[name]](BopDataset(root)), root)


CAM_FIELDS = {"cam_K": numbers(9), "depth_scale": FINITE, "cam_R_w2c": numbers(9), "cam_t_w2c": numbers(3)}
GT_FIELDS = {"obj_id": IDS | st.just(1.0), "cam_R_m2c": numbers(9), "cam_t_m2c": numbers(3)}
GT_INFO_FIELDS = {"bbox_obj": numbers(4), "bbox_visib": st.lists(st.integers(-5, 5), min_size=4, max_size=4),
                  "px_count_all": IDS, "px_count_valid": IDS, "px_count_visib": IDS, "visib_fract": FINITE}
INFO_FIELDS = {"diameter": FINITE, **{f"{k}_{a}": FINITE for k in ("min", "size") for a in "xyz"},
               "symmetries_discrete": st.lists(numbers(16) | JSON, max_size=2) | JSON,
               "symmetries_continuous": st.lists(records({"axis": numbers(3), "offset": numbers(3)}), max_size=2) | JSON}
CONTENTS = {
    "camera.json": records({"fx": FINITE, "fy": FINITE, "cx": FINITE, "cy": FINITE, "width": IDS | st.just(640.0),
                            "height": IDS, "depth_scale": FINITE}),
    "test/000001/scene_camera.json": id_keyed(records(CAM_FIELDS)),
    "test/000001/scene_gt.json": id_keyed(st.lists(records(GT_FIELDS), max_size=3) | JSON),
    "test/000001/scene_gt_info.json": id_keyed(st.lists(records(GT_INFO_FIELDS), max_size=3) | JSON),
    "models/models_info.json": id_keyed(records(INFO_FIELDS)),
    "test_targets_bop19.json": st.lists(records({"scene_id": IDS, "im_id": IDS, "obj_id": IDS, "inst_count": IDS}),
                                        max_size=3) | JSON,
}


@FUZZ
@given(data=st.data(), name=st.sampled_from(sorted(FILES)))
def test_dataset_json_random_content(bop_tree, data, name):
    root, valid = bop_tree
    _read_dataset_file(root, valid, name, dump_json(data.draw(CONTENTS[name])))


@FUZZ
@given(data=st.data(), name=st.sampled_from(sorted(FILES)))
def test_dataset_json_mutations(bop_tree, data, name):
    root, valid = bop_tree
    _read_dataset_file(root, valid, name, data.draw(mutated(valid[name])))


@FEW
@given(data=st.data(), n_images=st.integers(0, 3))
def test_dataset_json_round_trip(scratch, data, n_images):
    root = scratch / "rt"
    shutil.rmtree(root, ignore_errors=True)
    draw = data.draw
    write_camera(root, {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 4, "height": 3})
    finite = st.floats(allow_nan=False, allow_infinity=False)
    vec = lambda n: hnp.arrays(np.float64, (n,), elements=finite)  # noqa: E731
    im_ids = draw(st.lists(IDS, min_size=n_images, max_size=n_images, unique=True))
    cams = {i: CameraInfo(draw(vec(9)).reshape(3, 3), draw(finite), 4, 3,
                          *((draw(vec(9)).reshape(3, 3), draw(vec(3))) if draw(st.booleans()) else (None, None)))
            for i in im_ids}
    gt = {i: [GtPose(draw(IDS), draw(vec(9)).reshape(3, 3), draw(vec(3))) for _ in range(draw(st.integers(0, 2)))]
          for i in im_ids}
    box = st.tuples(*[st.integers(-(2 ** 31), 2 ** 31)] * 4)
    info = {i: [GtInfo(draw(box), draw(box), draw(IDS), draw(IDS), draw(IDS), draw(finite)) for _ in gt[i]] for i in im_ids}
    models = {o: ModelInfo(draw(finite), draw(vec(3)), draw(vec(3)), [draw(vec(16)).reshape(4, 4)],
                           [{"axis": draw(vec(3)), "offset": draw(vec(3))}]) for o in draw(st.sets(IDS, max_size=2))}
    scene = root / "test" / "000002"
    write_scene_camera(scene / "scene_camera.json", cams)
    write_scene_gt(scene / "scene_gt.json", gt)
    write_scene_gt_info(scene / "scene_gt_info.json", info)
    write_models_info(root / "models" / "models_info.json", models)
    ds = BopDataset(root)

    def same(a: Any, b: Any) -> bool:
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return a is None and b is None or np.array_equal(a, b)
        return a == b

    got = ds.scene_camera(2, check=False)  # random values: the round trip, not the camera rule (intrinsics_problem)
    assert list(got) == sorted(cams)
    for i, c in cams.items():
        assert all(same(getattr(got[i], k), getattr(c, k)) for k in ("K", "depth_scale", "width", "height", "R_w2c", "t_w2c"))
    for i, poses in gt.items():
        assert [(p.obj_id, p.R.tolist(), p.t.tolist()) for p in ds.scene_gt(2)[i]] == \
               [(p.obj_id, p.R.tolist(), p.t.tolist()) for p in poses]
    assert ds.scene_gt_info(2) == {i: info[i] for i in sorted(info)}
    for o, m in ds.models_info().items():
        assert m.diameter == models[o].diameter and np.array_equal(m.min_xyz, models[o].min_xyz)
        assert np.array_equal(m.symmetries_discrete[0], models[o].symmetries_discrete[0])


@FUZZ
@given(value=JSON, bom=st.booleans())
def test_load_json_round_trip(scratch, value, bom):
    path = scratch / "value.json"
    text = json.dumps(value)
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    assert json.dumps(load_json(path)) == text  # compare dumps: NaN != NaN


@FEW
@given(raw=st.one_of(st.binary(max_size=200), st.sampled_from(TOKENS)))
def test_load_json_random_bytes(scratch, raw):
    path = scratch / "bytes.json"
    path.write_bytes(raw)
    read_or_format_error(lambda: load_json(path), path)


# ---------------------------------------------------------------------------- run manifests

STAGE_KEYS = {"render_templates": ["n_views", "image_size"], "register": ["pca_dim", "signal_none", "signal_full"],
              "refine": ["icp", "select_by"], "score": ["n_workers"], "bogus": ["x"]}
MANIFEST_FIELDS = {
    "method": st.sampled_from(["freeze", "Bad_Name", ""]) | JSON,
    "datasets": st.lists(st.sampled_from(["synthmini", "x.yaml"]), max_size=2) | JSON,
    "geometric_encoder": st.sampled_from(["fpfh", "none"]) | JSON,
    "visual_encoder": st.sampled_from(["colortex", "none"]) | JSON,
    "bop_root": st.sampled_from([None, "", "bop", "~/bop", "a\x00b"]) | JSON,
    "priors": st.lists(st.text(max_size=4), max_size=2) | JSON,
    "weights_dir": st.none() | JSON,
    "extends": st.sampled_from(["base.yaml", "run.yaml", ".", "", "missing.yaml", "sub/x.yaml", "a\x00b"]) | JSON,
    "stages": st.dictionaries(st.sampled_from(sorted(STAGE_KEYS)), st.one_of(
        st.fixed_dictionaries({}, optional={k: JSON | st.integers(0, 100) for ks in STAGE_KEYS.values() for k in ks}),
        JSON), max_size=3) | JSON,
}


@pytest.fixture(scope="module")
def manifests(tmp_path_factory) -> Path:
    """A folder with a valid ``base.yaml`` (the default run) to extend."""
    d = tmp_path_factory.mktemp("runs")
    (d / "base.yaml").write_text((MANIFEST_DIR / "runs" / "default.yaml").read_text())
    return d


@FUZZ
@given(data=st.one_of(records(MANIFEST_FIELDS), JSON))
def test_run_manifest_random_yaml(manifests, data):
    path = manifests / "run.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True))
    read_or_manifest_error(path, manifests)


@FUZZ
@given(data=st.data())
def test_run_manifest_mutations(manifests, data):
    path = manifests / "run.yaml"
    raw = (MANIFEST_DIR / "runs" / "default.yaml").read_bytes()
    if data.draw(st.booleans()):
        raw = b"extends: base.yaml\n" + raw
    path.write_bytes(data.draw(mutated(raw, tokens=YAML_TOKENS)))
    read_or_manifest_error(path, manifests)


@FEW
@given(raw=st.one_of(st.binary(max_size=100), st.text(alphabet="{}[]:,-#&*!|>'\"%@` \n\tab1.?", max_size=40).map(str.encode),
                     st.sampled_from([b"[" * 600, b"- " * 600, b"a:\n " * 300, b"\xff\xfe", b"\xef\xbb\xbfmethod: x"])))
def test_run_manifest_random_text(manifests, raw):
    path = manifests / "run.yaml"
    path.write_bytes(raw)
    read_or_manifest_error(path, manifests)


# ---------------------------------------------------------------------------- the cases


def test_score_utf16_and_binary_results_csv_name_file_and_encoding(tmp_path):
    from typer.testing import CliRunner

    from pipeline.commands.cli import app

    valid = _valid_results_csv(tmp_path / "valid.csv").decode()
    utf16 = tmp_path / "utf16.csv"
    utf16.write_bytes(valid.encode("utf-16"))
    binary = tmp_path / "binary.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    for path in (utf16, binary):
        with pytest.raises(BopFormatError) as e:
            read_results_csv(path)
        assert str(e.value).startswith(f"{path}: not UTF-8 text") and "\n" not in str(e.value)
    assert "UTF-16" in str(pytest.raises(BopFormatError, read_results_csv, utf16).value)
    # `freeze score` prints that line and exits 1 (no traceback)
    result = CliRunner().invoke(app, ["score", str(utf16), "--dataset-root", str(tmp_path)])
    out = " ".join(result.output.split())  # rich wraps long lines
    assert result.exit_code == 1 and "Traceback" not in out, out
    assert "utf16.csv" in out and "not UTF-8 text" in out


def test_utf8_bom_accepted_in_csv_and_json(tmp_path):
    valid = _valid_results_csv(tmp_path / "valid.csv")
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + valid)
    a, b = read_results_csv(tmp_path / "valid.csv"), read_results_csv(bom)
    assert len(b) == 3 and (a.score == b.score).all() and all(np.array_equal(x, y) for x, y in zip(a.R, b.R))
    dets = tmp_path / "dets.json"
    raw = _valid_detections(dets)
    dets.write_bytes(b"\xef\xbb\xbf" + raw)
    assert len(load_detections(dets)) == 3
    (tmp_path / "x.json").write_bytes(b"\xef\xbb\xbf" + b'{"1": [1.5]}')
    assert load_json(tmp_path / "x.json") == {"1": [1.5]}


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_ply_non_finite_vertex_names_file_and_vertex(tmp_path, binary, bad):
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], np.float32)
    v[2, 1] = bad
    path = tmp_path / "nan.ply"
    write_ply(path, v, [[0, 1, 2], [0, 2, 3]], binary=binary)
    for reader in (read_ply, load_mesh):
        with pytest.raises(BopFormatError) as e:
            reader(path)
        assert str(e.value).startswith(f"{path}: vertex 2 has a non-finite coordinate")


def test_ply_without_faces_is_no_mesh(tmp_path):
    path = tmp_path / "cloud.ply"
    write_ply(path, np.eye(3, dtype=np.float32), np.zeros((0, 3), int))
    assert len(read_ply(path).vertices) == 3  # a point cloud is a valid PLY...
    with pytest.raises(BopFormatError) as e:
        load_mesh(path)  # ...but not a surface mesh
    assert str(e.value) == f"{path}: has no faces; a surface mesh is needed"


# ---------------------------------------------------------------------------- escapes the fuzzing found

_PLY_HEAD = "ply\nformat {fmt} 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
_TRI = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)


@pytest.mark.parametrize("raw, reason", [
    # element count in Unicode digits: int() raised ValueError
    (b"ply\nformat ascii 1.0\nelement vertex \xc2\xb2\nend_header\n", "malformed element line"),
    # the same property twice: numpy raised ValueError (field occurs more than once)
    ((_PLY_HEAD + "property float x\nend_header\n").format(fmt="binary_little_endian").encode() + _TRI,
     "property 'x' repeated"),
    # a float list count: numpy NaN -> int raised ValueError
    ((_PLY_HEAD + "element face 1\nproperty list float int vertex_indices\nend_header\n").format(
        fmt="binary_little_endian").encode() + _TRI + struct.pack("<f3i", float("nan"), 0, 1, 2),
     "list count type must be an integer type"),
    # a negative binary list count: numpy raised ValueError (negative dimension)
    ((_PLY_HEAD + "element face 1\nproperty list char int vertex_indices\nend_header\n").format(
        fmt="binary_little_endian").encode() + _TRI + struct.pack("<b3i", -1, 0, 1, 2), "negative list length"),
    # an ascii list length 'inf': int(float('inf')) raised OverflowError
    (_PLY_HEAD.format(fmt="ascii").encode() + b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"
     b"0 0 0 1 0 0 0 1 0\ninf 0 1 2\n", "list length 'inf' is not a non-negative integer"),
    # an element with no properties: numpy raised ValueError (itemsize 0 / reshape)
    ((_PLY_HEAD + "element material 5\nend_header\n").format(fmt="binary_little_endian").encode() + _TRI, None),
    # x as a list property: vertices came out (V, 3, n) and trimesh failed later
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nproperty float y\nproperty float z\n"
     b"end_header\n1 0 0 0\n", "property 'x' is a list; a number is needed"),
    # float face indices: NaN cast to int64 silently
    ((_PLY_HEAD + "element face 1\nproperty list uchar float vertex_indices\nend_header\n").format(
        fmt="binary_little_endian").encode() + _TRI + struct.pack("<B3f", 3, 0, 1, float("nan")),
     "face indices must be integers"),
    # faces of zero vertices (fixed width): silently dropped
    ((_PLY_HEAD + "element face 2\nproperty list uchar int vertex_indices\nend_header\n").format(
        fmt="binary_little_endian").encode() + _TRI + b"\x00\x00", "a face has 0 vertices"),
    # an ascii uchar colour of 300: wrapped to 44 silently
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
     b"property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n0 0 0 300 0 0\n",
     "value 300 does not fit property 'red' (uchar)"),
    # a double coordinate beyond float32: became inf with a RuntimeWarning
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\nproperty double z\n"
     b"end_header\n1e300 0 0\n", "vertex 0 has a coordinate beyond the float32 range"),
])
def test_ply_escapes(tmp_path, raw, reason):
    path = tmp_path / "bad.ply"
    path.write_bytes(raw)
    if reason is None:
        assert len(read_ply(path).vertices) == 3
        return
    with pytest.raises(BopFormatError) as e:
        read_ply(path)
    assert str(e.value).startswith(str(path)) and reason in str(e.value), str(e.value)


def test_ply_bad_texture_image_names_file(tmp_path):
    path = tmp_path / "tex.ply"
    write_ply(path, np.eye(3, dtype=np.float32), [[0, 1, 2]], texture_uv=np.zeros((3, 2), np.float32),
              texture_file="tex.png")
    (tmp_path / "tex.png").write_bytes(b"not an image")  # PIL raised UnidentifiedImageError
    with pytest.raises(BopFormatError, match=r"tex\.ply: texture file 'tex\.png' cannot be read"):
        load_mesh(path)


_CSV = "scene_id,im_id,obj_id,score,R,t,time\n"
_R = "1 0 0 0 1 0 0 0 1"


@pytest.mark.parametrize("line, reason", [
    (f"99999999999999999999,0,1,0.5,{_R},0 0 0,1", "field 'scene_id': 99999999999999999999 does not fit in int64"),
    (f"1,0,{'9' * 4400},0.5,{_R},0 0 0,1", "field 'obj_id'"),  # message shortened to one reasonable line
    (f"1,0,1,nan,{_R},0 0 0,1", "field 'score': non-finite value"),
    (f"1,0,1,0.5,{_R},0 0 0,inf", "field 'time': non-finite value"),
])
def test_results_csv_escapes(tmp_path, line, reason):
    path = tmp_path / "r.csv"
    path.write_text(_CSV + line + "\n")
    with pytest.raises(BopFormatError) as e:
        read_results_csv(path)
    assert str(e.value).startswith(f"{path}: line 2") and reason in str(e.value) and len(str(e.value)) < 400


@pytest.mark.parametrize("entry, reason", [
    ({"scene_id": None}, "field 'scene_id': expected an integer"),  # int(None): TypeError
    ({"obj_id": float("inf")}, "field 'obj_id': expected an integer"),  # int(inf): OverflowError
    ({"score": [1]}, "field 'score': expected a finite number"),  # float([1]): TypeError
    ({"time": "soon"}, "field 'time': expected a finite number"),  # float('soon'): ValueError
    ({"cam_t_m2c": [10 ** 400, 0, 0]}, "field 'cam_t_m2c': expected 3 finite numbers"),  # OverflowError
    ({"cam_R_m2c": [float("nan")] * 9}, "field 'cam_R_m2c': expected 9 finite numbers"),  # accepted NaN
    ({"scene_id": 2 ** 63}, "field 'scene_id': 9223372036854775808 does not fit in int64"),  # astype OverflowError
])
def test_estimates_json_escapes(tmp_path, entry, reason):
    good = {"scene_id": 1, "im_id": 2, "obj_id": 3, "score": 0.5, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1],
            "cam_t_m2c": [0, 0, 1]}
    path = tmp_path / "e.json"
    path.write_text(json.dumps([good, {**good, **entry}]))
    with pytest.raises(BopFormatError) as e:
        read_estimates_json(path)
    assert str(e.value).startswith(f"{path}: entry 1, ") and reason in str(e.value), str(e.value)


@pytest.mark.parametrize("raw, reason", [
    (b"\xff\xfe[\x00]\x00", "not UTF-8 text"),  # UnicodeDecodeError
    (b"[" * 1100, "nested too deeply"),  # RecursionError
    (b"[" + b"9" * 4400 + b"]", "invalid JSON"),  # ValueError: exceeds the limit for integer string conversion
])
def test_load_json_escapes(tmp_path, raw, reason):
    path = tmp_path / "x.json"
    path.write_bytes(raw)
    with pytest.raises(BopFormatError) as e:
        load_json(path)
    assert str(e.value).startswith(str(path)) and reason in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(BopFormatError, match="is a directory"):
        load_json(tmp_path)  # IsADirectoryError


@pytest.mark.parametrize("rle, reason", [
    ({"counts": [10 ** 30], "size": [10 ** 15, 10 ** 15]}, "RLE size"),  # np.repeat OverflowError
    ({"counts": b"\xff", "size": [1, 1]}, "RLE counts"),  # UnicodeDecodeError
])
def test_rle_escapes(rle, reason):
    with pytest.raises(ValueError, match=reason):
        rle_decode(rle)


@pytest.mark.parametrize("name, content, reason", [
    ("test/000001/scene_camera.json", [], "expected an object keyed by im_id"),  # list.items(): AttributeError
    ("test/000001/scene_gt.json", {"0": 5}, "entry '0': expected a list of instances"),  # iter(int): TypeError
    ("test/000001/scene_gt_info.json", {"0": [{"bbox_obj": [1, 2, 3, 4.5]}]}, "field 'bbox_obj': expected 4 integers"),
    ("test/000001/scene_camera.json", {"0": {"cam_K": [10 ** 400] * 9, "depth_scale": 1}},
     "field 'cam_K': expected 9 finite numbers"),  # np.asarray OverflowError
    ("test/000001/scene_camera.json", {"0": {"cam_K": ["1"] * 9, "depth_scale": 1}},
     "field 'cam_K': expected 9 finite numbers"),  # strings were parsed as numbers
    ("test/000001/scene_camera.json", {"0": {"cam_K": [1] * 9, "depth_scale": 1}, "00": {}},
     "key '00' repeats id 0"),  # silently overwritten
    ("camera.json", [1, 2], "expected an object"),  # dict([1, 2]): TypeError
    ("camera.json", {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": "wide", "height": 4},
     "field 'width': expected an integer"),  # int('wide'): ValueError
    ("models/models_info.json", {"1": {"diameter": 1, "min_x": 0, "min_y": 0, "min_z": 0, "size_x": 1, "size_y": 1,
                                       "size_z": 1, "symmetries_discrete": 3}},
     "field 'symmetries_discrete': expected a list"),  # iter(int): TypeError
    ("test/000001/scene_gt.json", {"x\ny": []}, "key 'x\\ny' is not an integer id"),  # message was two lines
])
def test_dataset_escapes(bop_tree, name, content, reason):
    root, valid = bop_tree
    for n, c in valid.items():
        (root / n).write_bytes(c)
    (root / name).write_text(json.dumps(content))
    with pytest.raises(BopFormatError) as e:
        READERS[FILES[name]](BopDataset(root))
    msg = str(e.value)
    assert msg.startswith(str(root / name)) and reason in msg and "\n" not in msg, msg


@pytest.mark.parametrize("text, reason", [
    (b"datasets: [a]\nbop_root: 5\n", "field 'bop_root': expected a folder path"),  # Path(5): TypeError
    (b"datasets: [a]\nbop_root: 2001-12-14\n", "field 'bop_root': expected a folder path"),  # Path(date)
    (b"datasets: [a]\nextends: .\n", "is a directory"),  # IsADirectoryError
    (b"\xff\xfe", "not UTF-8 text"),  # UnicodeDecodeError
    (b"[" * 600, "nested too deeply"),  # RecursionError
    (b"datasets: [a]\nstages: {score: {n_workers: " + b"9" * 4400 + b"}}\n", "not valid YAML"),  # int() limit
])
def test_run_manifest_escapes(tmp_path, text, reason):
    path = tmp_path / "run.yaml"
    path.write_bytes(text)
    with pytest.raises(ManifestError) as e:
        load_run(path=path)
    assert str(e.value).startswith(str(tmp_path)) and reason in str(e.value), str(e.value)

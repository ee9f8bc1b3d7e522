"""PLY reading and writing in the BOP layout."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from pipeline.formats.bop import BopFormatError, load_mesh, read_ply, write_ply


def _mesh(rng, n_v=50, n_f=80):
    v = (rng.standard_normal((n_v, 3)) * 37.3).astype(np.float32)
    f = rng.integers(0, n_v, (n_f, 3))
    n = rng.standard_normal((n_v, 3)).astype(np.float32)
    c = rng.integers(0, 256, (n_v, 3)).astype(np.uint8)
    uv = rng.random((n_v, 2)).astype(np.float32)
    return v, f, n, c, uv


@pytest.mark.parametrize("with_n, with_c, with_uv, binary", list(itertools.product([False, True], repeat=4)))
def test_round_trip_exact(tmp_path, with_n, with_c, with_uv, binary):
    v, f, n, c, uv = _mesh(np.random.default_rng(3))
    path = tmp_path / "m.ply"
    tex = "tex.png" if with_uv else None
    write_ply(path, v, f, n if with_n else None, c if with_c else None, uv if with_uv else None, tex, binary=binary)
    p = read_ply(path)
    assert p.vertices.dtype == np.float32 and p.faces.dtype == np.int64
    np.testing.assert_array_equal(p.vertices, v)
    np.testing.assert_array_equal(p.faces, f)
    for got, want, flag in ((p.normals, n, with_n), (p.colors, c, with_c), (p.texture_uv, uv, with_uv)):
        if flag:
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
        else:
            assert got is None
    assert p.texture_file == tex


def test_binary_header_and_size_are_bop_layout(tmp_path):
    v, f, n, c, uv = _mesh(np.random.default_rng(0), n_v=4, n_f=2)
    path = tmp_path / "m.ply"
    write_ply(path, v, f, n, c, uv, "obj_000001.png")
    raw = path.read_bytes()
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment TextureFile obj_000001.png\nelement vertex 4\n"
        "property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n"
        "property float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property float texture_u\nproperty float texture_v\nelement face 2\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode()
    assert raw.startswith(header)
    # 4 vertices x (8 floats + 3 bytes) + 2 faces x (1 byte + 3 int32)
    assert len(raw) == len(header) + 4 * (8 * 4 + 3) + 2 * (1 + 12)


ASCII_PLY = """ply
format ascii 1.0
comment VCGLIB generated
comment TextureFile ignored_without_uv.png
element vertex 4
property float x
property float y
property float z
property uchar red
property uchar green
property uchar blue
property uchar alpha
element face 2
property list uchar int vertex_indices
element material 1
property uchar ambient_red
end_header
0 0 0 255 0 0 255
10.5 0 0 0 255 0 255 
10.5 20.25 0 0 0 255 128
0 20.25 -3 7 8 9 255
4 0 1 2 3
3 0 2 3
12
"""


def test_ascii_with_quad_alpha_and_extra_element(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text(ASCII_PLY)
    p = read_ply(path)
    np.testing.assert_array_equal(p.vertices, np.array([[0, 0, 0], [10.5, 0, 0], [10.5, 20.25, 0], [0, 20.25, -3]], np.float32))
    np.testing.assert_array_equal(p.colors, np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [7, 8, 9]], np.uint8))
    # The quad is fan-split into two triangles, the triangle kept as is.
    np.testing.assert_array_equal(p.faces, [[0, 1, 2], [0, 2, 3], [0, 2, 3]])
    assert p.normals is None and p.texture_uv is None
    assert p.texture_file == "ignored_without_uv.png"


def test_big_endian_binary(tmp_path):
    v = np.array([[1.5, -2.0, 3.25], [0, 1, 0], [1, 0, 0]], np.float32)
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
        "property double z\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n"
    ).encode()
    body = v.astype(">f8").tobytes() + bytes([3]) + np.array([2, 1, 0], ">u4").tobytes()
    path = tmp_path / "b.ply"
    path.write_bytes(header + body)
    p = read_ply(path)
    np.testing.assert_array_equal(p.vertices, v)
    np.testing.assert_array_equal(p.faces, [[2, 1, 0]])


def test_malformed_files_name_the_file(tmp_path):
    v, f, *_ = _mesh(np.random.default_rng(1))
    good = tmp_path / "good.ply"
    write_ply(good, v, f)
    truncated = tmp_path / "trunc.ply"
    truncated.write_bytes(good.read_bytes()[:-7])
    with pytest.raises(BopFormatError, match=r"trunc\.ply: element 'face': file truncated"):
        read_ply(truncated)
    notply = tmp_path / "x.ply"
    notply.write_text("hello")
    with pytest.raises(BopFormatError, match=r"x\.ply: not a PLY file"):
        read_ply(notply)
    bad_index = tmp_path / "idx.ply"
    bad_index.write_text(ASCII_PLY.replace("3 0 2 3", "3 0 2 9"))
    with pytest.raises(BopFormatError, match=r"idx\.ply: face indices out of range"):
        read_ply(bad_index)
    with pytest.raises(ValueError, match="face indices"):
        write_ply(tmp_path / "w.ply", v, f + 1000)


def test_load_mesh_visuals(tmp_path):
    from PIL import Image

    box = trimesh.creation.box(extents=(10, 20, 30))
    v = box.vertices.astype(np.float32)
    colors = np.tile(np.array([[10, 200, 30]], np.uint8), (len(v), 1))
    write_ply(tmp_path / "c.ply", v, box.faces, colors=colors)
    m = load_mesh(tmp_path / "c.ply")
    assert m.visual.kind == "vertex"
    np.testing.assert_array_equal(m.visual.vertex_colors[:, :3], colors)
    np.testing.assert_array_equal(m.faces, box.faces)  # vertex order kept

    write_ply(tmp_path / "g.ply", v, box.faces)
    assert (load_mesh(tmp_path / "g.ply").visual.vertex_colors[:, :3] == 180).all()

    uv = np.random.default_rng(0).random((len(v), 2)).astype(np.float32)
    Image.fromarray(np.full((4, 4, 3), 90, np.uint8)).save(tmp_path / "t.png")
    write_ply(tmp_path / "t.ply", v, box.faces, texture_uv=uv, texture_file="t.png")
    mt = load_mesh(tmp_path / "t.ply")
    assert mt.visual.kind == "texture"
    np.testing.assert_allclose(mt.visual.uv, uv)
    write_ply(tmp_path / "u.ply", v, box.faces, texture_uv=uv, texture_file="missing.png")
    with pytest.raises(BopFormatError, match="missing.png"):
        load_mesh(tmp_path / "u.ply")

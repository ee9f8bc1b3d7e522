"""PLY meshes as the BOP datasets distribute them.

BOP models are triangle meshes in millimetres. LM/T-LESS/IC-BIN models carry vertex
colours (``red green blue``), YCB-V/HOPE models carry per-vertex ``texture_u texture_v``
plus a ``comment TextureFile <image>`` header line, and ``models_eval`` meshes are
geometry only. The official files are ascii; tools re-save them as
``binary_little_endian``. ``read_ply`` reads ascii and both binary byte orders, with any
scalar types, extra properties (alpha, quality) and extra elements (materials), which
it skips. ``write_ply`` always writes the compact BOP layout, so a float32/uint8
round trip is bit-exact.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING, Callable

import numpy as np

from .errors import BopFormatError
from .jsonio import brief
from .read_bytes import read_bytes

if TYPE_CHECKING:  # imported where a mesh is built: ~0.7 s that reading a PLY does not need
    import trimesh

_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
               "f4": "float", "f8": "double"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
# Property names used for texture coordinates by BOP (texture_u/v) and other exporters.
_UV_NAMES = (("texture_u", "texture_v"), ("s", "t"), ("u", "v"), ("texture_s", "texture_t"))
_FACE_LIST_NAMES = ("vertex_indices", "vertex_index")
# Grey given to meshes without colour, so renders are shaded rather than white.
_DEFAULT_GREY = np.array([180, 180, 180, 255], dtype=np.uint8)


@dataclass
class PlyData:
    """A triangle mesh read from a PLY file.

    vertices: (V, 3) float32, mm. faces: (F, 3) int64 vertex indices (polygons are
    fan-triangulated). normals: (V, 3) float32 or None. colors: (V, 3) uint8 or None.
    texture_uv: (V, 2) float32 or None (OpenGL convention, v up, as in BOP files).
    texture_file: the image named by ``comment TextureFile``, relative to the PLY, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    texture_uv: np.ndarray | None = None
    texture_file: str | None = None


@dataclass
class _Property:
    name: str
    dtype: str  # numpy type code without byte order, e.g. "f4"
    count_dtype: str | None = None  # set for list properties

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass
class _Element:
    name: str
    count: int
    properties: list[_Property]


# ---------------------------------------------------------------------------- writing


def write_ply(
    path: Path | str,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    texture_uv: np.ndarray | None = None,
    texture_file: str | None = None,
    *,
    binary: bool = True,
) -> None:
    """Write a triangle mesh as a BOP-style PLY.

    vertices (V, 3) and normals (V, 3) are stored as float32 (mm), colors (V, 3) as
    uint8, texture_uv (V, 2) as float32 ``texture_u texture_v``; faces (F, 3) as
    ``property list uchar int vertex_indices``. ``texture_file`` adds the
    ``comment TextureFile`` line BOP uses. ``binary=False`` writes ascii (values in
    shortest round-trip form, so it is still exact).
    """
    path = Path(path)
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"write_ply({path}): vertices must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"write_ply({path}): faces must be (F, 3), got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"write_ply({path}): face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    n_v = len(v)
    columns: list[tuple[list[str], str, np.ndarray]] = [(["x", "y", "z"], "f4", v)]
    for names, code, arr, width in (
        (["nx", "ny", "nz"], "f4", normals, 3),
        (["red", "green", "blue"], "u1", colors, 3),
        (["texture_u", "texture_v"], "f4", texture_uv, 2),
    ):
        if arr is None:
            continue
        arr = np.asarray(arr)
        if arr.shape != (n_v, width):
            raise ValueError(f"write_ply({path}): {'/'.join(names)} must be ({n_v}, {width}), got {arr.shape}")
        if code == "u1" and arr.dtype != np.uint8:
            if arr.min() < 0 or arr.max() > 255:
                raise ValueError(f"write_ply({path}): colors must be uint8 values in [0, 255]")
        columns.append((names, code, arr))

    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    if texture_file is not None:
        header.append(f"comment TextureFile {texture_file}")
    header.append(f"element vertex {n_v}")
    type_name = {"f4": "float", "u1": "uchar"}
    for names, code, _ in columns:
        header += [f"property {type_name[code]} {n}" for n in names]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")

    vdtype = np.dtype([(n, "<" + code) for names, code, _ in columns for n in names])
    vrec = np.empty(n_v, dtype=vdtype)
    for names, code, arr in columns:
        for i, n in enumerate(names):
            vrec[n] = arr[:, i].astype(code)
    frec = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    frec["n"] = 3
    frec["idx"] = f.astype(np.int32)

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(head)
        if binary:
            fh.write(vrec.tobytes())
            fh.write(frec.tobytes())
        else:
            fh.write(_ascii_rows(vrec).encode("ascii"))
            fh.write("".join(f"3 {a} {b} {c}\n" for a, b, c in f.tolist()).encode("ascii"))


def _ascii_rows(rec: np.ndarray) -> str:
    """One text line per record; float32 values in their shortest exact decimal form."""
    cols = []
    for name in rec.dtype.names:
        col = rec[name]
        if col.dtype.kind == "f":
            cols.append([np.format_float_positional(x, unique=True, trim="-") for x in col])
        else:
            cols.append([str(x) for x in col.tolist()])
    return "".join(" ".join(row) + "\n" for row in zip(*cols))


# ---------------------------------------------------------------------------- reading


def _parse_header(path: Path, raw: bytes) -> tuple[str | None, list[_Element], list[str], int]:
    """Return (byte order or None for ascii, elements, comments, offset of the body)."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise BopFormatError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    nl = raw.find(b"\n", end)
    body_start = len(raw) if nl < 0 else nl + 1
    lines = raw[:end].decode("ascii", errors="replace").replace("\r", "").split("\n")[1:]
    fmt: str | None = None
    seen_format = False
    elements: list[_Element] = []
    comments: list[str] = []
    for lineno, line in enumerate(lines, start=2):
        tok = line.split()
        where = f"{path}: header line {lineno}"
        if not tok:
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in _FORMATS:
                raise BopFormatError(f"{where}: unsupported format {brief(line.strip())}")
            fmt, seen_format = _FORMATS[tok[1]], True
        elif tok[0] == "comment":
            comments.append(line.strip()[len("comment"):].strip())
        elif tok[0] == "obj_info":
            continue
        elif tok[0] == "element":
            # isascii: str.isdigit() also accepts '²' and other digits int() refuses.
            if len(tok) != 3 or not (tok[2].isascii() and tok[2].isdigit()):
                raise BopFormatError(f"{where}: malformed element line {brief(line.strip())}")
            if any(e.name == tok[1] for e in elements):
                raise BopFormatError(f"{where}: element {brief(tok[1])} repeated")
            elements.append(_Element(tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise BopFormatError(f"{where}: property before any element")
            try:
                if tok[1] == "list":
                    prop = _Property(tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]])
                else:
                    prop = _Property(tok[2], _PLY_TYPES[tok[1]])
            except (IndexError, KeyError):
                raise BopFormatError(f"{where}: malformed property {brief(line.strip())}") from None
            # A float list length could be NaN or 2.5: the PLY format wants an integer type.
            if prop.is_list and np.dtype(prop.count_dtype).kind not in "iu":
                raise BopFormatError(f"{where}: list count type must be an integer type, got {brief(tok[2])}")
            # Records are read as numpy structured arrays, whose field names must be unique.
            if any(q.name == prop.name for q in elements[-1].properties):
                raise BopFormatError(f"{where}: property {brief(prop.name)} repeated in element {brief(elements[-1].name)}")
            elements[-1].properties.append(prop)
        else:
            raise BopFormatError(f"{where}: unknown keyword {brief(tok[0])}")
    if not seen_format:
        raise BopFormatError(f"{path}: header has no 'format' line")
    return fmt, elements, comments, body_start


def _truncated(path: Path, el: _Element) -> BopFormatError:
    return BopFormatError(f"{path}: element '{el.name}': file truncated ({el.count} records expected)")


def _binary_list_len(path: Path, buf: bytes, pos: int, el: _Element, p: _Property, order: str) -> int:
    """Length of the list of property ``p`` whose count starts at byte ``pos``."""
    if pos + np.dtype(p.count_dtype).itemsize > len(buf):
        raise _truncated(path, el)
    n = int(np.frombuffer(buf, order + p.count_dtype, 1, pos)[0])
    if n < 0:  # a signed count type; numpy would read "-1" as "the rest of the buffer"
        raise BopFormatError(f"{path}: element '{el.name}', property '{p.name}': negative list length {n}")
    return n


def _read_binary_element(path: Path, buf: bytes, offset: int, el: _Element, order: str) -> tuple[dict, int]:
    """Read one element from a binary body; returns ({prop: array}, new offset)."""
    if el.count == 0 or not el.properties:  # no records, or records of zero bytes
        return {p.name: np.zeros((0,), order + p.dtype) for p in el.properties}, offset
    # Fast path: assume every list has the length found in the first record (always
    # true for triangle meshes), read with one structured dtype, then verify. A space
    # cannot occur in a header token, so "<name> n" never clashes with a property.
    fields = []
    pos = offset
    for p in el.properties:
        if p.is_list:
            n = _binary_list_len(path, buf, pos, el, p, order)
            fields += [(p.name + " n", order + p.count_dtype), (p.name, order + p.dtype, (n,))]
            pos += np.dtype(p.count_dtype).itemsize + n * np.dtype(p.dtype).itemsize
        else:
            fields.append((p.name, order + p.dtype))
            pos += np.dtype(p.dtype).itemsize
        if pos > len(buf):  # checked before building a dtype from a corrupt, huge list length
            raise _truncated(path, el)
    dtype = np.dtype(fields)
    if offset + dtype.itemsize * el.count <= len(buf):
        rec = np.frombuffer(buf, dtype, el.count, offset)
        if all(np.all(rec[p.name + " n"] == rec.dtype[p.name].shape[0]) for p in el.properties if p.is_list):
            return {p.name: rec[p.name] for p in el.properties}, offset + dtype.itemsize * el.count
    if not any(p.is_list for p in el.properties):
        raise _truncated(path, el)
    # Slow path: lists of varying length (polygons), read record by record; every record
    # takes at least one byte, so a huge corrupt count ends at the end of the buffer.
    out: dict[str, list] = {p.name: [] for p in el.properties}
    pos = offset
    for _ in range(el.count):
        for p in el.properties:
            if p.is_list:
                n = _binary_list_len(path, buf, pos, el, p, order)
                pos += np.dtype(p.count_dtype).itemsize
                size = n
            else:
                size = 1
            if pos + size * np.dtype(p.dtype).itemsize > len(buf):
                raise _truncated(path, el)
            values = np.frombuffer(buf, order + p.dtype, size, pos)
            out[p.name].append(values if p.is_list else values[0])
            pos += size * np.dtype(p.dtype).itemsize
    return {p.name: (out[p.name] if p.is_list else np.array(out[p.name])) for p in el.properties}, pos


def _number_text(v: float) -> str:
    """A float read from ascii as the file most likely spelled it (300, 2.5, 1e+39)."""
    return str(int(v)) if v.is_integer() and abs(v) < 1e17 else repr(v)


def _cast(path: Path, el: _Element, p: _Property, values: np.ndarray) -> np.ndarray:
    """float64 values read from an ascii body as the property's declared type.

    An integer property must hold integral values in the type's range, and a float
    property finite values within its range (NaN and inf pass, for the caller to judge):
    numpy's cast would wrap (300 -> 44 as uchar) or overflow (1e39 -> inf) silently.
    """
    target = np.dtype(p.dtype)
    if target.kind in "iu":
        info = np.iinfo(target)
        ok = np.isfinite(values) & (values == np.round(values)) & (values >= info.min) & (values <= info.max)
        cast = values.astype(target) if np.all(ok) else None
    else:
        # Not |v| <= max: float32's max prints as 3.4028235e38, just above it, and rounds
        # back to it; only values that round to inf overflow.
        with np.errstate(over="ignore"):
            cast = values.astype(target)
        ok = ~np.isfinite(values) | np.isfinite(cast)
    if not np.all(ok):
        bad = float(values[~ok].flat[0])
        raise BopFormatError(f"{path}: element '{el.name}': value {_number_text(bad)} does not fit property "
                             f"'{p.name}' ({_TYPE_NAMES[p.dtype]})")
    return cast


def _ascii_list_len(path: Path, el: _Element, p: _Property, token: str) -> int:
    """Length of a list from its ascii token: a non-negative integer ("3" or "3.0")."""
    try:
        n = float(token)
    except ValueError:
        n = float("nan")
    if not (np.isfinite(n) and n >= 0 and n.is_integer()):
        raise BopFormatError(
            f"{path}: element '{el.name}', property '{p.name}': list length {brief(token)} is not a non-negative integer")
    return int(n)


def _read_ascii_element(path: Path, tokens: list[str], start: int, el: _Element) -> tuple[dict, int]:
    """Read one element from the whitespace-split ascii body; returns ({prop: array}, next token)."""
    if el.count == 0 or not el.properties:  # no records, or records of no values
        return {p.name: np.zeros((0,), p.dtype) for p in el.properties}, start

    def number_array(toks: list[str]) -> np.ndarray:
        try:
            return np.asarray(toks, dtype=np.float64)
        except ValueError as e:
            raise BopFormatError(f"{path}: element '{el.name}': non-numeric value ({brief(str(e), 100)})") from None

    # Fast path: all records have the list lengths of the first record.
    widths = []
    pos = start
    for p in el.properties:
        if p.is_list:
            if pos >= len(tokens):
                raise _truncated(path, el)
            n = _ascii_list_len(path, el, p, tokens[pos])
            widths.append(1 + n)
            pos += 1 + n
        else:
            widths.append(1)
            pos += 1
    row = sum(widths)
    end = start + row * el.count
    if end <= len(tokens):
        table = number_array(tokens[start:end]).reshape(el.count, row)
        cols = np.cumsum([0] + widths)
        ok = all(np.all(table[:, cols[i]] == widths[i] - 1) for i, p in enumerate(el.properties) if p.is_list)
        if ok:
            result = {}
            for i, p in enumerate(el.properties):
                if p.is_list:
                    result[p.name] = _cast(path, el, p, table[:, cols[i] + 1 : cols[i + 1]])
                else:
                    result[p.name] = _cast(path, el, p, table[:, cols[i]])
            return result, end
    if not any(p.is_list for p in el.properties):
        raise _truncated(path, el)
    # Slow path: record by record; each takes at least one token, so a huge corrupt
    # count ends at the end of the body.
    out: dict[str, list] = {p.name: [] for p in el.properties}
    pos = start
    for _ in range(el.count):
        for p in el.properties:
            if pos >= len(tokens):
                raise _truncated(path, el)
            if p.is_list:
                n = _ascii_list_len(path, el, p, tokens[pos])
                if pos + 1 + n > len(tokens):
                    raise _truncated(path, el)
                out[p.name].append(_cast(path, el, p, number_array(tokens[pos + 1 : pos + 1 + n])))
                pos += 1 + n
            else:
                out[p.name].append(tokens[pos])
                pos += 1
    return {p.name: (out[p.name] if p.is_list else _cast(path, el, p, number_array(out[p.name])))
            for p in el.properties}, pos


def _triangulate(path: Path, faces: np.ndarray | list) -> np.ndarray:
    """(F, 3) int64 triangles from a fixed (F, n) array or a list of polygons (fan split)."""
    if isinstance(faces, np.ndarray):
        if faces.ndim == 2 and faces.shape[1] == 3:
            return faces.astype(np.int64)
        if len(faces) == 0:
            return np.zeros((0, 3), np.int64)
        if faces.ndim == 2 and faces.shape[1] > 3:
            faces = list(faces)
        else:
            raise BopFormatError(f"{path}: a face has {faces.shape[-1] if faces.ndim == 2 else 1} vertices; "
                                 "at least 3 are needed")
    tris = []
    for poly in faces:
        if len(poly) < 3:
            raise BopFormatError(f"{path}: a face has {len(poly)} vertices; at least 3 are needed")
        for k in range(1, len(poly) - 1):
            tris.append((poly[0], poly[k], poly[k + 1]))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def read_ply(path: Path | str) -> PlyData:
    """Read a PLY mesh (ascii or binary) into a ``PlyData``; see the module docstring.

    Raises ``BopFormatError`` naming the file, on one line, on a missing file, bad
    header, truncated body, a value that does not fit its declared type, missing
    x/y/z, a non-finite vertex coordinate (or one beyond float32), non-integer or
    out-of-range face indices.
    """
    path = Path(path)
    raw = read_bytes(path)
    order, elements, comments, body = _parse_header(path, raw)
    data = _read_body(path, raw, body, order, elements)
    props = {el.name: {p.name: p for p in el.properties} for el in elements}
    if "vertex" not in data:
        raise BopFormatError(f"{path}: no 'vertex' element")

    def column(name: str) -> np.ndarray | None:
        """(V,) values of the scalar vertex property ``name``, None when absent."""
        return _vertex_column(path, data["vertex"], props["vertex"], name)

    vertices = _vertex_positions(path, column)
    normals, colors, uv = _vertex_attributes(column)
    faces = _face_indices(path, data, props, len(vertices))
    return PlyData(vertices, faces, normals, colors, uv, _texture_file(comments))


def _read_body(path: Path, raw: bytes, body: int, order: str | None,
               elements: list[_Element]) -> dict[str, dict[str, np.ndarray | list]]:
    """The values of every element after the header (which ends at byte ``body``):
    element name -> property name -> values; ascii when ``order`` is None, else binary
    of that byte order."""
    data: dict[str, dict] = {}
    if order is None:
        tokens = raw[body:].decode("ascii", errors="replace").split()
        pos = 0
        for el in elements:
            data[el.name], pos = _read_ascii_element(path, tokens, pos, el)
    else:
        pos = body
        for el in elements:
            data[el.name], pos = _read_binary_element(path, raw, pos, el, order)
    return data


def _vertex_column(path: Path, vertex: dict[str, np.ndarray | list], props: dict[str, _Property],
                   name: str) -> np.ndarray | None:
    """(V,) values of the scalar vertex property ``name`` (``vertex``: the vertex
    element's values, ``props`` its properties), None when absent; ``BopFormatError``
    when it is a list."""
    if name not in vertex:
        return None
    if props[name].is_list:
        raise BopFormatError(f"{path}: vertex property '{name}' is a list; a number is needed")
    return vertex[name]


def _vertex_positions(path: Path, column: Callable[[str], np.ndarray | None]) -> np.ndarray:
    """(V, 3) float32 vertex coordinates from the x, y, z columns; ``BopFormatError``
    when one is missing, or a vertex has a non-finite coordinate or one beyond the
    float32 range."""
    xyz = [column(name) for name in ("x", "y", "z")]
    for name, values in zip("xyz", xyz):
        if values is None:
            raise BopFormatError(f"{path}: vertex element has no property '{name}'")
    # Checked here, naming the vertex: a NaN would otherwise surface much later as a
    # NaN diameter or an empty render.
    with np.errstate(invalid="ignore"):  # a signalling NaN from a binary file warns when cast
        v64 = np.stack(xyz, axis=1).astype(np.float64)
    finite = np.isfinite(v64).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise BopFormatError(f"{path}: vertex {i} has a non-finite coordinate ({', '.join(map(repr, v64[i].tolist()))})")
    with np.errstate(over="ignore"):  # doubles beyond float32 become inf: reported next
        vertices = v64.astype(np.float32)
    beyond = ~np.isfinite(vertices).all(axis=1)
    if beyond.any():
        i = int(np.flatnonzero(beyond)[0])
        raise BopFormatError(f"{path}: vertex {i} has a coordinate beyond the float32 range "
                             f"({', '.join(map(repr, v64[i].tolist()))})")
    return vertices


def _vertex_attributes(column: Callable[[str], np.ndarray | None]
                       ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(normals (V, 3) float32, colours (V, 3) uint8, texture uv (V, 2) float32) of the
    vertices, each None when the file has no such columns. Colours stored as floats
    are taken as [0, 1]; any colour is clipped to [0, 255], never wrapped. Normals and
    uv are not checked (inf/NaN stay)."""
    normals = None
    nrm = [column(name) for name in ("nx", "ny", "nz")]
    if all(c is not None for c in nrm):
        with np.errstate(over="ignore", invalid="ignore"):  # normals are not checked: inf/NaN stay
            normals = np.stack(nrm, axis=1).astype(np.float32)
    colors = None
    for names in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        rgb = [column(name) for name in names]
        if all(c is not None for c in rgb):
            c = np.stack(rgb, axis=1)
            if c.dtype.kind == "f":  # some exporters store colours in [0, 1]
                with np.errstate(over="ignore", invalid="ignore"):
                    c = np.round(np.nan_to_num(c.astype(np.float64) * 255.0))
            colors = np.clip(c, 0, 255).astype(np.uint8)  # 16-bit or signed types: clip, never wrap
            break
    uv = None
    for u, v in _UV_NAMES:
        cu, cv = column(u), column(v)
        if cu is not None and cv is not None:
            with np.errstate(over="ignore", invalid="ignore"):
                uv = np.stack([cu, cv], axis=1).astype(np.float32)
            break
    return normals, colors, uv


def _face_indices(path: Path, data: dict[str, dict[str, np.ndarray | list]],
                  props: dict[str, dict[str, _Property]], n_vertices: int) -> np.ndarray:
    """(F, 3) int64 triangles of the face element (polygons fanned into triangles),
    (0, 3) without one; ``BopFormatError`` when its vertex index list is missing, not a
    list, not of an integer type, or an index is outside ``[0, n_vertices)``."""
    faces = np.zeros((0, 3), np.int64)
    if "face" in data:
        face_el = data["face"]
        key = next((n for n in _FACE_LIST_NAMES if n in face_el), None)
        if key is None:
            raise BopFormatError(f"{path}: face element has no 'vertex_indices' list")
        prop = props["face"][key]
        if not prop.is_list:
            raise BopFormatError(f"{path}: face property '{key}' must be a list of vertex indices")
        if np.dtype(prop.dtype).kind not in "iu":  # a float index would be truncated, NaN cast to garbage
            raise BopFormatError(f"{path}: face indices must be integers, got type '{_TYPE_NAMES[prop.dtype]}'")
        faces = _triangulate(path, face_el[key])
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise BopFormatError(
            f"{path}: face indices out of range [0, {n_vertices}): min {faces.min()}, max {faces.max()}"
        )
    return faces


def _texture_file(comments: list[str]) -> str | None:
    """The image named by the header's last ``comment TextureFile <image>`` line, if any."""
    texture_file = None
    for c in comments:
        parts = c.split(None, 1)
        if len(parts) == 2 and parts[0].lower() == "texturefile":
            texture_file = parts[1].strip()
    return texture_file


# ---------------------------------------------------------------------------- trimesh


SPAN_TOLERANCE = 1e-5
"""Relative size below which a mesh's second extent (or its area) counts as none: far
below any real object's proportions (a 150 mm pen 1 mm thick is 7e-3), above float32
rounding of vertices that lie on a line."""


def degenerate_mesh_problem(vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """None if the mesh (vertices (V, 3) mm, faces (F, 3) indices) spans a surface,
    else why not, in words: every used vertex one point, all on a line, or triangles
    of no area. Such a model cannot be rendered into templates nor sampled into surface
    points (the stages would fail on it with numpy's errors, far from the file), so the
    reader refuses it. Non-finite vertices are left out (reported elsewhere)."""
    v = np.asarray(vertices, dtype=np.float64)  # (V, 3) mm
    in_face = np.zeros(len(v), dtype=bool)
    in_face[np.asarray(faces).reshape(-1)] = True  # (no sort: models reach millions of faces)
    used = v[in_face & np.isfinite(v).all(axis=1)]  # (U, 3) mm
    if len(used) == 0:
        return None
    centred = used - used.mean(axis=0)
    # the principal extents from the 3x3 scatter matrix: cheap for millions of vertices
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(centred.T @ centred / len(used)), 0.0, None))[::-1]  # (3,) mm
    if spread[0] <= 0:
        return f"all its {len(used)} vertices are one point: the model spans no area"
    if spread[1] <= SPAN_TOLERANCE * spread[0]:
        return f"its {len(used)} vertices lie on a line: the model spans no area"
    # Summed chunk by chunk, stopping once it is enough: a real model's first chunk is,
    # and the memory of a multi-million-face model stays bounded.
    area, enough, chunk = 0.0, (SPAN_TOLERANCE * spread[0]) ** 2, 1 << 16
    for start in range(0, len(faces), chunk):
        tri = v[np.asarray(faces[start:start + chunk])]  # (f, 3, 3) mm
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area += float(np.nansum(np.linalg.norm(cross, axis=1))) / 2
        if area > enough:
            return None
    return f"its {len(faces)} triangles have no area (every face is degenerate): the model spans no surface"


def load_mesh(path: Path | str) -> trimesh.Trimesh:
    """Load a PLY as a ``trimesh.Trimesh`` (mm) that pyrender renders in colour.

    Vertex order is kept (``process=False``), so indices match the file. Texture UVs
    with their image become ``TextureVisuals``; vertex colours become ``ColorVisuals``;
    meshes with neither get a uniform grey. ``BopFormatError`` (naming the file) when
    ``read_ply`` fails, the PLY has no faces (a point cloud), spans no surface (its
    vertices on a line or one point, or its triangles without area:
    :func:`degenerate_mesh_problem`), or a texture image named in the header is missing
    or cannot be decoded.
    """
    import trimesh

    path = Path(path)
    ply = read_ply(path)
    if len(ply.faces) == 0:  # a point cloud: nothing to render or to sample a surface on
        raise BopFormatError(f"{path}: has no faces; a surface mesh is needed")
    flat = degenerate_mesh_problem(ply.vertices, ply.faces)
    if flat:
        raise BopFormatError(f"{path}: {flat}; templates, surface samples and scores need a surface mesh")
    mesh = trimesh.Trimesh(
        vertices=ply.vertices.astype(np.float64),
        faces=ply.faces,
        vertex_normals=None if ply.normals is None else ply.normals.astype(np.float64),
        process=False,
    )
    if ply.texture_uv is not None and ply.texture_file is not None:
        from PIL import Image

        tex_path = path.parent / ply.texture_file
        if not tex_path.is_file():
            raise BopFormatError(f"{path}: texture file '{ply.texture_file}' named in the header not found at {tex_path}")
        try:
            with Image.open(tex_path) as im:
                image = im.convert("RGB")
        except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:  # PIL's errors on bad images
            reason = " ".join(str(e).split())[:120]
            raise BopFormatError(f"{path}: texture file '{ply.texture_file}' cannot be read ({reason})") from None
        material = trimesh.visual.material.SimpleMaterial(image=image)
        mesh.visual = trimesh.visual.TextureVisuals(uv=ply.texture_uv.astype(np.float64), material=material)
    elif ply.colors is not None:
        rgba = np.concatenate([ply.colors, np.full((len(ply.colors), 1), 255, np.uint8)], axis=1)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    else:
        if ply.texture_uv is not None:
            warnings.warn(f"{path}: texture coordinates without a TextureFile comment; rendering grey", stacklevel=2)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile(_DEFAULT_GREY, (len(ply.vertices), 1)))
    return mesh

"""JSON files in the exact layout the BOP toolkit writes.

The toolkit writes a dict as ``{``, then one line per key ``  "key": <json>`` (keys in
sorted order, values dumped with ``sort_keys=True``), commas between lines, then ``}``
with no trailing newline; a list likewise with ``[``/``]``. Keeping that layout makes
our files diff cleanly against the official ones and keeps one entry per line for
``grep``. Id keys (ints, or digit strings) are sorted numerically, as in the files the
toolkit writes from int-keyed dicts, so ``"10"`` follows ``"9"`` and re-saving a loaded
BOP file reproduces it byte for byte.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.common.store import atomic_write_text

from .errors import BopFormatError
from .read_bytes import read_bytes


def _to_builtin(obj: Any) -> Any:
    """``json.dumps`` hook turning numpy scalars/arrays into Python builtins."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=_to_builtin)


def _is_id(key: Any) -> bool:
    if isinstance(key, bool):
        return False
    if isinstance(key, (int, np.integer)):
        return True
    return isinstance(key, str) and key.isascii() and key.isdigit()


def _sorted_items(content: dict) -> list[tuple[Any, Any]]:
    # Ids (ints, or digit strings as they come back from json.load) sort numerically,
    # like the files of the BOP datasets; any other key set sorts as strings.
    if all(_is_id(k) for k in content):
        return sorted(content.items(), key=lambda kv: int(kv[0]))
    return sorted(content.items(), key=lambda kv: str(kv[0]))


def bop_json_text(content: Any) -> str:
    """Text of ``content`` in the BOP toolkit's layout (see the module docstring)."""
    if isinstance(content, dict):
        lines = [f"  {json.dumps(str(k))}: {_dumps(v)}" for k, v in _sorted_items(content)]
        return "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}"
    if isinstance(content, (list, tuple)):
        lines = [f"  {_dumps(v)}" for v in content]
        return "[\n" + ",\n".join(lines) + ("\n" if lines else "") + "]"
    return _dumps(content)


def save_bop_json(path: Path | str, content: Any) -> None:
    """Write ``content`` (dict, list or scalar; numpy values allowed) atomically in BOP layout."""
    atomic_write_text(path, bop_json_text(content))


def brief(value: Any, limit: int = 80) -> str:
    """``repr(value)`` on one line, cut to about ``limit`` characters, for error messages.

    A file may hold a 10 000-element list or a string with newlines where a number was
    expected; the message names the field and shows the start of the value, on one line.
    """
    try:
        text = repr(value)
    except ValueError:  # an int beyond Python's int -> str digit limit
        text = f"<{type(value).__name__} too large to print>"
    text = " ".join(text.split("\n"))  # numpy arrays print on several lines
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_text(path: Path | str) -> str:
    """The text of a user-supplied file, decoded as UTF-8; a leading BOM is dropped.

    Windows tools (Excel, Notepad) save CSV and JSON with a UTF-8 BOM, which is still
    UTF-8 text, so it is accepted. A missing or unreadable file, a folder, or bytes
    that are not UTF-8 text (UTF-16, a binary file, NUL bytes) raise ``BopFormatError``
    naming the file and what is wrong, on one line.
    """
    path = Path(path)
    raw = read_bytes(path)
    # UTF-16 is the usual wrong encoding (PowerShell's `>`, Excel's "Unicode text"):
    # a BOM, or ASCII text whose bytes are NUL at every other position (only there).
    even, odd = raw[0:64:2].count(0), raw[1:64:2].count(0)
    utf16 = raw[:2] in (b"\xff\xfe", b"\xfe\xff") or (len(raw) >= 4 and min(even, odd) == 0
                                                       and max(even, odd) >= len(raw[:64]) // 2 * 0.8)
    hint = "; it looks like UTF-16: save it as UTF-8" if utf16 else ""
    nul = raw.find(b"\x00")
    if nul >= 0:  # valid UTF-8, but no text format has NUL bytes (UTF-16 ASCII text does)
        raise BopFormatError(f"{path}: not UTF-8 text (NUL byte at offset {nul}){hint}")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise BopFormatError(f"{path}: not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start}){hint}") from None


def load_json(path: Path | str) -> Any:
    """Parse a JSON file (UTF-8, a BOM allowed); a missing, non-UTF-8 or invalid file
    raises ``BopFormatError`` naming it, on one line."""
    path = Path(path)
    text = read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise BopFormatError(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except RecursionError:  # the C decoder recurses per nesting level
        raise BopFormatError(f"{path}: invalid JSON: nested too deeply") from None
    except ValueError as e:  # an integer of more than sys.get_int_max_str_digits() digits
        if "integer string conversion" in str(e):
            raise BopFormatError(f"{path}: invalid JSON: an integer has more digits than Python reads (4300)") from None
        raise BopFormatError(f"{path}: invalid JSON: {brief(str(e), 120)}") from None

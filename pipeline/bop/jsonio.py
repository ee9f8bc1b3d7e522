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

from pipeline.store import atomic_write_text

from .errors import BopFormatError


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


def load_json(path: Path | str) -> Any:
    """Parse a JSON file; a missing or invalid file raises ``BopFormatError`` naming it."""
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise BopFormatError(f"{path}: file not found") from None
    except json.JSONDecodeError as e:
        raise BopFormatError(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None

"""The one exception type of the BOP format layer."""

from __future__ import annotations

from pathlib import Path


class BopFormatError(ValueError):
    """A BOP file is missing, malformed, or lacks a field.

    The message always names the file and, when known, the entry and the field, so
    that a user can open the file and find the problem without a debugger.
    """


def format_error(path: Path | str, message: str, *, entry: object = None, field: str | None = None) -> BopFormatError:
    """Build a ``BopFormatError`` whose message reads ``<path>: [entry E, ][field 'F': ]message``."""
    where = []
    if entry is not None:
        where.append(f"entry {entry}")
    if field is not None:
        where.append(f"field '{field}'")
    prefix = f"{path}: " + (", ".join(where) + ": " if where else "")
    return BopFormatError(prefix + message)

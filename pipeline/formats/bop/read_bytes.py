"""The bytes of a user-supplied file, or one error line naming it.

The readers of the text (:func:`pipeline.formats.bop.jsonio.read_text`) and binary
(:func:`pipeline.formats.bop.ply.read_ply`) formats read a whole file first; a missing
file, a folder or an unreadable one is a :class:`BopFormatError` saying so, never an
``OSError`` traceback.
"""

from __future__ import annotations

from pathlib import Path

from .errors import BopFormatError


def read_bytes(path: Path | str) -> bytes:
    """The whole content of the file ``path``. ``BopFormatError`` naming it, on one line,
    when it is missing (``file not found``), a folder (``is a directory, not a file``)
    or cannot be read (``cannot read the file: <reason>``: permissions, I/O error)."""
    path = Path(path)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise BopFormatError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise BopFormatError(f"{path}: is a directory, not a file") from None
    except OSError as e:
        raise BopFormatError(f"{path}: cannot read the file: {e.strerror or e}") from None

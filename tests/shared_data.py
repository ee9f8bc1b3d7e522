"""Access to the real-data samples kept outside the repository, in ``<repo>/../shared``.

The samples (``../shared/realdata/*``, each with a SOURCE.txt giving its origin and
licence) are not part of the repository: CI runs on a clean checkout with a copy of
``shared/`` beside it. The rule for a test that reads them:

- it finds them RELATIVE to the repository (``SHARED`` below, never an absolute path);
- it is SKIPPED only when the whole ``../shared`` folder is absent (a checkout without
  the samples);
- it FAILS when ``../shared`` is present but a file or folder it needs is missing,
  unreadable or (for a file) empty: a broken sample must not pass silently as a skip.

Usage, inside a test or inside a fixture (a fixture's skip skips the tests that use
it; its failure is reported as an error of those tests)::

    from shared_data import shared_dir, shared_file

    def test_something():
        rgb = shared_file("realdata", "sam6d-example", "rgb.png")
        ...

    @pytest.fixture(scope="module")
    def tiny():
        return shared_dir("realdata", "synthetic-tinybop", "icbin", files=["camera.json"])

Call these at test or fixture time, not at import time (``pytest.skip`` outside a test
is a collection error); ``shared_path`` builds a path without any check for module
constants. The functions read the module attribute ``SHARED`` when called, so a test
can point it elsewhere with ``monkeypatch.setattr(shared_data, "SHARED", path)``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import pytest

#: ``<repo>/../shared``: this file is ``<repo>/tests/shared_data.py``.
SHARED: Path = Path(__file__).resolve().parent.parent.parent / "shared"

__all__ = ["SHARED", "shared_available", "shared_dir", "shared_file", "shared_path"]


def shared_available() -> bool:
    """Whether the ``../shared`` folder is present (a dangling symlink counts as present,
    so that it fails instead of skipping)."""
    return SHARED.exists() or SHARED.is_symlink()


def shared_path(*parts: str | os.PathLike[str]) -> Path:
    """``SHARED / parts``, without any check (for constants and messages)."""
    return SHARED.joinpath(*parts)


def _require_shared() -> None:
    """Skip when ``../shared`` is absent; fail when it is present but not a folder."""
    if not shared_available():
        pytest.skip(f"shared real-data folder {SHARED} (../shared next to the repository) is absent")
    if not SHARED.is_dir():
        pytest.fail(f"shared real-data folder {SHARED} is present but is not a readable folder", pytrace=False)


def _check_file(path: Path) -> None:
    """Fail (naming ``path``) unless it is a readable, non-empty file."""
    if not path.exists():
        pytest.fail(f"shared data file missing: {path} (../shared is present, so this is an error)", pytrace=False)
    if not path.is_file():
        pytest.fail(f"shared data path is not a file: {path}", pytrace=False)
    try:
        with path.open("rb") as fh:
            first = fh.read(1)
    except OSError as exc:
        pytest.fail(f"shared data file unreadable: {path} ({exc})", pytrace=False)
    if not first:
        pytest.fail(f"shared data file is empty: {path}", pytrace=False)


def shared_file(*parts: str | os.PathLike[str]) -> Path:
    """The path of the file ``../shared/<parts>``, checked.

    Skips the test when ``../shared`` is absent; fails it (naming the path) when
    ``../shared`` is present but the file is missing, not a regular file, unreadable or
    empty.
    """
    if not parts:
        raise TypeError("shared_file() needs at least one path part")
    _require_shared()
    path = shared_path(*parts)
    _check_file(path)
    return path


def shared_dir(*parts: str | os.PathLike[str], files: Iterable[str | os.PathLike[str]] = ()) -> Path:
    """The path of the folder ``../shared/<parts>``, checked.

    Skips the test when ``../shared`` is absent; fails it (naming the path) when
    ``../shared`` is present but the folder is missing, not a folder or cannot be
    listed, or when one of ``files`` (paths relative to the folder) is not a readable,
    non-empty file.
    """
    _require_shared()
    path = shared_path(*parts)
    if not path.exists():
        pytest.fail(f"shared data folder missing: {path} (../shared is present, so this is an error)", pytrace=False)
    if not path.is_dir():
        pytest.fail(f"shared data path is not a folder: {path}", pytrace=False)
    try:
        with os.scandir(path) as entries:
            next(entries, None)
    except OSError as exc:
        pytest.fail(f"shared data folder unreadable: {path} ({exc})", pytrace=False)
    for rel in files:
        _check_file(path / rel)
    return path

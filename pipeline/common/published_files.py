"""Files the project writes for the user (reports, figures, the AR table, the published
results CSV, ``freeze score --out``): atomic, and with the mode the umask gives.

They are written through :func:`pipeline.common.store.atomic_path` (a temporary sibling renamed
into place), and the rename keeps the temporary file's mode. Today ``atomic_path`` only
names the file and the writer's ``open()`` creates it under the umask; but a temporary
file made by a secure temp-file call is 0600 whatever the umask, so a report would end
up readable by its owner only. :func:`publishable` sets the written temporary file's
mode to ``0o666 & ~umask`` (0644 under the default umask 022), what ``open(path, "w")``
gives a new file, before the rename, however the file was created.
"""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

from pipeline.common.store import StorageError, atomic_path

_UMASK: int | None = None
_UMASK_LOCK = threading.Lock()


def _read_umask() -> int:
    """The process umask. Linux reports it in /proc/self/status (since 4.7), which reads
    it without changing it; elsewhere it can only be read by setting it and setting it
    back, during which a file another thread creates gets the wrong mode."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o077)  # the strict value, should another thread create a file meanwhile
    os.umask(old)
    return old


def process_umask() -> int:
    """The process umask (e.g. ``0o022``), read once (under a lock, so concurrent first
    callers neither race nor read it twice) and then remembered: a umask changed later
    in the process is not seen (see :func:`forget_umask`)."""
    global _UMASK
    if _UMASK is None:
        with _UMASK_LOCK:
            if _UMASK is None:
                _UMASK = _read_umask()
    return _UMASK


def forget_umask() -> None:
    """Read the umask again at the next :func:`process_umask` (for tests that set it)."""
    global _UMASK
    with _UMASK_LOCK:
        _UMASK = None


def file_mode() -> int:
    """Permission bits of a published file: ``0o666 & ~umask`` (0o644 under umask 022)."""
    return 0o666 & ~process_umask()


def publishable(tmp: Path | str) -> None:
    """Give the written temporary file ``tmp`` the mode of a new file under the umask
    (:func:`file_mode`); call it after writing, before the rename."""
    os.chmod(tmp, file_mode())


def write_text_published(path: Path | str, text: str) -> Path:
    """Write ``text`` (UTF-8, ``\\n`` line ends) to ``path`` atomically with mode
    :func:`file_mode`; returns ``path``.

    Raises :class:`OutputPathError` when ``path`` is a folder or lies below a file
    (:func:`check_output_file`), and :class:`pipeline.common.store.StorageError` naming ``path``
    when the disk refuses the write (full, read-only, no permission), the folder holding
    it included; nothing is written then."""
    path = check_output_file(path)
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "w", encoding="utf-8", newline="\n") as f:
                f.write(text)
            publishable(tmp)
    except StorageError:
        raise
    except OSError as e:  # creating the folder, or a refusal atomic_path leaves as it is (EACCES)
        raise storage_error(path, e) from None
    return path


class OutputPathError(StorageError):
    """An output path a command cannot write to because of what is there already (a
    folder where a file is to go, a file where a folder is); the message names the path
    and says what to give instead. Checked before the work, so that no work is lost. A
    :class:`pipeline.common.store.StorageError`, so that every command prints it as one line."""


def error_line(e: OSError) -> str:
    """The one-line message of a :class:`pipeline.common.store.StorageError` (or
    :class:`OutputPathError`) without Python's ``[Errno N]`` prefix."""
    return e.strerror if isinstance(e, StorageError) and e.strerror and e.errno is not None else str(e)


def _file_above(path: Path) -> Path | None:
    """The first of ``path``'s parents that exists and is not a folder, if any."""
    for parent in reversed(path.parents):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def check_output_file(path: Path | str, option: str = "") -> Path:
    """``path`` as a Path when a file can be written there (it does not exist or is a
    file, and every existing parent is a folder); else :class:`OutputPathError` naming it
    (and ``option``, the command-line option it came from, when given)."""
    path = Path(path)
    given = f"{option} " if option else ""
    if path.is_dir():
        raise OutputPathError(f"{given}{path}: is a folder; give the name of a file to write")
    blocker = _file_above(path)
    if blocker is not None:
        raise OutputPathError(f"{given}{path}: cannot write it, {blocker} is a file, not a folder")
    return path


def check_output_dir(path: Path | str, option: str = "") -> Path:
    """``path`` as a Path when files can be written into it (it is a folder, or does not
    exist and no existing parent is a file); else :class:`OutputPathError`."""
    path = Path(path)
    given = f"{option} " if option else ""
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{given}{path}: is a file; give a folder to write into (it is created if missing)")
    blocker = _file_above(path)
    if blocker is not None:
        raise OutputPathError(f"{given}{path}: cannot create the folder, {blocker} is a file, not a folder")
    return path


_WHY = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
        errno.EROFS: "read-only file system", errno.EACCES: "permission denied", errno.EPERM: "permission denied"}


def storage_error(path: Path | str, e: OSError) -> StorageError:
    """A :class:`pipeline.common.store.StorageError` saying in one line that ``path`` could not
    be written, and why (from ``e``'s errno)."""
    why = _WHY.get(e.errno, e.strerror or str(e))
    return StorageError(e.errno, f"{path}: cannot write it ({why}); nothing was written: free space or fix "
                                 "permissions, or give another path")

"""Files the project writes for the user (reports, figures, the AR table, the published
results CSV, ``freeze score --out``): atomic, and with the mode the umask gives.

They are written through :func:`pipeline.store.atomic_path` (a temporary sibling renamed
into place), and the rename keeps the temporary file's mode. Today ``atomic_path`` only
names the file and the writer's ``open()`` creates it under the umask; but a temporary
file made by a secure temp-file call is 0600 whatever the umask, so a report would end
up readable by its owner only. :func:`publishable` sets the written temporary file's
mode to ``0o666 & ~umask`` (0644 under the default umask 022), what ``open(path, "w")``
gives a new file, before the rename, however the file was created.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from pipeline.store import atomic_path

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
    :func:`file_mode`; returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
        publishable(tmp)
    return path

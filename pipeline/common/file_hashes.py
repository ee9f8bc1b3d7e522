"""Content fingerprints of the files a run reads, hashed once and remembered.

A cache key must change when any byte a stage reads changes (a model PLY replaced by
another of the same size, depth images overwritten with zeros), yet planning a run on a
40 GB dataset must not read 40 GB every time. :class:`FileHashes` keeps each file's
SHA-256 in a small SQLite table beside the cache, keyed by the file's path and checked
against its (size, modification time, inode): a file is read again only when one of
them changed. The first plan of a dataset reads every byte once; later plans only
``stat`` the files (``benchmarks/fingerprint.py`` measures both).
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
from pathlib import Path
from typing import Iterable, Mapping

from pipeline.common.store import file_digest

DB_NAME = ".file-hashes.sqlite"


class FileHashes:
    """SHA-256 of files, remembered in ``db`` (created on first use) by (path, size,
    mtime_ns, inode). Without a writable ``db`` it still hashes, remembering nothing."""

    def __init__(self, db: Path | str | None):
        self.db = Path(db) if db is not None else None

    def _connect(self) -> sqlite3.Connection | None:
        if self.db is None:
            return None
        try:
            self.db.parent.mkdir(parents=True, exist_ok=True)
            con = sqlite3.connect(str(self.db), timeout=60)
            con.execute("CREATE TABLE IF NOT EXISTS files (path TEXT PRIMARY KEY, size INTEGER, mtime_ns INTEGER, "
                        "inode INTEGER, sha256 TEXT)")
            return con
        except (sqlite3.Error, OSError):  # a read-only cache: hash without remembering
            return None

    def digests(self, paths: Iterable[str]) -> dict[str, str]:
        """``{path: sha256 hex}`` of every file in ``paths`` (absolute path strings)."""
        paths = list(dict.fromkeys(str(p) for p in paths))
        stats = {p: os.stat(p) for p in paths}
        con = self._connect()
        known: dict[str, tuple[int, int, int, str]] = {}
        if con is not None:
            try:
                rows = con.execute("SELECT path, size, mtime_ns, inode, sha256 FROM files").fetchall()
                known = {r[0]: (r[1], r[2], r[3], r[4]) for r in rows}
            except sqlite3.Error:
                con = None
        out: dict[str, str] = {}
        fresh = []
        for p in paths:
            st = stats[p]
            rec = known.get(p)
            if rec is not None and rec[:3] == (st.st_size, st.st_mtime_ns, st.st_ino):
                out[p] = rec[3]
            else:
                out[p] = file_digest(p)
                fresh.append((p, st.st_size, st.st_mtime_ns, st.st_ino, out[p]))
        if con is not None:
            try:
                if fresh:
                    with con:
                        con.executemany("INSERT OR REPLACE INTO files VALUES (?, ?, ?, ?, ?)", fresh)
            except sqlite3.Error:
                pass  # remembering is an optimisation; the digests are right either way
            finally:
                con.close()
        return out

    def fingerprints(self, root: Path | str, groups: Mapping[str, Iterable[str]]) -> dict[str, str]:
        """Per group of files (absolute path strings under ``root``), 12 hex digits over
        their paths relative to ``root`` and their contents; each file is hashed once."""
        groups = {k: sorted(set(map(str, v))) for k, v in groups.items()}
        digests = self.digests(p for files in groups.values() for p in files)
        prefix = len(str(root).rstrip(os.sep)) + 1
        out = {}
        for name, files in groups.items():
            h = hashlib.sha1()
            for f in files:
                h.update(f"{f[prefix:]}\0{digests[f]}\0".encode())
            out[name] = h.hexdigest()[:12]
        return out


def files_under(folder: Path | str) -> list[str]:
    """Every file below ``folder`` as absolute path strings (none when it does not
    exist), hidden files and folders excluded. (os.walk on strings: pathlib's objects
    cost more than the ``stat`` calls on a dataset of thousands of files.)"""
    out = []
    for top, dirs, files in os.walk(os.path.abspath(folder)):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        out += [os.path.join(top, f) for f in files if not f.startswith(".")]
    return out

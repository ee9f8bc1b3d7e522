"""Checking a cache against its manifests (``freeze verify``).

A cache holds artifact item folders, each published atomically by
:func:`pipeline.common.store.publish` with a ``_manifest.json`` that names its stage, item,
key and signature and lists every file's size and SHA-256 (:func:`pipeline.common.store.file_table`).
Most sit at ``<dataset>/<stage>/<signature>/<item>/``; ``freeze estimate``'s sit one
level deeper (``_estimate/<name>/<stage>/<signature>/<item>/``). An artifact is known by
its manifest, not by its depth: the whole cache is walked, without following a
symbolic link, and every folder whose own ``_manifest.json`` is an artifact manifest for
that folder is checked. Damage after publishing (a truncated chunk, a deleted array, a
hand-edited table, a half-written manifest) is found here, and ``--repair`` removes the
damaged item folders so that the next run rebuilds exactly those. Leftovers of killed
publishes (hidden ``.tmp-<item>-<hex>`` and ``.old-<item>-<hex>`` folders, and
``.<name>.<hex>.tmp`` files, beside the items of a signature folder) are found and
removed too: they are never read, only disk space.

Nothing else is ever removed: a folder that is not an artifact (a user's notes, an item
folder whose manifest was deleted), a symbolic link (to a file or a folder, in or out of
the cache) and the cache's own files (``.file-hashes.sqlite``) are left as they are. The
first two are reported (:attr:`VerifyReport.left_alone`) and do not make the check fail.
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from pipeline.commands.estimate.command import ESTIMATE_CACHE
from pipeline.common.file_hashes import DB_NAME
from pipeline.workflow.stage_graph import STAGES
from pipeline.common.store import MANIFEST_NAME, verify_item

# What store.atomic_dir / store.atomic_path leave when killed: ".tmp-<name>-<8 hex>" (the
# copy being written), ".old-<name>-<8 hex>" (the copy being replaced), and
# ".<name>.<8 hex>.tmp" (a file being written). Matched exactly, so that a user's
# ".tmp-notes" is not taken for one.
_LEFTOVER_DIR = re.compile(r"^\.(?:tmp|old)-.+-[0-9a-f]{8}$")
_LEFTOVER_FILE = re.compile(r"^\..+\.[0-9a-f]{8}\.tmp$")
# A signature folder's name: readable part, "-", 8 hex digits of the stage key (store.make_signature).
_SIGNATURE = re.compile(r"^.+-[0-9a-f]{8}$")
# Fields store.publish() writes into every manifest, by which an artifact manifest is recognised.
_MANIFEST_FIELDS = ("stage", "item", "key", "signature")
# Why a path is left alone, for those a folder's single line may stand for.
_PLAIN_FILE = "not part of an artifact"
_PLAIN_FOLDER = f"not an artifact: no {MANIFEST_NAME} in it"
_FOREIGN_MANIFEST = f"its {MANIFEST_NAME} is not an artifact manifest of this folder"
_COLLAPSIBLE = (_PLAIN_FILE, _PLAIN_FOLDER, _FOREIGN_MANIFEST)
_NO_MANIFEST_ITEM = (f"an item folder without its {MANIFEST_NAME} (never completed, or the manifest was deleted): "
                     "not an artifact; the next run of its stage replaces it")


@dataclass
class VerifyReport:
    """What :func:`verify_cache` found.

    checked: artifact items checked; damaged: item folder -> its problems (one line
    each); leftovers: leftovers of killed publishes old enough to remove; young_leftovers:
    those younger than the age limit (a running job's, perhaps: left alone); left_alone:
    (path, why) of what is not an artifact, a link included, never removed; removed: what
    ``repair`` removed; errors: one line per removal the file system refused (the rest
    were not attempted after it).
    """

    checked: int = 0
    damaged: dict[Path, list[str]] = field(default_factory=dict)
    leftovers: list[Path] = field(default_factory=list)
    young_leftovers: list[Path] = field(default_factory=list)
    left_alone: list[tuple[Path, str]] = field(default_factory=list)
    removed: list[Path] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """No damage and no leftover found (or all of it removed), no removal refused.
        What was left alone does not count: it is not the cache's to judge."""
        if self.errors:
            return False
        pending = [p for p in [*self.damaged, *self.leftovers] if p not in set(self.removed)]
        return not pending


@dataclass
class CacheScan:
    """The cache walked once: artifact item folders (sorted), leftover candidates of
    killed publishes, and what is neither (``(path, why)``)."""

    root: Path
    artifacts: list[Path] = field(default_factory=list)
    leftovers: list[Path] = field(default_factory=list)
    left_alone: list[tuple[Path, str]] = field(default_factory=list)


def _read_json(path: Path) -> Any:
    """The JSON content of ``path``, or None when it cannot be read or parsed."""
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def _manifest_state(folder: Path) -> str:
    """``"own"``: ``folder/_manifest.json`` is a regular file holding an artifact manifest
    of this folder (its fields name this item and this stage, as publish() writes them);
    ``"unreadable"``: a regular file that is not one (half-written, edited, another
    tool's); ``"link"``: a symbolic link; ``"none"``: no manifest."""
    path = folder / MANIFEST_NAME
    try:
        st = path.lstat()
    except FileNotFoundError:
        return "none"
    except OSError:
        return "unreadable"
    if stat.S_ISLNK(st.st_mode):
        return "link"
    if not stat.S_ISREG(st.st_mode):
        return "unreadable"
    man = _read_json(path)
    if (isinstance(man, dict) and all(isinstance(man.get(k), str) for k in _MANIFEST_FIELDS)
            and man["item"] == folder.name and man["stage"] == folder.parent.parent.name):
        return "own"
    return "unreadable"


def _is_cache_file(path: Path) -> bool:
    """A file the cache keeps for itself (the file-hash database and SQLite's journals of
    it: ``.file-hashes.sqlite``, ``-journal``, ``-wal``, ``-shm``), in the cache root or an
    estimate's cache root: never reported, never touched."""
    return path.name == DB_NAME or path.name.startswith(DB_NAME + "-")


def _wanted(rel: tuple[str, ...], wanted: list[tuple[str, ...]] | None) -> tuple[bool, bool]:
    """(inside a wanted dataset, an ancestor of one) for the path ``rel`` (parts below the root)."""
    if wanted is None:
        return True, False
    inside = any(rel[: len(w)] == w for w in wanted)
    above = any(len(rel) < len(w) and w[: len(rel)] == rel for w in wanted)
    return inside, above


def scan_cache(cache: Path | str, datasets: Iterable[str] | None = None) -> CacheScan:
    """Walk ``cache`` (or only the datasets named, e.g. ``synthtiny`` or
    ``_estimate/model``) without following symbolic links, and sort what it holds into
    artifacts, leftovers of killed publishes and the rest (:class:`CacheScan`). A folder
    that holds no artifact and no leftover anywhere below is reported as one entry.

    A folder is an artifact when its own ``_manifest.json`` is an artifact manifest of
    it (:func:`_manifest_state`); one whose manifest is unreadable counts as a (damaged)
    artifact only in a signature folder: one holding other artifacts, or named
    ``<readable>-<8 hex>`` inside a folder named after a stage. Leftovers count only in
    such a signature folder too. Artifacts are not looked into for more artifacts."""
    root = Path(cache)
    scan = CacheScan(root=root)
    wanted = [tuple(Path(d).parts) for d in datasets] if datasets else None

    def walk(folder: Path, rel: tuple[str, ...]) -> tuple[bool, bool]:
        """Sort the children of ``folder``; returns (it holds an artifact or leftover
        somewhere below, it holds any file or link at all)."""
        try:
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError as e:
            inside, _ = _wanted(rel, wanted)
            if inside:
                scan.left_alone.append((folder, f"cannot be listed ({e.strerror})"))
            return False, True
        dirs, files = [], []
        for e in entries:
            path = Path(e.path)
            child_rel = rel + (e.name,)
            inside, above = _wanted(child_rel, wanted)
            if not inside and not above:
                continue
            if e.is_symlink():  # never followed, never removed, whatever it points to
                if inside:
                    scan.left_alone.append((path, "a symbolic link: not followed, left as it is"))
                continue
            if e.is_dir(follow_symlinks=False):
                dirs.append((path, child_rel, inside))
            elif inside:
                files.append(path)
        states = {path: _manifest_state(path) for path, _, inside in dirs if inside and not path.name.startswith(".")}
        # A signature folder: its items are artifacts, or its name and its parent's say so.
        signature_folder = (any(s == "own" for s in states.values())
                            or (bool(_SIGNATURE.match(folder.name)) and folder.parent.name in STAGES))
        found = has_content = False
        for path in files:
            has_content = True
            if _is_cache_file(path) and rel in ((), (ESTIMATE_CACHE,)):
                continue
            if signature_folder and _LEFTOVER_FILE.match(path.name):
                scan.leftovers.append(path)
                found = True
            else:
                scan.left_alone.append((path, _PLAIN_FILE))
        for path, child_rel, inside in dirs:
            state = states.get(path)
            # first: a ".old-<item>-<hex>" holds the replaced item's manifest, but is a leftover
            if inside and signature_folder and _LEFTOVER_DIR.match(path.name):
                scan.leftovers.append(path)
                found = has_content = True
                continue
            if inside and state == "own" or inside and state == "unreadable" and signature_folder:
                scan.artifacts.append(path)
                found = has_content = True
                continue
            if inside and state == "link":
                scan.left_alone.append((path, f"its {MANIFEST_NAME} is a symbolic link: not an artifact"))
                has_content = True
                continue
            if inside and state == "unreadable":
                scan.left_alone.append((path, _FOREIGN_MANIFEST))
                has_content = True
                continue
            mark = len(scan.left_alone)
            sub_found, sub_content = walk(path, child_rel)
            found |= sub_found
            has_content |= sub_content
            if inside and not sub_found and sub_content and all(
                    why in _COLLAPSIBLE for _, why in scan.left_alone[mark:]):
                # nothing of the cache's below, no link, no item: one line for the whole folder
                del scan.left_alone[mark:]
                scan.left_alone.append((path, _NO_MANIFEST_ITEM if signature_folder else _PLAIN_FOLDER))
        return found, has_content

    if root.is_dir():
        walk(root, ())
    scan.artifacts.sort()
    scan.leftovers.sort()
    return scan


def _removable(path: Path, root: Path) -> str | None:
    """Why ``path`` must not be removed (None when it may): it is a link, it lies below a
    link, or it is not inside ``root``. Checked again right before removing, so that a
    folder swapped for a link since the walk is not followed."""
    try:
        rel = path.relative_to(root)
    except ValueError:
        return f"{path}: not inside the cache {root}, not removed"
    current = root
    for part in rel.parts:
        current = current / part
        if current.is_symlink():
            return f"{current}: a symbolic link, not removed (nor anything through it)"
    real_root = root.resolve()
    if not path.resolve().is_relative_to(real_root):
        return f"{path}: outside the cache {real_root}, not removed"
    return None


_WHY = {errno.EROFS: "read-only file system", errno.EACCES: "permission denied", errno.EPERM: "permission denied",
        errno.ENOSPC: "no space left on the device", errno.EBUSY: "in use"}


def _remove(path: Path) -> None:
    """Remove the folder (its tree, never following a link in it) or file ``path``."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)  # on Linux rmtree works through file descriptors and does not follow links
    else:
        path.unlink(missing_ok=True)


def verify_cache(cache: Path, datasets: Iterable[str] | None = None, *, checksums: bool = True,
                 repair: bool = False, leftover_min_age_s: float = 3600.0,
                 advance: Callable[[], None] = lambda: None, scan: CacheScan | None = None) -> VerifyReport:
    """Check every artifact item under ``cache`` (optionally only ``datasets``) against its
    manifest (:func:`pipeline.common.store.verify_item`; ``checksums=False`` compares sizes
    only). Leftovers younger than ``leftover_min_age_s`` may be a running job's and are
    left alone. With ``repair``, damaged items and leftovers are deleted, and nothing
    else; the first removal the file system refuses stops the repair
    (:attr:`VerifyReport.errors`). ``advance`` is called once per item (a progress bar);
    ``scan``: the :func:`scan_cache` of the same arguments, when already made."""
    import time

    from pipeline.workflow.artifacts import leftover_age_s

    cache = Path(cache)
    report = VerifyReport()
    if not cache.is_dir():
        return report
    scan = scan or scan_cache(cache, datasets)
    report.left_alone = list(scan.left_alone)
    for item in scan.artifacts:
        report.checked += 1
        problems = verify_item(item, checksums=checksums)
        if problems:
            report.damaged[item] = problems
        advance()
    now = time.time()
    for p in scan.leftovers:
        try:
            old = leftover_age_s(p, now) >= leftover_min_age_s
        except FileNotFoundError:  # finished (renamed or removed) since the walk
            continue
        (report.leftovers if old else report.young_leftovers).append(p)
    if repair:
        todo = [*report.damaged, *report.leftovers]
        for i, p in enumerate(todo):
            refused = _removable(p, cache)
            if refused:
                report.left_alone.append((p, refused))
                continue
            try:
                _remove(p)
            except OSError as e:
                why = _WHY.get(e.errno, e.strerror or str(e))  # rmtree names a file relative to its folder: name p
                report.errors.append(f"{p}: cannot remove it ({why}); {len(report.removed)} of {len(todo)} "
                                     f"removed, the rest left as they were")
                break
            report.removed.append(p)
    return report


def count_items(cache: Path, datasets: Iterable[str] | None = None) -> int:
    """Number of artifact items :func:`verify_cache` will check (for a progress bar)."""
    return len(scan_cache(Path(cache), datasets).artifacts) if Path(cache).is_dir() else 0

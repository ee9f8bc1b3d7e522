"""The ``--out`` folder of ``freeze estimate``: it writes only what it owns.

A folder is the estimate's when it holds the marker :data:`MARKER`
(``OUT/.freeze-estimate.json``), which lists every file the estimate wrote there, with
its size and SHA-256. The rules (checked before any stage runs, and again just before
the outputs are put in place):

- a new ``--out`` is created; an empty one is used; either gets the marker;
- a non-empty ``--out`` without the marker is refused, naming its first entry: the
  estimate never deletes, replaces or mixes into a folder it did not write;
- in a folder with the marker, a rerun replaces only what the marker lists. A file in
  the way of the outputs (``pose.json``, ``overlay.png``, ``points.png``, the stages'
  folders, ``bop/``) that the marker does not list, or that changed since it was
  written, is refused, naming it; other entries (the user's notes beside the outputs)
  are left as they are;
- ``--out`` onto a file, a read-only or full file system: one line naming the path.

Everything is first written to a staging folder inside ``--out``
(``.freeze-estimate-new-<id>``), and moved into place only once complete, so a failed
run (a full disk, an error in a stage) leaves the previous outputs as they were and no
half-written file; a folder the run created is removed again.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

from pipeline.workflow.stage_graph import stages_of_side

from .inputs import EstimateError

MARKER = ".freeze-estimate.json"
"""The marker file of a folder written by ``freeze estimate`` (lists the files it wrote)."""
TEMP_PREFIX = ".freeze-estimate-"
"""Prefix of the estimate's own temporary folders in ``--out`` (staging, replaced outputs):
leftovers of an interrupted run, removed by the next."""
OUTPUT_NAMES = ("pose.json", "overlay.png", "points.png", *stages_of_side("model"), *stages_of_side("scene"), "bop")
"""The entries the estimate writes at the top of ``--out``."""


def why(e: OSError) -> str:
    """A short reason for an OSError (errno's meaning, in words)."""
    return {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
            errno.EROFS: "read-only file system", errno.EACCES: "permission denied", errno.EPERM: "permission denied",
            errno.ENOTDIR: "a parent is not a folder", errno.EEXIST: "a parent is a file, not a folder",
            }.get(e.errno, e.strerror or str(e))


def _write_error(out: Path, path: Path | str, e: OSError) -> EstimateError:
    return EstimateError(f"{path}: cannot write it ({why(e)}); --out {out} is left as it was before the run")


def _entries(folder: Path) -> Iterator[tuple[str, Path, bool]]:
    """(relative posix path, path, whether it is a file or link) of every file, link and
    empty folder under ``folder``, sorted, links not followed."""
    for top, dirs, files in os.walk(folder):
        dirs.sort()
        rel_top = Path(top).relative_to(folder)
        links = [d for d in dirs if os.path.islink(os.path.join(top, d))]
        dirs[:] = [d for d in dirs if d not in links]
        leaves = sorted(files + links)
        for name in leaves:
            yield (rel_top / name).as_posix(), Path(top) / name, True
        if not dirs and not leaves and rel_top != Path("."):
            yield rel_top.as_posix(), Path(top), False


def file_list(folder: Path) -> dict[str, dict[str, Any]]:
    """``{relative posix path: {"size", "sha256"}}`` of every file under ``folder``."""
    from pipeline.common.store import file_digest

    return {rel: {"size": p.stat().st_size, "sha256": file_digest(p)} for rel, p, leaf in _entries(folder) if leaf}


def _read_marker(out: Path) -> dict[str, list[dict[str, Any]]] | None:
    """The files the marker of ``out`` lists, each with its recorded versions (``files``
    and, after an interrupted swap, ``previous``); None when there is no marker."""
    path = out / MARKER
    if not path.exists() and not path.is_symlink():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(doc, dict) or doc.get("written_by") != "freeze estimate":
            raise ValueError("not written by freeze estimate")
        files, previous = doc["files"], doc.get("previous", {})
        listed = {rel: [v for v in (files.get(rel), previous.get(rel)) if v is not None] for rel in {*files, *previous}}
        if not all(isinstance(v, dict) and {"size", "sha256"} <= set(v) for vs in listed.values() for v in vs):
            raise ValueError("entries without size and sha256")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise EstimateError(f"{path}: not a marker of freeze estimate ({e}); --out is refused: give a new or empty "
                            "folder") from None
    return listed


def _matching(path: Path, versions: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The version (``{"size", "sha256"}``) that the file ``path`` is, None when it is
    none of them (or not a plain file)."""
    from pipeline.common.store import file_digest

    if path.is_symlink() or not path.is_file():
        return None
    size = path.stat().st_size
    candidates = [v for v in versions if v["size"] == size]
    digest = file_digest(path) if candidates else None
    return next((v for v in candidates if v["sha256"] == digest), None)


def check_owned(out: Path, names: tuple[str, ...] = OUTPUT_NAMES) -> tuple[dict[str, dict], dict[str, list[dict]]]:
    """Check that the estimate may write ``names`` into ``out`` (see the module's rules)
    without losing a file it did not write. Returns (the files now in the way of
    ``names``, each with the version of the marker it is; everything the marker lists),
    both empty when ``out`` is new or empty. Raises EstimateError naming the first file
    in the way."""
    if out.is_symlink() and not out.exists():
        raise EstimateError(f"--out {out}: a broken link; give a new or empty folder")
    if out.exists() and not out.is_dir():
        raise EstimateError(f"--out {out}: exists and is not a folder; give a new or empty folder")
    if not out.exists():
        return {}, {}
    listed = _read_marker(out)
    in_the_way: dict[str, dict] = {}
    for rel, path, leaf in _entries(out):
        top = rel.split("/", 1)[0]
        if rel == MARKER or top.startswith(TEMP_PREFIX):
            continue
        if listed is None:
            raise EstimateError(f"--out {out}: holds {path}, which freeze estimate did not write (no {MARKER} "
                                "there); give a new or empty folder, it never replaces files it did not write")
        if top not in names or not leaf:
            continue  # not in the way (left as it is), or an empty folder: nothing to lose
        if rel not in listed:
            raise EstimateError(f"--out {out}: {path} is not a file freeze estimate wrote ({MARKER} does not list "
                                "it); move it away or give another folder")
        version = _matching(path, listed[rel])
        if version is None:
            raise EstimateError(f"--out {out}: {path} changed since freeze estimate wrote it; move it away or give "
                                "another folder")
        in_the_way[rel] = version
    return in_the_way, listed or {}


@dataclass
class OutFolder:
    """``--out`` claimed for one run: ``staging`` (inside it) is where the run writes;
    :meth:`commit` moves the outputs into place, :meth:`abort` removes what the run
    wrote. ``created``: the folders this run created (``out`` and missing parents),
    deepest first."""

    out: Path
    staging: Path
    created: list[Path] = field(default_factory=list)

    def final(self, path: Path) -> Path:
        """Where ``path`` (under :attr:`staging`) will be once committed."""
        return self.out / Path(path).relative_to(self.staging)

    def commit(self) -> None:
        """Put the staged outputs in place of the previous ones (which the marker lists
        and :func:`check_owned` checks again now: the stages took a while), then write the
        marker listing them. On an error the previous outputs are put back and
        EstimateError names the path."""
        from pipeline.common.store import atomic_write_text, swap_entries

        names = tuple(sorted(p.name for p in self.staging.iterdir()))
        in_the_way, listed = check_owned(self.out, names)
        marker = self.out / MARKER
        old_marker = marker.read_text(encoding="utf-8") if marker.is_file() else None
        aside = self.out / f"{TEMP_PREFIX}old-{uuid.uuid4().hex[:8]}"
        try:
            new = file_list(self.staging)
            # while the outputs are swapped both listings hold: an interruption leaves a
            # folder whose every file the next run recognises as its own
            atomic_write_text(self.out / MARKER, _marker_text(new, in_the_way))
            swap_entries(self.staging, self.out, names, aside)  # undone on an error
        except OSError as e:
            shutil.rmtree(aside, ignore_errors=True)
            try:
                if old_marker is None:
                    (self.out / MARKER).unlink(missing_ok=True)
                else:
                    atomic_write_text(self.out / MARKER, old_marker)
            except OSError:
                pass  # the interim marker (both listings) stays: it still names every file on disk
            raise _write_error(self.out, getattr(e, "filename", None) or self.out, e) from None
        try:
            atomic_write_text(self.out / MARKER, _marker_text(new, {}))
        except OSError:
            pass  # the interim marker lists the new outputs too: the next run still recognises them
        # files of the previous run outside what this one wrote were the estimate's too: stale now
        for rel, versions in _outside(listed, names).items():
            if _matching(self.out / rel, versions) is not None:
                (self.out / rel).unlink()
        shutil.rmtree(aside, ignore_errors=True)
        shutil.rmtree(self.staging, ignore_errors=True)

    def abort(self) -> None:
        """Remove the staging folder, and the folders this run created when they hold
        nothing else."""
        shutil.rmtree(self.staging, ignore_errors=True)
        for folder in self.created:
            try:
                folder.rmdir()
            except OSError:
                break  # not empty (or not ours to remove): stop


def _outside(listed: Mapping[str, list[dict]], names: tuple[str, ...]) -> dict[str, list[dict]]:
    """The marker's files that are not under ``names``."""
    return {rel: v for rel, v in listed.items() if rel.split("/", 1)[0] not in names}


def _marker_text(files: Mapping[str, Any], previous: Mapping[str, Any]) -> str:
    doc = {"written_by": "freeze estimate",
           "note": "freeze estimate wrote the files listed here; a rerun with this --out replaces only them",
           "files": dict(files), **({"previous": dict(previous)} if previous else {})}
    return json.dumps(doc, indent=1, sort_keys=True) + "\n"


def claim(out: Path | str) -> OutFolder:
    """Check ``out`` (:func:`check_owned`), create it (and its missing parents) and a
    staging folder in it; removes the leftovers of an interrupted run. Raises
    EstimateError, one line naming the path, when it is not the estimate's to write or
    cannot be written (a file, a read-only or full file system)."""
    out = Path(out)
    check_owned(out)
    missing = [p for p in (out, *out.parents) if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob(f"{TEMP_PREFIX}*"):
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
        staging = out / f"{TEMP_PREFIX}new-{uuid.uuid4().hex[:8]}"
        staging.mkdir()
    except OSError as e:
        for folder in missing:
            try:
                folder.rmdir()
            except OSError:
                break
        raise EstimateError(f"--out {out}: cannot write there ({why(e)})") from None
    return OutFolder(out=out, staging=staging, created=missing)

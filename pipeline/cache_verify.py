"""Checking a cache against its manifests (``freeze verify``).

A cache holds ``<dataset>/<stage>/<signature>/<item>/`` folders, each published
atomically with a ``_manifest.json`` that lists every file's size and SHA-256
(:func:`pipeline.store.file_table`). Damage after publishing (a truncated chunk, a
deleted array, a hand-edited table, a half-written manifest) is found here, and
``--repair`` removes the damaged item folders so that the next run rebuilds exactly
those. Leftovers of killed publishes (hidden ``.tmp-*`` and ``.old-*`` folders,
``.*.tmp`` files) are found and removed too: they are never read, only disk space.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

from pipeline.store import MANIFEST_NAME, verify_item


@dataclass
class VerifyReport:
    """What :func:`verify_cache` found: items checked, damaged items with their
    problems, leftovers of killed publishes, and what ``repair`` removed."""

    checked: int = 0
    damaged: dict[Path, list[str]] = field(default_factory=dict)
    leftovers: list[Path] = field(default_factory=list)
    removed: list[Path] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.damaged and not self.leftovers


def _is_leftover(p: Path) -> bool:
    """A folder of an interrupted publish (:data:`pipeline.artifacts.LEFTOVER_PREFIXES`)
    or a file of an interrupted :func:`pipeline.store.atomic_path` (``.<name>.<hex>.tmp``)."""
    from pipeline.artifacts import LEFTOVER_PREFIXES

    return p.name.startswith(LEFTOVER_PREFIXES) or (p.name.startswith(".") and p.name.endswith(".tmp"))


def item_folders(cache: Path, datasets: Iterable[str] | None = None) -> Iterator[Path]:
    """Every artifact item folder (``<dataset>/<stage>/<signature>/<item>``) under
    ``cache``, sorted, with leftovers of killed publishes excluded."""
    wanted = set(datasets) if datasets else None
    for ds in sorted(p for p in cache.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if wanted is not None and ds.name not in wanted:
            continue
        for stage in sorted(p for p in ds.iterdir() if p.is_dir() and not p.name.startswith(".")):
            for sig in sorted(p for p in stage.iterdir() if p.is_dir() and not p.name.startswith(".")):
                for item in sorted(p for p in sig.iterdir() if p.is_dir() and not _is_leftover(p)):
                    yield item


def leftovers(cache: Path, datasets: Iterable[str] | None = None) -> list[Path]:
    """Hidden temporary folders and files that killed publishes left in signature
    folders (or beside the cache's own files)."""
    wanted = set(datasets) if datasets else None
    out = []
    for ds in sorted(p for p in cache.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if wanted is not None and ds.name not in wanted:
            continue
        for stage in sorted(p for p in ds.iterdir() if p.is_dir()):
            for sig in sorted(p for p in stage.iterdir() if p.is_dir()):
                out += sorted(p for p in sig.iterdir() if _is_leftover(p))
    return out


def verify_cache(cache: Path, datasets: Iterable[str] | None = None, *, checksums: bool = True,
                 repair: bool = False, leftover_min_age_s: float = 3600.0,
                 advance: Callable[[], None] = lambda: None) -> VerifyReport:
    """Check every item folder under ``cache`` (optionally only ``datasets``) against its
    manifest (:func:`pipeline.store.verify_item`; ``checksums=False`` compares sizes
    only). Leftovers younger than ``leftover_min_age_s`` may be a running job's and are
    left out. With ``repair``, damaged items and leftovers are deleted. ``advance`` is
    called once per item (a progress bar)."""
    import time

    from pipeline.artifacts import leftover_age_s

    cache = Path(cache)
    report = VerifyReport()
    if not cache.is_dir():
        return report
    for item in item_folders(cache, datasets):
        report.checked += 1
        if not (item / MANIFEST_NAME).exists() and not any(item.iterdir()):
            advance()
            continue  # an empty folder: nothing to trust or distrust
        problems = verify_item(item, checksums=checksums)
        if problems:
            report.damaged[item] = problems
        advance()
    now = time.time()
    report.leftovers = [p for p in leftovers(cache, datasets) if leftover_age_s(p, now) >= leftover_min_age_s]
    if repair:
        for p in [*report.damaged, *report.leftovers]:
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink(missing_ok=True)
            report.removed.append(p)
    return report


def count_items(cache: Path, datasets: Iterable[str] | None = None) -> int:
    """Number of item folders :func:`verify_cache` will check (for a progress bar)."""
    return sum(1 for _ in item_folders(Path(cache), datasets)) if Path(cache).is_dir() else 0

"""Which weight files the encoder manifests can fetch, and what the weights folder holds.

The URLs live in the encoder manifests (``download:`` entries of
``manifests/encoders/*.yaml``), never in code. :func:`manifests_with_downloads` reads
them, :func:`select` turns the names a user gave (or ``--all``) into the files to fetch,
each once even when several manifests share it (``dinov2-vits14`` and
``dinov2-vits14-fp32`` load the same checkpoint), and :func:`entry_status` says what
the folder holds for an entry.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal

from pipeline.common import config as cfg
from pipeline.common.config import EncoderManifest, ManifestError, WeightDownload
from pipeline.common.stand_in import paper_fetch
from pipeline.common.store import file_digest
from pipeline.formats.weights.fetch import judge_file, part_path, pinned_digest, read_sidecar, sidecar_path, target_path
from pipeline.formats.weights.formats import FORMAT_NAMES, expected_format, sniff

Source = Literal["official", "hf"]
SOURCES: tuple[Source, ...] = ("official", "hf")


class UnknownWeights(ManifestError):
    """A name given to ``freeze weights fetch`` is not an encoder manifest with downloads."""


@dataclass(frozen=True)
class Listed:
    """An encoder manifest that has downloads: its name, file and contents."""

    name: str
    path: Path
    manifest: EncoderManifest


@dataclass
class Planned:
    """One file to fetch: the entry, the manifest it is taken from (named in messages)
    and every manifest asking for it."""

    download: WeightDownload
    manifest: Path
    names: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        """The first manifest naming the file (for the command that retries)."""
        return self.names[0]


def manifest_dir_default() -> Path:
    """The manifest folder, read at call time (tests point ``pipeline.common.config.MANIFEST_DIR`` elsewhere)."""
    return Path(cfg.MANIFEST_DIR)


def manifests_with_downloads(manifest_dir: str | os.PathLike | None = None) -> list[Listed]:
    """Every encoder manifest with at least one ``download:`` entry, sorted by name.
    A manifest that does not validate raises its ``ManifestError`` (naming the file)."""
    manifest_dir = Path(manifest_dir) if manifest_dir is not None else manifest_dir_default()
    out = []
    for name in cfg.encoder_manifest_names(manifest_dir):
        man = cfg.load_encoder_manifest(name, manifest_dir)
        if man.download:
            out.append(Listed(name, manifest_dir / "encoders" / f"{name}.yaml", man))
    return out


def select(names: Iterable[str], *, fetch_all: bool = False, source: Source = "official",
           manifest_dir: str | os.PathLike | None = None) -> tuple[list[Planned], list[str]]:
    """The files to fetch for the manifests ``names`` (or every manifest with
    downloads when ``fetch_all``), from ``source``; each file once.

    Returns (the files, notes): a note per manifest of ``--all`` skipped because it
    has no download from ``source``. Raises :class:`UnknownWeights` for a name that is
    no manifest with downloads, or that has none from ``source`` (both list the names
    that have), before anything is fetched.
    """
    if source not in SOURCES:
        raise UnknownWeights(f"unknown source {source!r}: use one of {', '.join(SOURCES)}")
    listed = {m.name: m for m in manifests_with_downloads(manifest_dir)}
    names = list(dict.fromkeys(names))
    if fetch_all:
        names = list(dict.fromkeys([*names, *listed]))
    if not names:
        paper = paper_fetch(Path(manifest_dir) if manifest_dir is not None else manifest_dir_default())
        raise UnknownWeights(f"name the encoders to fetch weights for, or pass --all; manifests with downloads: "
                             f"{', '.join(listed) or 'none'}"
                             + (f"; the paper's configuration: `{paper}`" if paper else ""))
    unknown = [n for n in names if n not in listed]
    if unknown:
        raise UnknownWeights(f"no encoder manifest with downloads named {', '.join(map(repr, unknown))}; those "
                             f"with downloads: {', '.join(listed) or 'none'}")
    planned: dict[str, Planned] = {}
    notes = []
    for name in names:
        entries = [d for d in listed[name].manifest.download if d.source == source]
        if not entries:
            has = sorted({d.source for d in listed[name].manifest.download})
            message = f"{name} has no download from source {source!r} (it has: {', '.join(has)})"
            if fetch_all:
                notes.append(message + ", skipped")
                continue
            with_source = [n for n, m in listed.items() if any(d.source == source for d in m.manifest.download)]
            raise UnknownWeights(f"{message}; manifests with {source} downloads: {', '.join(with_source) or 'none'}")
        for d in entries:
            key = Path(d.file).as_posix()
            if key not in planned:
                planned[key] = Planned(d, listed[name].path)
            planned[key].names.append(name)
    return list(planned.values()), notes


Status = Literal["missing", "partial", "present", "verified", "mismatch", "invalid"]


def entry_status(download: WeightDownload, weights_dir: Path, manifest: str | os.PathLike = "",
                 digests: dict[tuple, str] | None = None) -> dict[str, Any]:
    """What ``weights_dir`` holds for one entry: ``{"path", "status", "bytes", "partial_bytes", "sha256", "note"}``.

    status: ``missing`` (no file), ``partial`` (only an interrupted download's ``.part``),
    ``present`` (a file without a recorded digest, e.g. placed by hand, that agrees with
    the pinned one if any: ``fetch`` records it), ``verified`` (the file agrees with its
    recorded digest and the pinned one), ``mismatch`` (it disagrees with one of them),
    ``invalid`` (its first bytes are not of its format: a web page saved as the file).
    bytes: the file's size, or the manifest's approximate size when it is missing.
    Present files are hashed (about 1 GB/s); ``digests`` caches them across calls by
    (path, size, mtime), as manifests share files.
    """
    final = target_path(download, weights_dir, manifest)
    part = part_path(final)
    row: dict[str, Any] = {"path": str(final), "status": "missing", "bytes": download.size, "partial_bytes": 0,
                           "sha256": None, "note": ""}
    if part.is_file():
        row["partial_bytes"] = part.stat().st_size
    if not final.is_file():
        if row["partial_bytes"]:
            row.update(status="partial", note=f"{row['partial_bytes']} bytes in {part.name}: fetch resumes it")
        return row
    st = final.stat()
    key = (str(final), st.st_size, st.st_mtime_ns)
    digests = {} if digests is None else digests
    if key not in digests:
        digests[key] = file_digest(final)
    actual = digests[key]
    row.update(bytes=st.st_size, sha256=actual)
    verdict = judge_file(actual, read_sidecar(final), pinned_digest(download, manifest))
    row.update({
        "changed": {"status": "mismatch", "note": f"differs from {sidecar_path(final).name}: changed or corrupt"},
        "not-pinned": {"status": "mismatch", "note": "differs from the manifest's sha256"},
        "unrecorded": {"status": "present", "note": "no recorded digest yet (fetch records it)"},
        "verified": {"status": "verified"},
    }[verdict])
    fmt = expected_format(final)
    problem = sniff(final, fmt) if fmt is not None and row["status"] != "mismatch" else None
    if problem is not None:
        row.update(status="invalid", note=f"{problem}, not a {FORMAT_NAMES[fmt]}: delete it and fetch it again")
    return row

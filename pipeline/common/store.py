"""The artifact store: cache keys, atomic publish, manifests, Zarr and Parquet helpers.

Every artifact is a directory ``cache/<dataset>/<stage>/<signature>/<item>/`` holding its
data files and a ``_manifest.json`` written last. The signature is a readable name plus
a short hash of the stage's *key*; the key is the SHA-1 of the canonical JSON of
(stage name, stage code version, parameters, upstream keys), so it is known before
anything runs (Snakemake computes output paths from it at DAG time).

Publishing is atomic: an item is written into a hidden temporary sibling directory and
renamed into place only when complete, manifest included. A killed or failed stage
leaves the previous artifact untouched and no half-written one. The manifest lists every
file with its size and SHA-256 digest; :func:`verify_item` checks them, and stages check
their inputs (:func:`ensure_sound`) before reading them.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import platform
import resource
import shutil
import sys
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from pipeline.common.threads import job_threads

MANIFEST_NAME = "_manifest.json"

# Set by the stage runner when a job starts, so that a manifest's wall time covers the
# whole job (reading inputs and computing), not only the writing inside publish().
JOB_START: float | None = None


def mark_job_start() -> None:
    global JOB_START
    JOB_START = time.perf_counter()
MANIFEST_SCHEMA = 2  # 2: "files" lists each file's size and SHA-256 digest

# Libraries whose versions are recorded in every manifest (they change outputs).
_TRACKED_LIBRARIES = ("numpy", "scipy", "torch", "open3d-cpu", "open3d", "trimesh", "pyrender", "opencv-python-headless", "zarr", "pyarrow")


def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, no whitespace, floats via repr) used for hashing."""
    return json.dumps(_plain(obj), sort_keys=True, separators=(",", ":"), allow_nan=False)


def _plain(obj: Any) -> Any:
    """Convert numpy scalars/arrays, tuples and Paths into plain JSON values."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def make_key(stage: str, code_version: int | str, params: Mapping[str, Any], upstream: Mapping[str, str]) -> str:
    """Full SHA-1 hex key of a stage artifact."""
    payload = {"stage": stage, "code_version": code_version, "params": params, "upstream": dict(upstream)}
    return hashlib.sha1(canonical_json(payload).encode()).hexdigest()


def make_signature(readable: str, key: str) -> str:
    """Directory name: readable part plus 8 hex digits of the key, e.g. ``fpfh-ms+colortex-3f9a1c2e``."""
    readable = readable.replace("_", "-").replace("/", "-")
    return f"{readable}-{key[:8]}"


def _hash_file(path: Path | str, h, chunk: int = 1 << 20) -> str:
    """Hex digest of a file's bytes with the hashlib object ``h``, read in chunks."""
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def file_sha1(path: Path) -> str:
    """SHA-1 of a file's bytes (the priors' and real samples' keys)."""
    return _hash_file(path, hashlib.sha1())


def library_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in _TRACKED_LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def peak_rss_mb() -> float:
    """Peak resident memory of this process and its finished children, in MiB."""
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(self_kb, child_kb) / 1024.0


class DamagedArtifact(RuntimeError):
    """A published artifact whose files no longer match its manifest (truncated,
    deleted, altered) or whose manifest is unreadable. The message starts with the item
    folder, names the file, and says how to rebuild it."""


REPAIR_HINT = "run `freeze verify --repair` to remove it, then rerun to rebuild it"


def read_manifest(path: Path) -> dict[str, Any]:
    """Read an artifact's manifest; ``path`` is the item directory or the manifest file.
    Raises FileNotFoundError when there is none, :class:`DamagedArtifact` when it is not
    a readable manifest."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    if not path.exists():
        raise FileNotFoundError(f"{path}: no artifact manifest (the artifact is missing or was never completed)")
    try:
        content = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DamagedArtifact(f"{path.parent}: {MANIFEST_NAME} is not valid JSON ({e}); {REPAIR_HINT}") from None
    if not isinstance(content, dict) or "key" not in content:
        raise DamagedArtifact(f"{path.parent}: {MANIFEST_NAME} is not an artifact manifest (no 'key'); {REPAIR_HINT}")
    return content


# --------------------------------------------------------------------- checksums
# Every published file's size and SHA-256 digest are recorded in the manifest, so a
# reader can tell a damaged artifact (truncated chunk, deleted array) from a good one
# before it reads it. SHA-256 was the fastest of the standard library's hashes here
# (1.2 GB/s per core with the CPU's SHA instructions; BLAKE2b 0.49 GB/s, measured on
# 200 MB), far below the cost of computing any artifact.


def file_digest(path: Path | str) -> str:
    """SHA-256 hex digest of a file's bytes."""
    return _hash_file(path, hashlib.sha256())


def file_table(folder: Path | str) -> dict[str, dict[str, Any]]:
    """``{relative posix path: {"size": bytes, "sha256": hex}}`` of every file under
    ``folder`` except the manifest, sorted by path."""
    folder = Path(folder)
    out = {}
    for p in sorted(q for q in folder.rglob("*") if q.is_file() and q.name != MANIFEST_NAME):
        out[p.relative_to(folder).as_posix()] = {"size": p.stat().st_size, "sha256": file_digest(p)}
    return out


def verify_item(item_dir: Path | str, *, checksums: bool = True) -> list[str]:
    """Problems of one published artifact item (empty when sound): an unreadable
    manifest, a listed file missing, of another size or (with ``checksums``) another
    digest. Files the manifest does not list are not problems (a manifest from before
    checksums lists none: such an item can only be checked for its manifest)."""
    item_dir = Path(item_dir)
    try:
        manifest = read_manifest(item_dir)
    except DamagedArtifact as e:
        return [str(e)]
    except FileNotFoundError:
        return [f"{item_dir}: no {MANIFEST_NAME} (never completed, or deleted)"]
    problems = []
    files = manifest.get("files")
    if not isinstance(files, dict):
        return problems
    for rel, rec in files.items():
        p = item_dir / rel
        try:
            size = p.stat().st_size
        except FileNotFoundError:
            problems.append(f"{item_dir}: {rel} is missing")
            continue
        except OSError as e:
            problems.append(f"{item_dir}: {rel} cannot be read ({e.strerror})")
            continue
        if size != rec.get("size"):
            problems.append(f"{item_dir}: {rel} is {size} bytes, its manifest says {rec.get('size')}")
        elif checksums and file_digest(p) != rec.get("sha256"):
            problems.append(f"{item_dir}: {rel} differs from its manifest's checksum")
    return problems


_VERIFIED: dict[Path, tuple] = {}


def _stamp(item_dir: Path) -> tuple | None:
    """(path, size, mtime, inode) of every file of an item: what must not change for an
    earlier verification to still hold."""
    try:
        return tuple((p.as_posix(), st.st_size, st.st_mtime_ns, st.st_ino)
                     for p in sorted(item_dir.rglob("*")) if (st := p.stat()) and p.is_file())
    except FileNotFoundError:
        return None


def ensure_sound(item_dir: Path | str) -> None:
    """Raise :class:`DamagedArtifact` (naming the item, the file and the fix) unless the
    item verifies (:func:`verify_item`), as every stage does for each input before
    reading it. An item is hashed once per process while its files keep their sizes,
    times and inodes."""
    item_dir = Path(item_dir)
    if not item_dir.exists():
        raise FileNotFoundError(f"{item_dir}: this input artifact is not built yet (run its stage first)")
    stamp = _stamp(item_dir)
    if stamp is not None and _VERIFIED.get(item_dir) == stamp:
        return
    problems = verify_item(item_dir)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise DamagedArtifact(f"damaged artifact: {problems[0]}{more}; {REPAIR_HINT}")
    if stamp is not None:
        _VERIFIED[item_dir] = stamp


# ------------------------------------------------------------------- atomic writes
# Every file or folder the project publishes goes through these two context managers:
# the content is written under a temporary sibling name and renamed into place, so a
# reader never sees half of it and a killed writer leaves the previous version.


class StorageError(OSError):
    """The disk refused a write (full, over quota, read-only, no permission). The message
    names the file or folder being published; nothing was published."""


# Errors that can only mean the disk refused the write (a PermissionError inside the
# block may come from reading an input, so it is left as it is there).
_STORAGE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS}


def _storage_error(target: Path, e: OSError) -> StorageError:
    why = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
           errno.EROFS: "read-only file system"}.get(e.errno, e.strerror or str(e))
    return StorageError(e.errno, f"{target}: cannot write it ({why}); nothing was published and the previous "
                                 "version, if any, is intact: free space or fix permissions, then rerun")


@contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """A temporary sibling path to write the file ``path`` into; renamed onto ``path``
    when the block ends normally, removed when it raises."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except StorageError:
        raise
    except OSError as e:
        if e.errno in _STORAGE_ERRNOS:
            raise _storage_error(path, e) from None
        raise
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_dir(final_dir: Path | str, prefix: str = ".tmp-") -> Iterator[Path]:
    """A temporary sibling folder to fill; it replaces ``final_dir`` (an older copy is
    moved aside first and deleted after) when the block ends normally, and is deleted
    when it raises, leaving ``final_dir`` as it was."""
    final_dir = Path(final_dir)
    tmp = final_dir.parent / f"{prefix}{final_dir.name}-{uuid.uuid4().hex[:8]}"
    try:
        final_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as e:
        if e.errno in _STORAGE_ERRNOS | {errno.EACCES, errno.EPERM}:
            raise _storage_error(final_dir, e) from None
        raise
    try:
        yield tmp
        old = None
        if final_dir.exists() or final_dir.is_symlink():
            old = final_dir.parent / f".old-{final_dir.name}-{uuid.uuid4().hex[:8]}"
            os.replace(final_dir, old)
        os.replace(tmp, final_dir)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink()
    except StorageError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if e.errno in _STORAGE_ERRNOS:
            raise _storage_error(final_dir, e) from None
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def swap_entries(staging: Path | str, out: Path | str, names: tuple[str, ...], aside: Path | str) -> None:
    """Move the entries ``names`` (files or folders) of ``staging`` into ``out``, each
    previous entry of the same name first moved into the new folder ``aside`` (in
    ``out``, so that every move is a rename within one file system and needs no space).
    Several entries cannot be replaced at once; on an error the moves done so far are
    undone, as far as the file system allows, before the OSError propagates, so ``out``
    holds the previous entries again. ``aside`` is left for the caller to delete."""
    staging, out, aside = Path(staging), Path(out), Path(aside)
    moved: list[str] = []  # names whose previous version is in ``aside``
    placed: list[str] = []  # names whose new version is in ``out``
    try:
        aside.mkdir()
        for name in names:
            if (out / name).exists() or (out / name).is_symlink():
                os.replace(out / name, aside / name)
                moved.append(name)
            os.replace(staging / name, out / name)
            placed.append(name)
    except OSError:
        undo = [(out / n, staging / n) for n in placed] + [(aside / n, out / n) for n in moved]
        for src, dst in undo:
            try:
                os.replace(src, dst)
            except OSError:
                pass  # left under a name the caller's records still account for
        raise


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` (UTF-8, ``\\n`` line ends) to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)


def _write_json_atomic(path: Path, content: Any) -> None:
    atomic_write_text(path, json.dumps(_plain(content), indent=2, sort_keys=True) + "\n")


@dataclass
class ArtifactWriter:
    """Collects files in a temporary directory; :func:`publish` moves them into place.

    ``dir`` is the temporary directory to write into. Set ``summary`` entries (shapes,
    counts, skipped items with reasons) to have them recorded in the manifest.
    """

    final_dir: Path
    dir: Path
    manifest: dict[str, Any]
    summary: dict[str, Any] = field(default_factory=dict)


@contextmanager
def publish(
    final_dir: Path,
    *,
    stage: str,
    item: str,
    key: str,
    signature: str,
    params: Mapping[str, Any],
    upstream: Mapping[str, str],
    code_version: int | str,
    dataset: str,
) -> Iterator[ArtifactWriter]:
    """Write an artifact item atomically.

    Usage::

        with publish(item_dir, stage=..., ...) as w:
            save_arrays(w.dir / "features.zarr", {...})
            w.summary["n_points"] = 5000

    On normal exit the manifest is written into the temporary directory and the
    directory is renamed to ``final_dir`` (replacing an older copy, which is removed
    only after the new one is in place). On an exception the temporary directory is
    deleted and ``final_dir`` is left as it was.
    """
    t0 = JOB_START if JOB_START is not None else time.perf_counter()
    manifest: dict[str, Any] = {
        "schema": MANIFEST_SCHEMA,
        "dataset": dataset,
        "stage": stage,
        "item": item,
        "key": key,
        "signature": signature,
        "code_version": code_version,
        "params": _plain(dict(params)),
        "upstream": dict(upstream),
    }
    with atomic_dir(final_dir) as tmp:
        writer = ArtifactWriter(final_dir=Path(final_dir), dir=tmp, manifest=manifest)
        yield writer
        manifest["summary"] = _plain(writer.summary)
        manifest["created"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        manifest["wall_time_s"] = round(time.perf_counter() - t0, 3)
        manifest["peak_rss_mb"] = round(peak_rss_mb(), 1)
        manifest["threads"] = job_threads()
        manifest["host"] = platform.node()
        manifest["argv"] = sys.argv
        manifest["libraries"] = library_versions()
        manifest["files"] = file_table(tmp)
        _write_json_atomic(tmp / MANIFEST_NAME, manifest)


# ----------------------------------------------------------------------------- zarr


def save_arrays(
    path: Path,
    arrays: Mapping[str, np.ndarray],
    *,
    chunks: Mapping[str, tuple[int, ...]] | None = None,
    attrs: Mapping[str, Any] | None = None,
) -> None:
    """Write arrays into a Zarr group (Blosc-zstd compressed).

    By default each array is chunked along its first (item) axis one item at a time,
    whole along the other axes; pass ``chunks`` to override per array.
    """
    import zarr
    from zarr.codecs import BloscCodec

    group = zarr.open_group(str(path), mode="w")
    if attrs:
        group.attrs.update(_plain(dict(attrs)))
    compressor = BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")
    for name, arr in arrays.items():
        arr = np.asarray(arr)
        if chunks and name in chunks:
            ch = chunks[name]
        elif arr.ndim == 0:
            ch = ()
        else:
            ch = (1,) + arr.shape[1:] if arr.ndim > 1 else (max(1, arr.shape[0]),)
        ch = tuple(max(1, c) for c in ch)
        z = group.create_array(name, shape=arr.shape, dtype=arr.dtype, chunks=ch, compressors=compressor)
        if arr.size:
            z[...] = arr


def load_arrays(path: Path, names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Read arrays (all, or ``names``) of a Zarr group into memory."""
    import zarr

    if not Path(path).exists():
        raise FileNotFoundError(f"{path}: Zarr store not found")
    try:
        group = zarr.open_group(str(path), mode="r")
        keys = names if names is not None else sorted(group.array_keys())
        return {k: np.asarray(group[k][...]) for k in keys}
    except KeyError as e:  # an array deleted, or a store from another version
        raise DamagedArtifact(f"{path}: no array {e} in the Zarr store; {REPAIR_HINT}") from None
    except (ValueError, OSError, RuntimeError) as e:  # truncated chunks and metadata
        raise DamagedArtifact(f"{path}: cannot read the Zarr store ({type(e).__name__}: {e}); {REPAIR_HINT}") from None


def load_attrs(path: Path) -> dict[str, Any]:
    import zarr

    return dict(zarr.open_group(str(path), mode="r").attrs)


# -------------------------------------------------------------------------- parquet


def write_table(df, path: Path, *, metadata: Mapping[str, Any] | None = None) -> None:
    """Write a pandas DataFrame to Parquet, with ``metadata`` in the schema (as JSON)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pandas(df, preserve_index=False)
    if metadata:
        meta = dict(table.schema.metadata or {})
        meta[b"freeze"] = canonical_json(metadata).encode()
        table = table.replace_schema_metadata(meta)
    pq.write_table(table, str(path))


def read_table(path: Path):
    """Read a Parquet file written by :func:`write_table` into a DataFrame."""
    import pyarrow.parquet as pq

    if not Path(path).exists():
        raise FileNotFoundError(f"{path}: Parquet table not found")
    try:
        return pq.read_table(str(path)).to_pandas()
    except (ValueError, OSError) as e:  # pyarrow.ArrowInvalid is a ValueError: a truncated or altered file
        raise DamagedArtifact(f"{path}: cannot read the Parquet table ({e}); {REPAIR_HINT}") from None


def table_metadata(path: Path) -> dict[str, Any]:
    import pyarrow.parquet as pq

    meta = pq.read_schema(str(path)).metadata or {}
    raw = meta.get(b"freeze")
    return json.loads(raw) if raw else {}


def item_seed(key: str, item: str, seed: int = 0) -> int:
    """A 32-bit seed derived from an artifact key, the item name and a user seed, so that
    sampling is reproducible per artifact and differs between items."""
    return int(hashlib.sha1(f"{key}/{item}/{seed}".encode()).hexdigest()[:8], 16)

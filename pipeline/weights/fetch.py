"""Fetching one weight file: resumable HTTP download, SHA-256, atomic publication.

For a manifest entry with ``file: F`` (relative to the weights folder ``W``), the
folder holds at most three names:

- ``W/F.part``: the bytes of the URL received so far. An interrupted transfer leaves
  it; the next fetch asks the server for the rest (``Range: bytes=N-``) and appends
  when the server answers 206, or starts again from zero when it answers 200.
- ``W/F``: the file the loader reads. It appears only whole and verified: renamed into
  place by :func:`pipeline.store.atomic_path`, never written under its own name.
- ``W/F.sha256``: the file's SHA-256 in ``sha256sum`` format (``<hex>  <name>``),
  written just before ``F`` is published, so a file that has a name always has one.

A zip entry (``member`` set) downloads the archive to ``W/F.part``, extracts the
member into a hidden temporary file beside ``F`` (hashing it on the way), publishes
it and deletes the archive.

Errors are :class:`WeightsFetchError`, each a single line naming the file, the URL and
the manifest: an HTTP status, no network (with the path to place the file at by hand
and the URL to fetch it from elsewhere), an interrupted transfer, a digest that
differs from the manifest's or from the one recorded earlier.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import http.client
import os
import re
import sys
import urllib.error
import urllib.parse
import urllib.request
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator, Literal

from pipeline.config import ManifestError, WeightDownload
from pipeline.store import atomic_path, file_digest

TIMEOUT_S = 30.0
"""Seconds to wait for a connection and then for each read: a dead link fails instead of hanging."""
CHUNK = 1 << 20  # bytes per read: large enough that Python's per-call cost is nothing next to the network
USER_AGENT = "freeze-weights/1 (python urllib)"
SIDECAR_SUFFIX = ".sha256"
PART_SUFFIX = ".part"

Log = Callable[[str], None]
FetchStatus = Literal["downloaded", "verified", "recorded"]


class WeightsFetchError(RuntimeError):
    """A weight file could not be fetched, or is not the file it should be. The message
    is one line naming the file, the URL and the manifest, and what to do."""


@dataclass(frozen=True)
class FetchResult:
    """What :func:`fetch_download` did for one file.

    status: ``downloaded`` (transferred now), ``verified`` (already there, matching its
    recorded digest; nothing transferred) or ``recorded`` (already there without a
    recorded digest, e.g. placed by hand: its digest is now recorded).
    size: bytes of the final file. received: bytes transferred by this call.
    resumed_from: bytes of the URL already on disk when this transfer started (0: from the start).
    """

    path: Path
    status: FetchStatus
    sha256: str
    size: int
    received: int = 0
    resumed_from: int = 0


# ------------------------------------------------------------------- names and sidecars


def target_path(download: WeightDownload, weights_dir: Path, manifest: str | Path = "") -> Path:
    """The final path of ``download.file`` under ``weights_dir``. The file must stay
    inside the folder: an absolute path or one with ``..`` is a manifest error."""
    rel = Path(download.file)
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise ManifestError(f"{manifest}: download file {download.file!r} must be a path inside the weights folder "
                            "(relative, without '..')")
    return Path(weights_dir) / rel


def part_path(final: Path) -> Path:
    """Where the bytes of the URL accumulate until the transfer is complete."""
    return final.with_name(final.name + PART_SUFFIX)


def sidecar_path(final: Path) -> Path:
    """The ``sha256sum``-format record of ``final``'s digest."""
    return final.with_name(final.name + SIDECAR_SUFFIX)


_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def read_sidecar(final: Path) -> str | None:
    """The digest recorded beside ``final`` (lower-case hex), None when there is no
    record, or ``""`` when the record is not a SHA-256 line (it then agrees with nothing)."""
    try:
        text = sidecar_path(final).read_text(errors="replace")
    except FileNotFoundError:
        return None
    words = text.split()
    return words[0].lower() if words and _HEX64.match(words[0].lower()) else ""


def write_sidecar(final: Path, digest: str) -> None:
    """Record ``digest`` beside ``final`` (atomically; ``sha256sum -c`` reads it from the folder)."""
    with atomic_path(sidecar_path(final)) as tmp:
        tmp.write_text(f"{digest}  {final.name}\n")


def pinned_digest(download: WeightDownload, manifest: str | Path = "") -> str | None:
    """The manifest's ``sha256`` in lower-case hex, or None when it pins none."""
    if download.sha256 is None:
        return None
    value = download.sha256.strip().lower()
    if not _HEX64.match(value):
        raise ManifestError(f"{manifest}: sha256 of {download.file!r} must be 64 hex digits, got {download.sha256!r}")
    return value


def human_size(n: int | None) -> str:
    """``88226304`` -> ``"88.2 MB"`` (decimal units, as download sizes are usually given)."""
    if n is None:
        return "size unknown"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


# ------------------------------------------------------------------------- the fetch


def fetch_download(
    download: WeightDownload,
    weights_dir: str | os.PathLike,
    *,
    manifest: str | os.PathLike = "",
    name: str | None = None,
    progress: bool | None = None,
    log: Log | None = None,
    timeout: float = TIMEOUT_S,
) -> FetchResult:
    """Make ``weights_dir / download.file`` the verified file the entry describes.

    An existing file is hashed and compared with its recorded digest and the pinned
    one; nothing is transferred then. Otherwise the URL is downloaded (resuming a
    ``.part`` left by an earlier run), verified and published atomically.

    manifest: the manifest file the entry comes from (named in messages); name: the
    encoder manifest's name, for the command that retries (default: the manifest's stem).
    progress: show a byte progress bar (default: when stderr is a terminal).
    log: called with one line per event (what is fetched, from where, the outcome).
    timeout: seconds for connecting and for each read.
    Raises :class:`WeightsFetchError` (or ``ManifestError`` for a bad entry).
    """
    log = log or (lambda line: None)
    manifest = str(manifest)
    name = name or (Path(manifest).stem if manifest else "NAME")
    weights_dir = Path(weights_dir)
    final = target_path(download, weights_dir, manifest)
    pinned = pinned_digest(download, manifest)
    done = _existing(final, pinned, manifest, log)
    if done is not None:
        return done
    if progress is None:
        progress = sys.stderr.isatty()
    final.parent.mkdir(parents=True, exist_ok=True)
    part = part_path(final)
    what = f"{download.file} (member {download.member} of a zip)" if download.member else download.file
    log(f"fetching {what}, {human_size(download.size)}, from {download.url} to {final}")
    ctx = _Context(download=download, final=final, part=part, manifest=manifest, name=name, timeout=timeout)
    with _locked_part(ctx) as out:
        done = _existing(final, pinned, manifest, log)  # another fetch may have published it meanwhile
        if done is not None:
            if out.seek(0, os.SEEK_END) == 0:
                part.unlink(missing_ok=True)
            return done
        try:
            digest, total, received, resumed = _transfer(ctx, out, progress)
        except BaseException:
            if out.tell() == 0:  # nothing received (no network, 404): leave no empty .part behind
                part.unlink(missing_ok=True)
            raise
        if download.member:
            digest, size = _publish_member(ctx, pinned)
        else:
            size = total
            _publish_file(ctx, digest, pinned)
    log(f"{final}: {human_size(size)}, sha256 {digest}"
        + (f" (resumed at byte {resumed})" if resumed else ""))
    return FetchResult(final, "downloaded", digest, size, received, resumed)


@dataclass(frozen=True)
class _Context:
    """One fetch's names, for the messages."""

    download: WeightDownload
    final: Path
    part: Path
    manifest: str
    name: str
    timeout: float

    @property
    def url(self) -> str:
        return self.download.url

    def where(self) -> str:
        return f"manifest {self.manifest}" if self.manifest else "no manifest"


FileVerdict = Literal["verified", "unrecorded", "changed", "not-pinned"]


def judge_file(actual: str, recorded: str | None, pinned: str | None) -> FileVerdict:
    """What a file under its final name is, from its digest ``actual``, the one recorded
    beside it (None: no record) and the manifest's pinned one (None: not pinned):
    ``changed`` (it differs from its record: changed or corrupt since it was fetched),
    ``not-pinned`` (it differs from the pinned digest), ``unrecorded`` (no record yet,
    e.g. placed by hand, and the pinned digest agrees if there is one) or ``verified``.
    The one judgement of ``fetch`` (:func:`fetch_download`) and ``list``
    (:func:`pipeline.weights.catalog.entry_status`)."""
    if recorded is not None and recorded != actual:
        return "changed"
    if pinned is not None and actual != pinned:
        return "not-pinned"
    return "unrecorded" if recorded is None else "verified"


def _existing(final: Path, pinned: str | None, manifest: str, log: Log) -> FetchResult | None:
    """The outcome for a file already under its final name, or None when there is none.

    Its digest must agree with the one recorded beside it (else it changed since it was
    fetched) and with the pinned one; a file without a record (placed by hand) gets one.
    """
    if not final.exists():
        return None
    if not final.is_file():
        raise WeightsFetchError(f"{final} exists but is not a file; move it away to fetch the weights "
                                f"(manifest {manifest})")
    actual = file_digest(final)
    recorded = read_sidecar(final)
    side = sidecar_path(final)
    verdict = judge_file(actual, recorded, pinned)
    if verdict == "changed":
        raise WeightsFetchError(
            f"{final}: its SHA-256 is {actual} but {side.name} recorded {recorded or '(an unreadable line)'} when it "
            f"was fetched: the file changed or is corrupt; delete {final} and {side} to fetch it again "
            f"(manifest {manifest})")
    if verdict == "not-pinned":
        raise WeightsFetchError(
            f"{final}: its SHA-256 is {actual} but {manifest} pins {pinned}: it is not the published file, or it is "
            f"corrupt; delete it (and {side.name} if present) to fetch it again")
    size = final.stat().st_size
    if verdict == "unrecorded":
        write_sidecar(final, actual)
        log(f"{final}: present without a recorded digest; recorded sha256 {actual}"
            + (" (matches the manifest)" if pinned else "") + ", skipped")
        return FetchResult(final, "recorded", actual, size)
    log(f"{final}: verified, skipped (sha256 {actual})")
    return FetchResult(final, "verified", actual, size)


# ---------------------------------------------------------------------- HTTP transfer


@contextlib.contextmanager
def _locked_part(ctx: _Context) -> Iterator[BinaryIO]:
    """The ``.part`` opened for appending (created if absent) and locked (``flock``) until
    the file is published: two fetches of the same file cannot interleave their bytes."""
    with open(ctx.part, "ab") as out:
        try:
            fcntl.flock(out.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EACCES):
                raise WeightsFetchError(f"{ctx.part} is being downloaded by another `freeze weights fetch`; wait for "
                                        f"it to finish ({ctx.where()})") from None
            raise
        yield out


def _transfer(ctx: _Context, out: BinaryIO, progress: bool) -> tuple[str, int, int, int]:
    """Download ``ctx.url`` into ``out`` (the locked ``.part``), resuming what is there.

    Returns (SHA-256 hex of the URL's bytes, total bytes, bytes received now, bytes
    there before this transfer).
    """
    offset = out.seek(0, os.SEEK_END)
    hasher = hashlib.sha256()
    if offset:  # the digest covers the whole file: hash what an earlier run received
        _hash_prefix(ctx.part, offset, hasher)
    resp = _open(ctx, offset)
    if resp is None:  # 416: the .part already holds the whole file (an earlier run ended after its transfer)
        return hasher.hexdigest(), offset, 0, offset
    with resp:
        ctype = (resp.headers.get("Content-Type") or "").lower()
        if ctype.startswith("text/html") and not ctx.download.file.endswith((".html", ".htm")):
            # A sign-in, quota or virus-scan page instead of the file: none of it is written
            # (the .part keeps what earlier runs received).
            raise WeightsFetchError(
                f"{ctx.url} answered with a web page (Content-Type {ctype}), not the file {ctx.download.file}: "
                f"the link may need a browser (quota or confirmation page); fetch it by hand and place it at "
                f"{_hand_target(ctx)} ({ctx.where()})")
        start = _range_start(resp, offset)
        if start is None:  # 206 for another range than asked: the .part cannot be trusted as a prefix
            ctx.part.unlink(missing_ok=True)
            raise WeightsFetchError(
                f"{ctx.url}: asked for bytes {offset}- but the server sent {resp.headers.get('Content-Range')}; the "
                f"partial file was deleted: run `freeze weights fetch {ctx.name}` again to start from zero "
                f"({ctx.where()})")
        if start != offset:  # the whole file (200), not the rest: start again from zero
            out.truncate(0)
            out.seek(0)
            hasher = hashlib.sha256()
            offset = 0
        length = _int(resp.headers.get("Content-Length"))
        total = offset + length if length is not None else None
        received = _stream(ctx, resp, out, hasher, offset, total, progress)
    out.flush()
    os.fsync(out.fileno())  # the bytes are on disk before anything is published from them
    if length is not None and received < length:
        raise WeightsFetchError(
            f"download of {ctx.url} interrupted after {offset + received} of {total} bytes (the connection was "
            f"closed); the bytes received are kept in {ctx.part}: run `freeze weights fetch {ctx.name}` again to "
            f"resume ({ctx.where()})")
    return hasher.hexdigest(), offset + received, received, offset


def _hash_prefix(path: Path, n: int, hasher: Any) -> None:
    with open(path, "rb") as f:
        left = n
        while left:
            block = f.read(min(CHUNK, left))
            if not block:
                break
            hasher.update(block)
            left -= len(block)


def _open(ctx: _Context, offset: int) -> http.client.HTTPResponse | None:
    """The response to GET ``ctx.url`` (from byte ``offset`` when > 0); None when the
    server says the range starts at the end of a file of exactly ``offset`` bytes."""
    headers = {"User-Agent": USER_AGENT, "Accept-Encoding": "identity"}  # identity: byte offsets are the file's
    if offset:
        headers["Range"] = f"bytes={offset}-"
    request = urllib.request.Request(ctx.url, headers=headers)
    try:
        return urllib.request.urlopen(request, timeout=ctx.timeout)  # noqa: S310 (http(s) URLs from our manifests)
    except urllib.error.HTTPError as e:
        with contextlib.closing(e):
            if e.code == 416 and offset:
                total = _content_range(e.headers.get("Content-Range"))[2]
                if total == offset:
                    return None
                # The .part is longer than the file, or the server won't say: it is not a prefix of it.
                ctx.part.unlink(missing_ok=True)
                raise WeightsFetchError(
                    f"{ctx.url}: HTTP 416 for the rest of {ctx.part} ({offset} bytes, the file has "
                    f"{total if total is not None else 'an unknown number of'} bytes); the partial file was deleted: "
                    f"run `freeze weights fetch {ctx.name}` again to start from zero ({ctx.where()})") from None
            raise WeightsFetchError(
                f"{ctx.url}: HTTP {e.code} {e.reason} while fetching {ctx.download.file} ({ctx.where()}); if the file "
                f"moved, fetch it by hand and place it at {_hand_target(ctx)}") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
        raise _unreachable(ctx, e) from None


def _unreachable(ctx: _Context, e: BaseException) -> WeightsFetchError:
    """No connection to the host (DNS, refused, unreachable, timeout, TLS): how to place the file by hand."""
    reason = getattr(e, "reason", None) or e
    host = urllib.parse.urlsplit(ctx.url).netloc or ctx.url
    return WeightsFetchError(
        f"cannot reach {host} ({type(reason).__name__}: {reason}): this machine seems to have no network access to it. "
        f"On a machine that has, fetch {ctx.url} and place it at {_hand_target(ctx)}, then run "
        f"`freeze weights fetch {ctx.name}` here to verify it and record its digest ({ctx.where()})")


def _hand_target(ctx: _Context) -> str:
    """Where a user puts the file fetched elsewhere (for a zip: which member, extracted where)."""
    if ctx.download.member:
        return f"{ctx.final} (the URL is a zip archive: extract its member {ctx.download.member} to that path)"
    return str(ctx.final)


def _int(value: str | None) -> int | None:
    try:
        return int(value) if value is not None else None
    except ValueError:
        return None


def _content_range(value: str | None) -> tuple[int | None, int | None, int | None]:
    """``"bytes 100-199/200"`` -> (100, 199, 200); ``"bytes */200"`` -> (None, None, 200)."""
    m = re.fullmatch(r"\s*bytes\s+(?:(\d+)-(\d+)|\*)/(\d+|\*)\s*", value or "")
    if m is None:
        return None, None, None
    first, last, total = m.groups()
    return _int(first), _int(last), (None if total in (None, "*") else int(total))


def _range_start(resp: http.client.HTTPResponse, offset: int) -> int | None:
    """Where the body of ``resp`` starts in the file: ``offset`` for a 206 continuing it,
    0 for a whole file (200), None for a 206 starting elsewhere."""
    if resp.status == 206:
        first = _content_range(resp.headers.get("Content-Range"))[0]
        return offset if first == offset else None
    return 0


def _stream(ctx: _Context, resp: http.client.HTTPResponse, out: BinaryIO, hasher: Any, offset: int, total: int | None,
            progress: bool) -> int:
    """Copy the body to ``out`` (appending) and ``hasher``; returns the bytes received.

    Every chunk is written as it arrives, so an interruption keeps all of it for the
    resume. A body shorter than its Content-Length is detected by the caller: http.client
    returns 0 at a premature end rather than raising.
    """
    buf = bytearray(CHUNK)
    view = memoryview(buf)
    received = 0
    with _byte_bar(ctx.download.file, total, offset, progress) as advance:
        while True:
            try:
                n = resp.readinto(buf)
            except (OSError, http.client.HTTPException) as e:  # reset, timeout, broken chunked encoding
                out.flush()
                raise WeightsFetchError(
                    f"download of {ctx.url} interrupted after {offset + received} of "
                    f"{total if total is not None else '?'} bytes ({type(e).__name__}: {e}); the bytes received are "
                    f"kept in {ctx.part}: run `freeze weights fetch {ctx.name}` again to resume "
                    f"({ctx.where()})") from None
            if not n:
                return received
            out.write(view[:n])
            hasher.update(view[:n])
            received += n
            advance(n)


@contextlib.contextmanager
def _byte_bar(label: str, total: int | None, done: int, enabled: bool) -> Iterator[Callable[[int], None]]:
    """A rich bar in bytes (size, speed, time left) on stderr; yields ``advance(n_bytes)``."""
    if not enabled:
        yield lambda n: None
        return
    from rich.console import Console
    from rich.progress import (BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn,
                               TransferSpeedColumn)

    columns = [TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
               TimeRemainingColumn()]
    with Progress(*columns, console=Console(stderr=True)) as bar:
        task = bar.add_task(label, total=total, completed=done)
        yield lambda n: bar.advance(task, n)


# ------------------------------------------------------------------------- publishing


def _mismatch(ctx: _Context, pinned: str, actual: str, what: str) -> WeightsFetchError:
    return WeightsFetchError(
        f"{ctx.final}: SHA-256 mismatch for {what}: expected {pinned} (pinned in {ctx.manifest or 'the manifest'}), "
        f"got {actual}; the download was deleted and nothing was installed (a changed upstream file, or a corrupt "
        f"transfer: retry, and if it persists check the manifest's digest)")


def _publish_file(ctx: _Context, digest: str, pinned: str | None) -> None:
    """Verify the complete ``.part`` and rename it to the final name, its digest recorded first."""
    if pinned is not None and digest != pinned:
        ctx.part.unlink(missing_ok=True)
        raise _mismatch(ctx, pinned, digest, ctx.url)
    write_sidecar(ctx.final, digest)
    with atomic_path(ctx.final) as staged:
        # `staged` is atomic_path's hidden sibling of the final name (same folder, so this
        # is a rename, not a copy of gigabytes); the store renames it onto the final name.
        os.rename(ctx.part, staged)


def _publish_member(ctx: _Context, pinned: str | None) -> tuple[str, int]:
    """Extract ``member`` of the downloaded zip to the final name (hashed on the way),
    verify it, publish it, delete the archive. Returns (digest, size) of the member."""
    member = ctx.download.member
    assert member is not None
    try:
        archive = zipfile.ZipFile(ctx.part)
    except (zipfile.BadZipFile, OSError) as e:
        ctx.part.unlink(missing_ok=True)
        raise WeightsFetchError(
            f"{ctx.url} did not give a zip archive ({e}); the download was deleted. Fetch it by hand and place it at "
            f"{_hand_target(ctx)} ({ctx.where()})") from None
    with archive:
        try:
            info = archive.getinfo(member)
        except KeyError:
            names = archive.namelist()
            ctx.part.unlink(missing_ok=True)
            raise WeightsFetchError(
                f"{ctx.url}: the archive has no member {member} (it holds {len(names)} entries: "
                f"{', '.join(names[:5])}{', ...' if len(names) > 5 else ''}); the download was deleted "
                f"({ctx.where()})") from None
        hasher = hashlib.sha256()
        size = 0
        try:
            with atomic_path(ctx.final) as tmp:
                with archive.open(info) as src, open(tmp, "wb") as dst:
                    for block in iter(lambda: src.read(CHUNK), b""):
                        dst.write(block)
                        hasher.update(block)
                        size += len(block)
                    dst.flush()
                    os.fsync(dst.fileno())
                digest = hasher.hexdigest()
                if pinned is not None and digest != pinned:
                    raise _mismatch(ctx, pinned, digest, f"member {member} of {ctx.url}")
                write_sidecar(ctx.final, digest)
        except WeightsFetchError:
            ctx.part.unlink(missing_ok=True)
            raise
        except (zipfile.BadZipFile, EOFError, zlib.error) as e:  # CRC or deflate error: a corrupt archive
            ctx.part.unlink(missing_ok=True)
            raise WeightsFetchError(
                f"{ctx.url}: the archive is corrupt ({e}); the download was deleted: run `freeze weights fetch "
                f"{ctx.name}` again ({ctx.where()})") from None
    ctx.part.unlink(missing_ok=True)  # the archive served its purpose; the member is what the loader reads
    return digest, size


"""Fetching one weight file: resumable HTTP download, SHA-256, atomic publication.

For a manifest entry with ``file: F`` (relative to the weights folder ``W``), the
folder holds at most these names:

- ``W/F.part``: the bytes of the URL received so far. An interrupted transfer leaves
  it; the next fetch asks the server for the rest (``Range: bytes=N-``) and appends
  when the server answers 206, or starts again from zero when it answers 200.
- ``W/F``: the file the loader reads. It appears only whole and verified: renamed into
  place by :func:`pipeline.common.store.atomic_path`, never written under its own name.
- ``W/F.sha256``: the file's SHA-256 in ``sha256sum`` format (``<hex>  <name>``),
  written just before ``F`` is published, so a file that has a name always has one.
- ``W/F.part.json``: beside a ``.part``, what the server said of its file at the first
  transfer (URL, ETag, Last-Modified, length). A resume sends ``If-Range`` with the ETag
  (or the date): a server whose file changed answers 200 with the whole new file and the
  transfer starts again from zero, so old and new bytes are never joined. A ``.part``
  without that record (and without a pinned digest to catch a splice) is not resumed.

Nothing is published that is not whole and of its format: the received size must equal
the Content-Length (and the manifest's ``exact_size`` when it gives one), and the file's
first bytes (and a zip's central directory) must match its name's format
(:mod:`pipeline.formats.weights.formats`: a web page or a truncated zip is refused).

A zip entry (``member`` set) downloads the archive to ``W/F.part``, extracts the
member into a hidden temporary file beside ``F`` (hashing it on the way), publishes
it and deletes the archive.

Errors are :class:`WeightsFetchError`, each a single line naming the file, the URL and
the manifest: an HTTP status, no network (with the path to place the file at by hand
and the URL to fetch it from elsewhere), a server that did not answer in time, a
redirect loop, an interrupted transfer, bytes that are not the file (a web page, a
truncated archive), a disk that refused the write, a digest that differs from the
manifest's or from the one recorded earlier.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import http.client
import json
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

from pipeline.common.config import ManifestError, WeightDownload
from pipeline.common.store import StorageError, atomic_path, file_digest
from pipeline.formats.weights.formats import FORMAT_NAMES, Format, expected_format, sniff

TIMEOUT_S = 30.0
"""Seconds to wait for a connection, for the server's answer and then for each read
(``freeze weights fetch --timeout``): a dead link or a server that never answers fails
with a message saying so instead of hanging."""
URL_SCHEMES = ("http", "https")
"""The only URLs fetched: a manifest's ``file://`` or ``ftp://`` URL is refused."""
CHUNK = 1 << 20  # bytes per read: large enough that Python's per-call cost is nothing next to the network
USER_AGENT = "freeze-weights/1 (python urllib)"
SIDECAR_SUFFIX = ".sha256"
PART_SUFFIX = ".part"
PART_META_SUFFIX = ".part.json"

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


def part_meta_path(final: Path) -> Path:
    """What the server said of its file when the ``.part`` was started (for ``If-Range``)."""
    return final.with_name(final.name + PART_META_SUFFIX)


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
    ctx = _Context(download=download, final=final, part=part_path(final), manifest=manifest, name=name,
                   timeout=timeout, log=log)
    check_url(download.url, manifest, WeightsFetchError)
    try:
        return _fetch(ctx, pinned, progress)
    except OSError as e:  # the disk (network errors became WeightsFetchError where they happen)
        raise _disk_error(ctx, e) from None


def _fetch(ctx: _Context, pinned: str | None, progress: bool | None) -> FetchResult:
    """:func:`fetch_download` after the names are known; OSError is the disk's."""
    download, final, log = ctx.download, ctx.final, ctx.log
    done = _existing(ctx, pinned)
    if done is not None:
        return done
    if progress is None:
        progress = sys.stderr.isatty()
    _make_folder(ctx)
    what = f"{download.file} (member {download.member} of a zip)" if download.member else download.file
    log(f"fetching {what}, {human_size(download.size)}, from {download.url} to {final}")
    with _locked_part(ctx) as out:
        done = _existing(ctx, pinned)  # another fetch may have published it meanwhile
        if done is not None:
            if out.seek(0, os.SEEK_END) == 0:
                _discard_part(ctx)
            return done
        try:
            digest, total, received, resumed = _transfer(ctx, out, progress, pinned)
        except BaseException:
            if out.tell() == 0:  # nothing received (no network, 404): leave no empty .part behind
                _discard_part(ctx)
            raise
        _check_received(ctx, total)
        if download.member:
            digest, size = _publish_member(ctx, pinned)
        else:
            size = total
            _publish_file(ctx, digest, pinned)
    log(f"{final}: {human_size(size)}, sha256 {digest}"
        + (f" (resumed at byte {resumed})" if resumed else ""))
    return FetchResult(final, "downloaded", digest, size, received, resumed)


def check_url(url: str, manifest: str | os.PathLike = "", error: type[Exception] = ManifestError) -> None:
    """Raise ``error`` (one line naming the manifest) unless ``url`` is an http(s) URL
    with a host: a ``file://`` URL would copy any local file into the weights folder as
    if it had been downloaded."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() not in URL_SCHEMES or not parts.netloc:
        raise error(f"{manifest or 'the manifest'}: download url {url!r} is not an http(s) URL with a host; only "
                    f"{' and '.join(URL_SCHEMES)} URLs are fetched")


def _make_folder(ctx: _Context) -> None:
    """Create the file's folder; a path in the way that is not a folder is one line."""
    try:
        ctx.final.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((p for p in [ctx.final.parent, *ctx.final.parent.parents] if p.exists() and not p.is_dir()),
                       ctx.final.parent)
        raise WeightsFetchError(f"{blocker} is not a folder, so {ctx.final} cannot be written there: move it away or "
                                f"choose another --weights-dir ({ctx.where()})") from None


def _disk_error(ctx: _Context, e: OSError) -> WeightsFetchError:
    """A write the disk refused (full, read-only, no permission), as one line naming the
    path and what is left of the download."""
    try:
        kept = ctx.part.stat().st_size if ctx.part.is_file() else 0
    except OSError:
        kept = 0
    if kept:  # kept, not deleted: after freeing space the transfer resumes where it stopped
        left = (f"the {kept} bytes received are kept in {ctx.part}: free space (or fix the folder) and run "
                f"`freeze weights fetch {ctx.name}` again to resume, or delete it")
    else:
        left = "nothing was left behind"
    if isinstance(e, StorageError):  # from atomic_path (the digest record, the member): names its file already
        return WeightsFetchError(f"{e.strerror}; {left} ({ctx.where()})")
    why = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
           errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
           errno.EPERM: "operation not permitted"}.get(e.errno or 0, " ".join(str(e.strerror or e).split()))
    path = e.filename if getattr(e, "filename", None) else ctx.part
    return WeightsFetchError(f"{path}: cannot write the weights ({why}); nothing was installed, {left} "
                             f"({ctx.where()})")


@dataclass(frozen=True)
class _Context:
    """One fetch's names, for the messages."""

    download: WeightDownload
    final: Path
    part: Path
    manifest: str
    name: str
    timeout: float
    log: Log = lambda line: None

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
    (:func:`pipeline.formats.weights.catalog.entry_status`)."""
    if recorded is not None and recorded != actual:
        return "changed"
    if pinned is not None and actual != pinned:
        return "not-pinned"
    return "unrecorded" if recorded is None else "verified"


def _existing(ctx: _Context, pinned: str | None) -> FetchResult | None:
    """The outcome for a file already under its final name, or None when there is none.

    Its digest must agree with the one recorded beside it (else it changed since it was
    fetched) and with the pinned one, and its first bytes must be of its format (a web
    page saved under the name is refused, never recorded); a file without a record
    (placed by hand) gets one.
    """
    final, manifest, log = ctx.final, ctx.manifest, ctx.log
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
    fmt = expected_format(final)
    problem = sniff(final, fmt) if fmt is not None else None
    if problem is not None:
        raise WeightsFetchError(
            f"{final} is {problem}, not a {FORMAT_NAMES[fmt]}: a download that went wrong, or another file under its "
            f"name; its digest is not recorded. Delete it (and {side.name} if present) and run `freeze weights fetch "
            f"{ctx.name}` again ({ctx.where()})")
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


def _transfer(ctx: _Context, out: BinaryIO, progress: bool, pinned: str | None) -> tuple[str, int, int, int]:
    """Download ``ctx.url`` into ``out`` (the locked ``.part``), resuming what is there
    when it is safe (:func:`_resume_validator`).

    Returns (SHA-256 hex of the URL's bytes, total bytes, bytes received now, bytes
    there before this transfer).
    """
    offset = out.seek(0, os.SEEK_END)
    if_range = None
    if offset:
        meta = _read_part_meta(ctx)
        if_range = _resume_validator(meta)
        if if_range is None and pinned is None:
            # Without a validator the server cannot tell us that its file changed since the
            # .part began; with no pinned digest nothing would catch old and new bytes joined.
            ctx.log(f"{ctx.part}: {offset} bytes from an earlier transfer, but what the server then served was not "
                    "recorded (no ETag or Last-Modified): starting again from zero")
            offset = _restart(ctx, out)
    else:
        meta = None
    hasher = hashlib.sha256()
    if offset:  # the digest covers the whole file: hash what an earlier run received
        _hash_prefix(ctx.part, offset, hasher)
    resp = _open(ctx, offset, if_range)
    if resp is None:  # 416: the .part already holds the whole file (an earlier run ended after its transfer)
        return hasher.hexdigest(), offset, 0, offset
    if resp.status == 206 and meta is not None and _changed(meta, resp):
        # A server that ignores If-Range and sends the rest of its new file: start again.
        resp.close()
        ctx.log(f"{ctx.url} changed since {ctx.part} was started: starting again from zero")
        offset = _restart(ctx, out)
        hasher = hashlib.sha256()
        resp = _open(ctx, 0, None)
        assert resp is not None  # no Range, so no 416
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
            _discard_part(ctx)
            raise WeightsFetchError(
                f"{ctx.url}: asked for bytes {offset}- but the server sent {resp.headers.get('Content-Range')}; the "
                f"partial file was deleted: run `freeze weights fetch {ctx.name}` again to start from zero "
                f"({ctx.where()})")
        if start != offset:  # the whole file (200), not the rest: no ranges, or If-Range said it changed
            ctx.log(f"{ctx.url}: the server sent the whole file (it changed since {ctx.part} was started, or it "
                    "does not resume transfers): starting again from zero")
            offset = _restart(ctx, out)
            hasher = hashlib.sha256()
        length = _int(resp.headers.get("Content-Length"))
        total = offset + length if length is not None else None
        if offset == 0:
            _write_part_meta(ctx, resp, total)
        exact = ctx.download.exact_size
        if exact is not None and total is not None and total != exact:  # refused before gigabytes arrive
            _discard_part(ctx)
            raise WeightsFetchError(
                f"{ctx.url}: the server announces {total} bytes but {ctx.manifest or 'the manifest'} gives "
                f"exact_size {exact} for {ctx.download.file}: another file (or an error page) is served there; "
                f"nothing was installed ({ctx.where()})")
        received = _stream(ctx, resp, out, hasher, offset, total, progress)
    out.flush()
    os.fsync(out.fileno())  # the bytes are on disk before anything is published from them
    if length is not None and received < length:
        raise WeightsFetchError(
            f"download of {ctx.url} interrupted after {offset + received} of {total} bytes (the connection was "
            f"closed); the bytes received are kept in {ctx.part}: run `freeze weights fetch {ctx.name}` again to "
            f"resume ({ctx.where()})")
    return hasher.hexdigest(), offset + received, received, offset


def _restart(ctx: _Context, out: BinaryIO) -> int:
    """Empty the ``.part`` (and forget what the server said of it); returns the new offset, 0."""
    out.truncate(0)
    out.seek(0)
    part_meta_path(ctx.final).unlink(missing_ok=True)
    return 0


def _discard_part(ctx: _Context) -> None:
    """Delete the ``.part`` and its record: what they hold is not a prefix of the file."""
    ctx.part.unlink(missing_ok=True)
    part_meta_path(ctx.final).unlink(missing_ok=True)


def _read_part_meta(ctx: _Context) -> dict[str, Any] | None:
    """What the server said of its file when the ``.part`` began, or None (no record, an
    unreadable one, or one for another URL: the manifest's URL changed since)."""
    try:
        meta = json.loads(part_meta_path(ctx.final).read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and meta.get("url") == ctx.url else None


def _write_part_meta(ctx: _Context, resp: http.client.HTTPResponse, total: int | None) -> None:
    """Record the validators of the file that the ``.part`` now starts to hold."""
    meta = {"url": ctx.url, "etag": resp.headers.get("ETag"), "last_modified": resp.headers.get("Last-Modified"),
            "length": total}
    with atomic_path(part_meta_path(ctx.final)) as tmp:
        tmp.write_text(json.dumps(meta) + "\n")


def _resume_validator(meta: dict[str, Any] | None) -> str | None:
    """The ``If-Range`` value for a resume: the strong ETag, else the Last-Modified date
    (If-Range takes no weak ETag); None when the first transfer recorded neither."""
    if not meta:
        return None
    etag = meta.get("etag")
    if isinstance(etag, str) and etag and not etag.startswith("W/"):
        return etag
    modified = meta.get("last_modified")
    return modified if isinstance(modified, str) and modified else None


def _changed(meta: dict[str, Any], resp: http.client.HTTPResponse) -> bool:
    """Whether a 206's validators or total length differ from those recorded at the first transfer."""
    for key, header in (("etag", "ETag"), ("last_modified", "Last-Modified")):
        now = resp.headers.get(header)
        if meta.get(key) and now and now != meta[key]:
            return True
    total = _content_range(resp.headers.get("Content-Range"))[2]
    return meta.get("length") is not None and total is not None and total != meta["length"]


def _check_received(ctx: _Context, total: int) -> None:
    """Refuse a complete transfer that is not the file: another size than the manifest's
    ``exact_size``, or bytes not of the file's format (a web page, a truncated zip: what a
    connection dropped without a Content-Length leaves). The ``.part`` is deleted."""
    exact = ctx.download.exact_size
    if exact is not None and total != exact:
        _discard_part(ctx)
        raise WeightsFetchError(
            f"{ctx.url}: received {total} bytes but {ctx.manifest or 'the manifest'} gives exact_size {exact} for "
            f"{ctx.download.file} ({'cut short' if total < exact else 'another file'}); the download was deleted and "
            f"nothing was installed: run `freeze weights fetch {ctx.name}` again ({ctx.where()})")
    fmt: Format | None = "zip" if ctx.download.member else expected_format(ctx.download.file)
    problem = sniff(ctx.part, fmt) if fmt is not None else None
    if problem is not None:
        _discard_part(ctx)
        raise _not_the_file(ctx, problem, fmt, ctx.url)


def _not_the_file(ctx: _Context, problem: str, fmt: Format, what: str) -> WeightsFetchError:
    return WeightsFetchError(
        f"{what}: received {problem}, not a {FORMAT_NAMES[fmt]} for {ctx.download.file}; the download was deleted "
        f"and nothing was installed (a quota, sign-in or error page, or a transfer cut short: retry, or fetch it by "
        f"hand and place it at {_hand_target(ctx)}) ({ctx.where()})")


def _hash_prefix(path: Path, n: int, hasher: Any) -> None:
    with open(path, "rb") as f:
        left = n
        while left:
            block = f.read(min(CHUNK, left))
            if not block:
                break
            hasher.update(block)
            left -= len(block)


def _open(ctx: _Context, offset: int, if_range: str | None = None) -> http.client.HTTPResponse | None:
    """The response to GET ``ctx.url`` (from byte ``offset`` when > 0, only if the file
    is still ``if_range`` when given); None when the server says the range starts at the
    end of a file of exactly ``offset`` bytes."""
    headers = {"User-Agent": USER_AGENT, "Accept-Encoding": "identity"}  # identity: byte offsets are the file's
    if offset:
        headers["Range"] = f"bytes={offset}-"
        if if_range:
            headers["If-Range"] = if_range
    request = urllib.request.Request(ctx.url, headers=headers)
    try:
        return _opener().open(request, timeout=ctx.timeout)
    except urllib.error.HTTPError as e:
        with contextlib.closing(e):
            if e.code == 416 and offset:
                total = _content_range(e.headers.get("Content-Range"))[2]
                if total == offset:
                    return None
                # The .part is longer than the file, or the server won't say: it is not a prefix of it.
                _discard_part(ctx)
                raise WeightsFetchError(
                    f"{ctx.url}: HTTP 416 for the rest of {ctx.part} ({offset} bytes, the file has "
                    f"{total if total is not None else 'an unknown number of'} bytes); the partial file was deleted: "
                    f"run `freeze weights fetch {ctx.name}` again to start from zero ({ctx.where()})") from None
            if 300 <= e.code < 400:  # urllib's own message for a loop is three lines: say it in one
                limit = urllib.request.HTTPRedirectHandler.max_redirections
                raise WeightsFetchError(
                    f"{ctx.url}: the server's redirects loop or go on (HTTP {e.code} after up to {limit} redirects, "
                    f"last to {e.geturl()}), so {ctx.download.file} could not be fetched; fetch it by hand and place "
                    f"it at {_hand_target(ctx)} ({ctx.where()})") from None
            raise WeightsFetchError(
                f"{ctx.url}: HTTP {e.code} {_one_line(e.reason)} while fetching {ctx.download.file} ({ctx.where()}); "
                f"if the file moved, fetch it by hand and place it at {_hand_target(ctx)}") from None
    except ValueError as e:  # a URL urllib cannot parse (check_url let it through)
        raise WeightsFetchError(f"{ctx.url}: not a URL that can be fetched ({_one_line(e)}) ({ctx.where()})") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
        raise _unreachable(ctx, e) from None


def _opener() -> urllib.request.OpenerDirector:
    """urllib's opener with its HTTP(S) handlers only (proxies and redirects included):
    a redirect to ``ftp://`` or a ``file://`` URL is not followed, whatever the manifest says."""
    opener = urllib.request.OpenerDirector()
    for handler in (urllib.request.ProxyHandler(), urllib.request.UnknownHandler(), urllib.request.HTTPHandler(),
                    urllib.request.HTTPSHandler(), urllib.request.HTTPDefaultErrorHandler(),
                    urllib.request.HTTPRedirectHandler(), urllib.request.HTTPErrorProcessor()):
        opener.add_handler(handler)
    return opener


def _one_line(value: object) -> str:
    """``value`` as text on one line (servers' reasons and urllib's messages may hold newlines)."""
    return " ".join(str(value).split())


def _unreachable(ctx: _Context, e: BaseException) -> WeightsFetchError:
    """No answer from the host: a timeout (it may be up but slow or stuck) or no
    connection at all (DNS, refused, unreachable, TLS): how to place the file by hand."""
    reason = getattr(e, "reason", None) or e
    host = urllib.parse.urlsplit(ctx.url).netloc or ctx.url
    by_hand = (f"On a machine that has, fetch {ctx.url} and place it at {_hand_target(ctx)}, then run "
               f"`freeze weights fetch {ctx.name}` here to verify it and record its digest ({ctx.where()})")
    if isinstance(reason, TimeoutError):  # socket.timeout is TimeoutError: connected (or not) but no answer
        return WeightsFetchError(
            f"{host} did not answer within {ctx.timeout:g} s (no connection or no response to the request for "
            f"{ctx.url}): the server may be down or overloaded; retry later, or give it longer with --timeout "
            f"SECONDS ({ctx.where()})")
    return WeightsFetchError(
        f"cannot reach {host} ({type(reason).__name__}: {_one_line(reason)}): this machine seems to have no network "
        f"access to it. {by_hand}")


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
                why = (f"the server sent nothing for {ctx.timeout:g} s" if isinstance(e, TimeoutError)
                       else f"{type(e).__name__}: {_one_line(e)}")
                raise WeightsFetchError(
                    f"download of {ctx.url} interrupted after {offset + received} of "
                    f"{total if total is not None else '?'} bytes ({why}); the bytes received are "
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
        _discard_part(ctx)
        raise _mismatch(ctx, pinned, digest, ctx.url)
    write_sidecar(ctx.final, digest)
    try:
        with atomic_path(ctx.final) as staged:
            # `staged` is atomic_path's hidden sibling of the final name (same folder, so this
            # is a rename, not a copy of gigabytes); the store renames it onto the final name.
            os.rename(ctx.part, staged)
    except BaseException:
        sidecar_path(ctx.final).unlink(missing_ok=True)  # no digest recorded for a file that is not there
        raise
    part_meta_path(ctx.final).unlink(missing_ok=True)


def _publish_member(ctx: _Context, pinned: str | None) -> tuple[str, int]:
    """Extract ``member`` of the downloaded zip to the final name (hashed on the way),
    verify it, publish it, delete the archive. Returns (digest, size) of the member."""
    member = ctx.download.member
    assert member is not None
    try:
        archive = zipfile.ZipFile(ctx.part)
    except (zipfile.BadZipFile, OSError) as e:
        _discard_part(ctx)
        raise WeightsFetchError(
            f"{ctx.url} did not give a zip archive ({e}); the download was deleted. Fetch it by hand and place it at "
            f"{_hand_target(ctx)} ({ctx.where()})") from None
    with archive:
        try:
            info = archive.getinfo(member)
        except KeyError:
            names = archive.namelist()
            _discard_part(ctx)
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
                fmt = expected_format(ctx.download.file)
                problem = sniff(tmp, fmt) if fmt is not None else None
                if problem is not None:
                    raise _not_the_file(ctx, problem, fmt, f"member {member} of {ctx.url}")
                if pinned is not None and digest != pinned:
                    raise _mismatch(ctx, pinned, digest, f"member {member} of {ctx.url}")
                write_sidecar(ctx.final, digest)
        except WeightsFetchError:
            _discard_part(ctx)
            raise
        except (zipfile.BadZipFile, EOFError, zlib.error) as e:  # CRC or deflate error: a corrupt archive
            _discard_part(ctx)
            raise WeightsFetchError(
                f"{ctx.url}: the archive is corrupt ({e}); the download was deleted: run `freeze weights fetch "
                f"{ctx.name}` again ({ctx.where()})") from None
        except BaseException:  # the rename failed after the digest was recorded: no record without its file
            if not ctx.final.exists():
                sidecar_path(ctx.final).unlink(missing_ok=True)
            raise
    _discard_part(ctx)  # the archive served its purpose; the member is what the loader reads
    return digest, size


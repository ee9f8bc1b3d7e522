"""Whether a weight file is what its name says, from a few of its bytes (no load).

A download that went wrong usually still gives a file: a sign-in, quota or error page
(HTML, XML, JSON) served in place of the weights, or the first part of the file when the
connection dropped. Loading either takes torch seconds to minutes and ends in an
unpickling traceback; these checks read the first bytes and, for a zip, its central
directory (at the end of the file), so they take milliseconds at any size:

- ``torch`` (``.pth``, ``.pt``, ``.ckpt``, ``.bin``, and ``.tar``: GeDi's ``chkpt.tar`` is
  ``torch.save`` output under a tutorial-style name, as its manifest's comment says, not
  a tar archive): a zip archive holding ``data.pkl`` (torch >= 1.6) whose central
  directory is there (a truncated zip has no end-of-central-directory record), or a
  pickle (byte 0x80 and protocol 2-5: the legacy format; its truncation is not
  detectable without loading it, the SHA-256 is what guards it);
- ``safetensors``: an 8-byte little-endian header length, a JSON header, and exactly as
  many bytes after it as the header's tensors end at;
- ``json`` (a Hugging Face ``config.json``): a JSON object;
- ``zip`` (the archive of a ``member`` entry): a zip archive whose central directory is there.

:func:`sniff` says what a file is instead (``"an HTML page (title 'Quota exceeded')"``),
or None when it looks right. :class:`NotAWeightsFile` is the loaders' one-line error for
such a file: a :class:`WeightsNotFound`, so every command
prints it as its one line (``pipeline.commands.common.USER_ERRORS``).
"""

from __future__ import annotations

import json
import os
import re
import struct
import zipfile
from pathlib import Path
from typing import Literal


Format = Literal["torch", "safetensors", "json", "zip"]

FORMAT_NAMES: dict[str, str] = {"torch": "torch checkpoint", "safetensors": "safetensors file",
                                "json": "JSON file", "zip": "zip archive"}
"""How messages name each format: '... not a torch checkpoint'."""

_SUFFIXES: dict[str, Format] = {".pth": "torch", ".pt": "torch", ".ckpt": "torch", ".bin": "torch", ".tar": "torch",
                                ".safetensors": "safetensors", ".json": "json", ".zip": "zip"}
_HEAD = 4096  # bytes read to recognise a file (an HTML page's <title> is within them)
_MAX_JSON = 16 << 20  # a config.json is a few kB; a bigger "JSON" file is not one
_MAX_SAFETENSORS_HEADER = 100 << 20  # the format's own limit on the header


class WeightsNotFound(FileNotFoundError):
    """An encoder's weight files are missing; ``looked_in`` lists every path tried."""

    def __init__(self, message: str, looked_in: list[Path]):
        super().__init__(message)
        self.looked_in = [Path(p) for p in looked_in]


class NotAWeightsFile(WeightsNotFound):
    """A weight file is present but is not a checkpoint (a web page, a truncated
    download, another format). The message is one line naming the file, what it is, and
    how to fetch it again; ``looked_in`` is the file."""

    def __init__(self, message: str, path: Path):
        super().__init__(message, [Path(path)])
        self.path = Path(path)


def expected_format(name: str | os.PathLike) -> Format | None:
    """The format a weight file's name promises (``dinov2_vits14_pretrain.pth`` -> ``torch``);
    None for a suffix this module does not know (nothing is checked then)."""
    return _SUFFIXES.get(Path(name).suffix.lower())


def sniff(path: str | os.PathLike, fmt: Format) -> str | None:
    """None when the file at ``path`` looks like ``fmt``; else what it is instead, as a
    phrase for a message ('an HTML page (title ...)', 'a truncated zip archive ...').
    Reads the first 4 kB and, for a zip, its central directory. OSError propagates."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(_HEAD)
    if fmt in ("torch", "zip"):
        if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
            return _zip_problem(path, torch=fmt == "torch")
        if fmt == "torch" and len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5:
            return None  # a pickle: torch's legacy format
        return describe(head, size)
    if fmt == "safetensors":
        return _safetensors_problem(path, head, size)
    if fmt == "json":
        if size > _MAX_JSON:
            return describe(head, size)
        try:
            value = json.loads(path.read_bytes())
        except (UnicodeDecodeError, ValueError):
            return describe(head, size, json_ok=False)
        return None if isinstance(value, dict) else f"JSON that is not an object ({type(value).__name__})"
    raise ValueError(f"unknown weights format {fmt!r}")


def describe(head: bytes, size: int, *, json_ok: bool = True) -> str:
    """What a file that is not the expected format is, from its first bytes: a phrase
    ('an empty file', 'an HTML page (title ...)', 'a text file ...', '60 bytes of an unknown format ...')."""
    if size == 0:
        return "an empty file"
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n").lower()
    if text.startswith((b"<!doctype html", b"<html", b"<head", b"<body")) or b"<html" in text[:1024]:
        title = re.search(rb"<title[^>]*>(.*?)</title>", head, re.I | re.S)
        return "an HTML page" + (f" (title {_excerpt(title.group(1))!r})" if title and title.group(1).strip() else "")
    if text.startswith(b"<"):
        return f"an XML document ({_excerpt(head)!r})"
    if json_ok and text.startswith((b"{", b"[")):
        return f"a JSON document ({_excerpt(head)!r})"
    if head[:2] == b"\x1f\x8b":
        return "a gzip file"
    if head[:4] == b"PK\x03\x04":
        return "a zip archive"
    try:
        decoded = head.decode("utf-8")
    except UnicodeDecodeError:
        decoded = None
    if decoded is not None and all(c.isprintable() or c in "\t\r\n" for c in decoded):
        return f"a text file ({_excerpt(head)!r})"
    return f"{size} bytes of an unknown format (starting {head[:8].hex()})"


def _excerpt(raw: bytes, n: int = 60) -> str:
    """The first ``n`` characters of ``raw`` as one line (whitespace runs made one space)."""
    text = " ".join(raw.decode("utf-8", "replace").split())
    return text if len(text) <= n else text[: n - 3] + "..."


def _zip_problem(path: Path, *, torch: bool) -> str | None:
    """None for a zip whose central directory is whole (and, for ``torch``, that holds
    ``data.pkl``); else what is wrong. Reads only the directory, at the end of the file."""
    size = path.stat().st_size
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
    except (zipfile.BadZipFile, ValueError, EOFError) as e:
        # A zip's directory is its last bytes: the first to go when a transfer stops early.
        return f"a truncated or damaged zip archive ({size} bytes, {e}; no complete central directory)"
    # Where each member's data ends at the least (its local header's fixed 30 bytes and
    # name; the local extra field may be longer): beyond the file means bytes are missing.
    ends = [i.header_offset + 30 + len(i.orig_filename) + i.compress_size for i in infos]
    if ends and max(ends) > size:
        return f"a truncated zip archive ({size} bytes, its directory says {max(ends)})"
    if torch and not any(i.filename == "data.pkl" or i.filename.endswith("/data.pkl") for i in infos):
        names = ", ".join(i.filename for i in infos[:3]) + (", ..." if len(infos) > 3 else "")
        return f"a zip archive without data.pkl, so not torch.save output (it holds {len(infos)} entries: {names})"
    return None


def _safetensors_problem(path: Path, head: bytes, size: int) -> str | None:
    """None when the header parses and the tensors end exactly at the end of the file."""
    if size < 8:
        return describe(head, size)
    (n,) = struct.unpack("<Q", head[:8])
    if n < 2 or n > _MAX_SAFETENSORS_HEADER:
        return describe(head, size)
    if 8 + n > size:
        return f"a truncated safetensors file ({size} bytes, shorter than its {n}-byte header)"
    with open(path, "rb") as f:
        f.seek(8)
        raw = f.read(n)
    try:
        header = json.loads(raw)
        ends = [int(t["data_offsets"][1]) for k, t in header.items() if k != "__metadata__"]
    except (UnicodeDecodeError, ValueError, TypeError, KeyError, IndexError, AttributeError):
        return describe(head, size)
    want = 8 + n + max(ends, default=0)
    if want != size:
        return (f"a truncated safetensors file ({size} bytes, its header says {want})" if want > size
                else f"a safetensors file with {size - want} bytes after its tensors (damaged)")
    return None


def check_weights_file(path: str | os.PathLike, what: str = "weights", fetch: str | None = None) -> None:
    """Raise :class:`NotAWeightsFile` (one line naming ``path``) when the file's first
    bytes do not match its suffix's format (:func:`expected_format`); files of an
    unknown suffix pass. ``what`` prefixes the message (the encoder's name); ``fetch``
    is the manifest whose ``freeze weights fetch`` gets the file again, when known."""
    path = Path(path)
    fmt = expected_format(path)
    if fmt is None:
        return
    problem = sniff(path, fmt)
    if problem is not None:
        raise NotAWeightsFile(not_a_checkpoint_message(path, fmt, problem, what, fetch), path)


def _again(path: Path, fetch: str | None) -> str:
    """How to replace a bad file: delete it (and its digest record), fetch it again."""
    how = (f"`freeze weights fetch {fetch}`" if fetch
           else "`freeze weights fetch NAME` (`freeze weights list` names the manifest)")
    return f"Delete it (and {path.name}.sha256 if present) and fetch it again with {how}"


def not_a_checkpoint_message(path: Path, fmt: Format, problem: str, what: str = "weights",
                             fetch: str | None = None) -> str:
    """The one line for a present file that is not a ``fmt`` file."""
    return (f"{what}: {path} is {problem}, not a {FORMAT_NAMES[fmt]}: a download that went wrong (a web page "
            f"instead of the file, or a transfer cut short)? {_again(path, fetch)}")


def unreadable_checkpoint(path: str | os.PathLike, exc: BaseException, what: str = "weights",
                          fetch: str | None = None) -> NotAWeightsFile:
    """The one-line error for a file that passed :func:`sniff` but that ``torch.load``
    refused (a truncated legacy pickle, a damaged zip member, objects other than tensors).
    Torch's own message is quoted only when it gives no advice to load with
    ``weights_only=False`` (which would run whatever code the file holds)."""
    path = Path(path)
    text = str(exc)
    if "Weights only load failed" in text:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text)  # a cut-off pickle names a cut-off global
        named = f" ({found.group(1)})" if found else ""
        why = (f"it holds objects other than tensors and plain containers{named}, which are not loaded (loading them "
               "could run code): a damaged file, or not the published checkpoint")
    else:
        first = " ".join(text.strip().splitlines()[0].split()) if text.strip() else ""
        quoted = first and "weights_only" not in first
        why = f"torch cannot read it ({type(exc).__name__}{': ' + first[:160] if quoted else ''})"
    return NotAWeightsFile(f"{what}: {path} is not a readable checkpoint: {why}. {_again(path, fetch)}", path)

"""``freeze weights list`` and ``freeze weights fetch NAME...``: the encoders' weight files.

The URLs come from the encoder manifests' ``download:`` entries; the files go to the
weights folder the loaders read (``--weights-dir``, else ``$FREEZE_WEIGHTS``, else
``<project>/weights``). Runs stay offline: this is the one command that downloads.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from pipeline.formats.weights.fetch import TIMEOUT_S

weights_app = typer.Typer(add_completion=False, no_args_is_help=True,
                          help="The encoders' weight files: list them, fetch them into the weights folder.")

_WEIGHTS_DIR_HELP = "folder of encoder weights (default $FREEZE_WEIGHTS or <project>/weights)"


def _console() -> Console:
    # Paths and URLs are printed whole (soft wrap) and without markup: they may hold '['.
    return Console(stderr=True, highlight=False, soft_wrap=True)


@weights_app.command("list")
def list_weights(
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
    weights_dir: Optional[Path] = typer.Option(None, help=_WEIGHTS_DIR_HELP),
) -> None:
    """List the weight files the encoder manifests download, and their state here.

    Per manifest and file: source, path in the weights folder, state (missing, partial,
    present, verified, mismatch, invalid: not of its format), size and URL. Present files are hashed to verify them
    (about 1 s per GB)."""
    from pipeline.method.encoders.registry import resolve_weights_dir
    from pipeline.common.stand_in import paper_fetch
    from pipeline.formats.weights import entry_status, human_size, manifests_with_downloads

    wdir = resolve_weights_dir(weights_dir)
    digests: dict = {}
    rows = []
    for listed in manifests_with_downloads():
        for d in listed.manifest.download:
            state = entry_status(d, wdir, listed.path, digests)
            rows.append({"manifest": listed.name, "encoder": listed.manifest.encoder, "source": d.source,
                         "url": d.url, "file": d.file, "member": d.member, "pinned_sha256": d.sha256,
                         "approx_size": d.size, **state})
    if as_json:
        print(json.dumps({"weights_dir": str(wdir), "downloads": rows}, indent=1))
        return
    colour = {"verified": "green", "present": "yellow", "partial": "yellow", "mismatch": "red", "invalid": "red",
              "missing": "dim"}
    table = Table("manifest", "source", title=f"encoder weights in {wdir}")
    table.add_column("file", overflow="fold")
    table.add_column("state")
    table.add_column("size")
    table.add_column("url", overflow="fold")
    for r in rows:
        table.add_row(r["manifest"], r["source"], r["file"], f"[{colour[r['status']]}]{r['status']}",
                      human_size(r["bytes"]) if r["status"] != "missing" else f"~{human_size(r['bytes'])}", r["url"])
    Console(width=max(120, Console().width)).print(table)
    for r in rows:
        if r["status"] in ("mismatch", "partial", "invalid"):
            _console().print(f"{r['manifest']}: {r['path']}: {r['note']}", style=colour[r["status"]], markup=False)
    paper = paper_fetch()
    _console().print(f"weights folder: {wdir} (--weights-dir, $FREEZE_WEIGHTS, or <project>/weights); "
                     "fetch with `freeze weights fetch NAME` (--source hf for the Hugging Face copies)"
                     + (f"; the paper's configuration: `{paper}`" if paper else ""), markup=False)


@weights_app.command("fetch")
def fetch_weights(
    names: Optional[list[str]] = typer.Argument(None, help="encoder manifest names (see `freeze weights list`)"),
    weights_dir: Optional[Path] = typer.Option(None, help=_WEIGHTS_DIR_HELP),
    source: str = typer.Option("official", help="official (the authors' release) or hf (the Hugging Face copy, "
                                                "DINOv2 only)"),
    fetch_all: bool = typer.Option(False, "--all", help="every manifest that has downloads from SOURCE"),
    progress: Optional[bool] = typer.Option(None, "--progress/--no-progress",
                                            help="byte progress bar (default: when stderr is a terminal)"),
    timeout: float = typer.Option(TIMEOUT_S, min=0.1, help="seconds to wait for a connection, for the server's "
                                                          "answer and for each read"),
) -> None:
    """Download the weight files of the named encoder manifests into the weights folder.

    Resumed after an interruption, checked against the manifest's SHA-256 when it pins
    one, published only whole, the digest recorded beside each file (FILE.sha256). A
    file already there is verified and skipped. Exits with 1 when any file failed."""
    from pipeline.method.encoders.registry import resolve_weights_dir
    from pipeline.formats.weights import WeightsFetchError, fetch_download, select

    console = _console()
    wdir = resolve_weights_dir(weights_dir)
    # Unknown names (or a source a named manifest lacks) stop everything before any
    # transfer: UnknownWeights is a ManifestError, printed as one line by guard_commands.
    planned, notes = select(names or [], fetch_all=fetch_all, source=source)  # type: ignore[arg-type]
    for note in notes:
        console.print(note, style="dim", markup=False)
    failed = []
    for item in planned:
        who = ", ".join(item.names)
        try:
            fetch_download(item.download, wdir, manifest=item.manifest, name=item.name, progress=progress,
                           log=lambda line, who=who: console.print(f"{who}: {line}", markup=False), timeout=timeout)
        except WeightsFetchError as e:  # one line; the next file is still fetched
            console.print(f"error: {who}: {e}", style="red", markup=False)
            failed.append(item.download.file)
    if failed:
        console.print(f"{len(failed)} of {len(planned)} file(s) not fetched: {', '.join(failed)}", style="red",
                      markup=False)
        raise typer.Exit(1)
    console.print(f"{len(planned)} file(s) in {wdir}", markup=False)

"""Pieces shared by the ``freeze`` command modules."""

from __future__ import annotations

import typer

from pipeline.formats.bop.errors import BopFormatError
from pipeline.common.config import ManifestError
from pipeline.formats.weights.formats import WeightsNotFound
from pipeline.common.store import DamagedArtifact, StorageError

USER_ERRORS: tuple[type[Exception], ...] = (BopFormatError, ManifestError, DamagedArtifact, StorageError,
                                            WeightsNotFound)
"""Errors that mean bad input, missing weight files, a damaged artifact or a full or read-only disk: commands
print their one-line message (which names the file) and exit 1, without a traceback."""


def parse_overrides(config: list[str] | None) -> dict[str, str]:
    """``["k=v", ...]`` -> ``{"k": "v"}``: the run manifest overrides given with
    ``--config``/``-c``, as Snakemake's ``--config`` takes them."""
    out = {}
    for kv in config or []:
        if "=" not in kv:
            raise typer.BadParameter(f"expected key=value, got '{kv}'", param_hint="--config")
        k, v = kv.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def guard_commands(app: typer.Typer) -> None:
    """Make every command of ``app`` (and of its sub-apps) print a :data:`USER_ERRORS`
    error as its one line and exit 1, instead of a traceback: bad input is the user's to
    fix, and the message already names the file and the field."""
    import functools

    from rich.console import Console

    def guarded(callback):
        if getattr(callback, "_guarded", False):
            return callback

        @functools.wraps(callback)
        def run(*args, **kwargs):
            try:
                return callback(*args, **kwargs)
            except USER_ERRORS as e:
                # markup off for the message: a "[...]" in it (a path, a value) is text, not a style
                Console(stderr=True, highlight=False, soft_wrap=True).print(f"error: {e}", style="red", markup=False)
                raise typer.Exit(1) from None

        run._guarded = True  # type: ignore[attr-defined]
        return run

    for command in app.registered_commands:
        command.callback = guarded(command.callback)
    for group in app.registered_groups:
        if group.typer_instance is not None:
            guard_commands(group.typer_instance)

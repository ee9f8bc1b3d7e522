"""Pieces shared by the ``freeze`` command modules."""

from __future__ import annotations

import typer


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

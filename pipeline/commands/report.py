"""``freeze report``: the HTML report page of one dataset of the run.

Wired into the ``freeze`` app by ``pipeline.commands.cli`` through :func:`register`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console

from pipeline.commands.common import parse_overrides

# soft_wrap: messages hold paths, which must stay whole for copying (and for tests).
console = Console(stderr=True, soft_wrap=True)


def run_label(overrides: dict[str, str]) -> str:
    """How the run was chosen, for the page: ``default.yaml + visual=dinov2-vits14``."""
    from pipeline.common.config import DEFAULT_RUN, PROJECT_ROOT

    run = overrides.get("run") or str(DEFAULT_RUN)
    try:
        run = str(Path(run).resolve().relative_to(PROJECT_ROOT))
    except ValueError:
        pass
    rest = [f"{k}={v}" for k, v in overrides.items() if k != "run"]
    return " + ".join([run, *rest])


def add_commands(app: typer.Typer, show_app: typer.Typer) -> None:
    """Add ``report`` to the ``freeze`` app (``show_app`` is unused: the report is a page,
    not a figure)."""

    @app.command("report")
    def report(
        dataset: str = typer.Option(..., help="dataset of the run"),
        out: Optional[Path] = typer.Option(None, help="HTML file to write (default <cache>/../results/report_<dataset>.html)"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value"),
        samples: int = typer.Option(12, min=0, help="estimates drawn over their images"),
        worst: int = typer.Option(0, min=0, help="also draw this many of the worst estimates (largest MSSD / d)"),
        run_json: Optional[str] = typer.Option(None, envvar="FREEZE_RUN_JSON", help="resolved run manifest as JSON "
                                               "(Snakemake passes it in $FREEZE_RUN_JSON; --config is then ignored)"),
    ) -> None:
        """Write one self-contained HTML page for a dataset of the run: the AR table, AR
        against visible fraction, time and memory per stage, estimates drawn over their
        images, and the SAR figures."""
        from pipeline.common.config import ManifestError
        from pipeline.workflow.plan import plan_from_json
        from pipeline.common.published_files import check_output_file, error_line
        from pipeline.views.html import default_out, write_report
        from pipeline.common.store import StorageError

        overrides = parse_overrides(config)
        label = "as passed by Snakemake ($FREEZE_RUN_JSON)" if run_json else run_label(overrides)
        try:
            rp = plan_from_json(run_json, overrides)
            ok, why = rp.available(dataset)
        except ManifestError as e:
            console.print(f"[red]{e}")
            raise typer.Exit(2)
        if not ok:
            console.print(f"[red]{why}")
            raise typer.Exit(2)
        path = out or default_out(rp, dataset)
        t0 = time.perf_counter()
        try:
            check_output_file(path, "--out" if out else "")  # a folder given as --out: said before the work
            write_report(rp, dataset, path, samples=samples, run_label=label, worst=worst)
        except StorageError as e:  # that, or a read-only or full disk: one line naming the file
            console.print(error_line(e), style="red", markup=False)
            raise typer.Exit(1)
        except FileNotFoundError as e:
            console.print(f"[red]{e}")
            raise typer.Exit(2)
        console.print(f"{dataset}: report written to {path} ({path.stat().st_size / 1e6:.1f} MB, "
                      f"{time.perf_counter() - t0:.1f} s)")

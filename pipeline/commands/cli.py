"""The ``freeze`` command line (typer)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from pipeline.commands.common import USER_ERRORS, guard_commands, parse_overrides

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="FreeZe: training-free zero-shot 6D pose estimation, as a cached BOP pipeline.")
console = Console(stderr=True)


@app.command()
def synth(
    out: Path = typer.Argument(..., help="dataset folder to create (BOP layout)"),
    name: str = typer.Option("synthmini", help="dataset name (used in file names)"),
    preset: str = typer.Option("mini", help="mini | bench | tiny"),
    seed: int = typer.Option(0, help="random seed; the output is a function of (preset, seed)"),
    progress: bool = typer.Option(True, help="show a progress bar"),
) -> None:
    """Generate a synthetic BOP-format dataset with a faulty CNOS-style prior."""
    from pipeline.evaluation.synth import generate

    summary = generate(out, name, preset=preset, seed=seed, progress=progress)
    console.print_json(json.dumps(summary))


@app.command()
def stage(
    name: str = typer.Argument(..., help="stage name (render_templates, model_features, ...)"),
    dataset: str = typer.Option(..., help="dataset manifest name"),
    item: str = typer.Option(..., help="obj_XXXXXX, scene_XXXXXX, all or dataset"),
    run_json: Optional[str] = typer.Option(None, envvar="FREEZE_RUN_JSON", help="resolved run manifest as JSON (Snakemake passes it in $FREEZE_RUN_JSON)"),
    config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value (without --run-json)"),
    expect_sig: Optional[str] = typer.Option(None, help="fail unless the stage signature equals this"),
    progress: bool = typer.Option(True, help="show progress bars"),
    threads: Optional[int] = typer.Option(None, min=1, help="CPU threads the job may use (Snakemake passes the "
                                                            "rule's threads); default: the libraries' own"),
) -> None:
    """Run one stage for one item (what each Snakemake job calls)."""
    from pipeline.common import store
    from pipeline.workflow.plan import plan_from_json
    from pipeline.workflow.stage_graph import run_stage

    if threads:
        from pipeline.common.threads import use_threads

        use_threads(threads)
    store.mark_job_start()
    plan = plan_from_json(run_json, parse_overrides(config))[dataset]
    sp = plan[name]
    if expect_sig and sp.signature != expect_sig:
        console.print(f"[red]stage {name} of {dataset}: the plan's signature is {sp.signature}, but {expect_sig} was "
                      "requested (code or manifests changed since the DAG was built?)")
        raise typer.Exit(2)
    console.print(f"[bold]{name}[/] {dataset}/{item} -> {sp.item_dir(item)}")
    try:
        run_stage(plan, name, item, progress=progress)
    except USER_ERRORS as e:  # bad input or a damaged artifact: one line, no traceback
        # markup off: a "[...]" in the message (a path, a value) is text, not a style
        console.print(f"stage {name} failed on {dataset}/{item}: {e}", style="red", markup=False, soft_wrap=True)
        raise typer.Exit(1) from None
    except Exception as e:
        console.print(f"stage {name} failed on {dataset}/{item}: {type(e).__name__}: {e}", style="red", markup=False)
        raise


@app.command()
def encoders(
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
    weights_dir: Optional[Path] = typer.Option(
        None, help="folder of encoder weights (default $FREEZE_WEIGHTS or <project>/weights)"),
) -> None:
    """List the encoder manifests: kind, dimension, version, the weights each needs
    (found or not, and the exact path looked in), and which are the paper's (GeDi +
    DINOv2 ViT-g/14) and which weight-free stand-ins for them."""
    from pipeline.common.config import ManifestError, encoder_manifest_names, load_encoder_manifest
    from pipeline.formats.weights.formats import WeightsNotFound
    from pipeline.method.encoders.registry import (EncoderSpec, build_encoder, known_encoders, needs_weights,
                                            resolve_weights_dir)
    from pipeline.common.stand_in import paper_configuration, paper_fetch, paper_line
    from pipeline.formats.weights.formats import NotAWeightsFile

    wdir = resolve_weights_dir(weights_dir)
    rows = []
    for name in encoder_manifest_names():
        row: dict = {"manifest": name}
        try:
            man = load_encoder_manifest(name)
            row.update(encoder=man.encoder, kind=man.kind, paper=man.paper, stand_in=man.stand_in,
                       role="paper" if man.paper else "stand-in" if man.stand_in else "")
            enc = build_encoder(EncoderSpec(name=man.encoder, params=dict(man.params)), weights_dir=wdir)
            weights = getattr(enc, "weights_path", None) or getattr(enc, "weights", None)
            row.update(dim=enc.dim, version=enc.version, signature=enc.signature(),
                       weights=f"found: {weights}" if needs_weights(man.encoder) else "none needed", ok=True)
        except NotAWeightsFile as e:  # present, but a web page or a truncated download (a few bytes read)
            row.update(weights=f"NOT A CHECKPOINT: {e.path}", error=str(e), ok=False)
        except WeightsNotFound as e:
            row.update(weights="MISSING, looked in: " + ", ".join(map(str, e.looked_in)), error=str(e), ok=False)
        except (FileNotFoundError, ValueError, ManifestError) as e:
            row.update(weights=f"ERROR: {e}", error=str(e), ok=False)
        rows.append(row)
    unused = sorted(set(known_encoders()) - {r.get("encoder") for r in rows})
    paper = {kind: name for kind, (name, _) in paper_configuration().items()}
    paper_text = paper_line()
    if as_json:
        print(json.dumps({"weights_dir": str(wdir), "manifests": rows, "registered_without_manifest": unused,
                          "paper_configuration": {**paper, "fetch": paper_fetch(),
                                                  "note": paper_text} if paper else None}, indent=2))
        return
    table = Table("manifest", "encoder", "kind", "role", "dim", "version", "signature", title="encoders")
    table.add_column("weights", overflow="fold")
    for r in rows:
        table.add_row(r["manifest"], r.get("encoder", "?"), r.get("kind", "?"), r.get("role", ""),
                      str(r.get("dim", "-")), str(r.get("version", "-")), r.get("signature", "-"),
                      r["weights"] if r["ok"] else f"[red]{r['weights']}")
    Console(width=max(120, Console().width)).print(table)
    for r in rows:  # the whole message once, on one line: which file, what it is, what to do
        if str(r.get("weights", "")).startswith("NOT A CHECKPOINT"):
            console.print(f"{r['manifest']}: {r['error']}", style="red", markup=False, highlight=False,
                          soft_wrap=True)
    if paper_text:
        console.print(paper_text, markup=False, highlight=False, soft_wrap=True)
    console.print(f"weights folder: {wdir} (--weights-dir, $FREEZE_WEIGHTS, or <project>/weights)")
    if unused:
        console.print(f"registered encoders without a manifest: {', '.join(unused)}")


@app.command()
def plan(
    dataset: Optional[list[str]] = typer.Option(None, help="datasets (default: the run's)"),
    config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value"),
) -> None:
    """Print every stage's signature and artifact folder."""
    from pipeline.workflow.plan import plan_from_json

    rp = plan_from_json(None, parse_overrides(config))
    table = Table("dataset", "stage", "signature", "folder")
    for ds in dataset or rp.dataset_names:
        ok, why = rp.available(ds)
        if not ok:
            console.print(why)
            continue
        for st in rp[ds].stages.values():
            table.add_row(ds, st.stage, st.signature, str(st.dir))
    Console().print(table)


def _positive_finite(value: Optional[float]) -> Optional[float]:
    """typer callback: a finite number > 0 (or None, the default), as the dataset
    manifests require of ``vsd_delta``; NaN, inf, 0 and negatives are refused."""
    import math

    if value is not None and not (math.isfinite(value) and value > 0):
        raise typer.BadParameter(f"must be a finite number of mm > 0, got {value:g}")
    return value


@app.command()
def score(
    results: Path = typer.Argument(..., exists=True, dir_okay=False, help="BOP results CSV"),
    dataset_root: Path = typer.Option(..., exists=True, file_okay=False, help="BOP dataset folder (camera.json, models_eval/, test/...)"),
    split: str = typer.Option("test"),
    targets: Optional[Path] = typer.Option(None, help="targets file (default <root>/test_targets_bop19.json)"),
    out: Optional[Path] = typer.Option(None, help="folder to write errors.parquet and scores.json into (created if "
                                                  "missing)"),
    workers: int = typer.Option(1, help="worker processes"),
    vsd_delta: Optional[float] = typer.Option(None, callback=_positive_finite,
                                              help="VSD tolerance in mm, a finite number > 0 [default: 5 for itodd, "
                                                   "else 15]"),
    progress: bool = typer.Option(True, help="show what is being done (a spinner per step, a bar over the images)"),
) -> None:
    """Score a BOP results CSV with the BOP19 metrics (VSD, MSSD, MSPD, AR).

    Every R must be a rotation: max|R^T R - I| <= 0.001 and |det R - 1| <= 0.001
    (pipeline.evaluation.metrics.ROTATION_TOLERANCE). A file with another R (an all-zero
    one too) is refused with exit code 1, naming how many rows are bad and the
    first one.
    """
    from pipeline.formats.bop.errors import BopFormatError
    from pipeline.evaluation.metrics import score_results_file
    from pipeline.common.progress import StepTimer
    from pipeline.common.published_files import check_output_dir, error_line
    from pipeline.common.store import StorageError

    try:
        if out is not None:
            check_output_dir(out, "--out")  # before the work, not after it
        s = score_results_file(results, dataset_root, split=split, targets_file=targets, out_dir=out,
                               n_workers=workers, vsd_delta=vsd_delta, progress=progress,
                               steps=StepTimer(enabled=progress, console=console))
    except BopFormatError as e:
        # soft_wrap: one line, the path kept whole for copying.
        console.print(f"[red]{e}", soft_wrap=True)
        raise typer.Exit(1)
    except StorageError as e:  # --out a file, a read-only or full disk: one line naming the path
        console.print(error_line(e), style="red", markup=False, soft_wrap=True)
        raise typer.Exit(1)
    _print_scores({results.stem: s.summary})
    summ = s.summary
    console.print(f"{summ['n_estimates']} estimates: {summ['n_evaluated']} evaluated, {summ['n_ignored']} ignored "
                  f"(not a target), {summ['n_beyond_inst_count']} beyond inst_count")
    for note in summ.get("notes", []):
        console.print(note, style="yellow", markup=False, soft_wrap=True)


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)


def _print_scores(rows: dict[str, dict]) -> str:
    """Print the AR table and return it as Markdown."""
    cols = {"AR": "AR", "AR_VSD": "AR_VSD", "AR_MSSD": "AR_MSSD", "AR_MSPD": "AR_MSPD",
            "n_targets": "targets", "n_estimates": "estimates", "mean_time_per_image": "s/image"}
    table = Table("results", *cols.values(), title="BOP19 average recall")
    md = ["| results | " + " | ".join(cols.values()) + " |", "|" + "---|" * (len(cols) + 1)]
    for name, s in rows.items():
        vals = [_fmt(s.get(c)) for c in cols]
        table.add_row(name, *vals)
        md.append(f"| {name} | " + " | ".join(vals) + " |")
    Console(width=max(100, Console().width)).print(table)
    return "\n".join(md) + "\n"


def _publish_csv(plan, folder: Path) -> Path:
    """Copy the dataset's results CSV into ``folder`` atomically (a temporary sibling
    renamed into place) with the mode the umask gives a new file (0644 under umask 022);
    returns the copy. Raises :class:`pipeline.common.store.StorageError` naming the copy when it
    cannot be written (a folder in its place, a full or read-only disk)."""
    from pipeline.common.published_files import write_text_published

    dst = folder / plan.results_csv_name
    return write_text_published(
        dst, (plan["refine"].item_dir("all") / plan.results_csv_name).read_text(encoding="utf-8"))


@app.command("table")
def ar_table(
    config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value"),
    run_json: Optional[str] = typer.Option(None, envvar="FREEZE_RUN_JSON", help="resolved run manifest as JSON (Snakemake passes it in $FREEZE_RUN_JSON)"),
    out: Optional[Path] = typer.Option(None, help="also write the table as Markdown here"),
    csv_dir: Optional[Path] = typer.Option(None, help="also copy each dataset's BOP results CSV "
                                                      "(<method>_<dataset>-<split>.csv) into this folder"),
) -> None:
    """Print the AR table of the run's datasets from their score artifacts."""
    from pipeline.workflow.plan import plan_from_json
    from pipeline.common.published_files import check_output_dir, check_output_file, error_line
    from pipeline.common.store import DamagedArtifact, StorageError, ensure_sound, read_manifest

    try:  # a folder given as --out, a file as --csv-dir: said before anything is read or written
        if out:
            check_output_file(out, "--out")
        if csv_dir:
            check_output_dir(csv_dir, "--csv-dir")
    except StorageError as e:
        console.print(error_line(e), style="red", markup=False, soft_wrap=True)
        raise typer.Exit(1)
    rp = plan_from_json(run_json, parse_overrides(config))
    rows = {}
    failed = False
    for ds in rp.dataset_names:
        ok, why = rp.available(ds)
        if not ok:
            console.print(why)
            continue
        path = rp[ds]["score"].item_dir("all")
        try:
            ensure_sound(path)  # the AR shown must be that of an intact score artifact
            rows[ds] = read_manifest(path)["summary"]
        except FileNotFoundError:
            console.print(f"{ds}: not scored yet ({path} missing): run `snakemake --cores 2 bop_all`")
            failed = True
            continue
        except DamagedArtifact as e:
            console.print(f"[red]{ds}: {e}", soft_wrap=True)
            failed = True
            continue
        if csv_dir:
            try:
                _publish_csv(rp[ds], csv_dir)
            except StorageError as e:  # a full or read-only disk: one line naming the file
                console.print(error_line(e), style="red", markup=False, soft_wrap=True)
                failed = True
            except FileNotFoundError as e:  # the results CSV of a refine artifact deleted by hand
                console.print(f"{ds}: {e}", style="red", markup=False, soft_wrap=True)
                failed = True
    md = _print_scores(rows)
    notes = [f"{ds}: {note}" for ds, s in rows.items() for note in s.get("notes") or []]
    for line in notes:
        console.print(f"[yellow]{line}", soft_wrap=True)
    if notes:  # the Snakefile prints the table file: the warnings go with it
        md = md.rstrip("\n") + "\n\n" + "\n".join(f"- {line}" for line in notes) + "\n"
    if out:
        from pipeline.common.published_files import write_text_published

        try:
            write_text_published(out, md)  # atomic, mode 0o666 & ~umask
        except StorageError as e:
            console.print(error_line(e), style="red", markup=False, soft_wrap=True)
            failed = True
    if failed:
        raise typer.Exit(1)


show_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Pictures made from the artifacts.")
app.add_typer(show_app, name="show")


@show_app.command("sar")
def show_sar(
    dataset: str = typer.Option(..., help="dataset of the run"),
    obj: Optional[list[int]] = typer.Option(None, help="object ids (default: every object SAR ran on)"),
    limit: int = typer.Option(4, help="estimates per object: those SAR changed first"),
    out: Optional[Path] = typer.Option(None, help="folder for the PNGs (default <cache>/../results/figures)"),
    config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value"),
) -> None:
    """Per object, the scene crop, the ICP pose and the SAR pose over it, and every
    symmetric variant's similarity: sar_<dataset>_obj_<id>.png."""
    from pipeline.workflow.plan import plan_from_json
    from pipeline.views.sar_figure import draw_sar_figure, sar_cases
    from pipeline.common.store import read_table

    rp = plan_from_json(None, parse_overrides(config))
    plan = rp[dataset]
    folder = out or rp.cache.parent / "results" / "figures"
    ids = obj
    if not ids:
        ids = set()
        for item in plan.scene_items:
            path = plan["refine"].path(item, "sar")
            if not path.exists():
                console.print(f"[red]{path} missing: run the refine stage first (snakemake --cores 2 bop_all)")
                raise typer.Exit(2)
            ids |= set(read_table(path).obj_id.astype(int))
    if not ids:
        console.print(f"{dataset}: SAR ran on no estimate (no object with a geometric symmetry, or SAR off)")
    for obj_id in sorted(ids):
        cases = sar_cases(plan, obj_id, limit=limit)
        if not cases:
            console.print(f"object {obj_id}: no SAR case")
            continue
        path = draw_sar_figure(cases, folder / f"sar_{dataset}_obj_{obj_id:06d}.png",
                               title=f"{dataset}, object {obj_id}: symmetry-aware refinement")
        console.print(f"object {obj_id}: {path}")


datasets_app = typer.Typer(add_completion=False, no_args_is_help=True, help="BOP datasets on disk.")
app.add_typer(datasets_app, name="datasets")


@datasets_app.command("check")
def datasets_check(
    root: Path = typer.Argument(..., exists=True, file_okay=False, help="bop_root: the folder holding lmo/, tless/, ..."),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
    prior: Optional[str] = typer.Option(None, help="priors to check instead of the default detections, as in "
                                                   "--config prior=... (detector names or paths, comma-separated)"),
    deep: bool = typer.Option(False, "--deep", help="also open the first, the middle and the last target image of "
                                                    "every scene: RGB decodes; depth is 16-bit single-channel, of the "
                                                    "RGB's and the camera's size, not all zero"),
) -> None:
    """Check every BOP dataset found under ROOT before a long run: the files and fields
    each stage needs, every model file (readable PLY, faces, finite vertices spanning a
    surface, extent matching models_info's diameter in mm), units, the cameras (cam_K a
    plausible pinhole matrix, depth_scale positive), the ground truth the scorer reads,
    targets without images or listed twice, the prior; print a summary per dataset.
    Exits with 1 when a dataset has errors or when ROOT holds no dataset."""
    from pipeline.commands.datasets import check_root, no_dataset_message

    reports, absent = check_root(root, [p for p in prior.split(",") if p] if prior else None, deep=deep,
                                 progress=True)
    if not reports:  # nothing checked is not a pass: most likely the wrong folder
        message = no_dataset_message(root)
        if as_json:
            print(json.dumps({"datasets": [], "absent": absent, "error": message}, indent=1))
        console.print(message, style="red", markup=False, soft_wrap=True)
        raise typer.Exit(1)
    if as_json:
        print(json.dumps({"datasets": [r.to_json() for r in reports], "absent": absent}, indent=1))
    else:
        table = Table("dataset", "objects", "scenes", "images", "targets", "instances per target", "detections",
                      "image size", "ground truth", "status", title=f"BOP datasets under {root}")
        for r in reports:
            s = r.summary
            ipt = ", ".join(f"{k}: {v}" for k, v in s.get("instances_per_target", {}).items())
            table.add_row(r.name, *(str(s.get(k, "-")) for k in ("objects", "scenes", "images", "targets")), ipt or "-",
                          str(s.get("detections", "-")),
                          "x".join(map(str, s["image_size"])) if len(s.get("image_size") or []) == 2
                          and isinstance(s["image_size"][0], int) else str(s.get("image_size", "-")),
                          "-" if "ground_truth" not in s else "yes" if s["ground_truth"] else "private/absent",
                          "[green]ok" if r.ok else f"[red]{len(r.errors)} error(s)")
        Console(width=max(120, Console().width)).print(table)
        for r in reports:  # one line each, the path kept whole for copying; no markup: paths may hold '['
            for e in r.errors:
                console.print(f"{r.name}: {e}", style="red", markup=False, soft_wrap=True)
            for w in r.warnings:
                console.print(f"{r.name}: {w}", style="yellow", markup=False, soft_wrap=True)
        if absent:
            console.print(f"not found under {root}: {', '.join(absent)}")
    if any(not r.ok for r in reports):
        raise typer.Exit(1)


from pipeline.commands.weights import weights_app  # noqa: E402  (`freeze weights list|fetch`: the encoders' weight files)

app.add_typer(weights_app, name="weights")


def _add_module_commands() -> None:
    """Commands that live in their own modules (each has ``add_commands(app, show_app)``)."""
    from pipeline.commands.estimate import command as estimate_cli
    from pipeline.commands import inspect as inspect_cli
    from pipeline.commands import run as run_cli
    from pipeline.commands import report as report_cli

    for module in (run_cli, inspect_cli, report_cli, estimate_cli):
        module.add_commands(app, show_app)


_add_module_commands()
guard_commands(app)


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())

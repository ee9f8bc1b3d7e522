"""``freeze inspect``, ``freeze ls``, ``freeze gc`` and ``freeze show features``.

The library is :mod:`pipeline.workflow.artifacts` (and :mod:`pipeline.views.features_figure`);
this module only parses options and prints. :func:`add_commands` adds the commands to the
``freeze`` app and its ``show`` sub-app (one ``_add_*_command`` function per command).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import typer
from rich.console import Console
from rich.table import Table
from rich.markup import escape
from rich.tree import Tree

from pipeline.commands.common import parse_overrides
from pipeline.workflow.artifacts import human_bytes

if TYPE_CHECKING:
    from pipeline.commands.verify import VerifyReport
    from pipeline.workflow.artifacts import CacheListing, Removal


def _out() -> Console:
    """Console on stdout, wide enough for the tables even when piped."""
    return Console(width=max(120, Console().width), highlight=False)


def _err() -> Console:
    return Console(stderr=True, highlight=False, soft_wrap=True)  # error lines name paths: never break them


def _num(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool) or isinstance(v, int):
        return str(v)
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) >= 1e5 or abs(v) < 1e-3:
        return f"{v:.3g}"
    return f"{v:.4g}"


def _key_mark(ok: bool | None) -> str:
    return {True: "[green]key matches the manifest[/]", False: "[red]KEY DIFFERS FROM THE MANIFEST[/]",
            None: "[dim]no key recorded[/]"}[ok]


def _compact(obj: Any, limit: int = 400) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(", ", ": "))
    return text if len(text) <= limit else text[: limit - 3] + "..."


# ------------------------------------------------------------------------- inspect


def _print_upstream(tree: Tree, nodes: list[dict[str, Any]]) -> None:
    for n in nodes:
        if not n.get("found"):
            tree.add(f"[bold]{n['name']}[/] [dim]{n['key'][:12]}[/]: [yellow]not an artifact of this cache[/] "
                     "(a dataset fingerprint or file hash, or deleted)")
            continue
        items = n["items"]
        shown = ", ".join(items[:4]) + (f", ... {len(items)} items" if len(items) > 4 else "")
        label = (f"[bold]{n['name']}[/]: {n['stage']}/[cyan]{n['signature']}[/] ({escape(shown)})"
                 + (" [dim](see above)[/]" if n.get("repeated") else ""))
        branch = tree.add(label)
        _print_upstream(branch, n.get("upstream", []))


def print_inspection(info: dict[str, Any], console: Console) -> None:
    """Human-readable rendering of :func:`pipeline.workflow.artifacts.inspect_artifact`'s result."""
    a, m = info["artifact"], info["manifest"]
    console.rule(f"[bold]{a['stage']}[/] / [cyan]{a['signature']}[/] / {a['item']}   ({a['dataset']})")
    head = Table.grid(padding=(0, 2))
    head.add_column(style="dim", no_wrap=True)
    head.add_column(overflow="fold")
    head.add_row("folder", a["item_dir"])
    head.add_row("key", f"{m['key']}   code version {m['code_version']}   created {m['created']}")
    wall = f"{m['wall_time_s']:.1f} s" if m.get("wall_time_s") is not None else "-"
    rss = f"{m['peak_rss_mb']:.0f} MiB" if m.get("peak_rss_mb") is not None else "-"
    head.add_row("timing", f"wall time {wall}, peak RSS {rss} (host {m.get('host') or '-'})")
    enc = info.get("encoders")
    if enc:
        parts = [f"{kind} [bold]{enc[kind]['encoder']}[/] v{enc[kind]['version']} {escape(_compact(enc[kind]['params'], 160))}"
                 for kind in ("geometric", "visual") if kind in enc]
        head.add_row("encoders", "\n".join(parts + [f"[dim](recorded by {enc['recorded_by']})[/]"]))
    params = dict(m["params"] or {})
    if "encoders" in params and enc:
        params["encoders"] = "(above)"
    head.add_row("params", escape(_compact(params, 800)))
    head.add_row("summary", escape(_compact(m["summary"])))
    ups = m.get("upstream") or {}
    head.add_row("upstream", ", ".join(f"{k}={v[:12]}" for k, v in sorted(ups.items())) or "none")
    libs = m.get("libraries") or {}
    head.add_row("libraries", "[dim]" + ", ".join(f"{k} {v}" for k, v in sorted(libs.items())) + "[/]")
    console.print(head)

    for z in info["zarr"]:
        console.print()
        console.print(f"[bold]{Path(z['path']).name}[/] (Zarr v{z['zarr_format']}, {_key_mark(z['key_matches'])}) "
                      f"attrs {escape(_compact({k: v for k, v in z['attrs'].items() if k != 'key'}, 200))}")
        t = Table("array", "shape", "dtype", "chunks", "codec", "stored", "ratio", "NaN", "min", "max", "mean",
                  box=None, pad_edge=False)
        for arr in z["arrays"]:
            s = arr.get("stats") or {}
            t.add_row(arr["name"], "x".join(map(str, arr["shape"])) or "()", arr["dtype"],
                      "x".join(map(str, arr["chunks"])), arr["compressors"], human_bytes(arr["stored_bytes"]),
                      _num(arr["ratio"]), _num(s.get("nan")), _num(s.get("min")), _num(s.get("max")), _num(s.get("mean")))
        console.print(t)
        feats = [arr for arr in z["arrays"] if "norms" in arr]
        if feats:
            t = Table("feature rows (L2 norm)", "channels", "rows", "NaN rows", "zero rows", "min", "p05", "median", "p95",
                      "max", box=None, pad_edge=False)
            for arr in feats:
                nm = arr["norms"]
                t.add_row(arr["name"], str(nm["channels"]), str(nm["rows"]), str(nm["nan_rows"]), str(nm["zero_rows"]),
                          *(_num(nm.get(k)) for k in ("min", "p05", "median", "p95", "max")))
            console.print(t)

    for p in info["parquet"]:
        console.print()
        console.print(f"[bold]{Path(p['path']).name}[/] (Parquet: {p['rows']} rows, {p['row_groups']} row group(s), "
                      f"{human_bytes(p['size_bytes'])}, {_key_mark(p['key_matches'])})")
        body = Table.grid(padding=(0, 2))
        body.add_column(style="dim", no_wrap=True)
        body.add_column(overflow="fold")
        body.add_row("columns", ", ".join(escape(f"{c['name']}: {c['type']}")
                                          + (f" [yellow]({c['null_count']} null)[/]" if c["null_count"] else "")
                                          for c in p["columns"]))
        extra = {k: v for k, v in p["metadata"].items() if k != "key"}
        if extra:
            body.add_row("metadata", escape(_compact(extra, 200)))
        console.print(body)

    for f in info["files"]:
        console.print()
        desc = f"{f['files']} files" if f["kind"] == "dir" else f["kind"]
        line = f"[bold]{Path(f['path']).name}[/] ({desc}, {human_bytes(f['size_bytes'])})"
        if f.get("keys"):
            line += f" keys: {', '.join(f['keys'])}"
        if "rows" in f:
            line += f" {f['rows']} rows"
        console.print(line)

    console.print()
    root = Tree(f"[bold]{a['stage']}[/]/[cyan]{a['signature']}[/]/{a['item']} was built from")
    _print_upstream(root, info["upstream"])
    if not info["upstream"]:
        root.add("[dim]nothing: the head of the chain[/]")
    console.print(root)


# ------------------------------------------------------------------------- ls, gc


def _load_run(config: list[str] | None):
    from pipeline.common.config import ManifestError, load_run

    try:
        return load_run(parse_overrides(config))
    except (ManifestError, ValueError) as e:
        _err().print(f"[red]run configuration: {e}")
        raise typer.Exit(2)


_STATUS = {"current": "[green]current[/]", "stale": "[yellow]stale[/]", "unknown": "[dim]unknown[/]"}


def print_listing(listing, console: Console) -> None:
    """Per dataset, a table of stage signature folders (see :func:`pipeline.workflow.artifacts.list_artifacts`)."""
    by_ds: dict[str, list] = {}
    for e in listing.entries:
        by_ds.setdefault(e.dataset, []).append(e)
    for ds, entries in by_ds.items():
        t = Table("stage", "signature", "items", "size", "created", "status", title=f"{ds}  ({listing.cache}/{ds})",
                  title_justify="left")
        for e in entries:
            items = str(len(e.items)) + (f" [red](+{len(e.incomplete)} unfinished: running or failed)[/]" if e.incomplete else "")
            t.add_row(e.stage, e.signature, items, human_bytes(e.size_bytes), (e.created or "-")[:16].replace("T", " "),
                      _STATUS[e.status] + (f" [dim]{e.note}[/]" if e.note else ""))
        console.print(t)
    for ds, note in listing.notes.items():
        console.print(f"[yellow]{note}")
    stale = [e for e in listing.entries if e.status == "stale"]
    if stale:
        console.print(f"{len(stale)} stale signature folder(s), {human_bytes(sum(e.size_bytes for e in stale))}: "
                      "`freeze gc` (with the same --config) removes them")
    for lo in listing.leftovers:
        console.print(f"[yellow]leftover of an interrupted publish: {lo.path} ({human_bytes(lo.size_bytes)}, "
                      f"{lo.age_s / 60:.0f} min old)")


_CONFIG_HELP = ("run overrides key=value (as for snakemake --config, e.g. visual=none, run=manifests/runs/refine-icp.yaml): "
                "the run whose plan counts as current")
_STALE_NOTE = ("'Current' means: a stage signature the plan of the given run configuration (default run manifest plus "
               "--config overrides) points to. Artifacts of other runs (an encoder ablation, another run manifest) are "
               "'stale' for it, although they are valid for their own run: pass that run's --config to see them as "
               "current. Datasets without a plan here (no dataset manifest, BOP data not found) are 'unknown' and never "
               "removed.")


def add_commands(app: typer.Typer, show_app: typer.Typer) -> None:
    """Add ``verify``, ``inspect``, ``ls`` and ``gc`` to ``app`` and ``features`` and
    ``hypotheses`` to ``show_app`` (in that order: the order of ``--help``)."""
    _add_verify_command(app)
    _add_inspect_command(app)
    _add_ls_command(app)
    _add_gc_command(app)
    _add_show_features_command(show_app)
    _add_show_hypotheses_command(show_app)


def _add_verify_command(app: typer.Typer) -> None:
    """Add ``freeze verify``: check a cache's artifacts against their manifests."""

    @app.command("verify")
    def verify_cmd(
        dataset: Optional[list[str]] = typer.Option(None, "--dataset", "-d", help="datasets (default: every one in the cache)"),
        cache: Optional[Path] = typer.Option(None, help="cache root (default $FREEZE_CACHE or <project>/cache)"),
        repair: bool = typer.Option(False, "--repair", help="delete the damaged item folders and the leftovers of killed "
                                                           "runs, so that the next run rebuilds them"),
        quick: bool = typer.Option(False, "--quick", help="compare file sizes only, not checksums"),
        tmp_min_age: float = typer.Option(60.0, help="minutes: younger .tmp-*/.old-* leftovers may belong to a running "
                                                     "job and are left alone"),
        progress: bool = typer.Option(True, help="show a progress bar"),
    ) -> None:
        """Check every artifact of a cache against its manifest: each file's size and SHA-256 as recorded when it was
        published. Lists damaged items (a file missing, truncated or altered; an unreadable manifest) and leftovers
        of killed runs. An artifact is a folder with its own _manifest.json, at any depth (freeze estimate's too);
        --repair removes damaged ones and leftovers and nothing else: what is not an artifact, and symbolic links,
        are listed as left alone. Exits 1 when it finds damage, unless --repair removed it."""
        from pipeline.commands.verify import scan_cache, verify_cache
        from pipeline.workflow.plan import cache_root
        from pipeline.common.progress import progress_bar

        root = Path(cache) if cache else cache_root()
        if not root.is_dir():
            _err().print(f"[red]{escape(str(root))}: no cache folder")
            raise typer.Exit(1)
        scan = scan_cache(root, dataset)
        with progress_bar(f"verify {root}", total=len(scan.artifacts), enabled=progress) as bar:
            report = verify_cache(root, dataset, checksums=not quick, repair=repair,
                                  leftover_min_age_s=tmp_min_age * 60, advance=bar.advance, scan=scan)
        _print_verification(report, repair=repair, quick=quick, tmp_min_age=tmp_min_age)


def _print_verification(report: VerifyReport, *, repair: bool, quick: bool, tmp_min_age: float) -> None:
    """Print ``freeze verify``'s findings (a :func:`pipeline.commands.verify.verify_cache`
    report) on stderr; ``typer.Exit(1)`` when it found errors, or damage left in place."""
    out = _err()
    for item, problems in report.damaged.items():
        for line in problems:
            out.print(f"[red]damaged: {escape(line)}")
    for p in report.leftovers:
        out.print(f"[yellow]leftover of a killed run: {escape(str(p))}")
    shown = 20  # a user's folder of thousands of files is one line already; links are listed each
    for p, why in report.left_alone[:shown]:
        out.print(f"left alone: {escape(str(p))} ({escape(why)})")
    if len(report.left_alone) > shown:
        out.print(f"left alone: {len(report.left_alone) - shown} more paths that are not artifacts")
    if report.young_leftovers:
        out.print(f"left alone: {len(report.young_leftovers)} leftover(s) younger than {tmp_min_age:g} min (a "
                  f"running job's, perhaps), e.g. {escape(str(report.young_leftovers[0]))}")
    what = "sizes" if quick else "sizes and checksums"
    out.print(f"{report.checked} artifact items checked ({what}): {len(report.damaged)} damaged, "
              f"{len(report.leftovers)} leftovers; {len(report.left_alone)} paths left alone (not artifacts)")
    for line in report.errors:
        out.print(f"[red]error: {escape(line)}")
    if report.errors:
        raise typer.Exit(1)
    if repair and report.removed:
        out.print(f"removed {len(report.removed)}; the next run rebuilds the damaged items")
    if not report.ok:
        out.print("some were not removed (see 'left alone' above)" if repair else
                  "run `freeze verify --repair` to remove them; the next run rebuilds the damaged items")
        raise typer.Exit(1)


def _add_inspect_command(app: typer.Typer) -> None:
    """Add ``freeze inspect``: what one artifact holds and what it was built from."""

    @app.command("inspect")
    def inspect_cmd(
        path: Path = typer.Argument(..., help="an artifact folder <cache>/<dataset>/<stage>/<signature>/<item>, or a "
                                              "Zarr store, Zarr array or Parquet file in one"),
        as_json: bool = typer.Option(False, "--json", help="print everything as JSON (machine-readable)"),
    ) -> None:
        """Show what an artifact holds: its manifest (key, upstream keys, parameters, encoders, code version, wall
        time, peak RSS), its arrays (shape, dtype, chunks, compression ratio, NaN count, min/max/mean, L2 norms of
        feature rows), its Parquet tables (schema, rows, key metadata) and the tree of upstream artifacts it was
        built from."""
        from pipeline.workflow.artifacts import NotAnArtifact, inspect_artifact, locate
        from pipeline.common.store import verify_item

        try:
            problems = verify_item(locate(path).item_dir)
            info = None if problems else inspect_artifact(path)
        except NotAnArtifact as e:
            _err().print(f"[red]{e}")
            raise typer.Exit(2)
        if problems:  # name the damaged file rather than fail inside a reader
            for line in problems:
                _err().print(f"[red]damaged artifact: {escape(line)}")
            _err().print("run `freeze verify --repair` to remove the damaged items; a rerun rebuilds them")
            raise typer.Exit(1)
        if as_json:
            print(json.dumps(info, indent=2, default=str))
        else:
            print_inspection(info, _out())


def _add_ls_command(app: typer.Typer) -> None:
    """Add ``freeze ls``: the artifacts per dataset and stage, current or stale."""

    @app.command("ls", help="List the artifacts per dataset and stage: signature, items, size, date, and whether the "
                            "current plan points to them (current) or not (stale).\n\n" + _STALE_NOTE)
    def ls_cmd(
        dataset: Optional[list[str]] = typer.Option(None, "--dataset", "-d", help="datasets (default: every one in the cache)"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help=_CONFIG_HELP),
        cache: Optional[Path] = typer.Option(None, help="cache root (default $FREEZE_CACHE or <project>/cache)"),
        as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
    ) -> None:
        from pipeline.workflow.artifacts import list_artifacts
        from pipeline.workflow.plan import cache_root

        listing = list_artifacts(cache or cache_root(), _load_run(config), dataset)
        if as_json:
            print(json.dumps(listing.to_dict(), indent=2))
        else:
            print_listing(listing, _out())


def _add_gc_command(app: typer.Typer) -> None:
    """Add ``freeze gc``: remove the stale signature folders and leftovers, after asking."""

    @app.command("gc", help="Remove the stale artifact signature folders (those the current plan does not point to) "
                            "and the leftover .tmp-*/.old-* folders of interrupted publishes, after showing what goes and "
                            "how much space it frees, and asking. Never removes the current plan's artifacts or anything "
                            "outside the cache root. Do not run it while a pipeline of another configuration is running."
                            "\n\n" + _STALE_NOTE)
    def gc_cmd(
        dataset: Optional[list[str]] = typer.Option(None, "--dataset", "-d", help="datasets (default: every one in the cache)"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help=_CONFIG_HELP),
        cache: Optional[Path] = typer.Option(None, help="cache root (default $FREEZE_CACHE or <project>/cache)"),
        yes: bool = typer.Option(False, "--yes", "-y", help="do not ask for confirmation"),
        tmp_min_age: float = typer.Option(60.0, help="minutes: younger .tmp-*/.old-* folders may belong to a running job "
                                                     "and are kept"),
    ) -> None:
        from pipeline.workflow.artifacts import collect_garbage, garbage, list_artifacts
        from pipeline.workflow.plan import cache_root

        listing = list_artifacts(cache or cache_root(), _load_run(config), dataset)
        out = _out()
        for note in listing.notes.values():
            out.print(f"[yellow]{note}")
        removals = garbage(listing, tmp_min_age_s=tmp_min_age * 60)
        if not removals:
            out.print("nothing to remove")
            return
        _print_removals(listing, removals, out)
        if not yes and not typer.confirm("Remove them?", default=False):
            out.print("nothing removed")
            raise typer.Exit(1)
        try:
            freed = collect_garbage(listing, removals)
        except ValueError as e:
            _err().print(f"[red]{e}")
            raise typer.Exit(2)
        out.print(f"removed {len(removals)} folder(s), freed {human_bytes(freed)}")


def _print_removals(listing: CacheListing, removals: list[Removal], out: Console) -> None:
    """The table of what ``freeze gc`` removes (path in the cache, size, why) and the total."""
    t = Table("remove", "size", "why", title=f"garbage in {listing.cache}", title_justify="left")
    for r in removals:
        t.add_row(str(Path(r.path).relative_to(listing.cache)), human_bytes(r.size_bytes), r.reason)
    out.print(t)
    total = sum(r.size_bytes for r in removals)
    out.print(f"{len(removals)} folder(s), {human_bytes(total)} to free")


def _add_show_features_command(show_app: typer.Typer) -> None:
    """Add ``freeze show features``: the feature PCA figure of a model and a candidate."""

    @show_app.command("features")
    def show_features(
        dataset: str = typer.Option(..., help="dataset of the run"),
        obj: int = typer.Option(..., help="object id"),
        scene: Optional[int] = typer.Option(None, help="scene id (default: any scene with a registered candidate)"),
        candidate: Optional[int] = typer.Option(None, help="candidate id (default: the object's first registered one)"),
        out: Optional[Path] = typer.Option(None, help="folder for the PNG (default <cache>/../results/figures)"),
        max_lines: int = typer.Option(50, help="correspondence lines drawn at most"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value"),
    ) -> None:
        """The geometric, visual and fused features of an object's model and of one of its scene candidates, coloured
        by a shared 3-component PCA (fitted on the model), and the candidate's RANSAC inlier correspondences:
        features_<dataset>_obj_<id>_scene_<id>_cand_<id>.png."""
        from pipeline.workflow.plan import RunPlan
        from pipeline.views.features_figure import draw_features_figure, feature_case

        run = _load_run(config)
        rp = RunPlan(run)
        try:
            plan = rp[dataset]
            case = feature_case(plan, obj, scene_id=scene, cand_id=candidate)
        except (FileNotFoundError, LookupError, ValueError) as e:
            _err().print(f"[red]{e}")
            raise typer.Exit(2)
        folder = out or rp.cache.parent / "results" / "figures"
        path = folder / f"features_{dataset}_obj_{obj:06d}_scene_{case.scene_id:06d}_cand_{case.cand_id}.png"
        draw_features_figure(case, path, max_lines=max_lines)
        for note in case.notes:
            _err().print(f"[yellow]{note}")
        _out().print(f"object {obj}, scene {case.scene_id}, image {case.im_id}, candidate {case.cand_id}: {path}")


def _add_show_hypotheses_command(show_app: typer.Typer) -> None:
    """Add ``freeze show hypotheses``: every coarse hypothesis of some candidates, as verified."""

    @show_app.command("hypotheses")
    def show_hypotheses(
        dataset: str = typer.Option(..., help="dataset of the run"),
        scene: Optional[int] = typer.Option(None, help="scene id (default: every scene)"),
        candidate: Optional[int] = typer.Option(None, help="candidate id (default: the most telling candidates)"),
        obj: Optional[int] = typer.Option(None, help="only this object's candidates"),
        limit: int = typer.Option(6, min=1, help="candidates drawn at most"),
        out: Optional[Path] = typer.Option(None, help="folder for the PNG (default <cache>/../results/figures)"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value"),
    ) -> None:
        """Every coarse hypothesis of some candidates after ICP, as the verification saw it: the model at each pose
        coloured by its depth against the sensor's, the mask, each term of the score, the chosen one framed:
        hypotheses_<dataset>[_scene_<id>][_cand_<id>].png. By default the candidates whose chosen hypothesis is not
        the paper's fused pose come first."""
        from pipeline.workflow.plan import RunPlan
        from pipeline.views.hypotheses_figure import draw_hypotheses_figure, hypothesis_cases

        rp = RunPlan(_load_run(config))
        try:
            plan = rp[dataset]
            if scene is not None and scene not in plan.scene_ids:
                raise LookupError(f"{dataset}: no scene {scene} (scenes: {', '.join(map(str, plan.scene_ids))})")
            cases = hypothesis_cases(plan, limit=limit, scene_id=scene, cand_id=candidate, obj_id=obj)
        except (FileNotFoundError, LookupError, ValueError) as e:
            _err().print(f"[red]{e}")
            raise typer.Exit(2)
        if not cases:
            _err().print(f"[red]{dataset}: no candidate with hypotheses to draw")
            raise typer.Exit(1)
        folder = out or rp.cache.parent / "results" / "figures"
        name = f"hypotheses_{dataset}" + (f"_scene_{scene:06d}" if scene is not None else "") + (
            f"_cand_{candidate}" if candidate is not None else "")
        path = draw_hypotheses_figure(cases, folder / f"{name}.png")
        _out().print(f"{len(cases)} candidate(s): {path}")

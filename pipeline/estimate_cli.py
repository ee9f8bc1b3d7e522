"""``freeze estimate``: the method on one RGB-D image of one object (see :mod:`pipeline.estimate`).

Wired into the ``freeze`` app by ``register(app, show_app)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer, show_app: typer.Typer) -> None:
    """Add ``freeze estimate`` to ``app`` (``show_app`` is unused)."""

    @app.command("estimate")
    def estimate_cmd(
        model: Path = typer.Option(..., "--model", help="object model, PLY in mm (BOP models are)"),
        rgb: Path = typer.Option(..., "--rgb", help="RGB image (PNG/JPEG)"),
        depth: Path = typer.Option(..., "--depth", help="depth image, uint16 PNG: depth_mm = value * depth_scale"),
        camera: Path = typer.Option(..., "--camera", help="camera JSON: {\"cam_K\": [9], \"depth_scale\": s} "
                                                         "(BOP scene_camera entry, SAM-6D), {\"K\": [[...]]} or "
                                                         "{\"fx\", \"fy\", \"cx\", \"cy\"}"),
        mask: Optional[Path] = typer.Option(None, "--mask", help="object mask image (non-zero = object), or a "
                                                                 "detections JSON (CNOS/SAM-6D; best score used)"),
        bbox: Optional[str] = typer.Option(None, "--bbox", help="object box x,y,w,h in pixels (instead of --mask)"),
        depth_scale: Optional[float] = typer.Option(None, "--depth-scale", help="mm per depth unit (default: the "
                                                                                "camera file's depth_scale, else 1)"),
        model_scale: float = typer.Option(1.0, "--model-scale", help="multiply the model's coordinates (1000 for "
                                                                     "a model in metres)"),
        out: Path = typer.Option(Path("estimate_out"), "--out", help="output folder"),
        bop_name: Optional[str] = typer.Option(None, "--bop-name", help="name of the one-image BOP dataset written to "
                                               "OUT/bop/NAME, lowercase letters and digits (default: the model "
                                               "file's name reduced to them: obj_000005.ply -> obj000005)"),
        config: Optional[list[str]] = typer.Option(None, "--config", "-c", help="run overrides key=value, e.g. "
                                                   "visual=dinov2-vits14 or register.max_iterations=20000"),
        progress: bool = typer.Option(True, help="show each step with its time"),
    ) -> None:
        """Estimate the 6D pose of one object in one RGB-D image.

        Writes OUT/pose.json (R, t in mm, score and the intermediate numbers),
        OUT/overlay.png (the model at the estimated pose over the image),
        OUT/points.png (the depth points used) and the artifacts OUT/model_features,
        scene_features, register, refine (the stages' files). The model side is cached
        under <cache>/_estimate/ and reused for the same model and parameters.

        The frame is also written as a one-image BOP dataset, OUT/bop/NAME (camera,
        model in mm, models_info, targets, rgb, depth), with its prior
        OUT/bop/detections/estimate_NAME-test.json (the --mask, or the pixels of the
        depth points kept inside the --bbox): read it with pipeline.bop.BopDataset, or
        run the pipeline on it with bop_root=OUT/bop. It has no ground truth, so it is
        not scored. A dataset of the same NAME already in OUT/bop is replaced.
        """
        from rich.console import Console

        from pipeline.bop.errors import BopFormatError
        from pipeline.cli_common import parse_overrides
        from pipeline.config import ManifestError
        from pipeline.estimate import EstimateError, estimate

        console = Console(stderr=True)
        console.print(f"[bold]freeze estimate[/] {model.name} in {rgb.name} -> {out}")
        try:
            res = estimate(model, rgb, depth, camera, mask=mask, bbox=bbox, depth_scale=depth_scale,
                           model_scale=model_scale, out_dir=out, bop_name=bop_name, overrides=parse_overrides(config),
                           progress=progress, console=console)
        except (EstimateError, ManifestError, BopFormatError) as e:
            console.print(f"[red]error:[/] {e}")
            raise typer.Exit(1)
        r = res.record
        console.print(f"score {r['score']:.3f} (inlier ratio {r['inlier_ratio']:.3f} x ICP fitness {r['fitness']:.3f}); "
                      f"{r['n_inliers']} RANSAC inliers of {r['n_points']} points; SAR "
                      + (f"variant {r['sar_variant']} of {r['sar_n_variants']}" if r["sar_variant"] >= 0 else f"not run ({r['sar_reason']})"))
        console.print("R = " + "; ".join(" ".join(f"{v:+.4f}" for v in row) for row in res.R.tolist()))
        console.print("t = " + " ".join(f"{v:.1f}" for v in res.t.tolist()) + " mm")
        console.print(f"model cache: {res.model.cache_dir} ({'reused' if res.model_cache_reused else 'built'})")
        for name, path in res.files.items():
            console.print(f"  {name:<15} {path}")
        ds = res.files["bop"]
        console.print(f"BOP dataset (1 image, no ground truth): {ds}; load it with pipeline.bop.BopDataset(\"{ds}\"), "
                      f"or run bop_all with bop_root={ds.parent} datasets={ds.name} after adding "
                      f"manifests/datasets/{ds.name}.yaml (name: {ds.name}, kind: bop, "
                      f"prior: {res.files['bop_prior'].relative_to(ds.parent)})", soft_wrap=True, markup=False,
                      highlight=False)

"""Time the BOP19 scorer on a large synthetic results file (run by hand).

    .venv/bin/python benchmarks/score_speed.py [--dataset-root DIR] [--workers 1 2] [--repeat 3]
        [--versus-pipeline LABEL=DIR ...] [--versus LABEL=COMMAND ...] [--versus-repeat 5]

What it builds. On the ``bench`` synthetic dataset (84 images, 540 targets, 561 valid
GT instances; default: the one in ``cache/synthbench/synth/*/dataset/synthbench``, else
make one with ``freeze synth DIR --name synthbench --preset bench``) it writes a BOP
results CSV with, per GT instance of every target: two near-GT poses (0.5-3 deg /
1-3 mm and 5-10 deg / 5-15 mm), an exact duplicate of the first with a lower score,
a pose turned by a declared symmetry (or a 180 deg flip), a random rotation at the
right place, a 30-80 mm lateral shift, a 2-5 % depth shift, a pose far away (so VSD
takes the toolkit's no-overlap shortcut) and a random pose in the view frustum; plus
5 estimates per image for objects that are not targets of that image and 100
estimates for images that are not targets (both ignored, as in BOP). One time per
image. About 5,500 estimates (``--per-gt`` scales it).

What it times. ``score_results_file`` (read the CSV, select, compute every pose error,
match, recall, write ``errors.parquet`` + ``scores.json``), in-process, with each
worker count of ``--workers``, alternating the configurations ``--repeat`` times so
that they see the same machine load, and reports medians. Two target sets:

- ``official``: the dataset's ``test_targets_bop19.json``. Only the top ``inst_count``
  estimates per target are scored (BOP19 rule), so ~560 of the ~5,500 estimates reach
  the error computation: this is what scoring a method's results costs.
- ``all``: the same file with every target's ``inst_count`` raised to the number of
  estimates of that (image, object), so every estimate of a target (~5,000) is scored
  against every GT instance of its object: the scorer's worst case per estimate
  (GT instances under 10 % visibility become valid targets too).

Reported per configuration: wall time (median), estimates per second (estimates in
the file / wall, and scored estimates / wall), speed-up over the first worker count,
and the split from ``summary["timing"]``: in the main process, reading the CSV,
selecting the estimates and reading the GT annotations, matching + recalls +
breakdowns, writing ``errors.parquet``; in the error computation (seconds summed over
the worker processes, so with 2 workers their sum exceeds its wall time, which
includes starting the workers): loading depth images and models, VSD rendering
(model depth, in crops around the object), VSD comparison, MSSD, MSPD. Also the
number of model renders. Writes the tables to ``benchmarks/results/score_speed.md``.
The machine has 2 cores shared with other work: compare the ratios measured in one
run, not absolute numbers across runs.

Side by side (``--versus*``). Other scorers run on the same results file, each as a
fresh process timed from start to exit, interleaved with ours (``freeze score`` run the
same way: ours, other, ours, other, ... ``--versus-repeat`` times) so that both see the
same machine load. Reported: median wall times, the median of the paired ratios
other / ours, the AR each wrote, and, for scorers writing our ``errors.parquet``, the
largest per-estimate difference from ours.

- ``--versus-pipeline LABEL=DIR``: another version of this project's scorer, DIR holding
  its ``pipeline`` package (e.g. a copy made before a change), run as ``freeze score``.
- ``--versus LABEL=COMMAND``: any command, e.g. the reference BOP toolkit's
  ``scripts/eval_bop19_pose.py``. ``{python} {csv} {csv_name} {csv_dir} {root}
  {root_parent} {targets} {out} {workers}`` are replaced (paths shell-quoted). Its AR
  is read from ``{out}/**/scores_bop19.json`` (the toolkit's) or ``{out}/scores.json``
  (ours). The toolkit scores only datasets it knows by name: link the bench dataset
  under such a name and register its objects in the toolkit's ``dataset_params.py``
  (``benchmarks/results/score_speed.md`` gives the command and the edits that were used).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def _random_rot(rng: np.random.Generator) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()


def _small_rot(rng: np.random.Generator, lo_deg: float, hi_deg: float) -> np.ndarray:
    return _rot(rng.normal(size=3), np.deg2rad(rng.uniform(lo_deg, hi_deg)))


def build_estimates(root: Path, per_gt_scale: int, seed: int = 0) -> tuple[list[dict], dict[tuple[int, int, int], int]]:
    """Estimates (dicts for ``write_results_csv``) and the count per (scene, image, object) of targets."""
    from pipeline.formats.bop import BopDataset
    from pipeline.evaluation.metrics.calc_errors import eval_models_info

    ds = BopDataset(root)
    rng = np.random.default_rng(seed)
    infos = eval_models_info(ds)
    targets = ds.targets()
    by_image: dict[tuple[int, int], set[int]] = {}
    for t in targets:
        by_image.setdefault((t.scene_id, t.im_id), set()).add(t.obj_id)
    all_objs = sorted(infos)
    rows: list[dict] = []
    counts: dict[tuple[int, int, int], int] = {}
    for (scene_id, im_id), objs in sorted(by_image.items()):
        time_s = float(np.round(rng.uniform(0.5, 3.0), 3))
        cam = ds.scene_camera(scene_id)[im_id]
        K = cam.K

        def add(obj_id: int, score: float, R: np.ndarray, t: np.ndarray) -> None:
            rows.append(dict(scene_id=scene_id, im_id=im_id, obj_id=obj_id, score=float(score), R=R, t=t, time=time_s))
            if obj_id in objs:
                counts[(scene_id, im_id, obj_id)] = counts.get((scene_id, im_id, obj_id), 0) + 1

        for gt in ds.scene_gt(scene_id)[im_id]:
            if gt.obj_id not in objs:
                continue
            info = infos[gt.obj_id]
            d = float(info.diameter)
            R, t = gt.R, gt.t
            for _ in range(per_gt_scale):
                R1 = _small_rot(rng, 0.5, 3.0) @ R
                t1 = t + rng.normal(size=3) * rng.uniform(1, 3)
                add(gt.obj_id, rng.uniform(0.9, 1.0), R1, t1)  # near GT
                add(gt.obj_id, rng.uniform(0.8, 0.9), R1, t1.copy())  # duplicate, lower score
                add(gt.obj_id, rng.uniform(0.7, 0.8), _small_rot(rng, 5, 10) @ R, t + rng.normal(size=3) * 8)
                if info.symmetries_discrete:
                    S = np.asarray(info.symmetries_discrete[rng.integers(len(info.symmetries_discrete))], float).reshape(4, 4)
                    Rs, ts = R @ S[:3, :3], R @ S[:3, 3] + t
                elif info.symmetries_continuous:
                    c = info.symmetries_continuous[0]
                    Rs, ts = R @ _rot(c["axis"], rng.uniform(0, 2 * np.pi)), t.copy()
                else:
                    Rs, ts = R @ _rot([0, 0, 1], np.pi), t.copy()
                add(gt.obj_id, rng.uniform(0.6, 0.7), Rs, ts)  # symmetric variant (or a flip)
                add(gt.obj_id, rng.uniform(0.5, 0.6), _random_rot(rng), t + rng.normal(size=3) * 5)  # wrong rotation
                shift = np.append(rng.normal(size=2), 0.0)
                add(gt.obj_id, rng.uniform(0.4, 0.5), R, t + shift / np.linalg.norm(shift) * rng.uniform(30, 80))
                add(gt.obj_id, rng.uniform(0.4, 0.5), R, t * (1 + rng.choice([-1, 1]) * rng.uniform(0.02, 0.05)))
                add(gt.obj_id, rng.uniform(0.2, 0.3), R, t + np.array([4 * d, 3 * d, 0.0]))  # far: no overlap
                z = rng.uniform(400, 1200)
                uv = rng.uniform([0, 0], [cam.width, cam.height])
                ray = np.linalg.solve(K, np.append(uv, 1.0))
                add(gt.obj_id, rng.uniform(0.0, 0.3), _random_rot(rng), ray * z)  # random in the frustum
        others = [o for o in all_objs if o not in objs]
        for _ in range(5 * per_gt_scale):
            if others:
                add(int(rng.choice(others)), rng.uniform(0, 1), _random_rot(rng), np.array([0.0, 0.0, 800.0]))
    last = max(by_image)
    for k in range(100 * per_gt_scale):  # images that are not targets
        rows.append(dict(scene_id=last[0], im_id=100000 + k % 10, obj_id=all_objs[k % len(all_objs)], score=0.5,
                         R=_random_rot(rng), t=np.array([0.0, 0.0, 700.0]), time=1.0))
    return rows, counts


def write_all_targets(root: Path, counts: dict[tuple[int, int, int], int], path: Path) -> None:
    """The dataset's targets with inst_count raised so that every estimate of a target is scored."""
    from pipeline.formats.bop import BopDataset

    out = []
    for t in BopDataset(root).targets():
        n = max(t.inst_count, counts.get((t.scene_id, t.im_id, t.obj_id), 0))
        out.append({"scene_id": t.scene_id, "im_id": t.im_id, "obj_id": t.obj_id, "inst_count": n})
    path.write_text(json.dumps(out))


TIMING_KEYS = [
    ("read", "read CSV"),
    ("prepare", "select + GT"),
    ("load", "depth + models"),
    ("vsd_render", "VSD render"),
    ("vsd_compare", "VSD compare"),
    ("mssd", "MSSD"),
    ("mspd", "MSPD"),
    ("errors_wall", "errors (wall)"),
    ("match", "match + recall"),
    ("write", "write errors"),
]


# ---------------------------------------------------------------------------- side by side

#: ``freeze score`` on the bench file, as a command template (fields: see ``--versus``).
OURS_COMMAND = (
    "{python} -c 'import sys; from pipeline.commands.cli import app; sys.argv[0] = \"freeze\"; app()' "
    "score {csv} --dataset-root {root} --out {out} --workers {workers} {targets_option}"
)


def run_timed(cmd: str, env: dict[str, str], log: Path) -> float:
    """Wall seconds of one shell command from start to exit (output in ``log``, working
    folder that of ``log``, so that ``python -c`` imports the ``pipeline`` of PYTHONPATH,
    not one of the working folder); raises ``CalledProcessError`` when it fails."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        subprocess.run(cmd, shell=True, env=env, stdout=f, stderr=subprocess.STDOUT, check=True, cwd=log.parent)
    return time.perf_counter() - t0


def read_ar(out: Path) -> float | None:
    """The AR a scorer wrote under ``out``: ours (scores.json) or the BOP toolkit's
    (scores_bop19.json); None when neither is there."""
    if (out / "scores.json").is_file():
        return json.loads((out / "scores.json").read_text())["summary"]["AR"]
    for f in sorted(out.rglob("scores_bop19.json")):
        return float(json.loads(f.read_text())["bop19_average_recall"])
    return None


def error_differences(ours: Path, other: Path) -> dict[str, float] | None:
    """Largest |other - ours| per error column of two ``errors.parquet`` (inf where one
    is infinite and the other not); None when one is missing or their rows differ."""
    import pandas as pd

    if not (ours / "errors.parquet").is_file() or not (other / "errors.parquet").is_file():
        return None
    a, b = pd.read_parquet(ours / "errors.parquet"), pd.read_parquet(other / "errors.parquet")
    key = ["scene_id", "im_id", "obj_id", "est_id", "gt_id"]
    if len(a) != len(b) or not (a[key].to_numpy() == b[key].to_numpy()).all():
        return None
    diffs = {}
    for c in [c for c in a.columns if c in ("mssd", "mspd") or c.startswith("vsd_tau")]:
        x, y = a[c].to_numpy(np.float64), b[c].to_numpy(np.float64)
        if (np.isfinite(x) != np.isfinite(y)).any():
            diffs[c] = float("inf")
            continue
        fin = np.isfinite(x)
        diffs[c] = float(np.abs(x[fin] - y[fin]).max(initial=0.0))
    return diffs


def side_by_side(
    systems: dict[str, tuple[str, dict[str, str]]], fields: dict[str, str], work: Path, repeat: int
) -> dict[str, dict]:
    """Run every (command template, environment) of ``systems`` ``repeat`` times,
    interleaved (first, second, ..., first, second, ...).

    Returns per label: ``walls`` (s), ``ratios`` (wall / the first system's wall of
    the same round), ``AR`` (from its output) and ``out`` (its output folder).
    """
    labels = list(systems)
    res: dict[str, dict] = {k: {"walls": [], "ratios": [], "AR": None, "out": work / f"versus-{k}"} for k in labels}
    for rep in range(repeat):
        for label in labels:
            cmd, env = systems[label]
            out = res[label]["out"]
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir(parents=True)
            wall = run_timed(cmd.format(**fields, out=shlex.quote(str(out))), env, work / f"versus-{label}.log")
            res[label]["walls"].append(wall)
            res[label]["AR"] = read_ar(out)
            print(f"[{rep + 1}/{repeat}] {label}: {wall:.1f} s  AR={res[label]['AR']}", flush=True)
        for label in labels:
            res[label]["ratios"].append(res[label]["walls"][-1] / res[labels[0]]["walls"][-1])
    return res


def versus_section(args: argparse.Namespace, root: Path, csv: Path, targets: Path | None, work: Path) -> list[str]:
    """Markdown lines of the side-by-side comparison (runs it)."""
    fields = {
        "python": shlex.quote(sys.executable),
        "csv": shlex.quote(str(csv)),
        "csv_name": shlex.quote(csv.name),
        "csv_dir": shlex.quote(str(csv.parent)),
        "root": shlex.quote(str(root)),
        "root_parent": shlex.quote(str(root.parent)),
        "targets": shlex.quote(str(targets if targets is not None else root / "test_targets_bop19.json")),
        "targets_option": f"--targets {shlex.quote(str(targets))}" if targets is not None else "",
        "workers": str(args.versus_workers),
    }

    def env_with_path(path: Path) -> dict[str, str]:
        env = dict(os.environ)
        env["PYTHONPATH"] = str(path)
        return env

    systems: dict[str, tuple[str, dict[str, str]]] = {"ours": (OURS_COMMAND, env_with_path(ROOT))}
    for spec in args.versus_pipeline:
        label, path = spec.split("=", 1)
        systems[label] = (OURS_COMMAND, env_with_path(Path(path).resolve()))
    for spec in args.versus:
        label, cmd = spec.split("=", 1)
        systems[label] = (cmd, dict(os.environ))
    res = side_by_side(systems, fields, work, args.versus_repeat)
    lines = [
        "",
        f"## Side by side: each scorer as a fresh process (imports included), targets `{args.versus_targets}`, "
        f"{args.versus_workers} worker(s), alternated {args.versus_repeat} times",
        "",
        "| scorer | median wall s | min wall s | this / ours (median of paired ratios) | AR | max per-estimate |error - ours| |",
        "|---|---|---|---|---|---|",
    ]
    for label, r in res.items():
        diffs = error_differences(res["ours"]["out"], r["out"]) if label != "ours" else None
        diff_text = "-" if diffs is None else ", ".join(f"{k} {v:.2g}" for k, v in diffs.items() if k in ("mssd", "mspd"))
        if diffs is not None:
            diff_text += f", VSD {max(v for k, v in diffs.items() if k.startswith('vsd')):.2g}"
        ar = "-" if r["AR"] is None else repr(r["AR"])
        lines.append(
            f"| {label} | {statistics.median(r['walls']):.2f} | {min(r['walls']):.2f} "
            f"| {statistics.median(r['ratios']):.2f}x | {ar} | {diff_text} |"
        )
    lines += ["", "Commands (fields as in `score_speed.py --help`):", ""]
    lines += [f"- {label}: `{systems[label][0]}`" + (f" with PYTHONPATH={systems[label][1].get('PYTHONPATH')}"
                                                       if systems[label][0] == OURS_COMMAND else "")
              for label in systems]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset-root", type=Path, default=None)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--targets", nargs="+", default=["official", "all"], choices=["official", "all"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--per-gt", type=int, default=1, help="multiply the estimates per GT instance")
    ap.add_argument("--workdir", type=Path, default=None, help="keep the results file and outputs here")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "score_speed.md")
    ap.add_argument("--label", default="", help="free text put in the Markdown heading")
    ap.add_argument("--versus-pipeline", action="append", default=[], metavar="LABEL=DIR",
                    help="another version of the scorer (DIR holds its pipeline package), run side by side")
    ap.add_argument("--versus", action="append", default=[], metavar="LABEL=COMMAND",
                    help="a command (e.g. the BOP toolkit's eval_bop19_pose.py) run side by side")
    ap.add_argument("--versus-repeat", type=int, default=5)
    ap.add_argument("--versus-targets", default="official", choices=["official", "all"])
    ap.add_argument("--versus-workers", type=int, default=1)
    ap.add_argument("--skip-in-process", action="store_true", help="only the side-by-side runs")
    args = ap.parse_args()

    import warnings

    from pipeline.formats.bop import write_results_csv
    from pipeline.evaluation.metrics import score_results_file

    root = args.dataset_root
    if root is None:
        found = sorted(glob.glob(str(ROOT / "cache" / "synthbench" / "synth" / "*" / "dataset" / "synthbench")))
        if not found:
            raise SystemExit("no bench dataset: run `freeze synth DIR --name synthbench --preset bench` and pass --dataset-root DIR/synthbench")
        root = Path(found[0])
    work = args.workdir or Path(tempfile.mkdtemp(prefix="score_speed-"))
    work.mkdir(parents=True, exist_ok=True)

    rows, counts = build_estimates(root, args.per_gt)
    csv = work / "bench_synthbench-test.csv"
    write_results_csv(csv, rows)
    targets = {"official": None, "all": work / "targets_all.json"}
    write_all_targets(root, counts, targets["all"])
    print(f"{len(rows)} estimates ({sum(counts.values())} for targets) -> {csv}")

    configs = [] if args.skip_in_process else [(tg, w) for tg in args.targets for w in args.workers]
    walls: dict[tuple[str, int], list[float]] = {c: [] for c in configs}
    splits: dict[tuple[str, int], list[dict]] = {c: [] for c in configs}
    summaries: dict[tuple[str, int], dict] = {}
    for rep in range(args.repeat):
        for tg, w in configs:
            out = work / f"out-{tg}-{w}"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t0 = time.perf_counter()
                s = score_results_file(csv, root, targets_file=targets[tg], out_dir=out, n_workers=w)
                wall = time.perf_counter() - t0
            walls[(tg, w)].append(wall)
            splits[(tg, w)].append(s.summary.get("timing", {}))
            summaries[(tg, w)] = s.summary
            print(f"[{rep + 1}/{args.repeat}] targets={tg} workers={w}: {wall:.1f} s  AR={s.summary['AR']:.4f}", flush=True)

    # The same errors whatever the worker count.
    for tg in args.targets if configs else []:
        ars = {summaries[(tg, w)]["AR"] for w in args.workers}
        assert len(ars) == 1, f"AR differs between worker counts: {ars}"

    lines = [
        f"# Scorer speed{(' — ' + args.label) if args.label else ''}",
        "",
        f"`benchmarks/score_speed.py {' '.join(shlex.quote(a) for a in sys.argv[1:])}` on `{root.name}` "
        f"({platform.node()}, {time.strftime('%Y-%m-%d %H:%M')}); medians of {args.repeat} alternating runs.",
        "",
        f"Results file: {len(rows)} estimates, {sum(counts.values())} of them for targets.",
    ]
    if configs:
        lines += [
            "",
            "In process (`score_results_file`, imports excluded):",
            "",
            "| targets | workers | scored est. | wall s | est./s (file) | scored est./s | speed-up | AR |",
            "|---|---|---|---|---|---|---|---|",
        ]
    for tg in args.targets if configs else []:
        base = statistics.median(walls[(tg, args.workers[0])])
        for w in args.workers:
            med = statistics.median(walls[(tg, w)])
            s = summaries[(tg, w)]
            lines.append(
                f"| {tg} | {w} | {s['n_evaluated']} | {med:.1f} | {len(rows) / med:.0f} | {s['n_evaluated'] / med:.0f} "
                f"| {base / med:.2f}x | {s['AR']:.4f} |"
            )
    if any(sp for v in splits.values() for sp in v):
        lines += [
            "",
            "Time split (s, medians; worker parts summed over worker processes):",
            "",
            "| targets | workers | " + " | ".join(name for _, name in TIMING_KEYS) + " | wall |",
            "|---|---|" + "---|" * (len(TIMING_KEYS) + 1),
        ]
        for tg, w in configs:
            vals = [statistics.median([sp.get(k, float("nan")) for sp in splits[(tg, w)]]) for k, _ in TIMING_KEYS]
            lines.append(f"| {tg} | {w} | " + " | ".join(f"{v:.2f}" for v in vals) + f" | {statistics.median(walls[(tg, w)]):.1f} |")
        extra = summaries[configs[0]].get("timing", {})
        if "n_renders" in extra:
            lines += ["", "Renders per run: " + ", ".join(
                f"{tg}: {summaries[(tg, args.workers[0])]['timing'].get('n_renders')}" for tg in args.targets)]
    if args.versus_pipeline or args.versus:
        lines += versus_section(args, root, csv, targets[args.versus_targets], work)
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"written {args.out}")


if __name__ == "__main__":
    main()

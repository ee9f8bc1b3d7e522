"""Bad inputs are refused where they enter (issue 28): by `freeze datasets check`, and by
the stage that reads them, each in one line naming the file and the field, with a
non-zero exit and no traceback.

- absurd intrinsics (`cam_K` all zeros, fx = 1e-300, cy = 1e9, NaN, inf, negative focal
  lengths) and `depth_scale` 0, which used to pass into a run that ended with AR 0;
- a NaN in `scene_gt.json`, which only the score stage refused, at the end of a run:
  now the check and the first scene-side stage (segment_prior) refuse it;
- a model whose vertices lie on a line or in one point (a ValueError in model_features);
- `-c` values that are not YAML, carry a `!!python` tag, or are not finite, and
  non-finite numbers in a run manifest;
- targets listed twice, counted once with one warning.

The datasets are the tiny LM-O-layout root of `tests/test_datasets_check.py` (two box
models, one scene of three images), written per test in well under a second; the stage
tests run `freeze stage` on it with a cache of their own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from pipeline.formats.bop import write_ply
from pipeline.formats.bop.dataset import intrinsics_problem
from pipeline.commands.cli import app
from pipeline.common.config import ManifestError, load_run, load_run_with_overrides
from test_datasets_check import BOXES, K, check, write_lmo

FREEZE = Path(sys.executable).parent / "freeze"
ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()
SCENE = Path("lmo") / "test" / "000001"


@pytest.fixture
def lmo(tmp_path) -> tuple[Path, Path]:
    """(bop_root, dataset folder) of a fresh healthy dataset."""
    root = tmp_path / "bop"
    return root, write_lmo(root)


def _edit_json(path: Path, edit) -> None:
    """Apply ``edit`` to the parsed JSON of ``path`` and write it back (NaN and inf as
    JSON's NaN / Infinity, as Python's json writes them and the readers accept them)."""
    content = json.loads(path.read_text())
    edit(content)
    path.write_text(json.dumps(content))


def _freeze(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """`freeze ARGS` with a cache of its own under ``tmp_path``."""
    env = {k: v for k, v in os.environ.items() if k != "FREEZE_RUN_JSON"}
    env.update(FREEZE_CACHE=str(tmp_path / "cache"), PYOPENGL_PLATFORM="egl", HF_HUB_OFFLINE="1")
    return subprocess.run([str(FREEZE), *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


def _stage(tmp_path: Path, bop_root: Path, stage: str, item: str, *config: str) -> subprocess.CompletedProcess:
    """`freeze stage STAGE --dataset lmo --item ITEM` on the tiny root."""
    args = ["-c", "datasets=lmo", "-c", f"bop_root={bop_root}"]
    for c in config:
        args += ["-c", c]
    return _freeze(tmp_path, "stage", stage, "--dataset", "lmo", "--item", item, *args, "--no-progress")


def _one_line(out: str, *needles: str) -> str:
    """The one line of ``out`` holding every needle (asserting there is one, and no traceback)."""
    assert "Traceback" not in out, out[-3000:]
    lines = [line for line in out.splitlines() if all(n in line for n in needles)]
    assert lines, f"no line with {needles} in:\n{out[-3000:]}"
    return lines[0]


def _plain_check(root: Path, *args: str):
    """`freeze datasets check ROOT ARGS` as a user runs it (the table and the lines)."""
    result = runner.invoke(app, ["datasets", "check", str(root), *args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result


# ------------------------------------------------------------------ intrinsics


ABSURD = {
    "zeros": lambda k: [0.0] * 9,
    "fx_1e-300": lambda k: [1e-300, *k[1:]],
    "cy_1e9": lambda k: k[:5] + [1e9] + k[6:],
    "negative_focal": lambda k: [-k[0], *k[1:4], -k[4], *k[5:]],
    "nan": lambda k: [float("nan"), *k[1:]],
    "inf": lambda k: k[:4] + [float("inf")] + k[5:],
}


@pytest.mark.parametrize("case", sorted(ABSURD))
def test_check_refuses_absurd_intrinsics_naming_file_image_and_field(lmo, case):
    root, ds = lmo
    path = ds / "test" / "000001" / "scene_camera.json"
    _edit_json(path, lambda c: c["1"].update(cam_K=ABSURD[case](K.reshape(-1).tolist())))
    code, rep = check(root, "--deep")
    assert code == 1, rep
    (line,) = [e for e in rep["errors"] if "cam_K" in e]
    assert line.startswith(f"{path}: ") and "'cam_K'" in line and "\n" not in line, line
    if case not in ("nan", "inf"):  # those the JSON reader refuses as not finite, naming the entry
        assert "scene 1, image 1" in line, line
    result = _plain_check(root, "--deep")
    assert result.exit_code == 1
    _one_line(result.output, str(path), "cam_K")


def test_plausible_cameras_pass():
    """Real cameras are not refused: the samples' (LM-O, HOPE, YCB-V), a long lens, a
    wide one, a principal point off a cropped image's frame, a small skew."""
    for k, w, h in (([572.4114, 0, 325.2611, 0, 573.57043, 242.04899, 0, 0, 1], 640, 480),
                    ([1390.53, 0, 964.957, 0, 1386.99, 522.586, 0, 0, 1], 1920, 1080),
                    ([1066.778, 0, 312.9869, 0, 1067.487, 241.3109, 0, 0, 1], 640, 480),
                    ([20000.0, 0, 320, 0, 20000.0, 240, 0, 0, 1], 640, 480),
                    ([120.0, 0, 320, 0, 120.0, 240, 0, 0, 1], 640, 480),
                    ([572.0, 0, -150.0, 0, 572.0, 700.0, 0, 0, 1], 640, 480),
                    ([572.0, 0.5, 320, 0, 572.0, 240, 0, 0, 1], 640, 480)):
        assert intrinsics_problem(np.reshape(k, (3, 3)), w, h) is None, k


@pytest.mark.slow
def test_scene_features_refuses_zero_intrinsics_and_a_zero_depth_scale(lmo, tmp_path):
    """The stage that reads scene_camera.json refuses what the check refuses, before any
    depth is lifted: one line naming the file, the image and the field, exit 1 (it was
    exit 0 and AR 0, every candidate "valid depth points < min_points")."""
    root, ds = lmo
    path = ds / "test" / "000001" / "scene_camera.json"
    _edit_json(path, lambda c: c["1"].update(cam_K=[0.0] * 9))
    proc = _stage(tmp_path, root, "scene_features", "scene_000001")
    assert proc.returncode == 1, proc.stderr[-3000:]
    line = _one_line(proc.stdout + proc.stderr, str(path), "'cam_K'")
    assert "scene 1, image 1" in line and "focal lengths must be positive" in line

    _edit_json(path, lambda c: [c[i].update(cam_K=K.reshape(-1).tolist(), depth_scale=0.0) for i in c])
    code, rep = check(root)
    assert code == 1 and rep["errors"] == [f"{path}: scene 1, image 0, field 'depth_scale': must be positive (mm per "
                                           "depth unit), got 0 (and 2 more images of the scene)"], rep["errors"]
    proc = _stage(tmp_path, root, "scene_features", "scene_000001")
    assert proc.returncode == 1, proc.stderr[-3000:]
    _one_line(proc.stdout + proc.stderr, str(path), "'depth_scale'", "must be positive")


def test_a_zero_depth_scale_in_camera_json_is_named_there(lmo):
    """An image without its own depth_scale takes camera.json's: a 0 there is reported
    against camera.json, once per scene, not once per image."""
    root, ds = lmo
    _edit_json(ds / "test" / "000001" / "scene_camera.json", lambda c: [c[i].pop("depth_scale") for i in c])
    _edit_json(ds / "camera.json", lambda c: c.update(depth_scale=0))
    code, rep = check(root)
    assert code == 1
    assert rep["errors"] == [f"{ds / 'camera.json'}: scene 1, image 0, field 'depth_scale': must be positive (mm "
                             "per depth unit), got 0 (and 2 more images of the scene)"], rep["errors"]


# ------------------------------------------------------------------ ground truth


def test_check_refuses_nan_ground_truth_naming_file_entry_and_field(lmo):
    root, ds = lmo
    path = ds / "test" / "000001" / "scene_gt.json"
    _edit_json(path, lambda c: c["2"][0]["cam_t_m2c"].__setitem__(2, float("nan")))
    code, rep = check(root)
    assert code == 1
    assert rep["errors"] == [f"{path}: entry '2'[0], field 'cam_t_m2c': expected 3 finite numbers, got "
                             "[-120.0, 0.0, nan]"], rep["errors"]
    _one_line(_plain_check(root).output, str(path), "cam_t_m2c")


def test_check_refuses_ground_truth_the_scorer_cannot_read(lmo):
    """A target image without a ground-truth entry, and a scene_gt_info.json of another
    length: the scorer's ValueError at the end of a run, now the check's lines."""
    root, ds = lmo
    scene = ds / "test" / "000001"
    _edit_json(scene / "scene_gt.json", lambda c: c.pop("0"))
    _edit_json(scene / "scene_gt_info.json", lambda c: c["2"].pop())
    code, rep = check(root)
    assert code == 1
    assert rep["errors"] == [f"{scene / 'scene_gt.json'}: no entry for target image 0",
                             f"{scene / 'scene_gt_info.json'}: image 2 has 1 entries, scene_gt.json has 2 (one per "
                             "instance in both)"], rep["errors"]
    (scene / "scene_gt_info.json").unlink()
    code, rep = check(root)
    assert code == 1 and rep["errors"] == [f"{scene / 'scene_gt_info.json'}: not found beside scene_gt.json (the "
                                           "scores need each instance's visib_fract)"], rep["errors"]


@pytest.mark.slow
def test_segment_prior_refuses_nan_ground_truth_at_the_start_of_a_run(lmo, tmp_path):
    """No stage before score reads scene_gt.json; segment_prior, the first scene-side
    job, refuses a NaN pose there, so that a run stops at its start, not at its end."""
    root, ds = lmo
    path = ds / "test" / "000001" / "scene_gt.json"
    _edit_json(path, lambda c: c["1"][1]["cam_R_m2c"].__setitem__(4, float("nan")))
    proc = _stage(tmp_path, root, "segment_prior", "all")
    assert proc.returncode == 1, proc.stderr[-3000:]
    line = _one_line(proc.stdout + proc.stderr, str(path), "'cam_R_m2c'")
    assert "entry '1'[1]" in line and "public_gt: false" in line
    assert not list((tmp_path / "cache").rglob("prior_candidates.parquet"))  # nothing published


# ------------------------------------------------------------------ degenerate models


def _write_model(ds: Path, obj_id: int, vertices: np.ndarray, faces: np.ndarray) -> list[Path]:
    paths = [ds / folder / f"obj_{obj_id:06d}.ply" for folder in ("models", "models_eval")]
    for path in paths:
        write_ply(path, vertices, faces)
    return paths


@pytest.mark.parametrize("shape, reason", [("line", "lie on a line"), ("point", "are one point"),
                                           ("no_area", "have no area")])
def test_check_refuses_a_model_that_spans_no_surface(lmo, shape, reason):
    root, ds = lmo
    box = trimesh.creation.box(extents=BOXES[1])
    v = box.vertices.copy()
    faces = box.faces
    if shape == "line":
        v[:, 1], v[:, 2] = 0.5 * v[:, 0], 2.0 * v[:, 0]
    elif shape == "point":
        v[:] = (1.0, 2.0, 3.0)
    else:  # every triangle repeats a vertex: a 3D point set without a surface
        faces = np.repeat(np.arange(len(v))[:, None], 3, axis=1)
    paths = _write_model(ds, 1, v, faces)
    code, rep = check(root)
    assert code == 1
    for path in paths:
        (line,) = [e for e in rep["errors"] if e.startswith(f"{path}: ")]
        assert reason in line and "\n" not in line, line


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["render_templates", "symmetries", "model_features"])
def test_model_side_stages_refuse_a_model_on_a_line(lmo, tmp_path, stage):
    """Whichever model-side stage runs first refuses the model in one line naming its
    file (model_features raised numpy's ValueError)."""
    root, ds = lmo
    box = trimesh.creation.box(extents=BOXES[1])
    v = box.vertices.copy()
    v[:, 1], v[:, 2] = 0.5 * v[:, 0], 2.0 * v[:, 0]
    path, _ = _write_model(ds, 1, v, box.faces)
    proc = _stage(tmp_path, root, stage, "obj_000001")
    assert proc.returncode == 1, proc.stderr[-3000:]
    _one_line(proc.stdout + proc.stderr, f"stage {stage} failed", str(path), "lie on a line")


# ------------------------------------------------------------------ duplicated targets


def test_check_counts_a_repeated_target_once_with_one_warning(lmo):
    """The scorer (as BOP's toolkit, which keys the targets by scene, image and
    object) counts a repeated line once, with its last inst_count; so does the check,
    saying how many lines repeat and the first."""
    root, ds = lmo
    path = ds / "test_targets_bop19.json"
    targets = json.loads(path.read_text())
    path.write_text(json.dumps(targets + [dict(targets[3], inst_count=2), targets[4], targets[4]]))
    code, rep = check(root)
    assert code == 0, rep
    t = targets[3]
    assert rep["warnings"] == [f"{path}: 3 repeated target lines (first: scene {t['scene_id']}, image {t['im_id']}, "
                               f"object {t['obj_id']}, with inst_count 1 and 2); each target is counted once, with "
                               "its last line's inst_count, as the scorer and BOP's toolkit read it"]
    assert rep["summary"]["targets"] == 6 and rep["summary"]["instances"] == 7
    assert rep["summary"]["instances_per_target"] == {"1": 5, "2": 1}


# ------------------------------------------------------------------ -c values and run manifests


def test_config_values_that_are_not_yaml_or_carry_tags_are_one_line(tmp_path):
    marker = tmp_path / "x"
    cases = {
        "[1,": "--config register.seed=[1,: not a YAML value",
        f'!!python/object/apply:os.system ["touch {marker}"]': "--config register.seed=!!python/object/apply:os.system",
    }
    for value, start in cases.items():
        with pytest.raises(ManifestError) as e:
            load_run_with_overrides({"datasets": "synthtiny", "register.seed": value})
        assert str(e.value).startswith(start) and "\n" not in str(e.value), str(e.value)
    assert "YAML tags" in str(e.value)
    assert not marker.exists()  # nothing was executed


@pytest.mark.parametrize("key, value", [("register.inlier_frac", ".inf"), ("register.inlier_frac", "inf"),
                                        ("register.signal_none", ".nan"), ("refine.verify_tol_frac", "nan"),
                                        ("register.seed", ".inf"), ("score.n_workers", "-.inf")])
def test_non_finite_config_values_are_refused_naming_key_and_value(key, value):
    with pytest.raises(ManifestError) as e:
        load_run_with_overrides({"datasets": "synthtiny", key: value})
    msg = str(e.value)
    assert msg.startswith(f"--config {key}={value}: field 'stages.{key}': ") and "\n" not in msg, msg
    assert "finite number" in msg or "valid integer" in msg, msg


def test_non_finite_numbers_in_a_run_manifest_are_refused(tmp_path):
    """load_run directly, as the Snakefile calls it, and with Snakemake's own parsing
    of `--config images_per_job=inf` (a float)."""
    for body, field in (("stages:\n  register:\n    inlier_frac: .inf\n", "stages.register.inlier_frac"),
                        ("stages:\n  refine:\n    sar_step_deg: .nan\n", "stages.refine.sar_step_deg"),
                        ("images_per_job: .inf\n", "images_per_job")):
        run = tmp_path / "run.yaml"
        run.write_text(f"extends: {ROOT / 'manifests' / 'runs' / 'default.yaml'}\n{body}")
        with pytest.raises(ManifestError) as e:
            load_run({"run": str(run), "datasets": "synthtiny"})
        assert str(e.value).startswith(f"{run}: field '{field}': Input should be a finite number"), str(e.value)
    with pytest.raises(ManifestError, match=r"^--config images_per_job=inf: field 'images_per_job': .*finite"):
        load_run({"datasets": "synthtiny", "images_per_job": float("inf")})


def test_plan_and_stage_print_bad_values_as_one_line(tmp_path):
    """`freeze plan -c ...` and `freeze stage ... -c ...`: exit 1, one line, no traceback
    (a run manifest's `.inf` reached json.dumps of the cache key as a ValueError)."""
    run = tmp_path / "inf.yaml"
    run.write_text(f"extends: {ROOT / 'manifests' / 'runs' / 'default.yaml'}\nstages:\n  register:\n"
                   "    inlier_frac: .inf\n")
    cases = [
        (["plan", "-c", "datasets=synthtiny", "-c", f"run={run}"], (str(run), "stages.register.inlier_frac", "finite")),
        (["plan", "-c", "datasets=synthtiny", "-c", "images_per_job=.inf"],
         ("--config images_per_job=.inf", "field 'images_per_job'")),
        (["plan", "-c", "datasets=synthtiny", "-c", "register.seed=[1,"], ("'register.seed' is a stage parameter",)),
        (["plan", "-c", "datasets=synthtiny", "-c", "register.seed=!!python/object/apply:os.system [\"touch x\"]"],
         ("'register.seed' is a stage parameter",)),
        (["stage", "register", "--dataset", "synthtiny", "--item", "scene_000001", "-c", "datasets=synthtiny", "-c",
          f"run={run}"], (str(run), "stages.register.inlier_frac", "finite")),
    ]
    for args, needles in cases:
        proc = _freeze(tmp_path, *args)
        assert proc.returncode == 1, (args, proc.stdout + proc.stderr)
        _one_line(proc.stdout + proc.stderr, *needles)
    assert not (tmp_path / "x").exists()
    assert not (tmp_path / "cache").exists()  # refused before anything was planned into the cache


@pytest.mark.slow
def test_a_run_on_zero_intrinsics_exits_non_zero_with_the_line_in_the_job_log(lmo, tmp_path):
    """`freeze run` up to scene_features (segment_prior, then the refusing job; the
    model side is not needed to show it): the run exits non-zero instead of 0 with AR 0,
    and the job's log holds the one line naming the file and the field."""
    from pipeline.workflow.plan import RunPlan

    root, ds = lmo
    path = ds / "test" / "000001" / "scene_camera.json"
    _edit_json(path, lambda c: [c[i].update(cam_K=[0.0] * 9) for i in c])
    plan = RunPlan(load_run({"datasets": "lmo", "bop_root": str(root)}), cache=tmp_path / "cache")["lmo"]
    target = plan["scene_features"].item_dir("scene_000001") / "_manifest.json"
    proc = _freeze(tmp_path, "run", str(target), "-c", "datasets=lmo", "-c", f"bop_root={root}")
    assert proc.returncode != 0, (proc.stdout + proc.stderr)[-3000:]
    assert not target.exists()
    (log,) = (tmp_path / "logs").rglob("scene_000001.log")
    _one_line(log.read_text(), "stage scene_features failed", str(path), "'cam_K'", "scene 1, image 0")
    # and freeze run says it too, with the log's path, not only Snakemake's "check the log"
    _one_line(proc.stdout + proc.stderr, "stage scene_features failed", str(path), "'cam_K'", f"(log: {log})")


def test_a_message_holding_brackets_is_printed_whole():
    """Commands print a user error as plain text: a "[...]" in it (a path such as
    /data/[v2]/models, a list of values) is not taken for rich markup and lost."""
    import typer

    from pipeline.commands.common import guard_commands
    from pipeline.common.config import ManifestError

    demo = typer.Typer()

    @demo.command()
    def fail() -> None:
        raise ManifestError("/data/[v2]/scene_camera.json: field 'cam_K': got [bold]0, 0[/bold]")

    @demo.command()
    def other() -> None:
        pass

    guard_commands(demo)
    res = CliRunner().invoke(demo, ["fail"])
    assert res.exit_code == 1
    assert res.output.strip() == "error: /data/[v2]/scene_camera.json: field 'cam_K': got [bold]0, 0[/bold]"


def test_a_results_file_without_ground_truth_counts_a_repeated_target_once(tmp_path):
    """The summary of an unscored results file counts targets as the scorer does: a
    target line given twice counts once, with the later line's inst_count."""
    from pipeline.formats.bop.dataset import Target
    from pipeline.evaluation.metrics.evaluate import unscored_summary

    csv = tmp_path / "m_d-test.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n"
                   "1,0,2,0.9,1 0 0 0 1 0 0 0 1,0 0 500,1.5\n")
    targets = [Target(1, 0, 2, 1), Target(1, 0, 3, 2), Target(1, 0, 2, 3)]
    summ = unscored_summary(csv, targets, "no scene_gt.json")
    assert summ["n_targets"] == 5 and summ["n_estimates"] == 1 and summ["mean_time_per_image"] == 1.5

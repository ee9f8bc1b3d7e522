"""`freeze estimate` writes only what it owns, and says one line for bad outputs and inputs
(issue 28: the --out folder, output paths, a prior below min_area, absurd intrinsics,
the printed follow-up command, bad -c values).

Each case runs the real command (`pipeline.commands.cli.app` through typer's CliRunner) on the
synthetic frame of tests/test_estimate.py and asserts the message, the exit code, and,
where the issue asks, that nothing outside what the command owns changed: a snapshot of
every path and its bytes under the folder holding --out. The cases refused at input
time run no stage (no artifact appears in the cache); the others reuse one model side,
built once for the module.
"""

from __future__ import annotations

import errno
import json
import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from test_estimate import FAST_ARGS, _run, case  # noqa: F401  (the synthetic frame fixture)

from pipeline.commands.estimate import EstimateError, check_intrinsics, load_camera
from pipeline.commands.estimate.output import MARKER, OUTPUT_NAMES, TEMP_PREFIX


def _app():
    from pipeline.commands.cli import app

    return app


def _args(case: dict, out: Path, *extra: str, camera: Path | None = None, prior: tuple[str, str] | None = None
          ) -> list[str]:
    prior = prior or ("--mask", str(case["mask"]))
    return ["estimate", "--model", str(case["model"]), "--rgb", str(case["rgb"]), "--depth", str(case["depth"]),
            "--camera", str(camera or case["camera"]), *prior, "--out", str(out), *FAST_ARGS, *extra]


def _invoke(case: dict, cache: Path, args: list[str], monkeypatch):
    monkeypatch.setenv("FREEZE_CACHE", str(cache))
    return CliRunner().invoke(_app(), args)


def _one_error(result) -> str:
    """The run's one error line; the run exited 1 through typer (no traceback)."""
    assert result.exit_code == 1, result.output
    assert isinstance(result.exception, SystemExit), result.exception  # not an uncaught exception
    assert "Traceback" not in result.output
    [line] = [ln for ln in result.output.splitlines() if ln.startswith("error:")]
    return line


def _snapshot(root: Path) -> dict[str, bytes | str]:
    """Every path under ``root`` with its bytes (a folder: "<dir>", a link: its target)."""
    out: dict[str, bytes | str] = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        out[rel] = f"<link {os.readlink(p)}>" if p.is_symlink() else ("<dir>" if p.is_dir() else p.read_bytes())
    return out


def _no_stage_ran(cache: Path) -> None:
    assert not (cache / "_estimate").exists() or not any((cache / "_estimate").rglob("_manifest.json"))


@pytest.fixture(scope="module")
def built(case):
    """The case with its model side built once (in the case's cache), for the runs that
    reach the stages."""
    _run(case, mask=case["mask"])
    return case


# --------------------------------------------------------- 1. the --out folder is the estimate's own


def test_refuses_an_out_folder_it_did_not_write_and_changes_nothing(case, tmp_path, monkeypatch):
    """`mkdir -p out/refine && echo t > out/refine/thesis.tex`, then `freeze estimate --out
    out`: refused before any stage runs, naming the file; nothing under out's parent changed."""
    out = tmp_path / "work" / "out"
    (out / "refine").mkdir(parents=True)
    (out / "refine" / "thesis.tex").write_text("t\n")
    (tmp_path / "work" / "sibling.txt").write_text("keep me\n")
    before = _snapshot(tmp_path / "work")
    cache = tmp_path / "cache"
    line = _one_error(_invoke(case, cache, _args(case, out), monkeypatch))
    assert str(out / "refine" / "thesis.tex") in line and "did not write" in line and MARKER in line
    assert _snapshot(tmp_path / "work") == before
    _no_stage_ran(cache)


def test_out_onto_a_file_is_one_line(case, tmp_path, monkeypatch):
    target = tmp_path / "out.txt"
    target.write_text("mine\n")
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, target), monkeypatch))
    assert f"--out {target}: exists and is not a folder" in line
    assert target.read_text() == "mine\n" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    # under a file: mkdir fails (ENOTDIR), one line naming --out
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, target / "sub"), monkeypatch))
    assert f"--out {target / 'sub'}: cannot write there" in line
    assert target.read_text() == "mine\n" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_marker_that_is_not_the_estimates_is_refused(case, tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).write_text("{not json")
    before = _snapshot(tmp_path)
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out), monkeypatch))
    assert str(out / MARKER) in line and "not a marker of freeze estimate" in line
    assert _snapshot(tmp_path) == before


@pytest.mark.slow
def test_reruns_replace_only_their_own_outputs_and_the_printed_command_is_quoted(built, tmp_path, monkeypatch):
    """A first run into a new --out (its path holds a space and a quote) marks it; the
    printed follow-up command, split as a shell splits it, gives the right paths. A rerun
    (another prior) replaces its own outputs and leaves a note beside them; a foreign file
    inside its outputs, or an output changed by hand, is refused before any stage runs,
    with nothing changed."""
    case = built
    parent = tmp_path / "my estimates' dir"
    out = parent / "out one"
    parent.mkdir()
    (parent / "other.txt").write_text("not the estimate's\n")
    result = _invoke(case, case["cache"], _args(case, out), monkeypatch)
    assert result.exit_code == 0, result.output
    marker = json.loads((out / MARKER).read_text())
    assert marker["written_by"] == "freeze estimate" and "previous" not in marker
    assert {rel.split("/")[0] for rel in marker["files"]} == set(OUTPUT_NAMES)
    assert not list(out.glob(f"{TEMP_PREFIX}*"))  # no staging folder left
    assert (parent / "other.txt").read_text() == "not the estimate's\n"
    # the printed command pastes whole into a shell (item 5)
    [line] = [ln for ln in result.output.splitlines() if "run the pipeline on it: " in ln]
    command = shlex.split(line.split("run the pipeline on it: ", 1)[1])
    assert command == ["snakemake", "--cores", "2", "bop_all", "--config", f"bop_root={out / 'bop'}",
                       f"datasets={out / 'bop' / 'model.yaml'}"]
    comment = (out / "bop" / "model.yaml").read_text().splitlines()[1]
    assert shlex.split(comment.lstrip("# ")) == command
    ds_arg = line.split("pipeline.formats.bop.BopDataset(", 1)[1].split("), or run", 1)[0]
    assert Path(eval(ds_arg)) == out / "bop" / "model"  # a Python string literal of the path
    first_pose = (out / "pose.json").read_bytes()

    # a rerun (a box prior this time) replaces its outputs, and only them
    (out / "notes.txt").write_text("my notes\n")
    before = _snapshot(tmp_path)
    x, y, w, h = case["bbox"]
    result = _invoke(case, case["cache"], _args(case, out, prior=("--bbox", f"{x},{y},{w},{h}")), monkeypatch)
    assert result.exit_code == 0, result.output
    after = _snapshot(tmp_path)
    ours = {f"{parent.name}/{out.name}/{n}" for n in (*OUTPUT_NAMES, MARKER)}

    def foreign(snap):
        return {k: v for k, v in snap.items() if not any(k == o or k.startswith(o + "/") for o in ours)}

    assert foreign(after) == foreign(before)  # the note, the sibling, the parent: unchanged
    assert (out / "pose.json").read_bytes() != first_pose
    assert json.loads((out / "pose.json").read_text())["inputs"]["prior"] == "bbox"
    marker = json.loads((out / MARKER).read_text())
    assert "notes.txt" not in marker["files"] and "previous" not in marker
    assert marker["files"]["pose.json"]["size"] == (out / "pose.json").stat().st_size
    assert not list(out.glob(f"{TEMP_PREFIX}*"))

    # a foreign file inside an output folder: refused, naming it, before any stage runs
    (out / "refine" / "thesis.tex").write_text("t\n")
    before = _snapshot(tmp_path)
    line = _one_error(_invoke(case, case["cache"], _args(case, out), monkeypatch))
    assert str(out / "refine" / "thesis.tex") in line and "does not list it" in line
    assert _snapshot(tmp_path) == before
    (out / "refine" / "thesis.tex").unlink()
    # an output edited by hand is no longer the estimate's to replace
    (out / "pose.json").write_text((out / "pose.json").read_text() + " ")
    before = _snapshot(tmp_path)
    line = _one_error(_invoke(case, case["cache"], _args(case, out), monkeypatch))
    assert str(out / "pose.json") in line and "changed since freeze estimate wrote it" in line
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------------------ 2. output paths


def _full_disk_at(monkeypatch, module: str, name: str, when=lambda path: True) -> None:
    """Make ``module.name`` (a writer taking the path first) raise ENOSPC, as a full disk does."""
    import importlib

    mod = importlib.import_module(module)
    real = getattr(mod, name)

    def full(path, *args, **kwargs):
        if when(Path(path)):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(mod, name, full)


def test_a_full_disk_while_writing_the_frame_is_one_line_and_leaves_nothing(case, tmp_path, monkeypatch):
    """ENOSPC at the frame's first image (simulated at the write call): one line naming
    the file at its place under --out and the reason (not the image's extension), no stage
    run, and the folder the run created is gone again."""
    _full_disk_at(monkeypatch, "pipeline.formats.bop.dataset", "write_image")
    out = tmp_path / "new" / "out"
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out), monkeypatch))
    assert f"--out {out}: cannot write {out / 'bop'}" in line and "no space left on the device" in line
    assert "extension" not in line and TEMP_PREFIX not in line
    assert not (tmp_path / "new").exists()
    _no_stage_ran(tmp_path / "cache")


@pytest.mark.slow
def test_a_full_disk_after_the_stages_leaves_the_previous_outputs(built, tmp_path, monkeypatch):
    """ENOSPC when pose.json is written, after every stage ran, into a folder an earlier
    run wrote: one line naming OUT/pose.json, the earlier outputs and marker untouched, no
    staging folder left."""
    case = built
    out = tmp_path / "out"
    assert _invoke(case, case["cache"], _args(case, out), monkeypatch).exit_code == 0
    before = _snapshot(tmp_path)
    _full_disk_at(monkeypatch, "pipeline.common.store", "atomic_write_text", when=lambda p: p.name == "pose.json")
    x, y, w, h = case["bbox"]
    line = _one_error(_invoke(case, case["cache"], _args(case, out, prior=("--bbox", f"{x},{y},{w},{h}")),
                              monkeypatch))
    assert f"--out {out}: cannot write {out / 'pose.json'} (no space left on the device)" in line
    assert _snapshot(tmp_path) == before


def _mount_tmpfs(where: Path, options: str) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True)
    return proc.returncode == 0


@pytest.fixture
def mounts(tmp_path):
    """Mount tmpfs file systems (root with CAP_SYS_ADMIN only; skipped elsewhere), unmounted after."""
    done: list[Path] = []

    def mount(name: str, options: str) -> Path:
        if shutil.which("mount") is None or not _mount_tmpfs(tmp_path / name, options):
            pytest.skip("cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN)")
        done.append(tmp_path / name)
        return tmp_path / name

    yield mount
    for where in done:
        subprocess.run(["umount", str(where)], capture_output=True)


def test_a_read_only_mount_is_one_line(case, tmp_path, monkeypatch, mounts):
    ro = mounts("ro", "ro,size=64k")
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, ro / "out"), monkeypatch))
    assert line == f"error: --out {ro / 'out'}: cannot write there (read-only file system)"
    _no_stage_ran(tmp_path / "cache")


def test_a_real_full_disk_is_one_line_and_leaves_nothing(case, tmp_path, monkeypatch, mounts):
    """A 64 KiB tmpfs: the frame's images do not fit."""
    full = mounts("full", "size=64k")
    (full / "keep.txt").write_text("mine\n")
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, full / "out"), monkeypatch))
    assert f"--out {full / 'out'}: cannot write {full / 'out' / 'bop'}" in line
    assert "(no space left on the device)" in line and "extension" not in line
    assert sorted(p.name for p in full.iterdir()) == ["keep.txt"]


# ------------------------------------------------------------------ 3. a prior below min_area


def test_a_tiny_mask_is_refused_before_any_stage_runs(case, tmp_path, monkeypatch):
    from pipeline.formats.bop.dataset import save_mask_png

    tiny = np.zeros_like(case["mask_array"])
    v, u = np.nonzero(case["mask_array"])
    tiny[v[0]:v[0] + 2, u[0]:u[0] + 2] = True  # 4 pixels on the object
    save_mask_png(tmp_path / "tiny.png", tiny)
    out = tmp_path / "out"
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out, prior=("--mask", str(tmp_path / "tiny.png"))),
                              monkeypatch))
    assert f"--mask {tmp_path / 'tiny.png'}: the prior's mask has 4 pixels, below segment_prior.min_area = 64" in line
    assert "-c segment_prior.min_area=" in line
    assert not out.exists()
    _no_stage_ran(tmp_path / "cache")
    # lowered below the mask's area, the next check speaks: too few depth points for scene_features
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out, "-c", "segment_prior.min_area=4",
                                                                  prior=("--mask", str(tmp_path / "tiny.png"))),
                              monkeypatch))
    assert "below scene_features.min_points = 50" in line and "-c scene_features.min_points=4" in line
    _no_stage_ran(tmp_path / "cache")


@pytest.mark.parametrize("box", ["330,250,0.001,0.001", "330,250,3,1"])
def test_a_tiny_box_is_refused_before_any_stage_runs(case, tmp_path, monkeypatch, box):
    x, y, w, h = case["bbox"]
    cx, cy = x + w // 2, y + h // 2
    bx, by, bw, bh = (float(v) for v in box.split(","))
    box = f"{cx},{cy},{bw:g},{bh:g}"  # on the object's middle
    out = tmp_path / "out"
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out, prior=("--bbox", box)), monkeypatch))
    area = int(np.ceil(bw)) * int(np.ceil(bh))  # the box's pixels (all on the object)
    assert line == (f"error: --bbox {box}: the prior's mask has {area} pixel{'s' * (area != 1)}, below "
                    "segment_prior.min_area = 64, so no candidate would be left: give the object's whole mask or "
                    f"box, or lower the limit with -c segment_prior.min_area={area}")
    assert not out.exists()
    _no_stage_ran(tmp_path / "cache")


# ---------------------------------------------------------------------------- 4. absurd intrinsics


K_OK = [572.4, 0.0, 325.3, 0.0, 573.6, 242.0, 0.0, 0.0, 1.0]


def _with(i: int, v) -> list:
    k = list(K_OK)
    k[i] = v
    return k


@pytest.mark.parametrize("doc, expect", [
    ({"cam_K": _with(0, 1e-300)}, "'cam_K[0]' (fx) = 1e-300 px is no focal length for a 640x480 image"),
    ({"cam_K": _with(5, 1e9)}, "'cam_K[5]' (cy) = 1e+09 px puts the principal point far outside the 640x480 image"),
    ({"cam_K": _with(2, -5000)}, "'cam_K[2]' (cx) = -5000 px puts the principal point far outside"),
    ({"cam_K": _with(0, 0)}, "'cam_K[0]' (fx) = 0: the focal length must be a positive number of pixels"),
    ({"cam_K": _with(4, -573.6)}, "'cam_K[4]' (fy) = -573.6: the focal length must be a positive"),
    ({"cam_K": _with(4, 1e12)}, "'cam_K[4]' (fy) = 1e+12 px is no focal length"),
    ({"cam_K": _with(3, 5.0)}, "'cam_K[3]' = 5 must be 0: a pinhole camera matrix is [[fx, s, cx], [0, fy, cy]"),
    ({"cam_K": _with(7, 0.5)}, "'cam_K[7]' = 0.5 must be 0"),
    ({"cam_K": _with(8, 2.0)}, "'cam_K[8]' = 2 must be 1"),
    ({"K": [[572.4, 0, 325.3], [0, 573.6, 242.0], [0.1, 0, 1]]}, "'K[2][0]' = 0.1 must be 0"),
    ({"fx": 572.4, "fy": 1e-300, "cx": 325.3, "cy": 242.0}, "'fy' = 1e-300 px is no focal length"),
    ({"fx": 572.4, "fy": 573.6, "cx": 1e9, "cy": 242.0}, "'cx' = 1e+09 px puts the principal point far outside"),
])
def test_absurd_intrinsics_name_the_field_and_what_is_expected(case, tmp_path, doc, expect):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(EstimateError) as e:
        check_intrinsics(load_camera(path), 640, 480)
    assert str(e.value).startswith(f"{path}: field ") and expect in str(e.value), str(e.value)
    assert "expected" in str(e.value) or "must be" in str(e.value)


@pytest.mark.parametrize("text, field", [('{"cam_K": [NaN, 0, 325.3, 0, 573.6, 242, 0, 0, 1]}', "cam_K[0]"),
                                         ('{"cam_K": [572.4, 0, Infinity, 0, 573.6, 242, 0, 0, 1]}', "cam_K[2]"),
                                         ('{"fx": 572.4, "fy": 573.6, "cx": 325.3, "cy": -Infinity}', "cy")])
def test_non_finite_intrinsics_name_the_element(tmp_path, text, field):
    path = tmp_path / "cam.json"
    path.write_text(text)
    with pytest.raises(EstimateError, match=re.escape(f"{path}: field '{field}' must be a finite number")):
        load_camera(path)


def test_sane_intrinsics_pass(tmp_path):
    path = tmp_path / "cam.json"
    for doc in ({"cam_K": K_OK}, {"fx": 572.4, "fy": 573.6, "cx": -100.0, "cy": 700.0}):  # an off-centre crop
        path.write_text(json.dumps(doc))
        check_intrinsics(load_camera(path), 640, 480)


def test_absurd_intrinsics_through_the_command_run_nothing(case, tmp_path, monkeypatch):
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"cam_K": _with(5, 1e9), "depth_scale": 0.1}))
    out = tmp_path / "out"
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out, camera=cam), monkeypatch))
    assert line.startswith(f"error: {cam}: field 'cam_K[5]' (cy) = 1e+09 px") and "mask" not in line
    assert not out.exists()
    _no_stage_ran(tmp_path / "cache")


# ------------------------------------------------------------------------------------ 6. -c values


@pytest.mark.parametrize("value", ["register.seed=[1,", "register.seed=!!python/object/apply:os.system ['touch {pwned}']",
                                   "register.seed=inf", "register.seed=.inf", "register.seed=nan"])
def test_bad_config_values_are_one_line(case, tmp_path, monkeypatch, value):
    pwned = tmp_path / "pwned"
    out = tmp_path / "out"
    line = _one_error(_invoke(case, tmp_path / "cache", _args(case, out, "-c", value.format(pwned=pwned)), monkeypatch))
    assert "register.seed" in line or "seed" in line, line
    assert not pwned.exists() and not out.exists()
    _no_stage_ran(tmp_path / "cache")

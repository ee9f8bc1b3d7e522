"""What ``freeze verify --repair`` may remove, and the output paths of ``freeze score``,
``freeze table`` and ``freeze report`` (issue 28, items on verify, output paths, read-only
caches, ``--vsd-delta``, ``freeze score`` progress and mixed times).

Each fault is set up, the real command runs (typer's CliRunner on ``pipeline.commands.cli.app``),
and the test asserts the exit code, the one-line message, and, for verify, that nothing
but what it owns changed: every path and content hash under the cache (and under the
target of a link out of it) is compared before and after.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from conftest import current_dir
from pipeline.formats.bop.results import read_estimates_json, write_results_csv
from pipeline.commands.cli import app
from pipeline.common.store import MANIFEST_NAME, publish, read_manifest, save_arrays, write_table
# The estimate's test case (a rendered truck, its model, camera and mask; a module fixture)
# and the smaller model side it runs with.
from test_estimate import FAST, case  # noqa: F401

runner = CliRunner()
TINYBOP = Path(__file__).parent / "data" / "tinybop"
HOURS_AGO = time.time() - 3 * 3600


# ------------------------------------------------------------------ helpers


def snapshot(*roots: Path) -> dict[str, str]:
    """Every path under ``roots`` (not following links) -> "dir", "link:<target>" or the
    SHA-256 of the file's bytes."""
    out = {}
    for root in roots:
        for dirpath, dirnames, filenames in os.walk(root):  # followlinks=False
            for name in dirnames + filenames:
                p = Path(dirpath) / name
                if p.is_symlink():
                    out[str(p)] = "link:" + os.readlink(p)
                elif p.is_dir():
                    out[str(p)] = "dir"
                else:
                    out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def under(paths: list[Path], snap: dict[str, str]) -> set[str]:
    """The entries of ``snap`` that are one of ``paths`` or lie below one."""
    return {k for k in snap for p in paths if k == str(p) or k.startswith(str(p) + os.sep)}


def assert_only_removed(before: dict[str, str], after: dict[str, str], removed: list[Path]) -> None:
    """Nothing added or changed; what went is exactly ``removed`` with its contents."""
    gone = set(before) - set(after)
    assert gone == under(removed, before), sorted(gone ^ under(removed, before))[:10]
    assert set(after) <= set(before), sorted(set(after) - set(before))[:10]
    assert all(after[k] == before[k] for k in after), [k for k in after if after[k] != before[k]][:10]


def make_item(item_dir: Path, *, dataset: str = "d") -> Path:
    """A real artifact at ``item_dir`` (``.../<stage>/<signature>/<item>``) published with
    :func:`pipeline.common.store.publish`: a Zarr store and a Parquet table."""
    stage, signature, item = item_dir.parent.parent.name, item_dir.parent.name, item_dir.name
    with publish(item_dir, stage=stage, item=item, key=signature[-8:] * 5, signature=signature, params={},
                 upstream={}, code_version=1, dataset=dataset) as w:
        save_arrays(w.dir / "features.zarr", {"points": np.arange(300, dtype=np.float32).reshape(10, 10, 3)})
        write_table(pd.DataFrame({"a": [1, 2, 3]}), w.dir / "coarse_hypotheses.parquet")
    return item_dir


def verify(cache: Path, *args: str):
    return runner.invoke(app, ["verify", "--cache", str(cache), "--no-progress", *args])


def one_line(output: str, needle: str) -> str:
    """The one output line holding ``needle`` (failing when there is none)."""
    lines = [line for line in output.splitlines() if needle in line]
    assert lines, output
    return lines[0]


@pytest.fixture
def cache(tmp_path) -> Path:
    """Artifacts at four and at five levels (``_estimate/<name>/...``, as freeze estimate
    writes them) and the cache's own file-hash databases."""
    root = tmp_path / "cache"
    make_item(root / "d" / "register" / "fpfh-aaaaaaaa" / "scene_000001")
    make_item(root / "d" / "register" / "fpfh-aaaaaaaa" / "scene_000002")
    make_item(root / "_estimate" / "model" / "model_features" / "fpfh-bbbbbbbb" / "obj_000001", dataset="model")
    make_item(root / "_estimate" / "model" / "render_templates" / "r16-cccccccc" / "obj_000001", dataset="model")
    (root / ".file-hashes.sqlite").write_bytes(b"SQLite format 3\0" + bytes(100))
    (root / "_estimate" / ".file-hashes.sqlite").write_bytes(b"SQLite format 3\0" + bytes(100))
    return root


# ------------------------------------------------------------------ verify: what it owns


def test_artifacts_five_deep_verify_clean_and_survive_repair(cache):
    before = snapshot(cache)
    res = verify(cache)
    assert res.exit_code == 0, res.output
    assert "4 artifact items checked" in res.output and "0 damaged" in res.output
    assert "no _manifest.json" not in res.output and "left alone:" not in res.output
    res = verify(cache, "--repair")
    assert res.exit_code == 0, res.output
    assert snapshot(cache) == before
    # and only the estimate's, by its path below the cache
    res = verify(cache, "-d", "_estimate/model")
    assert res.exit_code == 0 and "2 artifact items checked" in res.output, res.output


def test_a_user_folder_survives_repair_and_is_reported(cache):
    notes = cache / "userdata" / "a" / "b" / "c" / "notes.txt"
    notes.parent.mkdir(parents=True)
    notes.write_text("my thesis notes\n")
    mine = cache / "userdata" / "x" / MANIFEST_NAME  # someone else's manifest: no stage, item, key, signature
    mine.parent.mkdir(parents=True)
    mine.write_text('{"name": "my project", "version": 3}\n')
    (cache / "README.txt").write_text("what this folder is\n")
    before = snapshot(cache)
    res = verify(cache, "--repair")
    assert res.exit_code == 0, res.output
    assert snapshot(cache) == before
    assert one_line(res.output, "left alone").startswith("left alone:")
    assert f"left alone: {cache / 'userdata'} (not an artifact" in res.output  # one line for the whole folder
    assert f"left alone: {cache / 'README.txt'}" in res.output
    assert "2 paths left alone" in res.output and "Traceback" not in res.output
    assert ".file-hashes.sqlite" not in res.output  # the cache's own files are neither reported nor touched


def test_a_symlinked_signature_folder_is_not_followed_and_its_target_is_untouched(cache, tmp_path):
    outside = tmp_path / "outside"
    target = make_item(outside / "register" / "fpfh-dddddddd" / "scene_000001")
    (target / "coarse_hypotheses.parquet").write_bytes(b"PAR1")  # damaged: a followed link would have it removed
    old = outside / "register" / "fpfh-dddddddd" / ".tmp-scene_000002-1234abcd"
    old.mkdir()
    os.utime(old, (HOURS_AGO, HOURS_AGO))
    sig = cache / "d" / "register" / "fpfh-dddddddd"
    sig.symlink_to(outside / "register" / "fpfh-dddddddd", target_is_directory=True)
    item_link = cache / "d" / "register" / "fpfh-aaaaaaaa" / "scene_000009"
    item_link.symlink_to(target, target_is_directory=True)
    file_link = cache / "d" / "register" / "fpfh-aaaaaaaa" / "notes.parquet"
    file_link.symlink_to(target / "coarse_hypotheses.parquet")
    before = snapshot(cache, outside)
    res = verify(cache, "--repair")
    assert res.exit_code == 0, res.output
    assert snapshot(cache, outside) == before
    for link in (sig, item_link, file_link):
        assert f"left alone: {link} (a symbolic link: not followed" in res.output, res.output
    assert "damaged" not in res.output.replace("0 damaged", "") and "Traceback" not in res.output


def test_repair_removes_damaged_items_and_leftovers_and_nothing_else(cache):
    sig = cache / "d" / "register" / "fpfh-aaaaaaaa"
    bad = sig / "scene_000002"
    (bad / "coarse_hypotheses.parquet").write_bytes(b"PAR1")  # a truncated table
    half = make_item(sig / "scene_000003")
    (half / MANIFEST_NAME).write_text('{"key": "kkk", "fil')  # a half-written manifest, in a signature folder
    bad5 = cache / "_estimate" / "model" / "model_features" / "fpfh-bbbbbbbb" / "obj_000001"
    next(p for p in (bad5 / "features.zarr").rglob("*") if p.is_file() and p.name != "zarr.json").write_bytes(b"")
    no_manifest = make_item(sig / "scene_000004")
    (no_manifest / MANIFEST_NAME).unlink()  # not an artifact any more: left for the next run to replace
    old_tmp, old_old = sig / ".tmp-scene_000005-0123abcd", sig / ".old-scene_000001-89abcdef"
    old_tmp.mkdir()
    (old_tmp / "half.parquet").write_bytes(b"PAR")
    shutil.copytree(sig / "scene_000001", old_old)
    old_file = sig / ".coarse_hypotheses.parquet.4567cdef.tmp"
    old_file.write_bytes(b"PAR")
    young = sig / ".tmp-scene_000006-fedcba98"  # a running job's, perhaps
    young.mkdir()
    users_tmp = cache / "userdata" / ".tmp-notes"  # not a publish's: no signature folder, no hex suffix
    users_tmp.mkdir(parents=True)
    (users_tmp / "draft.txt").write_text("draft\n")
    for p in (old_tmp, old_tmp / "half.parquet", old_old, old_file, *old_old.rglob("*")):
        os.utime(p, (HOURS_AGO, HOURS_AGO))
    before = snapshot(cache)

    res = verify(cache)
    assert res.exit_code == 1, res.output
    assert f"damaged: {bad}: coarse_hypotheses.parquet is 4 bytes" in res.output
    assert f"damaged: {half}: {MANIFEST_NAME} is not valid JSON" in res.output
    assert f"damaged: {bad5}: features.zarr/points" in res.output
    assert "3 damaged, 3 leftovers" in res.output and "run `freeze verify --repair`" in res.output
    assert f"left alone: {no_manifest} (an item folder without its {MANIFEST_NAME}" in res.output
    assert "1 leftover(s) younger than 60 min" in res.output
    assert snapshot(cache) == before  # without --repair nothing changes

    res = verify(cache, "--repair")
    assert res.exit_code == 0, res.output
    assert "removed 6" in res.output and "Traceback" not in res.output
    assert_only_removed(before, snapshot(cache), [bad, half, bad5, old_tmp, old_old, old_file])
    assert young.is_dir() and no_manifest.is_dir() and (users_tmp / "draft.txt").is_file()
    res = verify(cache)
    assert res.exit_code == 0 and "0 damaged, 0 leftovers" in res.output, res.output


# ------------------------------------------------------------------ verify on a read-only cache


def test_repair_on_a_read_only_cache_is_one_line_naming_the_item(cache, monkeypatch):
    bad = cache / "d" / "register" / "fpfh-aaaaaaaa" / "scene_000002"
    (bad / "coarse_hypotheses.parquet").write_bytes(b"PAR1")
    before = snapshot(cache)

    def read_only(path, *args, **kwargs):  # what the file system says at the first unlink
        raise OSError(errno.EROFS, "Read-only file system", "coarse_hypotheses.parquet")

    monkeypatch.setattr("pipeline.commands.verify.shutil.rmtree", read_only)
    res = verify(cache, "--repair")
    assert res.exit_code == 1, res.output
    line = one_line(res.output, "cannot remove")
    assert line == f"error: {bad}: cannot remove it (read-only file system); 0 of 1 removed, the rest left as they were"
    assert "Traceback" not in res.output
    assert snapshot(cache) == before


def _bind_read_only(src: Path, dst: Path) -> bool:
    """Bind-mount ``src`` read-only at ``dst``; False where this process may not mount
    (not root, or a container without CAP_SYS_ADMIN)."""
    dst.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None:
        return False
    if subprocess.run(["mount", "--bind", str(src), str(dst)], capture_output=True).returncode:
        return False
    if subprocess.run(["mount", "-o", "remount,bind,ro", str(dst)], capture_output=True).returncode:
        subprocess.run(["umount", str(dst)], capture_output=True)
        return False
    return True


@pytest.fixture
def read_only_view(tmp_path):
    """``view(src)``: a read-only bind mount of ``src`` (skips the test where mounting is
    not allowed); unmounted after the test."""
    mounts = []

    def view(src: Path) -> Path:
        dst = tmp_path / f"ro-{len(mounts)}"
        if not _bind_read_only(src, dst):
            pytest.skip("cannot bind-mount read-only here (needs root with CAP_SYS_ADMIN)")
        mounts.append(dst)
        return dst

    yield view
    for dst in mounts:
        subprocess.run(["umount", str(dst)], capture_output=True)


def test_repair_on_a_real_read_only_mount_is_one_line(cache, read_only_view):
    (cache / "d" / "register" / "fpfh-aaaaaaaa" / "scene_000002" / "coarse_hypotheses.parquet").write_bytes(b"PAR1")
    before = snapshot(cache)
    ro = read_only_view(cache)
    res = verify(ro, "--repair")
    assert res.exit_code == 1, res.output
    line = one_line(res.output, "cannot remove")
    assert str(ro / "d" / "register" / "fpfh-aaaaaaaa" / "scene_000002") in line and "read-only file system" in line
    assert "Traceback" not in res.output
    assert snapshot(cache) == before


# ------------------------------------------------------------------ freeze score


@pytest.fixture
def results_csv(tmp_path) -> Path:
    """The tinybop icbin estimates as a results CSV (one time per image)."""
    est = read_estimates_json(TINYBOP / "estimates" / "tx20_icbin-test.json")
    csv = tmp_path / "tx20_icbin-test.csv"
    write_results_csv(csv, est)
    return csv


def _score(csv: Path, *args: str):
    return runner.invoke(app, ["score", str(csv), "--dataset-root", str(TINYBOP / "icbin"), *args])


def test_score_out_onto_a_file_is_one_line_before_any_work(results_csv, tmp_path):
    out = tmp_path / "scores"
    out.write_text("not a folder\n")
    res = _score(results_csv, "--out", str(out), "--no-progress")
    assert res.exit_code == 1, res.output
    assert res.output.strip() == f"--out {out}: is a file; give a folder to write into (it is created if missing)"
    assert out.read_text() == "not a folder\n"
    below = out / "sub"  # below a file
    res = _score(results_csv, "--out", str(below), "--no-progress")
    assert res.exit_code == 1 and f"{out} is a file, not a folder" in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("value", ["-5", "0", "nan", "inf", "-inf"])
def test_score_refuses_a_vsd_delta_that_is_not_a_finite_positive_number(results_csv, tmp_path, value):
    out = tmp_path / "scores"
    res = _score(results_csv, "--out", str(out), "--no-progress", "--vsd-delta", value)
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert "Invalid value for '--vsd-delta': must be a finite number of mm > 0" in text
    assert not out.exists() and "Traceback" not in res.output


def test_the_library_refuses_such_a_vsd_delta_too(results_csv):
    from pipeline.evaluation.metrics import score_results_file

    with pytest.raises(ValueError, match=r"vsd_delta must be a finite number of mm > 0, got nan"):
        score_results_file(results_csv, TINYBOP / "icbin", vsd_delta=float("nan"))


def _strict_json(text: str):
    def refuse(name: str):
        raise AssertionError(f"non-standard JSON token {name}")

    return json.loads(text, parse_constant=refuse)


def test_scores_json_never_holds_nan_or_infinity(results_csv, tmp_path, monkeypatch):
    from pipeline.evaluation.metrics.evaluate import Scores

    out = tmp_path / "scores"
    res = _score(results_csv, "--out", str(out), "--no-progress", "--vsd-delta", "15")
    assert res.exit_code == 0, res.output
    _strict_json((out / "scores.json").read_text())
    real = Scores.to_json

    def with_nan(self):  # a value that is not finite anywhere in the content
        content = real(self)
        content["summary"]["odd"] = [float("nan"), float("inf"), {"x": -float("inf")}]
        return content

    monkeypatch.setattr(Scores, "to_json", with_nan)
    res = _score(results_csv, "--out", str(out), "--no-progress")
    assert res.exit_code == 0, res.output
    assert _strict_json((out / "scores.json").read_text())["summary"]["odd"] == [None, None, {"x": None}]


def test_score_no_progress_is_clean_and_progress_does_not_change_the_result(results_csv, tmp_path):
    quiet = _score(results_csv, "--out", str(tmp_path / "a"), "--no-progress")
    assert quiet.exit_code == 0, quiet.output
    assert not any(mark in quiet.output for mark in ("✓", "pose errors", "it/s", "read tx20"))
    assert quiet.output.lstrip().startswith("BOP19 average recall")
    loud = _score(results_csv, "--out", str(tmp_path / "b"), "--progress")
    assert loud.exit_code == 0, loud.output
    assert "check " in loud.output and "estimates" in loud.output
    a = json.loads((tmp_path / "a" / "scores.json").read_text())["summary"]
    b = json.loads((tmp_path / "b" / "scores.json").read_text())["summary"]
    assert a["AR"] == b["AR"] and a["AR_VSD"] == b["AR_VSD"]


def test_mixed_unknown_and_measured_times_of_one_image_are_one_note(tmp_path):
    est = read_estimates_json(TINYBOP / "estimates" / "tx20_icbin-test.json")
    images = est.groupby(["scene_id", "im_id"]).size()
    scene, image = next(k for k, n in images.items() if n > 1)
    est["time"] = 0.5
    csv = tmp_path / "mixed_icbin-test.csv"
    write_results_csv(csv, est)
    lines = csv.read_text().splitlines()
    i = next(i for i, line in enumerate(lines[1:], 1) if line.split(",")[:2] == [str(scene), str(image)])
    lines[i] = lines[i].rsplit(",", 1)[0] + ",-1"  # one estimate of the image "not measured", the others 0.5 s
    csv.write_text("\n".join(lines) + "\n")
    out = tmp_path / "scores"
    res = _score(csv, "--out", str(out), "--no-progress")
    assert res.exit_code == 0, res.output
    note = (f"results: 1 image(s) have both unknown (-1) and measured times for their estimates (first: scene "
            f"{scene} image {image}); BOP needs one time for all estimates of an image, and any unknown time makes "
            "the mean time per image unknown (-1), as in the BOP toolkit")
    assert note in res.output.splitlines()  # the note, on one line
    summary = json.loads((out / "scores.json").read_text())["summary"]
    assert summary["mean_time_per_image"] == -1.0 and note in summary["notes"]


# ------------------------------------------------------------------ with the pipeline's cache


@pytest.fixture
def work(tiny_run, tmp_path) -> Path:
    """A work folder holding a copy of the finished synthtiny cache."""
    clean, _ = tiny_run
    shutil.copytree(clean / "cache", tmp_path / "work" / "cache", symlinks=True)
    return tmp_path / "work"


def _env(work: Path) -> dict[str, str]:
    return {"FREEZE_CACHE": str(work / "cache"), "PYOPENGL_PLATFORM": "egl", "HF_HUB_OFFLINE": "1"}


@pytest.mark.slow
def test_a_real_estimate_beside_a_run_verifies_clean_and_survives_repair(work, case):
    """After one `freeze estimate` into the run's cache, verify checks its five-deep
    model and scene sides with the run's artifacts, and --repair removes nothing."""
    from pipeline.commands.estimate.command import estimate

    res = estimate(case["model"], case["rgb"], case["depth"], case["camera"], overrides=FAST, cache=work / "cache",
                   mask=case["mask"])
    assert (work / "cache" / "_estimate") in res.artifacts["model_features"].parents
    n_run = sum(1 for _ in (work / "cache" / "synthtiny").glob(f"*/*/*/{MANIFEST_NAME}"))
    n_estimate = sum(1 for _ in (work / "cache" / "_estimate").rglob(MANIFEST_NAME))
    assert n_estimate >= 7
    before = snapshot(work / "cache")
    out = verify(work / "cache")
    assert out.exit_code == 0, out.output
    assert f"{n_run + n_estimate} artifact items checked" in out.output and "0 damaged" in out.output
    assert "left alone: " not in out.output
    out = verify(work / "cache", "--repair")
    assert out.exit_code == 0, out.output
    assert snapshot(work / "cache") == before


@pytest.mark.slow
def test_table_and_report_output_paths_are_one_line_each(work):
    env = _env(work)
    folder = work / "a_folder"
    folder.mkdir()
    (folder / "keep.txt").write_text("keep\n")
    a_file = work / "a_file"
    a_file.write_text("keep\n")
    before = snapshot(folder, a_file)
    cases = [
        (["table", "-c", "datasets=synthtiny", "--out", str(folder)],
         f"--out {folder}: is a folder; give the name of a file to write"),
        (["table", "-c", "datasets=synthtiny", "--csv-dir", str(a_file)],
         f"--csv-dir {a_file}: is a file; give a folder to write into (it is created if missing)"),
        (["report", "--dataset", "synthtiny", "-c", "datasets=synthtiny", "--out", str(folder)],
         f"--out {folder}: is a folder; give the name of a file to write"),
        (["report", "--dataset", "synthtiny", "-c", "datasets=synthtiny", "--out", str(a_file / "r.html")],
         f"--out {a_file / 'r.html'}: cannot write it, {a_file} is a file, not a folder"),
    ]
    for args, message in cases:
        res = runner.invoke(app, args, env=env)
        assert res.exit_code == 1, (args, res.output)
        assert res.output.strip() == message, (args, res.output)
    assert snapshot(folder, a_file) == before
    # a file in --csv-dir where the CSV is to go is a folder: one line too, after the table
    csv_dir = work / "csvs"
    name = next(p.name for p in (current_dir(work, "refine") / "all").glob("*.csv"))
    (csv_dir / name).mkdir(parents=True)
    res = runner.invoke(app, ["table", "-c", "datasets=synthtiny", "--csv-dir", str(csv_dir)], env=env)
    assert res.exit_code == 1 and f"{csv_dir / name}: is a folder" in res.output and "Traceback" not in res.output


@pytest.mark.slow
def test_report_on_a_read_only_cache_is_one_line(work, monkeypatch):
    """Without --out the report goes to <cache>/../results; on a read-only disk the write
    (here refused at the call that creates the file, as a read-only mount does) is one
    line naming the file, exit 1."""
    from pipeline.common import published_files

    def read_only(path, *args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(published_files, "open", read_only, raising=False)
    res = runner.invoke(app, ["report", "--dataset", "synthtiny", "-c", "datasets=synthtiny", "--samples", "1"],
                        env=_env(work))
    assert res.exit_code == 1, res.output
    target = work / "results" / "report_synthtiny.html"
    (line,) = res.output.strip().splitlines()
    assert line.startswith(f"{target}: cannot write it (read-only file system); nothing was ")
    assert "Traceback" not in res.output and not target.exists()


@pytest.mark.slow
def test_report_and_repair_on_a_real_read_only_mount(work, read_only_view):
    score = current_dir(work, "score") / "all"
    assert read_manifest(score)["summary"]["AR"] is not None
    ro = read_only_view(work)
    res = runner.invoke(app, ["report", "--dataset", "synthtiny", "-c", "datasets=synthtiny", "--samples", "1"],
                        env={**_env(work), "FREEZE_CACHE": str(ro / "cache")})
    assert res.exit_code == 1, res.output
    assert str(ro / "results" / "report_synthtiny.html") in res.output and "read-only file system" in res.output
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1

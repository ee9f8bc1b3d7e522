"""The BOP19 scorer against the reference BOP toolkit on the tiny synthetic dataset.

tests/data/tinybop holds a 3-image BOP dataset (stored as "icbin"), ten estimate files
and the toolkit's scores for each (see its SOURCE.txt). Every variant must agree on
AR and each component within 0.001, MSSD/MSPD per estimate within 1e-3 relative and
VSD within 0.005.
"""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.formats.bop import BopDataset, read_estimates_json, write_results_csv
from pipeline.evaluation.metrics import evaluate, load_scores, score_results_file, vsd_column

DATA = Path(__file__).parent / "data" / "tinybop"
REF = json.loads((DATA / "reference_scores_tinybop.json").read_text())["variants"]
VARIANTS = sorted(REF)


@pytest.fixture(scope="module")
def dataset() -> BopDataset:
    return BopDataset(DATA / "icbin")


def _estimates(variant: str) -> pd.DataFrame:
    return read_estimates_json(DATA / "estimates" / f"{variant}_icbin-test.json")


def _error_row(errors: pd.DataFrame, im_id: int, obj_id: int, gt_id: int, score: float) -> pd.Series:
    sel = errors[
        (errors.im_id == im_id) & (errors.obj_id == obj_id) & (errors.gt_id == gt_id) & np.isclose(errors.score, score)
    ]
    assert len(sel) == 1, f"expected one error row for im {im_id} obj {obj_id} gt {gt_id} score {score}"
    return sel.iloc[0]


@pytest.mark.parametrize("variant", VARIANTS)
def test_matches_reference_toolkit(dataset: BopDataset, variant: str) -> None:
    ref = REF[variant]
    scores = evaluate(_estimates(variant), dataset, progress=False)
    s, b = scores.summary, ref["bop19"]
    assert s["AR"] == pytest.approx(b["bop19_average_recall"], abs=1e-3)
    assert s["AR_VSD"] == pytest.approx(b["bop19_average_recall_vsd"], abs=1e-3)
    assert s["AR_MSSD"] == pytest.approx(b["bop19_average_recall_mssd"], abs=1e-3)
    assert s["AR_MSPD"] == pytest.approx(b["bop19_average_recall_mspd"], abs=1e-3)
    assert s["mean_time_per_image"] == pytest.approx(b["bop19_average_time_per_image"])
    assert s["n_targets"] == 6

    n_checked = 0
    for key, entries in ref["per_estimate_errors"].items():
        for e in entries:
            for gt_id, (value,) in e["errors_vs_gt_id"].items():
                row = _error_row(scores.errors, e["im_id"], e["obj_id"], int(gt_id), e["score"])
                if key.startswith("error=mssd") or key.startswith("error=mspd"):
                    ours = row["mssd" if "mssd" in key else "mspd"]
                    # The reference is rounded to 4 decimals: allow half a unit on ~0 values.
                    assert abs(ours - value) <= max(1e-3 * abs(value), 5e-5), (key, e, ours)
                else:
                    tau = float(key.split("tau=")[1])
                    assert abs(row[vsd_column(tau)] - value) <= 0.005, (key, e, row[vsd_column(tau)])
                n_checked += 1
    # Only the top inst_count (= 1) estimate per target is scored, as in the toolkit.
    assert len(scores.errors) == len(ref["per_estimate_errors"]["error=mssd_ntop=-1"])
    assert n_checked == 5 * len(scores.errors)


def test_batched_renders_give_the_errors_of_single_renders(dataset: BopDataset) -> None:
    """The scorer's batched depth renders (one readback per image, back faces skipped)
    and the previous path (one pyrender render per depth) give the same errors, on every
    estimate of every variant, including image 2 where the box hides 15 % of the
    cylinder (occlusion): MSSD and MSPD identical, VSD within the toolkit tolerance of
    ``test_matches_reference_toolkit`` (the renders differ by float rounding only)."""
    from pipeline.evaluation.metrics.calc_errors import ErrorCalculator, ErrorParams
    from pipeline.evaluation.metrics.evaluate import _image_jobs

    est = pd.concat([_estimates(v) for v in VARIANTS], ignore_index=True)
    est["est_id"] = est.groupby(["scene_id", "im_id", "obj_id"], sort=False).cumcount()
    jobs = _image_jobs(dataset, est)
    rows = {}
    for batch in (True, False):
        calc = ErrorCalculator(dataset, ErrorParams(batch_render=batch))
        try:
            rows[batch] = [r for job in jobs for r in calc.image_errors(job)]
        finally:
            calc.close()
    fast, single = rows[True], rows[False]
    assert len(fast) == len(single) == len(est)  # one GT instance per object and image
    occluded = 0
    for a, b in zip(fast, single):
        assert (a["im_id"], a["obj_id"], a["est_id"], a["gt_id"]) == (b["im_id"], b["obj_id"], b["est_id"], b["gt_id"])
        assert a["mssd"] == b["mssd"] and a["mspd"] == b["mspd"]
        np.testing.assert_allclose(a["vsd"], b["vsd"], rtol=0, atol=0.005)
        if a["im_id"] == 2 and a["obj_id"] == 1 and 0 < a["vsd"].min() < 1:
            occluded += 1
    assert occluded >= 3  # partly wrong estimates of the occluded cylinder


def test_translation_gives_exact_mssd(dataset: BopDataset) -> None:
    """tx20 / tz50 move every estimate by a pure translation: MSSD is exactly that length."""
    for variant, d in (("tx20", 20.0), ("tz50", 50.0)):
        errors = evaluate(_estimates(variant), dataset, progress=False).errors
        np.testing.assert_allclose(errors["mssd"], d, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_symmetric_variants_score_one(dataset: BopDataset) -> None:
    """Rotating the cylinder by a declared symmetry (discrete flip or continuous turn) is exact."""
    for variant in ("gt", "symflip", "symrotz"):
        s = evaluate(_estimates(variant), dataset, progress=False)
        assert s.summary["AR"] == 1.0
        assert (s.per_object["AR"] == 1.0).all()
    flip = evaluate(_estimates("symflip"), dataset, progress=False).errors
    assert flip["mssd"].max() < 1e-9 and flip["mspd"].max() < 1e-6


@pytest.mark.slow
def test_score_results_file_writes_outputs_and_uses_workers(tmp_path: Path, dataset: BopDataset) -> None:
    csv = tmp_path / "rx20_icbin-test.csv"
    write_results_csv(csv, _estimates("rx20"))
    out = tmp_path / "scores"
    scores = score_results_file(csv, DATA / "icbin", out_dir=out, n_workers=2)
    assert scores.summary["AR"] == pytest.approx(REF["rx20"]["bop19"]["bop19_average_recall"], abs=1e-3)
    summary, errors = load_scores(out)
    assert summary["summary"]["AR"] == pytest.approx(scores.summary["AR"])
    assert len(summary["recalls"]["vsd"]) == 10 and len(summary["recalls"]["mssd"]) == 10
    assert [r["obj_id"] for r in summary["per_object"]] == [1, 2]
    pd.testing.assert_frame_equal(errors, scores.errors)
    assert not list(out.glob(".*.tmp"))
    # The worker processes compute the same errors as the in-process path.
    single = evaluate(_estimates("rx20"), dataset, progress=False)
    pd.testing.assert_frame_equal(single.errors, scores.errors)


def test_ignored_estimates_and_time_warning(dataset: BopDataset) -> None:
    est = _estimates("gt")
    stray = est.iloc[:2].copy()
    stray["im_id"] = 7  # not a target image
    est = pd.concat([est, stray], ignore_index=True)
    est.loc[1, "time"] = 0.75  # image 0 now has two different times
    with pytest.warns(UserWarning, match="scene 1 image 0"):
        s = evaluate(est, dataset, progress=False)
    assert s.summary["n_estimates"] == 8
    assert s.summary["n_ignored"] == 2
    assert s.summary["n_evaluated"] == 6
    assert s.summary["AR"] == 1.0
    # The toolkit averages the first time of every image in the file, targets or not.
    assert s.summary["mean_time_per_image"] == pytest.approx(0.25)


def test_only_top_inst_count_estimates_are_scored(dataset: BopDataset) -> None:
    """fphigh puts a wrong pose above the right one: the right one is never looked at."""
    s = evaluate(_estimates("fphigh"), dataset, progress=False)
    assert s.summary["n_beyond_inst_count"] == 6
    assert s.summary["AR"] == 0.0
    np.testing.assert_allclose(s.errors["mssd"], 100.0, atol=1e-9)


def test_reading_ahead_gives_the_same_rows_and_names_a_bad_depth(tmp_path: Path, dataset: BopDataset) -> None:
    """``ErrorCalculator.errors_of`` (a reader thread loads models and depth ahead) gives
    every row of ``image_errors`` bit for bit, and a depth image that cannot be read
    fails the job that needs it with the file's name, as without reading ahead."""
    from pipeline.formats.bop import BopFormatError
    from pipeline.evaluation.metrics.calc_errors import ErrorCalculator, ErrorParams
    from pipeline.evaluation.metrics.evaluate import _image_jobs

    est = pd.concat([_estimates(v) for v in VARIANTS], ignore_index=True)
    est["est_id"] = est.groupby(["scene_id", "im_id", "obj_id"], sort=False).cumcount()
    jobs = _image_jobs(dataset, est)
    assert len(jobs) == 3
    rows = {}
    for ahead in (False, True):
        calc = ErrorCalculator(dataset, ErrorParams())
        try:
            if ahead:
                rows[ahead] = [r for part in calc.errors_of(jobs, ahead=2) for r in part]
            else:
                rows[ahead] = [r for job in jobs for r in calc.image_errors(job)]
        finally:
            calc.close()
    assert len(rows[True]) == len(rows[False]) == len(est)
    for a, b in zip(rows[True], rows[False]):
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])

    root = tmp_path / "icbin"
    shutil.copytree(DATA / "icbin", root)
    bad = root / "test" / "000001" / "depth" / "000002.png"
    bad.write_bytes(b"not a png")
    calc = ErrorCalculator(BopDataset(root), ErrorParams())
    done = []
    try:
        with pytest.raises(BopFormatError, match="000002.png"):
            for part in calc.errors_of(_image_jobs(BopDataset(root), est)):
                done.append(part)
    finally:
        calc.close()
    assert len(done) == 2  # images 0 and 1 were scored before image 2 failed


def test_missing_depth_reports_no_vsd(tmp_path: Path) -> None:
    root = tmp_path / "icbin"
    shutil.copytree(DATA / "icbin", root, ignore=shutil.ignore_patterns("depth"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = evaluate(_estimates("tx20"), BopDataset(root), progress=False)
    assert s.summary["AR"] is None and s.summary["AR_VSD"] is None
    assert s.summary["images_without_depth"] == 3
    assert "VSD not computed" in s.summary["notes"][0]
    assert s.summary["AR_MSSD"] == pytest.approx(REF["tx20"]["bop19"]["bop19_average_recall_mssd"], abs=1e-3)
    assert s.errors[vsd_column(0.05)].isna().all()
    assert "vsd" not in s.recalls
    assert json.dumps(s.to_json())  # None/NaN survive as JSON null


def test_bad_input_is_named(dataset: BopDataset) -> None:
    est = _estimates("gt")
    est.at[2, "t"] = np.array([1.0, 2.0])
    with pytest.raises(ValueError, match=r"row 2, field 't'"):
        evaluate(est, dataset, progress=False)
    with pytest.raises(ValueError, match=r"missing column\(s\) \['R'\]"):
        evaluate(_estimates("gt").drop(columns=["R"]), dataset, progress=False)
    from pipeline.formats.bop import Target

    with pytest.raises(ValueError, match=r"target object\(s\) \[9\]"):
        evaluate(_estimates("gt"), dataset, targets=[Target(1, 0, 9, 1)], progress=False)


@pytest.mark.parametrize("variant", ["gt", "rx20", "tx20", "symflip"])
def test_per_visibility_breakdown(dataset: BopDataset, variant: str) -> None:
    """Targets are counted in the bin of their visible fraction; the target-weighted
    mean of the per-bin recalls is the overall recall."""
    from pipeline.evaluation.metrics.evaluate import VISIB_BIN_EDGES, visib_bin

    s = evaluate(_estimates(variant), dataset, progress=False)
    pv = s.per_visibility
    assert len(pv) == 10 and list(pv["visib_min"]) == list(VISIB_BIN_EDGES[:-1])
    assert pv["n_targets"].sum() == s.summary["n_targets"]
    # Every valid GT instance has an estimate of its object here, so errors lists them all.
    valid = s.errors.drop_duplicates(["scene_id", "im_id", "gt_id"])
    valid = valid[valid["gt_valid"]]
    assert len(valid) == s.summary["n_targets"]
    np.testing.assert_array_equal(pv["n_targets"], np.bincount(visib_bin(valid["gt_visib_fract"]), minlength=10))
    filled = pv[pv["n_targets"] > 0]
    empty = pv[pv["n_targets"] == 0]
    assert empty[["AR_VSD", "AR_MSSD", "AR_MSPD", "AR"]].isna().all().all()
    for col in ("AR_VSD", "AR_MSSD", "AR_MSPD", "AR"):
        pooled = (filled[col] * filled["n_targets"]).sum() / filled["n_targets"].sum()
        assert pooled == pytest.approx(s.summary[col], abs=1e-12), col
    if variant in ("gt", "symflip"):
        assert (filled["AR"] == 1.0).all()
    js = json.loads(json.dumps(s.to_json()))
    assert len(js["per_visibility"]) == 10
    assert all(r["AR"] is None for r in js["per_visibility"] if r["n_targets"] == 0)


@pytest.mark.slow
def test_timing_split_is_reported(tmp_path: Path) -> None:
    csv = tmp_path / "tx20_icbin-test.csv"
    write_results_csv(csv, _estimates("tx20"))
    for workers in (1, 2):
        s = score_results_file(csv, DATA / "icbin", out_dir=tmp_path / f"out{workers}", n_workers=workers)
        t = s.summary["timing"]
        for k in ("read", "prepare", "load", "vsd_render", "vsd_compare", "mssd", "mspd", "errors_wall", "match", "write"):
            assert t[k] >= 0.0, k
        assert t["vsd_render"] > 0 and t["mssd"] > 0 and t["mspd"] > 0
        assert t["n_workers"] == workers
        # One render per GT instance of each image, plus one per estimate (6 + 6).
        assert t["n_renders"] == 12
        summary, _ = load_scores(tmp_path / f"out{workers}")
        assert summary["summary"]["timing"]["n_renders"] == 12


def test_malformed_results_file_names_the_line(tmp_path: Path) -> None:
    from pipeline.formats.bop import BopFormatError

    csv = tmp_path / "gt_icbin-test.csv"
    write_results_csv(csv, _estimates("gt"))
    lines = csv.read_text().splitlines()
    lines[3] = lines[3].replace(",", ";", 1)
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(BopFormatError, match=r"line 4: expected 7 comma-separated fields"):
        score_results_file(csv, DATA / "icbin")
    lines = csv.read_text().splitlines()
    lines[3] = "1,0,1,0.5,1 0 0 0 1 0 0 0 nan,0 0 500,0.25"
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(BopFormatError, match=r"line 4, field 'R'"):
        score_results_file(csv, DATA / "icbin")


def test_estimates_for_unknown_objects_are_ignored(dataset: BopDataset) -> None:
    """An object that is not a target of the image (even one with no model) is ignored and counted."""
    est = _estimates("gt")
    stray = est.iloc[:3].copy()
    stray["obj_id"] = 99
    est = pd.concat([est, stray], ignore_index=True)
    s = evaluate(est, dataset, progress=False)
    assert s.summary["n_ignored"] == 3 and s.summary["n_evaluated"] == 6
    assert s.summary["AR"] == 1.0
    assert 99 not in set(s.errors["obj_id"])


def _rotation_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_rotation_deviations() -> None:
    from pipeline.evaluation.metrics.evaluate import rotation_deviations

    R = np.stack([_rotation_z(30), np.zeros((3, 3)), 1.01 * np.eye(3), np.diag([1.0, 1.0, -1.0])])
    ortho, det = rotation_deviations(R)
    np.testing.assert_allclose(ortho, [0.0, 1.0, 0.0201, 0.0], atol=1e-12)
    np.testing.assert_allclose(det, [0.0, 1.0, 1.01 ** 3 - 1, 2.0], atol=1e-12)
    assert rotation_deviations(np.zeros((0, 3, 3)))[0].shape == (0,)


@pytest.mark.parametrize("bad, deviation", [
    (np.zeros((3, 3)), "max|R^T R - I| = 1, |det R - 1| = 1"),       # all-zero R
    (1.01 * np.eye(3), "max|R^T R - I| = 0.0201, |det R - 1| = 0.0303"),  # scaled by 1%
    (np.diag([1.0, 1.0, -1.0]), "|det R - 1| = 2"),  # a reflection (R^T R = I up to rounding)
    (np.array([[1.0, 0.01, 0], [0, 1, 0], [0, 0, 1]]), "max|R^T R - I| = 0.01, "),  # a shear (det 1)
])
def test_an_r_that_is_not_a_rotation_is_refused(dataset: BopDataset, bad: np.ndarray, deviation: str) -> None:
    from pipeline.evaluation.metrics import NotARotationError

    est = _estimates("gt")
    for i in (2, 4):
        est.at[i, "R"] = est.at[i, "R"] @ bad  # (R B)^T (R B) = B^T B: the deviation is that of B
    r = est.iloc[2]
    with pytest.raises(NotARotationError) as info:
        evaluate(est, dataset, progress=False)
    msg = str(info.value)
    assert msg.startswith(f"results: 2 of 6 estimates have an R that is not a rotation (max|R^T R - I| or "
                          f"|det R - 1| above 0.001); first: estimate 3 (scene_id {r.scene_id}, im_id {r.im_id}, "
                          f"obj_id {r.obj_id}) with max|R^T R - I| = ")
    assert deviation in msg
    assert "\n" not in msg and isinstance(info.value, ValueError)


def test_rotations_within_the_tolerance_score_as_the_toolkit(dataset: BopDataset) -> None:
    """R written with few digits (deviation 1e-4 < ROTATION_TOLERANCE) is accepted and
    scores as the exact one."""
    from pipeline.evaluation.metrics import ROTATION_TOLERANCE
    from pipeline.evaluation.metrics.evaluate import rotation_deviations

    est = _estimates("tx20")
    rounded = est.copy()
    rounded["R"] = [np.round(R, 4) for R in est["R"]]
    ortho, det = rotation_deviations(np.stack(rounded["R"]))
    assert 0 < max(ortho.max(), det.max()) < ROTATION_TOLERANCE
    a, b = evaluate(est, dataset, progress=False).summary, evaluate(rounded, dataset, progress=False).summary
    for key in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD"):
        assert b[key] == pytest.approx(a[key], abs=1e-3), key
    assert a["AR"] == pytest.approx(REF["tx20"]["bop19"]["bop19_average_recall"], abs=1e-3)


def test_results_file_with_a_bad_r_names_the_file_and_writes_nothing(tmp_path: Path) -> None:
    from pipeline.formats.bop import BopFormatError
    from pipeline.evaluation.metrics.evaluate import unscored_summary

    est = _estimates("gt")
    est.at[5, "R"] = np.zeros((3, 3))
    csv = tmp_path / "zero_icbin-test.csv"
    write_results_csv(csv, est)
    out = tmp_path / "out"
    with pytest.raises(BopFormatError, match=rf"^{csv}: 1 of 6 estimates have an R that is not a rotation .*"
                                             r"first: estimate 6 \(scene_id 1, im_id \d+, obj_id \d+\)"):
        score_results_file(csv, DATA / "icbin", out_dir=out)
    assert not out.exists()
    # the private-ground-truth path (nothing scored, the file is for the BOP server) refuses it too
    with pytest.raises(BopFormatError, match=rf"^{csv}: 1 of 6 estimates"):
        unscored_summary(csv, [], "no ground truth")


def test_score_stage_fails_on_a_bad_r_and_publishes_nothing(tmp_path: Path) -> None:
    """stages/score.py, scored and unscored (private ground truth): the same one-line
    error as `freeze score`, raised inside the publish block, so nothing is published."""
    import contextlib
    from types import SimpleNamespace

    from pipeline.common.config import RunManifest
    from pipeline.evaluation.metrics import NotARotationError
    from stages import score as score_stage

    est = _estimates("gt")
    est.at[1, "R"] = 2 * np.eye(3)
    refine = tmp_path / "refine"
    refine.mkdir()
    csv = refine / "freeze_icbin-test.csv"
    write_results_csv(csv, est)
    published = []

    @contextlib.contextmanager
    def publish():
        w = SimpleNamespace(dir=tmp_path / "tmp-score", summary={})
        w.dir.mkdir()
        yield w
        published.append(w)  # reached only when the block ends normally

    for public_gt in (True, False):
        root = tmp_path / f"root{public_gt}"
        shutil.copytree(DATA / "icbin", root)
        if not public_gt:
            (root / "test" / "000001" / "scene_gt.json").unlink()
        io = SimpleNamespace(input_dir=lambda stage: refine, bop=lambda: BopDataset(root), publish=publish,
                             params=SimpleNamespace(n_workers=1))
        plan = SimpleNamespace(io=lambda stage, item: io, results_csv_name=csv.name, scene_ids=[1], root=root,
                               run=RunManifest(datasets=["icbin"]),  # no dask scheduler: the job's threads
                               dataset=SimpleNamespace(public_gt=public_gt, targets_file="test_targets_bop19.json",
                                                       split="test", split_type=None, vsd_delta=15.0))
        with pytest.raises(NotARotationError, match=rf"^{csv}: 1 of 6 estimates .* first: estimate 2 "):
            score_stage.run(plan, "all", progress=False)
        shutil.rmtree(tmp_path / "tmp-score")
    assert published == []

"""`freeze inspect`, `freeze ls`, `freeze gc` and `freeze show features` on a small artifact
store built here with the store's own publish(), so every shape, NaN count, norm, row
count and upstream link is known in advance. The stage folders carry the signatures of
the real plan of `synthtiny` (nothing is run), so the plan sees them as current."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from pipeline.common.config import load_run
from pipeline.workflow.artifacts import ArtifactIndex, Removal, collect_garbage, inspect_artifact, list_artifacts
from pipeline.workflow.plan import RunPlan
from pipeline.views.features_figure import (DPI, FIGSIZE, FeatureCase, draw_features_figure, feature_case,
                                             fused_features, inlier_matches, pca_colours)
from pipeline.common.store import publish, save_arrays, write_table

DS = "synthtiny"
N, G, V = 200, 8, 5           # model points, geometric and visual channels
C, M = 3, 50                  # scene candidates, points per candidate (padded)
N_POINTS = [50, 30, 10]       # valid points per candidate: 60 padding rows in all
CAND_IDS = [10, 11, 12]
runner = CliRunner()


def _app() -> typer.Typer:
    """The real `freeze` app (the commands' wiring is part of what is tested)."""
    from pipeline.commands.cli import app

    return app


def _rotation(seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _model(rng) -> dict[str, np.ndarray]:
    """N points on a sphere of radius 50 mm (diameter 100), geometric rows of norm 2."""
    normals = rng.normal(size=(N, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    geo = rng.normal(size=(N, G))
    geo = 2.0 * geo / np.linalg.norm(geo, axis=1, keepdims=True)
    return {"points": (50.0 * normals).astype(np.float32), "normals": normals.astype(np.float32),
            "geometric": geo.astype(np.float32), "visual": rng.normal(size=(N, V)).astype(np.float32),
            "view_count": np.full(N, 3, np.int32)}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A cache with one item for every stage but symmetries, in the plan's folders.

    Candidate 10 (object 2) is the model's first 50 points (of a permutation) moved by
    (R, t), with the model's features; candidate 11 (object 5) and 12 (object 2, not
    registered) are random."""
    cache = tmp_path_factory.mktemp("inspect") / "cache"
    plan = RunPlan(load_run({"datasets": DS}), cache=cache)[DS]
    rng = np.random.default_rng(0)
    model = _model(rng)
    R, t = _rotation(1), np.array([10.0, -20.0, 800.0])
    idx = rng.permutation(N)[: N_POINTS[0]]

    def item(stage: str, name: str):
        return publish(plan[stage].item_dir(name), **plan[stage].publish_kwargs(name))

    for stage, name in (("synth", "dataset"), ("render_templates", "obj_000002"), ("segment_prior", "all"),
                        ("refine", "scene_000001"), ("score", "all"), ("model_features", "obj_000005")):
        with item(stage, name) as w:
            (w.dir / "note.json").write_text(json.dumps({"a": 1, "b": [1, 2]}))
    with item("model_features", "obj_000002") as w:
        save_arrays(w.dir / "features.zarr", model, attrs={"key": plan["model_features"].key, "diameter": 100.0})
    points = np.full((C, M, 3), np.nan, np.float32)
    geo = np.full((C, M, G), np.nan, np.float32)
    vis = np.full((C, M, V), np.nan, np.float32)
    for c, k in enumerate(N_POINTS):
        g = rng.normal(size=(k, G))
        geo[c, :k] = 2.0 * g / np.linalg.norm(g, axis=1, keepdims=True)
        vis[c, :k] = rng.normal(size=(k, V))
        points[c, :k] = rng.normal(size=(k, 3)) * 30 + t
    points[0, :50] = model["points"][idx] @ R.T + t
    geo[0, :50], vis[0, :50] = model["geometric"][idx], model["visual"][idx]
    with item("scene_features", "scene_000001") as w:
        save_arrays(w.dir / "features.zarr", {"cand_id": np.array(CAND_IDS, np.int64), "n_points": np.array(N_POINTS, np.int32),
                                              "points": points, "geometric": geo, "visual": vis},
                    attrs={"key": plan["scene_features"].key, "scene_id": 1})
        write_table(pd.DataFrame({"cand_id": CAND_IDS, "prior_score": [0.9, None, None]}), w.dir / "candidate_status.parquet",
                    metadata={"key": "0" * 40})  # deliberately not this artifact's key
    with item("register", "scene_000001") as w:
        table = pd.DataFrame({
            "cand_id": CAND_IDS, "scene_id": 1, "im_id": [0, 0, 1], "obj_id": [2, 5, 2],
            "status": ["ok", "ok", "skipped"], "reason": ["", "", "too few points"],
            "R": [R.reshape(9).tolist(), np.eye(3).reshape(9).tolist(), None],
            "t": [t.tolist(), t.tolist(), None], "n_inliers": [50, 3, None]})
        write_table(table, w.dir / "coarse_hypotheses.parquet", metadata={"key": plan["register"].key})
    return {"cache": cache, "plan": plan, "model": model, "idx": idx, "R": R, "t": t}


# ------------------------------------------------------------------------ inspect


def test_inspect_reports_arrays_exactly(store):
    plan = store["plan"]
    info = inspect_artifact(plan["scene_features"].item_dir("scene_000001"))
    z = info["zarr"][0]
    assert z["key_matches"] is True
    arrays = {a["name"]: a for a in z["arrays"]}
    assert arrays["geometric"]["shape"] == [C, M, G] and arrays["geometric"]["dtype"] == "float32"
    assert arrays["geometric"]["chunks"] == [1, M, G]
    assert arrays["geometric"]["stats"]["nan"] == 60 * G
    assert arrays["points"]["stats"]["nan"] == 60 * 3
    norms = arrays["geometric"]["norms"]
    assert (norms["rows"], norms["nan_rows"], norms["zero_rows"], norms["channels"]) == (C * M, 60, 0, G)
    assert norms["min"] == pytest.approx(2.0, abs=1e-5) and norms["max"] == pytest.approx(2.0, abs=1e-5)
    n = arrays["n_points"]
    assert (n["stats"]["min"], n["stats"]["max"], n["stats"]["mean"], n["stats"]["nan"]) == (10, 50, 30, 0)
    assert "norms" not in n and "norms" not in arrays["points"]  # not feature arrays
    # stored size and ratio are zarr's own account of the array
    import zarr

    za = zarr.open_group(str(Path(z["path"])), mode="r")["geometric"]
    assert arrays["geometric"]["stored_bytes"] == za.nbytes_stored()
    assert arrays["geometric"]["nbytes"] == C * M * G * 4
    assert arrays["geometric"]["ratio"] == pytest.approx(C * M * G * 4 / za.nbytes_stored(), abs=1e-3)


def test_inspect_reports_tables_manifest_and_upstream_chain(store):
    plan = store["plan"]
    info = inspect_artifact(plan["scene_features"].item_dir("scene_000001"))
    (table,) = info["parquet"]
    assert table["rows"] == 3 and table["row_groups"] == 1
    cols = {c["name"]: c for c in table["columns"]}
    assert cols["prior_score"]["type"] == "double" and cols["prior_score"]["null_count"] == 2
    assert table["key_matches"] is False  # written with another key on purpose

    info = inspect_artifact(plan["register"].item_dir("scene_000001"))
    m = info["manifest"]
    assert m["key"] == plan["register"].key and m["params"] == plan["register"].params
    assert m["upstream"] == plan["register"].upstream and m["code_version"] == plan["register"].code_version
    assert m["wall_time_s"] >= 0 and m["peak_rss_mb"] > 0
    assert info["encoders"]["recorded_by"] == f"model_features/{plan['model_features'].signature}"
    assert info["encoders"]["geometric"]["encoder"] == "fpfh" and info["encoders"]["visual"]["encoder"] == "colortex"
    assert info["parquet"][0]["rows"] == 3 and info["parquet"][0]["key_matches"] is True
    nulls = {c["name"]: c["null_count"] for c in info["parquet"][0]["columns"]}
    assert (nulls["R"], nulls["n_inliers"], nulls["cand_id"]) == (1, 1, 0)  # the unregistered candidate
    up = {n["name"]: n for n in info["upstream"]}
    assert set(up) == {"model_features", "scene_features"}
    assert up["model_features"]["signature"] == plan["model_features"].signature
    assert up["model_features"]["items"] == ["obj_000002", "obj_000005"]
    assert up["scene_features"]["item_path"] == str(plan["scene_features"].item_dir("scene_000001"))
    (rt,) = up["model_features"]["upstream"]
    assert (rt["stage"], rt["signature"]) == ("render_templates", plan["render_templates"].signature)
    assert rt["upstream"][0]["stage"] == "synth" and "repeated" not in rt["upstream"][0]
    sf = {n["name"]: n for n in up["scene_features"]["upstream"]}
    assert sf["dataset"]["repeated"] is True  # synth was shown under render_templates already
    assert {n["name"] for n in sf["segment_prior"]["upstream"]} == {"dataset", "prior"}

    # refine's symmetries were never built: the key is reported as not found
    info = inspect_artifact(plan["refine"].item_dir("scene_000001"))
    up = {n["name"]: n for n in info["upstream"]}
    assert up["symmetries"] == {"name": "symmetries", "key": plan["symmetries"].key, "found": False}


def test_inspect_json_command_and_sub_paths(store):
    plan = store["plan"]
    item = plan["model_features"].item_dir("obj_000002")
    result = runner.invoke(_app(), ["inspect", str(item / "features.zarr" / "geometric"), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    (arr,) = info["zarr"][0]["arrays"]
    assert arr["name"] == "geometric" and arr["shape"] == [N, G] and arr["norms"]["median"] == pytest.approx(2.0, abs=1e-5)
    result = runner.invoke(_app(), ["inspect", str(item)])
    assert result.exit_code == 0, result.output
    for text in ("model_features", plan["model_features"].signature, "render_templates", "geometric", "200x8"):
        assert text in result.stdout
    info = inspect_artifact(plan["scene_features"].path("scene_000001", "candidate_status"))
    assert not info["zarr"] and info["parquet"][0]["rows"] == 3


def test_inspect_names_a_path_that_is_not_an_artifact(store, tmp_path):
    result = runner.invoke(_app(), ["inspect", str(tmp_path / "nowhere")])
    assert result.exit_code == 2 and "nowhere" in result.output and "no such file" in result.output
    sig_dir = store["plan"]["model_features"].dir
    result = runner.invoke(_app(), ["inspect", str(sig_dir)])
    assert result.exit_code == 2 and "signature folder holding 2 artifacts" in result.output


def test_index_finds_artifacts_by_key(store):
    index = ArtifactIndex(store["cache"])
    plan = store["plan"]
    assert index.items(plan["model_features"].key) == [plan["model_features"].item_dir(i) for i in ("obj_000002", "obj_000005")]
    assert index.items("f" * 40) == []


# ---------------------------------------------------------------------- ls and gc


@pytest.fixture
def cache_with_garbage(store, tmp_path):
    """A copy of the store plus: a stale register folder, a dataset without a plan, an old
    and a young .tmp- leftover."""
    import shutil

    cache = tmp_path / "cache"
    shutil.copytree(store["cache"], cache)
    plan = RunPlan(load_run({"datasets": DS}), cache=cache)[DS]
    stale = cache / DS / "register" / "fpfh-ms+colortex-ransac-deadbeef"
    with publish(stale / "scene_000001", stage="register", item="scene_000001", key="deadbeef" * 5,
                 signature=stale.name, params={}, upstream={}, code_version=0, dataset=DS) as w:
        (w.dir / "x.bin").write_bytes(b"0" * 1000)
    unplanned = cache / "mydata" / "register" / "whatever-12345678" / "scene_000001"
    with publish(unplanned, stage="register", item="scene_000001", key="1" * 40, signature="whatever-12345678",
                 params={}, upstream={}, code_version=0, dataset="mydata"):
        pass
    old = plan["register"].dir / ".tmp-scene_000001-0badc0de"
    young = plan["model_features"].dir / ".tmp-obj_000005-12345678"
    for d in (old, young):
        d.mkdir()
        (d / "half.bin").write_bytes(b"1" * 500)
    two_hours_ago = time.time() - 7200
    for p in (old / "half.bin", old):
        os.utime(p, (two_hours_ago, two_hours_ago))
    return {"cache": cache, "plan": plan, "stale": stale, "unplanned": unplanned.parent, "old": old, "young": young}


def test_ls_marks_stale_current_and_unknown(cache_with_garbage):
    g = cache_with_garbage
    result = runner.invoke(_app(), ["ls", "--cache", str(g["cache"]), "--json", "--config", f"datasets={DS}"])
    assert result.exit_code == 0, result.output
    listing = json.loads(result.stdout)
    status = {(e["dataset"], e["stage"], e["signature"]): e["status"] for e in listing["entries"]}
    plan = g["plan"]
    for stage in ("synth", "render_templates", "model_features", "segment_prior", "scene_features", "register", "refine",
                  "score"):
        assert status[(DS, stage, plan[stage].signature)] == "current"
    assert status[(DS, "register", g["stale"].name)] == "stale"
    assert status[("mydata", "register", "whatever-12345678")] == "unknown"
    assert sum(s == "stale" for s in status.values()) == 1
    entry = next(e for e in listing["entries"] if e["signature"] == plan["model_features"].signature)
    assert entry["items"] == ["obj_000002", "obj_000005"] and entry["created"]
    assert sorted(Path(lo["path"]).name for lo in listing["leftovers"]) == sorted([g["old"].name, g["young"].name])
    # an ablation run's folders are stale for the default run, current for their own
    ablation = list_artifacts(g["cache"], load_run({"datasets": DS, "visual": "none"}), [DS])
    by_sig = {e.signature: e.status for e in ablation.entries}
    assert by_sig[plan["model_features"].signature] == "stale" and by_sig[plan["render_templates"].signature] == "current"
    text = runner.invoke(_app(), ["ls", "--cache", str(g["cache"])]).stdout
    assert "stale" in text and g["stale"].name in text


def test_gc_asks_and_removes_exactly_the_garbage(cache_with_garbage):
    g = cache_with_garbage
    before = sorted(p for p in g["cache"].rglob("*"))
    result = runner.invoke(_app(), ["gc", "--cache", str(g["cache"])], input="n\n")
    assert result.exit_code == 1 and "nothing removed" in result.output
    assert sorted(p for p in g["cache"].rglob("*")) == before
    assert "2 folder(s)" in result.output  # the stale register folder and the old .tmp-

    result = runner.invoke(_app(), ["gc", "--cache", str(g["cache"]), "--yes"])
    assert result.exit_code == 0, result.output
    assert not g["stale"].exists() and not g["old"].exists()
    assert g["young"].exists() and g["unplanned"].exists()
    for stage, sp in g["plan"].stages.items():
        if stage != "symmetries":
            assert sp.dir.exists(), stage
    listing = list_artifacts(g["cache"], load_run({}), [DS])
    assert all(e.status == "current" for e in listing.entries)


def test_gc_refuses_paths_outside_the_cache_and_current_ones(cache_with_garbage, tmp_path):
    g = cache_with_garbage
    listing = list_artifacts(g["cache"], load_run({}), [DS])
    outside = tmp_path / "precious"
    outside.mkdir()
    with pytest.raises(ValueError, match="outside the cache root"):
        collect_garbage(listing, [Removal(str(outside), 0, "stale")])
    current = g["plan"]["register"].dir
    with pytest.raises(ValueError, match="current plan"):
        collect_garbage(listing, [Removal(str(g["stale"]), 0, "stale"), Removal(str(current), 0, "stale")])
    assert outside.exists() and current.exists() and g["stale"].exists()  # checked before anything goes


# ----------------------------------------------------------------- feature figure


def test_shared_pca_gives_identical_features_identical_colours():
    rng = np.random.default_rng(3)
    model = rng.normal(size=(500, 12)) * np.linspace(3, 0.1, 12)
    pick = rng.choice(500, 80, replace=False)
    scene = np.concatenate([model[pick], rng.normal(size=(20, 12))])
    cm, cs, explained = pca_colours(model, scene)
    assert np.array_equal(cs[:80], cm[pick])
    assert cm.min() >= 0 and cm.max() <= 1 and 0 < explained < 1
    # the robust range: each component spans its 1st to 99th percentile over the 500
    # model points, so the 5 below the 1st (ranks 0-4) are clipped to 0, the 5 above the
    # 99th (ranks 495-499) to 1
    assert np.array_equal((cm == 0).sum(axis=0), [5, 5, 5]) and np.array_equal((cm == 1).sum(axis=0), [5, 5, 5])
    # features without spread get a single colour
    flat_m, flat_s, e = pca_colours(np.ones((10, 4)), np.zeros((3, 4)))
    assert np.all(flat_m == 0.5) and np.all(flat_s == 0.5) and e == 0


def test_feature_case_from_artifacts(store):
    case = feature_case(store["plan"], 2)
    assert (case.cand_id, case.scene_id, case.im_id) == (10, 1, 0)  # the first registered candidate of object 2
    assert case.scene_points.shape == (50, 3) and case.parts["fused"][0].shape == (N, G + V)
    assert case.inlier_threshold == pytest.approx(0.05 * 100.0)
    nn, inl = inlier_matches(case)
    assert np.array_equal(nn, store["idx"]) and inl.all()  # identical features match their own point
    cm, cs, _ = pca_colours(*case.parts["fused"])
    assert np.array_equal(cs, cm[store["idx"]])
    with pytest.raises(ValueError, match="candidate 11 is of object 5"):
        feature_case(store["plan"], 2, cand_id=11)
    with pytest.raises(ValueError, match="not registered"):
        feature_case(store["plan"], 2, cand_id=12)
    with pytest.raises(LookupError, match="no scene 7"):
        feature_case(store["plan"], 2, scene_id=7)


def test_show_features_writes_the_png(store, tmp_path, monkeypatch):
    monkeypatch.setenv("FREEZE_CACHE", str(store["cache"]))
    result = runner.invoke(_app(), ["show", "features", "--dataset", DS, "--obj", "2", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    path = tmp_path / f"features_{DS}_obj_000002_scene_000001_cand_10.png"
    assert path.exists()
    assert Image.open(path).size == (round(FIGSIZE[0] * DPI), round(FIGSIZE[1] * DPI))
    result = runner.invoke(_app(), ["show", "features", "--dataset", DS, "--obj", "9", "--out", str(tmp_path)])
    assert result.exit_code == 2 and "object 9 has no model features" in result.output


def test_figure_of_a_geometry_only_run(tmp_path):
    rng = np.random.default_rng(5)
    model = _model(rng)
    R, t = _rotation(2), np.array([0.0, 0.0, 600.0])
    none = np.zeros((N, 0), np.float32)
    fused = fused_features(model["geometric"], none, model["geometric"][:40], none[:40], pca_dim=64)
    assert fused[0].shape == (N, G)
    case = FeatureCase(dataset="d", obj_id=1, scene_id=1, im_id=0, cand_id=0, model_points=model["points"],
                       scene_points=model["points"][:40] @ R.T + t,
                       parts={"geometric": (model["geometric"], model["geometric"][:40]), "visual": (none, none[:40]),
                              "fused": fused},
                       R=R, t=t, diameter=100.0, inlier_threshold=5.0, model_normals=model["normals"])
    out = draw_features_figure(case, tmp_path / "geo_only.png")
    assert Image.open(out).size == (round(FIGSIZE[0] * DPI), round(FIGSIZE[1] * DPI))
    assert inlier_matches(case)[1].sum() == 40
